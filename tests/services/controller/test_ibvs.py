"""Sensors 2022 IBVS formulas and laws against independent computations."""
import math

import numpy as np
import pinocchio as pin
import pytest

from protocol.conventions import AngularConvention, DepthSource, ErrorRateSource
from services.model import frames
from services.model.frames import PoseConfig
from services.model.kinematics import ArmKinematics
from services.controller import ibvs
from services.controller.law import Gains, LawConfig, ServoInput
from services.controller.laws import make_law
from tests.helpers import iterations_in_a_late_loop, tag_corners_seen
from services.model.arm import load_arm

ARM = load_arm("j2s7s300")

CAMERA_IN_EE = PoseConfig(xyz=(0.065, 0.0, -0.02), rpy_deg=(0.0, 0.0, 90.0)).matrix()


def project(P):
    return P[:, :2] / P[:, 2:3]


def test_interaction_matrix_against_finite_differences(rng):
    for _ in range(20):
        P = np.column_stack([rng.uniform(-0.2, 0.2, 4), rng.uniform(-0.2, 0.2, 4), rng.uniform(0.3, 1.0, 4)])
        Vc = rng.normal(size=6)
        L = ibvs.interaction_matrix(project(P), P[:, 2])
        # the camera moves with Vc (its own frame): a static point moves by −v − ω × P in the camera frame
        h = 1e-6
        P_dot = -Vc[:3] - np.cross(Vc[3:], P)
        s_dot = (project(P + h * P_dot) - project(P - h * P_dot)) / (2 * h)
        assert np.allclose(L @ Vc, s_dot.reshape(-1), atol=1e-6)


def test_interaction_matrix_validates_depths():
    with pytest.raises(ValueError):
        ibvs.interaction_matrix([[0, 0]], [0.0])
    with pytest.raises(ValueError):
        ibvs.interaction_matrix([[0, 0], [1, 1]], [0.5])


def test_depth_sources():
    pts, depths = np.array([[0.1, 0.1], [-0.1, 0.1]]), np.array([0.5, 0.6])
    goal, goal_depths = np.array([[0.2, 0.2], [-0.2, 0.2]]), np.array([0.3, 0.3])
    cur = ibvs.interaction_matrix(pts, depths)
    des = ibvs.interaction_matrix(goal, goal_depths)
    assert np.allclose(ibvs.approximate_interaction_matrix(pts, depths, goal, goal_depths, "current"), cur)
    assert np.allclose(ibvs.approximate_interaction_matrix(pts, depths, goal, goal_depths, DepthSource.GOAL), des)
    assert np.allclose(ibvs.approximate_interaction_matrix(pts, depths, goal, goal_depths, "mean"), (cur + des) / 2)


def test_adaptive_gain_at_zero_infinity_and_its_slope():
    l0, linf, slope = 4.5, 0.5, 30.0
    assert ibvs.adaptive_gain(0.0, l0, linf, slope) == pytest.approx(l0)
    assert ibvs.adaptive_gain(1e6, l0, linf, slope) == pytest.approx(linf)
    h = 1e-7
    assert (ibvs.adaptive_gain(h, l0, linf, slope) - l0) / h == pytest.approx(-slope, rel=1e-4)
    values = [ibvs.adaptive_gain(x, l0, linf, slope) for x in np.linspace(0, 1, 50)]
    assert np.all(np.diff(values) < 0)
    with pytest.raises(ValueError):
        ibvs.adaptive_gain(0.1, 0.5, 4.5, 30.0)


def test_error_rate_filter():
    rate = ibvs.ErrorRate(tau_s=0.0)
    assert np.all(rate.update([0.0, 1.0], 1.0) == 0)
    assert np.allclose(rate.update([0.1, 0.8], 1.1), [1.0, -2.0])
    smooth = ibvs.ErrorRate(tau_s=0.05)
    for k in range(200):
        value = smooth.update([0.5 * k / 30], k / 30)
    assert value == pytest.approx([0.5])
    smooth.update([1.0], 200 / 30 + 5.0)  # a long gap restarts the estimate
    assert smooth.value == pytest.approx([0.0])


