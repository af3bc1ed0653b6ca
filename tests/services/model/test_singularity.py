"""A person drives toward a wrist singularity: safety slows any source's twist as the Jacobian's condition grows and
stops it before the bound (services/model/singularity.py), on both arms; driving away is never slowed."""
import numpy as np
import pytest

from protocol import messages as m
from services.model import frames
from services.model.arm import load_arm
from services.model.kinematics import ArmKinematics, normalized_jacobian
from services.model.singularity import (Braking, SingularityBounds, angle_to_bound, braking_scale, condition_gradient,
                                        condition_number, raises_condition, singularity_scale)
from protocol.conventions import AngularConvention, Frame
from services.model.limits import arm_limits
from services.safety.checks import CommandChecker, SafetyLimits
from services.safety.sources import SourceRegistry, default_sources
from services.safety.core import SafetyCore, Send
from tests.helpers import ARM_DECLARED

S = 1_000_000_000
PERIOD_NS = 10_000_000


def robot_state(arm, kin, q, dq, stamp_ns):
    R, p = kin.pose(q)
    return m.RobotState(**{**ARM_DECLARED, "arm": arm.name, "arm_digest": arm.digest}, header=m.Header(stamp_ns=stamp_ns),
                        q=list(q), dq=list(dq), tau=[0.0] * arm.n_joints, pose=m.KinovaPose(**frames.kinova_pose(R, p)),
                        control_mode=m.ControlMode.CARTESIAN_VELOCITY)


def kappa(kin, q):
    return condition_number(normalized_jacobian(kin.jacobian_base(q), kin.characteristic_length_m))


def drive(arm_name, start, omega_ee_of, seconds):
    """A wrist jog at ``omega_ee_of(q)`` (rad/s about the hand's axes) for ``seconds``, through safety as shipped, the
    arm following what safety sends exactly (its joints by the Jacobian's pseudo-inverse); (κ, the speed the arm
    was given, what safety said limited it) at each cycle, and the arm's last q."""
    arm = load_arm(arm_name)
    kin = ArmKinematics(arm)
    safety = SafetyCore(SafetyLimits(), upstream=[], robots=["robot_sim"], rate_hz=100.0, lockstep=False)
    safety.liveliness("robot_sim", True)
    q, dq, t = np.array(start, dtype=float), np.zeros(arm.n_joints), 10 * S
    log = []
    for i in range(int(seconds * 100)):
        safety.state(robot_state(arm, kin, q, dq, t), t)
        mode, motion = omega_ee_of(kin, q)
        jog = m.Jog(header=m.Header(seq=i + 1, stamp_ns=t, source_stamp_ns=t), mode=mode, deadman=True,
                    **{"linear" if mode is m.JogMode.TRANSLATION else "angular": tuple(float(w) for w in motion)})
        sent = [a.command for a in safety.jog(jog, t, t) if isinstance(a, Send)][-1]
        assert sent.mode is m.CommandMode.CARTESIAN_VELOCITY, sent.reason
        R, _, J = kin.pose_and_jacobian(q)
        base = frames.base_twist_from_mixed(np.array([*sent.twist.linear, *sent.twist.rotational]), R,
                                            sent.twist.angular)
        dq = np.linalg.pinv(J) @ base
        log.append((kappa(kin, q), float(np.linalg.norm(base[3:] if mode is m.JogMode.WRIST else base[:3])),
                    list(safety.active_limits)))
        q = q + dq * PERIOD_NS * 1e-9
        t += PERIOD_NS
    return log, q


def turning_the_wrist(joint, sign):
    """A person's wrist jog (0.3 rad/s about the hand's axes): the hand's rotation that ``joint`` alone would make,
    turning it by ``sign`` (toward its singular angle)."""
    def omega_ee(kin, q):
        R, _, J = kin.pose_and_jacobian(q)
        omega = R.T @ J[3:, joint] * sign
        return m.JogMode.WRIST, 0.3 * omega / np.linalg.norm(omega)
    return omega_ee


def reaching_out(sign):
    """A person's translation jog (0.1 m/s) straight out from the base (``sign`` -1: back in), horizontally."""
    def linear(kin, q):
        _, p = kin.pose(q)
        out = np.array([p[0], p[1], 0.0])
        return m.JogMode.TRANSLATION, 0.1 * sign * out / np.linalg.norm(out)
    return linear


def wrist_start(arm, joint, degrees):
    q = arm.home.copy()
    q[joint] = np.radians(degrees)
    return q


