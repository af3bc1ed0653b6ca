"""The robot's contact monitor over its own joint readings, and what each state says of it (no zenoh, no clock, no
locks: the node serialises it between its loop, which feeds it every reading, and the thread that publishes the
states).

Why here: the robot node is the one place that sees the joints at the bus's rate (500 Hz, where its driver has the
actuators) and the DSP's 100 Hz state alike, before any hop on the network; safety sees only the 100 Hz states,
a network hop later, and a reflex that waits for it would wait a cycle more (docs/contact.md). The monitor is
the model layer's (services/model/contact.py); a contact is the rise of its isolation from no joint to one, counted
and said in every state from then on (``contacts``), so a reader that missed the state of the contact still sees it.
"""
from __future__ import annotations

from typing import Optional

from protocol.messages import ContactState, contact_line
from services.model.arm import ArmDescription
from services.model.contact import GAIN_TIMES_PERIOD, ContactMonitor, ContactSample, Uncertainty
from services.robot.hardware import JointReading
from services.runtime.config import ConfigStruct


class ContactConfig(ConfigStruct):
    #: the monitor runs. Off as shipped until it meets issue 60's "no false stops": a held object is not yet
    #: declared to it, and lifting a 0.35 kg cup trips it (docs/contact.md says what else is open)
    enabled: bool = False
    #: which readings feed it: ``bus`` every reading the driver gives (the bus cycle's, 500 Hz, where the driver
    #: has the actuators; the DSP's where it has not), ``dsp`` only those of the DSP's ticks (100 Hz: what the
    #: high-level API's GetAngularForce gives a client)
    rate: str = "bus"
    #: the description's uncertainty the thresholds allow for (services/model/contact.py, docs/contact.md)
    hand_mass_uncertainty: float = 0.4
    #: a payload in the hand the model is not told of (kg, at the end effector)
    payload_kg: float = 0.0
    #: the observer's gain times its sample period (0 < K_O·Δt < 2)
    gain_times_period: float = GAIN_TIMES_PERIOD

    def __post_init__(self) -> None:
        if self.rate not in ("bus", "dsp"):
            raise ValueError(f"contact.rate {self.rate!r}: bus or dsp")
        if not 0.0 <= self.hand_mass_uncertainty <= 2.0:
            raise ValueError("contact.hand_mass_uncertainty must be within 0..2 (a fraction of the hand's mass)")
        if not 0.0 <= self.payload_kg <= 10.0:
            raise ValueError("contact.payload_kg must be within 0..10 kg")
        if not 0.0 < self.gain_times_period < 2.0:
            raise ValueError("contact.gain_times_period must be within (0, 2): the observer is unstable beyond")


class ContactWatch:
    """The monitor fed by the node's readings, and each state's view of it: the newest residual, the largest ratio
    and the joint named since the last state, the contacts and restarts so far."""

    def __init__(self, arm: ArmDescription, config: ContactConfig, bus_period_s: float, dsp_period_s: float) -> None:
        self.config = config
        self.dsp_only = config.rate == "dsp"
        period = dsp_period_s if self.dsp_only else bus_period_s
        self.monitor = ContactMonitor(arm, period, Uncertainty(config.hand_mass_uncertainty, config.payload_kg),
                                      config.gain_times_period)
        self.rate_hz = 1.0 / period
        self._threshold = self.monitor.threshold.tolist()
        self._last_stamp_ns: Optional[int] = None
        self._in_contact = False
        self._window_ratio, self._window_joint = 0.0, 0
        #: the largest |residual|/threshold since the robot started (the margin the status reports)
        self.peak_ratio = 0.0
        self.contacts = 0
        self._last = (0, 0.0, 0.0)
        self._residual = [0.0] * arm.n_joints

    def observe(self, reading: JointReading, at_dsp_tick: bool, fallback_stamp_ns: int) -> Optional[ContactSample]:
        """A new reading (one already seen, by its stamp, is not taken twice); the sample when it starts a contact,
        else None. ``fallback_stamp_ns``: the reading's time where the hardware gives none."""
        if self.dsp_only and not at_dsp_tick:
            return None
        stamp_ns = reading.stamp_ns or fallback_stamp_ns
        if stamp_ns == self._last_stamp_ns:
            return None
        self._last_stamp_ns = stamp_ns
        sample = self.monitor.update(reading.q, reading.dq, reading.tau, stamp_ns * 1e-9)
        self._residual = sample.residual.tolist()
        if sample.ratio >= self._window_ratio:
            self._window_ratio, self._window_joint = sample.ratio, sample.joint
        self.peak_ratio = max(self.peak_ratio, sample.ratio)
        started = sample.in_contact and not self._in_contact
        self._in_contact = sample.in_contact
        if not started:
            return None
        self.contacts += 1
        j = sample.joint - 1
        self._last = (sample.joint, float(sample.residual[j]), float(self.monitor.threshold[j]))
        return sample

    def summary(self) -> str:
        """The monitor in the robot's health (``mfvs status``): contacts, the largest residual-to-threshold ratio
        so far, restarts, and the last contact."""
        last = f" last: {self.last_contact()}" if self.contacts else ""
        return (f"contact: contacts={self.contacts} peak_ratio={self.peak_ratio:.2f} at {self.rate_hz:.0f} Hz "
                f"restarts={self.monitor.restarts}{last}")

    def last_contact(self) -> str:
        """The last contact, in a line."""
        return contact_line(*self._last)

    def for_state(self) -> ContactState:
        """What the next state says (the window starts again)."""
        ratio, joint = self._window_ratio, self._window_joint
        self._window_ratio, self._window_joint = 0.0, 0
        return ContactState(residual_nm=self._residual, threshold_nm=self._threshold, ratio=ratio, joint=joint,
                            rate_hz=self.rate_hz, contacts=self.contacts, restarts=self.monitor.restarts,
                            last_joint=self._last[0], last_residual_nm=self._last[1],
                            last_threshold_nm=self._last[2])
