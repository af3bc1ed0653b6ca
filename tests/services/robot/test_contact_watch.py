"""The robot's contact watch: which readings feed the monitor, a contact counted once at its rise, and what each
state says of the cycle (tests/services/model/test_contact.py checks the observer itself)."""
import numpy as np
import pytest

from services.model.arm import load_arm
from services.model.dynamics import DynamicsModel
from services.robot.contact_watch import ContactConfig, ContactWatch
from services.robot.hardware import JointReading

ARM = load_arm("j2n6s300")
GRAVITY = DynamicsModel(ARM, rotor_inertia=True).gravity(ARM.home)


def reading(stamp_ns, push=None):
    """The arm at rest at home, its sensors holding gravity, less a push's joint torque (the motors hold it)."""
    tau = GRAVITY.copy() if push is None else GRAVITY - push
    return JointReading(q=ARM.home.copy(), dq=np.zeros(ARM.n_joints), tau=tau, stamp_ns=stamp_ns)


def test_a_contact_is_counted_once_at_its_rise_and_each_state_says_the_cycle_and_the_last_contact():
    watch = ContactWatch(ARM, ContactConfig(), 0.002, 0.01)
    push = np.array([0.0, 12.0, 6.0, 0.0, 0.0, 0.0])
    for k in range(5):
        assert watch.observe(reading(k * 2_000_000), k == 0, 0) is None
    quiet = watch.for_state()
    assert quiet.contacts == 0 and quiet.joint == 0 and quiet.ratio < 1.0 and quiet.rate_hz == 500.0
    started = [watch.observe(reading(k * 2_000_000, push), False, 0) for k in range(5, 30)]
    assert sum(s is not None for s in started) == 1  # the rise, not every sample in contact
    touched = watch.for_state()
    assert touched.contacts == 1 and touched.joint == touched.last_joint == 3 and touched.ratio > 1.0
    assert touched.last_contact().startswith("contact at joint 3: residual")
    assert np.allclose(touched.residual_nm, push, atol=0.05)
    # the window starts again; the count and the last contact stay; a second push after a release is a second
    for k in range(30, 40):  # the residual falls back through the filter
        watch.observe(reading(k * 2_000_000), False, 0)
    watch.for_state()
    for k in range(40, 80):
        watch.observe(reading(k * 2_000_000), False, 0)
    released = watch.for_state()
    assert released.joint == 0 and released.contacts == 1 and released.last_joint == 3
    assert any(watch.observe(reading(k * 2_000_000, push), False, 0) is not None for k in range(80, 100))
    assert watch.for_state().contacts == 2
    summary = watch.summary()  # what the robot's health says (mfvs status)
    assert summary.startswith("contact: contacts=2 peak_ratio=") and "at 500 Hz restarts=0 last: contact at joint 3" \
        in summary and float(summary.split("peak_ratio=")[1].split()[0]) > 1.0


def test_a_reading_seen_before_is_not_taken_twice_and_the_dsp_rate_takes_only_the_ticks():
    watch = ContactWatch(ARM, ContactConfig(), 0.002, 0.01)
    watch.observe(reading(2_000_000), False, 0)
    watch.observe(reading(2_000_000), False, 0)
    assert watch.monitor.samples == 1
    # a reading without a stamp of its own is taken at the host's time it is given
    watch.observe(reading(0), False, 4_000_000)
    assert watch.monitor.samples == 2 and watch.monitor.restarts == 0
    at_ticks = ContactWatch(ARM, ContactConfig(rate="dsp"), 0.002, 0.01)
    for k in range(10):
        at_ticks.observe(reading(k * 2_000_000), k % 5 == 0, 0)
    assert at_ticks.monitor.samples == 2 and at_ticks.for_state().rate_hz == 100.0


@pytest.mark.parametrize("field, value", [("rate", "usb"), ("hand_mass_uncertainty", -0.1), ("payload_kg", 20.0),
                                          ("gain_times_period", 2.0)])
def test_a_contact_config_that_means_nothing_is_refused(field, value):
    with pytest.raises(ValueError, match=field):
        ContactConfig(**{field: value})