#: (the arm, where it starts, the person's jog toward a singularity, and back): reaching straight out (the elbow
#: stretched: no arm goes round it), and the j2n6s300's wrist turned toward its 5th joint's singular angle (about
#: -177°; the j2s7s300's redundancy takes its wrist round its own, as the last test shows)
DRIVES = {
    "j2s7s300 reaching out": ("j2s7s300", lambda arm: arm.home.copy(), reaching_out(1.0), reaching_out(-1.0)),
    "j2n6s300 reaching out": ("j2n6s300", lambda arm: arm.home.copy(), reaching_out(1.0), reaching_out(-1.0)),
    "j2n6s300 wrist": ("j2n6s300", lambda arm: wrist_start(arm, 4, -137.0), turning_the_wrist(4, -1.0),
                       turning_the_wrist(4, 1.0)),
}


@pytest.mark.parametrize("case", sorted(DRIVES))
def test_a_jog_toward_a_singularity_is_slowed_and_stopped_before_it_and_driving_back_is_not(case):
    arm_name, start_of, toward, back = DRIVES[case]
    arm = load_arm(arm_name)
    start = start_of(arm)
    bounds = SingularityBounds()
    assert kappa(ArmKinematics(arm), start) < bounds.slow_from  # it starts where nothing is slowed
    log, q = drive(arm_name, start, toward, seconds=8.0)
    conditions = np.array([c for c, _, _ in log])
    speeds = np.array([s for _, s, _ in log])
    full = speeds.max()
    # slowed between the bounds: never faster than the rule's fraction of its full speed (and the arm's
    # acceleration limit then brakes it to that), and stopped before the bound
    band = conditions > bounds.slow_from
    assert band.any(), "it never drove near a singularity"
    allowed = 1.0 - (conditions - bounds.slow_from) / (bounds.stop_at - bounds.slow_from)
    assert np.all(speeds[1:][band[1:]] <= np.maximum(allowed[:-1][band[1:]], 0.0) * full * 1.05 + 1e-3)
    assert conditions.max() < bounds.stop_at * 1.01 and speeds[-1] < 1e-3
    assert any("singularity" in limits for _, _, limits in log)
    # the person drives back out: at once, never slowed by the rule (near the singularity the joints' speed limit
    # may still bound the hand's speed a little, as anywhere the arm needs fast joints)
    out, _ = drive(arm_name, q, back, seconds=1.0)
    assert max(s for _, s, _ in out) > 0.8 * full
    assert not any(name.startswith("singularity") for _, _, limits in out for name in limits)


def test_a_redundant_arm_takes_its_wrist_round_its_singularity_and_is_never_driven_into_it():
    arm = load_arm("j2s7s300")
    log, _ = drive("j2s7s300", wrist_start(arm, 5, 200.0), turning_the_wrist(5, -1.0), seconds=5.0)
    conditions = np.array([c for c, _, _ in log])
    assert conditions.max() < SingularityBounds().stop_at


def wrist_toward_its_singularity(degrees: float):
    """The j2n6s300 with its 5th joint at ``degrees``, and a wrist twist (base frame) that joint alone would make
    turning toward its singular angle: (kinematics, q, J, the normalized J, κ, the twist)."""
    kin = ArmKinematics(load_arm("j2n6s300"))
    q = wrist_start(kin.arm, 4, degrees)
    _, _, J = kin.pose_and_jacobian(q)
    Jn = normalized_jacobian(J, kin.characteristic_length_m)
    omega = J[3:, 4] * -1.0
    return kin, q, J, Jn, condition_number(Jn), np.concatenate([np.zeros(3), omega / np.linalg.norm(omega)])


def test_the_rule_slows_only_what_raises_the_condition_and_ramps_linearly_between_its_bounds():
    kin, q, J, Jn, condition, twist = wrist_toward_its_singularity(-160.0)
    assert raises_condition(kin, q, Jn, twist, condition) and not raises_condition(kin, q, Jn, -twist, condition)
    bounds = SingularityBounds(slow_from=condition / 2, stop_at=condition * 2)
    near = singularity_scale(kin, q, J, twist, bounds)
    assert near.toward and near.factor == pytest.approx(1 - (condition / 2) / (condition * 1.5))
    assert singularity_scale(kin, q, J, -twist, bounds).factor == 1.0
    assert singularity_scale(kin, q, J, twist, SingularityBounds(slow_from=1.0, stop_at=condition * 0.9)).factor == 0.0
    assert singularity_scale(kin, q, J, np.zeros(6), bounds).factor == 1.0
    with pytest.raises(ValueError):
        SingularityBounds(slow_from=40.0, stop_at=30.0)


