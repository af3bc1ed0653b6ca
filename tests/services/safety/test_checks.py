"""Safety watches what the arm does: the measured end-effector and joint speeds (J(q)·dq of each robot state)
against its limits, with a margin, for longer than one state period (services.safety.checks.MotionMonitor), and
the service latches a protective stop on it."""
import time

import msgspec
import numpy as np
import pytest

from protocol import messages as m
from protocol.conventions import AngularConvention, ClockMode, Frame
from services.model.kinematics import ArmKinematics
from services.model.limits import arm_limits, stricter
from services.runtime.transport import open_session
from services.model import frames
from services.safety.checks import CommandChecker, MotionMonitor, SafetyLimits
from services.safety.service import SafetyConfig, SafetyService
from tests.stack import KEYS, Recorder, wait_for
from services.model.arm import load_arm
from tests.helpers import ARM_DECLARED

ARM = load_arm("j2s7s300")

PERIOD_NS = 10_000_000  # the robot state's period (100 Hz)
KIN = ArmKinematics(ARM)
Q = ARM.home.copy()
#: the limits the robot declares in its states (the monitor's reference)
ROBOT = stricter(arm_limits(ARM), linear_speed_mps=0.15, angular_speed_rps=0.8)
#: a robot whose Cartesian limits are out of reach (only the joints' speeds count)
JOINTS_ONLY = msgspec.structs.replace(arm_limits(ARM), linear_speed_mps=100.0, angular_speed_rps=100.0)


def dq_for_linear(speed_mps: float, direction=(1.0, 0.0, 0.0)) -> np.ndarray:
    """Joint velocities that move the end effector at ``speed_mps`` along ``direction`` without rotating it."""
    twist = np.zeros(6)
    twist[:3] = speed_mps * np.asarray(direction) / np.linalg.norm(direction)
    return np.linalg.pinv(KIN.jacobian_base(Q)) @ twist


def feed(monitor: MotionMonitor, dq, states: int, start_ns: int = 0, robot=ROBOT) -> list:
    return [monitor.observe(Q, dq, start_ns + i * PERIOD_NS, robot) for i in range(states)]


def test_measured_speed_within_the_margin_never_trips():
    monitor = MotionMonitor(SafetyLimits(), ArmKinematics(ARM))
    assert feed(monitor, dq_for_linear(0.15 * 1.09), 50) == [None] * 50
    assert monitor.peak_ratio["linear"] == pytest.approx(1.09, rel=1e-6)
    assert monitor.peak_linear_mps == pytest.approx(0.15 * 1.09, rel=1e-6)


def test_one_state_over_is_tolerated_two_in_a_row_trip():
    monitor = MotionMonitor(SafetyLimits(), ArmKinematics(ARM))
    fast, slow = dq_for_linear(0.15 * 1.16, (0.3, -0.5, 0.8)), dq_for_linear(0.05)
    assert feed(monitor, fast, 1) == [None]
    assert monitor.observe(Q, slow, PERIOD_NS, ROBOT) is None  # back under: the count starts again
    assert monitor.observe(Q, fast, 2 * PERIOD_NS, ROBOT) is None
    reason = monitor.observe(Q, fast, 3 * PERIOD_NS, ROBOT)
    assert reason is not None and "end-effector speed 0.174" in reason and "10 ms" in reason


@pytest.mark.parametrize("joint", range(7))
def test_a_joint_over_its_own_limit_trips(joint):
    monitor = MotionMonitor(SafetyLimits(), ArmKinematics(ARM))
    dq = np.zeros(7)
    dq[joint] = ARM.max_speed[joint] * 1.12
    reasons = feed(monitor, dq, 2, robot=JOINTS_ONLY)
    assert reasons[0] is None and f"joint {joint + 1} speed" in reasons[1]
    dq[joint] = ARM.max_speed[joint] * 1.05
    assert feed(MotionMonitor(SafetyLimits(), ArmKinematics(ARM)), dq, 20, robot=JOINTS_ONLY) == [None] * 20


def test_a_site_limit_stricter_than_the_robots_is_watched_and_a_looser_one_is_not():
    fast = dq_for_linear(0.12)
    assert feed(MotionMonitor(SafetyLimits(max_linear_speed_mps=0.1), ArmKinematics(ARM)), fast, 2)[1] is not None
    assert feed(MotionMonitor(SafetyLimits(max_linear_speed_mps=0.5), ArmKinematics(ARM)), dq_for_linear(0.15 * 1.2), 2)[1] is not None


def test_angular_overspeed_trips():
    monitor = MotionMonitor(SafetyLimits(max_angular_speed_rps=0.5), ArmKinematics(ARM))
    twist = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.5 * 1.2])
    dq = np.linalg.pinv(KIN.jacobian_base(Q)) @ twist
    assert "angular speed" in feed(monitor, dq, 2)[1]


@pytest.fixture
def safety(router):
    service = SafetyService(SafetyConfig(clock=ClockMode.REALTIME, zenoh=router.client_config())).start()
    client = open_session(router.client_config())
    yield service, client
    client.close()
    service.stop()