def test_pd_law_decays_the_error_exponentially_when_it_can():
    rng = np.random.default_rng(1)
    P = np.column_stack([rng.uniform(-0.2, 0.2, 4), rng.uniform(-0.2, 0.2, 4), rng.uniform(0.3, 1.0, 4)])
    L = ibvs.interaction_matrix(project(P), P[:, 2])
    e = L @ rng.normal(size=6)  # an error the camera can cancel
    Vc = ibvs.pd_camera_twist(L, e, 2.0, 0.0)
    assert np.allclose(L @ Vc, -2.0 * e)
    e_dot = rng.normal(size=8)
    Vc_pd = ibvs.pd_camera_twist(L, e, 2.0, 0.5, e_dot)
    assert np.allclose(Vc_pd, -np.linalg.pinv(L) @ (2.0 * e + 0.5 * e_dot))


def test_camera_motion_error_rate_is_the_features_rate_along_a_joint_motion(rng):
    """L̂·J_c·q̇ (eq. 21's ė due to the camera's motion) against the corners' own change when the joints move."""
    kin = ArmKinematics(ARM)
    tag = PoseConfig(xyz=(0.03, -0.02, 0.45), rpy_deg=(175.0, 4.0, 15.0)).matrix()
    tag_in_base = frames.homogeneous(*kin.pose(ARM.home)) @ CAMERA_IN_EE @ tag
    law = make_law("adaptive-pd-joint", None, ArmKinematics(ARM))
    for _ in range(5):
        q = ARM.home + rng.uniform(-0.05, 0.05, ARM.n_joints)
        dq = rng.normal(scale=0.2, size=ARM.n_joints)
        points, depths = tag_corners_seen(q, tag_in_base, CAMERA_IN_EE, kin)
        L = ibvs.interaction_matrix(points, depths)
        J_c = law._camera_jacobian(q, CAMERA_IN_EE)[0]
        h = 1e-6
        s_dot = (tag_corners_seen(q + h * dq, tag_in_base, CAMERA_IN_EE, kin)[0]
                 - tag_corners_seen(q - h * dq, tag_in_base, CAMERA_IN_EE, kin)[0]) / (2 * h)
        assert np.allclose(ibvs.camera_motion_error_rate(L, J_c, dq), s_dot.reshape(-1), atol=1e-6)


@pytest.mark.parametrize("name", ["adaptive-pd-mixed", "adaptive-pd-joint"])
def test_pd_laws_take_e_dot_from_the_measured_joint_velocities(name, rng):
    """With camera_motion the derivative term sees the arm's joint velocities, not the frames' difference: an arm
    at rest gives the proportional law's output whatever the previous frame was; frame_difference does not."""
    q = ARM.home.copy()
    first, second = servo_input(q, rng), servo_input(q, rng)
    second.t_s = first.t_s + 1 / 30
    outputs = {}
    for source in ErrorRateSource:
        for kd in (0.0, 0.55):
            law = make_law(name, LawConfig(gains=Gains(kd=kd), error_rate=source), ArmKinematics(ARM))
            first.dq = second.dq = np.zeros(ARM.n_joints)
            law.step(first)
            out = law.step(second)
            outputs[source, kd] = out.twist if out.twist is not None else out.joint_velocities
    assert np.allclose(outputs[ErrorRateSource.CAMERA_MOTION, 0.55], outputs[ErrorRateSource.CAMERA_MOTION, 0.0])
    assert not np.allclose(outputs[ErrorRateSource.FRAME_DIFFERENCE, 0.55], outputs[ErrorRateSource.FRAME_DIFFERENCE, 0.0])


def test_features_after_camera_motion_are_the_projection_from_the_moved_camera(rng):
    """Points seen from camera pose A, carried to pose B, against projecting the same 3-D points from B."""
    for _ in range(10):
        P_a = np.column_stack([rng.uniform(-0.2, 0.2, 4), rng.uniform(-0.2, 0.2, 4), rng.uniform(0.3, 1.0, 4)])
        R = frames.quat_wxyz_to_matrix(frames.matrix_to_quat_wxyz(
            PoseConfig(xyz=(0, 0, 0), rpy_deg=tuple(rng.uniform(-8, 8, 3))).matrix()[:3, :3]))
        b_in_a = frames.homogeneous(R, rng.uniform(-0.03, 0.03, 3))
        points, depths = ibvs.features_after_camera_motion(project(P_a), P_a[:, 2], b_in_a)
        P_b = (np.linalg.inv(b_in_a) @ np.column_stack([P_a, np.ones(4)]).T).T[:, :3]
        assert np.allclose(points, project(P_b), atol=1e-12) and np.allclose(depths, P_b[:, 2], atol=1e-12)
    same, depth = ibvs.features_after_camera_motion(project(P_a), P_a[:, 2], np.eye(4))
    assert np.allclose(same, project(P_a)) and np.allclose(depth, P_a[:, 2])


