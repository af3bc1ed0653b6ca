"""The robot node's rules running in the gateway, over the RS-485 link to robot_sim's actuators (in-process bus, no
zenoh): a mixed-frame velocity command moves the end effector as it does in robot_sim. The arm runs a cycle per
exchange here (lockstep), so the figures are exact; tests/services/robot_gateway/test_service.py runs both sides in realtime, as
processes."""
import numpy as np
import pytest

from protocol import messages as m
from protocol.conventions import AngularConvention, Frame
from services.robot.dsp import DSPConfig, KinovaDSP
from services.robot.core import Plan, RobotCore
from services.robot.hardware import CYCLES_PER_DSP, BusTiming, HardwareError, JointReading
from services.robot.rs485_bus import BusConfig
from services.robot_gateway.link import LinkHardware
from services.stack.local import simulated_link
from services.model.kinematics import ArmKinematics
from tests.helpers import ARM


def twist_command(linear, rotational):
    twist = m.Twist(header=m.Header(), frame=Frame.MIXED, angular=AngularConvention.SEED000, linear=linear,
                    rotational=rotational)
    return m.RobotCommand(header=m.Header(), mode=m.CommandMode.CARTESIAN_VELOCITY, twist=twist)


@pytest.fixture
def gateway():
    with simulated_link(lockstep=True) as (arm, link):
        hardware = LinkHardware(link, ARM, pipelined=False)  # in step with the arm, as the gateway runs in lockstep
        yield arm, hardware, RobotCore(KinovaDSP(DSPConfig(), ArmKinematics(ARM)), hardware.read())


def run_dsp(hardware, core, command, cycles, on_cycle=None):
    """The gateway's loop in miniature: an exchange per bus cycle, the DSP every fifth (resending the command)."""
    for k in range(cycles):
        reading = hardware.exchange(core.targets())
        core.observe(reading)
        if k % CYCLES_PER_DSP == 0:
            core.dsp_cycle(command)
        if on_cycle is not None:
            on_cycle(reading)


def test_mixed_velocity_through_the_gateway_matches_robot_sim(gateway):
    arm, hardware, core = gateway
    linear = (0.04, -0.03, 0.03)
    start = arm.sim.time_ns
    run_dsp(hardware, core, twist_command(linear, (0.0, 0.0, 0.2)), 450)  # 0.9 s: past the acceleration ramp
    samples = []

    def sample(_reading):
        with arm.lock:  # the arm finishes its cycle (physics) after it replied
            samples.append(arm.sim.ee_twist_base())

    run_dsp(hardware, core, twist_command(linear, (0.0, 0.0, 0.2)), 350, sample)
    with arm.lock:
        assert arm.sim.time_ns - start == 800 * 2_000_000  # one arm cycle per exchange
    v = np.mean(samples, axis=0)
    assert np.linalg.norm(v[:3] - np.array(linear)) <= 0.02 * np.linalg.norm(linear)  # within 2 %
    assert hardware.link.bus.counters.get("link.timeouts") == 0


def test_bus_failure_holds_the_arm(gateway):
    arm, hardware, core = gateway
    arm.stop(close_bus=False)  # the actuators fall silent
    core.dq_ref = np.full(7, 0.1)
    with pytest.raises(HardwareError, match="no reply"):
        hardware.exchange(core.targets())
    core.hold()
    assert np.all(core.dq_ref == 0) and np.allclose(core.targets().q, core.reading.q)


@pytest.mark.parametrize("period_ms, cycles", [(2, 5), (2.5, 4), (3.33, 3), (3.333, 3), (5, 2)])
def test_a_bus_period_divides_the_dsps_10_ms_tick_and_every_tick_stays_on_its_grid(period_ms, cycles):
    timing = BusTiming.from_period_ms(period_ms)
    assert timing.cycles_per_dsp == cycles and timing.period_ns * cycles <= 10_000_000
    stamps = [timing.stamp_ns(k) for k in range(4 * cycles + 1)]
    assert stamps[::cycles] == [0, 10_000_000, 20_000_000, 30_000_000, 40_000_000]  # 3.33 ms's rounding included
    assert all(timing.cycles_in(b - a) == 1 for a, b in zip(stamps, stamps[1:]))
    assert timing.cycles_in(stamps[3] - stamps[0]) == 3