def robot_state(dq, stamp_ns: int) -> bytes:
    return m.encode(m.RobotState(**ARM_DECLARED, header=m.Header(stamp_ns=stamp_ns), q=Q.tolist(), dq=list(map(float, dq)),
                                 tau=[0.0] * 7, pose=m.KinovaPose(X=0, Y=0, Z=0, ThetaX=0, ThetaY=0, ThetaZ=0),
                                 control_mode=m.ControlMode.CARTESIAN_VELOCITY, limits=ROBOT))


def test_an_arm_faster_than_told_gets_a_latched_protective_stop(safety):
    """A robot whose states say it moves 20 % over the linear limit they declare (as the gateway's arm did before
    the emulated arm kept its own time): safety stops it, counts the trip, says so in its status and health, and stays stopped
    until an operator resets it."""
    service, client = safety
    commands = Recorder(client, KEYS.robot_command, m.RobotCommand)
    status = Recorder(client, KEYS.safety_status, m.SafetyStatus)
    time.sleep(0.3)
    now = time.time_ns()
    client.put(KEYS.robot_state, robot_state(dq_for_linear(0.10), now))
    time.sleep(0.1)
    assert service.counters.snapshot().get("overspeed.trips", 0) == 0
    for i in range(3):
        client.put(KEYS.robot_state, robot_state(dq_for_linear(0.18), now + (i + 1) * PERIOD_NS))
    assert wait_for(lambda: service.counters.snapshot().get("overspeed.trips", 0) >= 1, timeout=5)
    assert wait_for(lambda: any(c.mode is m.CommandMode.EMERGENCY_STOP and "protective stop" in c.reason
                                for c in commands.snapshot()), timeout=5)
    assert wait_for(lambda: status.last() is not None and status.last().state is m.SafetyState.ESTOP, timeout=5)
    assert service.core.estop_latched and "end-effector speed 0.180" in service.core.estop_reason
    assert "peak_linear=1.20" in service.check_health()[1]
    # slow again: still stopped (latched) until the operator's reset
    client.put(KEYS.robot_state, robot_state(np.zeros(7), now + 10 * PERIOD_NS))
    time.sleep(0.3)
    assert service.core.estop_latched
    client.put(KEYS.estop, m.encode(m.EStop(header=m.Header(), reset=True, operator="test")))
    assert wait_for(lambda: not service.core.estop_latched, timeout=5)


def test_safety_refuses_an_input_from_the_future(safety):
    """Freshness is two-sided: a twist stamped an hour ahead (or derived from an image stamped ahead) is refused
    like a stale one; one within the skew passes."""
    service, client = safety
    tokens = [client.liveliness().declare_token(KEYS.liveliness(name)) for name in ("vision", "controller",
                                                                                   "robot_sim")]
    commands = Recorder(client, KEYS.robot_command, m.RobotCommand)
    time.sleep(0.3)

    def twist(stamp, source):
        h = m.Header(stamp_ns=stamp, source_stamp_ns=source)
        return m.encode(m.Twist(header=h, frame=Frame.MIXED, angular=AngularConvention.SEED000,
                                linear=(0.01, 0.0, 0.0), rotational=(0.0, 0.0, 0.0)))

    now = time.time_ns()
    client.put(KEYS.robot_state, robot_state(np.zeros(7), now))
    client.put(KEYS.desired_twist, twist(now + 3600 * 10**9, now))
    client.put(KEYS.desired_twist, twist(now, now + 3600 * 10**9))
    assert wait_for(lambda: service.counters.get("refused.freshness") >= 2, timeout=5)
    assert "in the future" in service.core.last_refusal
    now = time.time_ns()
    client.put(KEYS.robot_state, robot_state(np.zeros(7), now))
    client.put(KEYS.desired_twist, twist(now + 20_000_000, now))
    assert wait_for(lambda: any(c.mode is m.CommandMode.CARTESIAN_VELOCITY for c in commands.snapshot()), timeout=5)
    for token in tokens:
        token.undeclare()


@pytest.mark.parametrize("over_limit", ["clamp", "refuse"])
def test_a_twist_over_one_speed_limit_is_scaled_as_a_whole_or_refused(over_limit):
    """Issue 34: the linear part at 2× its limit, the angular within: clamped, the whole twist is halved (its
    direction kept, as the law asked); refused, the reason names the part over."""
    checker = CommandChecker(SafetyLimits(over_limit=over_limit, robot_convention=AngularConvention.OMEGA), ArmKinematics(ARM))
    asked = np.array([0.0, -0.3, 0.0, 0.0, 0.0, 0.4])
    decision = checker.check_twist(Frame.MIXED, AngularConvention.OMEGA, asked, Q, dt=1.0, robot=ROBOT)
    if over_limit == "refuse":
        assert decision.refused and decision.limits == ["linear_speed"]
        assert "linear_speed: 0.300 over the limit 0.150" in decision.refusal
        return
    assert not decision.refused and "linear_speed" in decision.limits
    assert np.allclose(decision.twist, asked / 2.0)