def late_uneven_loop(source: ErrorRateSource, seed: int) -> int | None:
    """Iterations for adaptive-pd-joint to bring ‖e‖ under 5e-5 when frames come 30-100 ms apart, each command
    takes effect 100-200 ms after its frame (a loaded host's pipeline) and the corners carry 2e-5 of noise, as a
    realtime stack on two busy cores sees them; None if it does not."""
    law = make_law("adaptive-pd-joint", LawConfig(error_rate=source, joint_limit_gain=0.0), ArmKinematics(ARM))
    tag = PoseConfig(xyz=(0.03, -0.02, 0.42), rpy_deg=(175.0, 4.0, 15.0)).matrix()
    return iterations_in_a_late_loop(law, tag, CAMERA_IN_EE, seed=seed, command_delay_s=(0.1, 0.2), noise=2e-5,
                                     frame_gaps={0.03: 0.45, 0.04: 0.35, 0.07: 0.15, 0.1: 0.05})


def test_camera_motion_e_dot_keeps_a_late_uneven_loop_converging_steadily():
    """The realtime failure of the frame-difference ė (a filtered derivative lagging a late pipeline: 93-258
    iterations over three runs of easy.yaml), reproduced without services and removed by camera_motion."""
    seeds = range(4)
    camera = [late_uneven_loop(ErrorRateSource.CAMERA_MOTION, seed) for seed in seeds]
    frames_differenced = [late_uneven_loop(ErrorRateSource.FRAME_DIFFERENCE, seed) for seed in seeds]
    assert all(n is not None for n in camera), camera
    assert max(camera) < 1.3 * min(camera), camera
    assert max(camera) < min(n or 10**6 for n in frames_differenced), (camera, frames_differenced)


def servo_input(q, rng):
    """Features of a tag ~0.5 m in front of the camera at configuration q."""
    P = np.column_stack([rng.uniform(-0.1, 0.1, 4), rng.uniform(-0.1, 0.1, 4), rng.uniform(0.4, 0.6, 4)])
    goal = np.array([[-0.1666, -0.1666], [0.1666, -0.1666], [0.1666, 0.1666], [-0.1666, 0.1666]])
    return ServoInput(t_s=1.0, points=project(P), depths=P[:, 2], goal_points=goal, goal_depths=np.full(4, 0.2888),
                      q=q, camera_in_ee=CAMERA_IN_EE)


def camera_twist_achieved(kin, q, dq):
    """Camera twist (camera frame) from finite differences of the camera pose when the joints move by dq."""
    h = 1e-6
    T = pin.SE3(CAMERA_IN_EE[:3, :3], CAMERA_IN_EE[:3, 3])
    poses = []
    for sign in (-1, 1):
        R, p = kin.pose(q + sign * h * dq)
        poses.append(pin.SE3(R, p) * T)
    return pin.log6(poses[0].inverse() * poses[1]).vector / (2 * h)


@pytest.mark.parametrize("convention", list(AngularConvention), ids=lambda c: c.value)
def test_mixed_twist_moves_the_camera_with_the_camera_twist(convention, rng):
    """The proposed law's output, executed by an arm that reads ``convention``, moves the camera exactly with
    the camera twist of eq. 21 (through eq. 22-25 and the frame math)."""
    kin = ArmKinematics(ARM)
    law = make_law("adaptive-pd-mixed", LawConfig(robot_convention=convention), kin)
    inp = servo_input(ARM.home, rng)
    out = law.step(inp)
    R, _, J = kin.pose_and_jacobian(inp.q)
    # the arm realises the mixed twist: base twist from the declared convention, joint velocities through J⁺
    dq = np.linalg.pinv(J) @ frames.base_twist_from_mixed(out.twist, R, convention)
    assert np.allclose(camera_twist_achieved(kin, inp.q, dq), out.camera_twist, atol=1e-5)
    assert out.gain == pytest.approx(ibvs.adaptive_gain(np.max(np.abs(inp.error)), 4.5, 0.5, 30.0))


