"""services/robot/arm_driver.py without zenoh or a node: the emulated DSP's driver exchanges the core's targets for
readings, says which cycle is a DSP tick, counts the cycles the arm ran without it, holds the reference when the
bus fails for longer than the actuators go on, and tells the node's health how the link is doing."""
import logging
import threading

import numpy as np
import pytest

from services.model.kinematics import ArmKinematics
from services.robot.arm_driver import JointDriver, LinkHealth, NodeLoop
from services.robot.core import Plan
from services.robot.dsp import DSPConfig
from services.robot.hardware import DEFAULT_TIMING, DSP_CYCLE_NS, BusTiming, HardwareError, JointReading
from services.robot.torque_setup import TorqueSetup
from services.runtime.clock import SimulatedClock, WallClock
from services.runtime.logs import RateLimitedLogger
from services.runtime.metrics import Counters, DurationStats, RateMeter
from tests.helpers import ARM

EPOCH_NS = 1_000_000_000


class ScriptedJoints:
    """Joints that answer each exchange as the test scripts it: a reading stamped ``stamp_ns`` (0: unstamped, as a
    real arm's bus gives none), or a failure (a message)."""

    simulated_in_process = False
    actuators_compensate_gravity = False

    def __init__(self, script, arm_timeline=False, timing: BusTiming = DEFAULT_TIMING) -> None:
        self.script = list(script)
        self.arm_timeline = arm_timeline
        self.timing = timing
        self.targets = []
        self.closed = False

    def exchange(self, targets):
        self.targets.append(targets.q.copy())
        step = self.script.pop(0)
        if isinstance(step, str):
            raise HardwareError(step)
        return JointReading(q=ARM.home.copy(), dq=np.zeros(ARM.n_joints), tau=np.zeros(ARM.n_joints), stamp_ns=step)

    def close(self) -> None:
        self.closed = True


class Seconds:
    """A monotonic clock the test sets."""

    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def driver(hardware, lockstep=False, missed_clock=None) -> JointDriver:
    loop = NodeLoop("robot_test", lockstep, SimulatedClock(EPOCH_NS) if lockstep else WallClock(), Counters(),
                    RateLimitedLogger(logging.getLogger("test")), RateMeter(clock=missed_clock or Seconds()),
                    DurationStats())
    first = JointReading(q=ARM.home.copy(), dq=np.zeros(ARM.n_joints), tau=np.zeros(ARM.n_joints))
    kin = ArmKinematics(ARM)
    return JointDriver(hardware, first, loop, dsp=DSPConfig(), kin=kin, gravity=kin.gravity,
                       torque_setup=TorqueSetup(ARM), core_lock=threading.Lock())


def ticks(joints: JointDriver, cycles: int) -> list:
    return [joints.cycle() for _ in range(cycles)]


def test_a_real_arm_s_dsp_ticks_every_fifth_exchange_stamped_as_its_reading():
    received = [1_700_000_000_000_000_000 + k * 2_100_000 for k in range(11)]  # when the replies came (host clock)
    script = received[:10] + ["timeout"]
    joints = driver(ScriptedJoints(script))
    stamps = ticks(joints, 11)
    assert [k for k, s in enumerate(stamps) if s is not None] == [0, 5, 10] and joints.cycles == 11
    assert stamps[0] == received[0] and stamps[5] == received[5]
    assert stamps[10] > received[9]  # no reading at that tick: the node's clock stamps it
    slow = driver(ScriptedJoints([0] * 7, timing=BusTiming(2)))  # a 5 ms bus: two exchanges a tick
    assert [k for k, s in enumerate(ticks(slow, 7)) if s is not None] == [0, 2, 4, 6]


def test_on_the_arm_s_timeline_the_tick_is_the_first_reading_at_or_past_each_10_ms_line():
    # joined mid-cycle (12 ms: no tick before the 20 ms line); the arm ran the cycle at 20 ms without us (the line
    # is crossed at 22 ms); a reading lost at 26 ms
    ms = [12, 14, 16, 18, 22, 24, "timeout", 28, 30, 32]
    script = [EPOCH_NS + t * 1_000_000 if isinstance(t, int) else t for t in ms]
    joints = driver(ScriptedJoints(script, arm_timeline=True))
    out = ticks(joints, len(script))
    assert [s for s in out if s is not None] == [EPOCH_NS + 22_000_000, EPOCH_NS + 30_000_000]
    assert joints.loop.counters.get("cycles.arm_missed") == 2  # the gaps in the stamps: at 20 and at 26 ms
    assert joints.loop.counters.get("bus.failed_exchanges") == 1


def test_in_lockstep_the_arm_s_stamps_are_the_node_s_time_and_its_10_ms_grid_the_ticks():
    period = DEFAULT_TIMING.period_ns
    script = [EPOCH_NS + period * k for k in range(1, 11)]
    joints = driver(ScriptedJoints(script), lockstep=True)
    out = ticks(joints, len(script))
    assert [s for s in out if s is not None] == [s for s in script if s % DSP_CYCLE_NS == 0]
    assert joints.loop.clock.now_ns() == script[-1]


def test_failed_exchanges_are_counted_said_and_hold_the_reference_after_the_actuators_stop():
    seconds = Seconds()
    joints = driver(ScriptedJoints([0, "nack", "timeout", "timeout", 0]), missed_clock=seconds)
    core = joints.core
    core.take_plan(Plan(np.full(ARM.n_joints, 0.1)))
    joints.cycle()
    assert joints.link.consecutive_errors == 0 and not joints.link.faults
    joints.cycle()  # one lost exchange: a missed cycle, the reference goes on
    assert joints.link.faults == ["bus: nack"] and core.dq_ref.any()
    joints.cycle()  # the actuators went on one cycle along their last targets and hold now: so does the reference
    assert joints.link.consecutive_errors == 2 and not core.dq_ref.any()
    joints.cycle()
    assert joints.link.failing(3) and not joints.link.failing(4)
    counters = joints.loop.counters
    seconds.now = 1.0
    assert counters.get("bus.failed_exchanges") == 3 and joints.loop.missed.rate_hz() == 3.0  # the states' timing
    joints.cycle()  # the bus answers again
    assert joints.link.consecutive_errors == 0 and joints.link.faults == []


def test_a_dsp_too_late_holds_the_joints_and_is_counted_once_per_cycle_held():
    joints = driver(ScriptedJoints([0] * 30))
    joints.core.take_plan(Plan(np.full(ARM.n_joints, 0.1)))
    ticks(joints, 30)  # no DSP cycle at all: after two DSP periods the joints hold
    assert joints.loop.counters.get("dsp.stale_holds") == joints.core.dsp_stale_cycles == 1


def test_the_dsp_runs_in_the_driver_s_terms_and_closing_closes_the_hardware():
    hardware = ScriptedJoints([])
    joints = driver(hardware)
    assert joints.run_dsp(lambda: 0.25) == 0.25  # the emulated DSP's failures are no link's: the caller's
    with pytest.raises(ZeroDivisionError):
        joints.run_dsp(lambda: 1 / 0)
    assert joints.dsp_beside_loop and joints.torque_joints is not None and joints.lowlevel_unavailable == ""
    joints.close()
    assert hardware.closed


def test_link_health_fails_and_recovers():
    link = LinkHealth()
    link.failed("bus: " + "x" * 200)
    assert link.consecutive_errors == 1 and len(link.faults[0]) == 120 and not link.failing(2)
    link.failed("bus: again")
    assert link.failing(2) and link.faults == ["bus: again"]
    link.answered()
    assert not link.failing(1) and link.faults == []