def test_the_angle_left_follows_one_over_the_distance_and_never_overestimates_it():
    # κ = c/d: from κ and its gradient the angle left to the bound is exact
    c, d, bound = 2.0, 0.05, 80.0
    condition, gradient = c / d, c / d**2
    assert angle_to_bound(condition, gradient, bound) == pytest.approx(d - c / bound)
    # a straight line through the gradient would leave more (bound/κ times as much)
    assert angle_to_bound(condition, gradient, bound) < (bound - condition) / gradient
    assert angle_to_bound(bound, gradient, bound) == 0.0 and angle_to_bound(90.0, gradient, bound) == 0.0
    assert angle_to_bound(condition, 0.0, bound) == float("inf")


def test_the_braking_scale_stops_the_motion_within_the_angle_left():
    omega, T, lag = 0.5, 0.2, 0.03
    for left in (1e-4, 1e-3, 0.01, 0.02):
        s = braking_scale(omega, T, lag, left)
        assert 0.0 < s <= 1.0
        travelled = s * omega * lag + s * omega * s * T / 2.0  # on at s·ω for the lag, then a ramp to 0 in s·T
        assert travelled == pytest.approx(left) or (s == 1.0 and travelled < left)
    assert braking_scale(omega, T, lag, 0.0) == 0.0
    assert braking_scale(omega, T, lag, 10.0) == 1.0
    assert braking_scale(omega, 0.0, lag, 1e-3) == pytest.approx(1e-3 / (omega * lag))


def test_near_the_bound_the_braking_rule_slows_more_than_the_ramp_and_the_joints_limit_binds():
    kin, q, J, Jn, condition, twist = wrist_toward_its_singularity(-172.0)
    twist = twist * 0.3
    bounds = SingularityBounds(slow_from=condition * 0.99, stop_at=condition * 1.1)
    ramp = singularity_scale(kin, q, J, twist, bounds)
    gradient = condition_gradient(kin, q, Jn, twist, condition)
    assert gradient > 0.0
    braking = Braking(linear_mps2=0.64, angular_rps2=2.75, joint_rps2=np.radians(200.0), lag_s=0.03)
    braked = singularity_scale(kin, q, J, twist, bounds, braking)
    assert braked.toward and 0.0 < braked.factor < ramp.factor
    dq = np.linalg.pinv(J) @ twist
    assert braking.time_to_stop(twist, dq) == pytest.approx(np.max(np.abs(dq)) / np.radians(200.0))
    # far from the bound, braking takes nothing off the ramp
    gentle = SingularityBounds(slow_from=condition * 0.5, stop_at=condition * 50)
    assert singularity_scale(kin, q, J, twist, gentle, braking).factor == singularity_scale(kin, q, J, twist,
                                                                                            gentle).factor


def test_the_servos_twists_are_left_to_the_robot_near_a_singularity_and_a_persons_are_stopped():
    """Each source's rule (services/safety/sources.py NearSingularity): the visual servo, a closed loop that a stop
    would hold at the bound, is left to the robot's DSP as the seed papers' arm ran; the person's stick is stopped."""
    registry = SourceRegistry(default_sources())
    assert not registry.stops_near_singularity("controller/servo")
    assert registry.stops_near_singularity("jog/stick") and registry.stops_near_singularity("jog/ros-joy")
    kin, q, J, _, condition, twist = wrist_toward_its_singularity(-178.0)
    assert condition > SingularityBounds().stop_at
    R, _ = kin.pose(q)
    mixed = frames.mixed_from_base_twist(twist * 0.3, R, AngularConvention.OMEGA)
    checker = CommandChecker(SafetyLimits(robot_convention=AngularConvention.OMEGA), kin)
    robot = arm_limits(kin.arm)
    stopped = checker.check_twist(Frame.MIXED, AngularConvention.OMEGA, mixed, q, 0.01, robot)
    assert "singularity_stop" in stopped.limits and not np.any(stopped.twist)
    checker.reset_motion()
    left = checker.check_twist(Frame.MIXED, AngularConvention.OMEGA, mixed, q, 0.01, robot, near_singularity=False)
    assert not any(name.startswith("singularity") for name in left.limits) and np.any(left.twist)