def test_ee_frame_law_sends_the_end_effector_twist_as_if_mixed(rng):
    kin = ArmKinematics(ARM)
    inp = servo_input(ARM.home, rng)
    mixed = make_law("adaptive-pd-mixed", None, kin).step(inp)
    wrong = make_law("ee-frame", None, kin).step(inp)
    V_e = frames.ee_twist_from_camera(wrong.camera_twist, CAMERA_IN_EE[:3, :3], CAMERA_IN_EE[:3, 3])
    assert np.allclose(wrong.twist, V_e)
    assert not np.allclose(wrong.twist, mixed.twist, atol=1e-3)


@pytest.mark.parametrize("name", ["p-joint", "adaptive-p-joint", "adaptive-pd-joint"])
def test_joint_laws_drive_the_features_as_eq_17_18(name, rng):
    kin = ArmKinematics(ARM)
    config = LawConfig(gains=Gains(lambda_=1.2, lambda0=2.8, lambda_inf=0.3, slope0=30.0, kd=0.25),
                       joint_limit_gain=0.0)
    law = make_law(name, config, kin)
    inp = servo_input(ARM.home, rng)
    out = law.step(inp)
    L = ibvs.interaction_matrix(inp.points, inp.depths)
    s_dot = L @ camera_twist_achieved(kin, inp.q, out.joint_velocities)
    Lc = L @ law._camera_jacobian(inp.q, CAMERA_IN_EE)[0]
    expected = -Lc @ np.linalg.pinv(Lc) @ (out.gain * inp.error)  # first sample: ė = 0
    assert np.allclose(s_dot, expected, atol=1e-6)
    assert out.gain == pytest.approx(1.2 if name == "p-joint" else
                                     ibvs.adaptive_gain(np.max(np.abs(inp.error)), 2.8, 0.3, 30.0))


def test_joint_limit_task_stays_in_the_null_space(rng):
    kin = ArmKinematics(ARM)
    inp = servo_input(ARM.home, rng)
    with_xi = make_law("p-joint", LawConfig(joint_limit_gain=2.0), kin).step(inp)
    without = make_law("p-joint", LawConfig(joint_limit_gain=0.0), kin).step(inp)
    assert not np.allclose(with_xi.joint_velocities, without.joint_velocities)
    L = ibvs.interaction_matrix(inp.points, inp.depths)
    J_c = make_law("p-joint", None, kin)._camera_jacobian(inp.q, CAMERA_IN_EE)[0]
    assert np.allclose(L @ J_c @ with_xi.joint_velocities, L @ J_c @ without.joint_velocities, atol=1e-9)


def test_mixed_jacobian_joint_law_realises_the_seed000_twist(rng):
    kin = ArmKinematics(ARM)
    inp = servo_input(ARM.home, rng)
    out = make_law("mixed-jacobian-joint", LawConfig(joint_limit_gain=0.0), kin).step(inp)
    assert np.allclose(camera_twist_achieved(kin, inp.q, out.joint_velocities), out.camera_twist, atol=1e-5)


def test_unknown_law_is_refused():
    with pytest.raises(ValueError, match="unknown law 'pid'"):
        make_law("pid", None, ArmKinematics(ARM))
    assert math.isfinite(Gains().lambda0)