@pytest.mark.parametrize("period_ms", [4, 1, 10, 0, -2, float("nan"), float("inf"), "2", True])
def test_a_bus_period_that_is_no_whole_fraction_of_the_tick_is_refused_saying_why(period_ms):
    with pytest.raises(ValueError, match="bus period_ms|bus period_ms 4 does not divide"):
        BusTiming.from_period_ms(period_ms)
    with pytest.raises(ValueError):
        BusConfig(period_ms=period_ms)


@pytest.mark.parametrize("period_ms", [2, 5])
def test_the_core_ramps_to_the_dsps_velocities_over_one_tick_and_holds_after_two_ticks_without_one(period_ms):
    """Whatever the bus period, the joints reach the DSP's velocities within its 10 ms and keep them at most two
    DSP periods (20 ms of exchanges) without a new DSP cycle."""
    timing = BusTiming.from_period_ms(period_ms)
    reading = JointReading(q=ARM.home.copy(), dq=np.zeros(ARM.n_joints), tau=np.zeros(ARM.n_joints))
    core = RobotCore(KinovaDSP(DSPConfig(), ArmKinematics(ARM)), reading, timing)
    dq = np.full(ARM.n_joints, 0.1)
    core.take_plan(Plan(dq))
    positions = [core.targets().q[0] for _ in range(timing.cycles_per_dsp)]
    steps = np.diff([ARM.home[0], *positions])
    assert steps[-1] == pytest.approx(0.1 * timing.period_s * (1 - 0.5 / timing.cycles_per_dsp))
    assert np.all(np.diff(steps) > 0)  # a ramp, not a jump
    # no DSP cycle for two ticks: held after them
    for _ in range(timing.cycles_per_dsp):
        core.targets()
    assert core.dsp_stale_cycles == 0
    core.targets()
    assert core.dsp_stale_cycles == 1 and not core.dq_ref.any()


def test_a_counted_timeline_is_the_emulated_arms_2_ms_cycles_only():
    with simulated_link(lockstep=True) as (_arm, link):
        with pytest.raises(ValueError, match="2 ms cycles"):
            LinkHardware(link, ARM, pipelined=False, counted_from_ns=10**9, timing=BusTiming.from_period_ms(5))


def test_after_a_hold_the_dsp_starts_again_from_rest_not_from_the_velocity_it_last_planned():
    """A DSP that was late (the joints held after two DSP periods without a plan) or an exchange that failed: the
    arm is at rest, and the DSP's next plan ramps from there within its acceleration limit (it went on from its
    own last velocity, and the arm jumped back to it: 26 mm/s after a stall on a slow host)."""
    reading = JointReading(q=ARM.home.copy(), dq=np.zeros(ARM.n_joints), tau=np.zeros(ARM.n_joints))
    dsp = KinovaDSP(DSPConfig(), ArmKinematics(ARM))
    core = RobotCore(dsp, reading)
    command = twist_command((0.1, 0.0, 0.0), (0.0, 0.0, 0.0))
    for _ in range(60):  # 0.6 s: up to speed
        core.dsp_cycle(command)
    moving = np.abs(core.dq_ref).max()
    assert moving > 0.05
    for _ in range(2 * CYCLES_PER_DSP + 1):  # no DSP for two of its periods: held
        core.targets()
    assert core.dsp_stale_cycles == 1 and not core.dq_ref.any()
    core.dsp_cycle(command)  # the DSP again, the command still on: one acceleration step from rest
    assert 0.0 < np.abs(core.dq_ref).max() < 0.2 * moving