def test_target_motion_term_reduces_the_tracking_lag():
    """A target moving at constant velocity: estimating ∂ê/∂t (eq. 19/21) shrinks the steady tracking error."""
    from tests.kinematic_loop import KinematicLoop

    T_be = ARM.dh_forward_kinematics(ARM.home)
    tag = PoseConfig(xyz=(0.0, 0.0, 0.2888), rpy_deg=(180.0, 0.0, 0.0)).matrix()
    goal = np.array([[-0.1666, -0.1666], [0.1666, -0.1666], [0.1666, 0.1666], [-0.1666, 0.1666]])
    errors = {}
    for compensate in (False, True):
        law = make_law("adaptive-pd-joint", LawConfig(target_motion=compensate, joint_limit_gain=0.0),
                       ArmKinematics(ARM))
        loop = KinematicLoop(law, T_be @ CAMERA_IN_EE @ tag, CAMERA_IN_EE, ARM.home, goal, np.full(4, 0.2888),
                             tag_velocity=np.array([0.02, 0.0, 0.0]))
        steps = loop.run(150)
        errors[compensate] = np.mean([s.error_norm for s in steps[100:]])
    assert errors[True] < 0.5 * errors[False]


def many_points_input(q, rng, n=12):
    """Features of n points of a plane ~0.5 m ahead at configuration q, their goal the same points at 0.3 m."""
    P = np.column_stack([rng.uniform(-0.1, 0.1, n), rng.uniform(-0.1, 0.1, n), rng.uniform(0.45, 0.55, n)])
    goal = P * np.array([1.0, 1.0, 0.6]) + np.array([0.01, -0.01, 0.0])
    return ServoInput(t_s=1.0, points=project(P), depths=P[:, 2], goal_points=project(goal),
                      goal_depths=goal[:, 2], q=q, camera_in_ee=CAMERA_IN_EE, ids=np.arange(100, 100 + n))


@pytest.mark.parametrize("name", ["adaptive-pd-mixed", "adaptive-pd-joint", "p-joint"])
def test_weights_of_one_are_the_unweighted_law_to_the_bit(name, rng):
    q = ARM.home.copy()
    inp = many_points_input(q, rng)
    plain = make_law(name, LawConfig(), ArmKinematics(ARM)).step(inp)
    weighted = make_law(name, LawConfig(), ArmKinematics(ARM)).step(
        ServoInput(**{**inp.__dict__, "weights": np.ones(len(inp.points))}))
    for a, b in ((plain.twist, weighted.twist), (plain.joint_velocities, weighted.joint_velocities)):
        assert (a is None and b is None) or np.array_equal(a, b)


@pytest.mark.parametrize("name", ["adaptive-pd-mixed", "adaptive-pd-joint"])
def test_a_point_fading_out_changes_the_command_gradually_to_the_law_without_it(name, rng):
    """Weighted IBVS (D·L̂, D·e): a point's weight going from 1 to 0 moves the command continuously from the law with
    it to the law without it, so that a point leaving the set makes no jump."""
    q = ARM.home.copy()
    inp = many_points_input(q, rng)
    n = len(inp.points)

    def command(weight_of_last: float, keep_last: bool = True) -> np.ndarray:
        rows = slice(None) if keep_last else slice(0, n - 1)
        weights = np.ones(n)
        weights[-1] = weight_of_last
        given = ServoInput(t_s=1.0, points=inp.points[rows], depths=inp.depths[rows], goal_points=inp.goal_points[rows],
                           goal_depths=inp.goal_depths[rows], q=q, camera_in_ee=CAMERA_IN_EE, ids=inp.ids[rows],
                           weights=weights[rows])
        out = make_law(name, LawConfig(), ArmKinematics(ARM)).step(given)
        return out.twist if out.twist is not None else out.joint_velocities

    without = command(1.0, keep_last=False)
    fade = [command(w) for w in np.linspace(1.0, 0.0, 11)]
    assert np.allclose(fade[-1], without, atol=1e-12)
    steps = [np.linalg.norm(b - a) for a, b in zip(fade, fade[1:])]
    assert max(steps) < 0.25 * np.linalg.norm(fade[0] - without) + 1e-12  # no step takes a large share at once


def test_the_error_rate_restarts_when_the_points_change():
    rate = ibvs.ErrorRate(tau_s=0.0)
    rate.update(np.zeros(4), 0.0, ids=[1, 2])
    assert np.allclose(rate.update(np.ones(4), 0.1, ids=[1, 2]), 10.0)
    # the same number of values, but other points: a difference between them would mean nothing
    assert np.allclose(rate.update(np.full(4, 5.0), 0.2, ids=[1, 3]), 0.0)
