"""Nelson 1995's manipulability-aware tracking law against its formulas and independent computations."""
import math

import numpy as np
import pytest

from services.model import frames
from services.model.frames import PoseConfig
from services.controller.law import ServoInput
from services.controller.laws import make_law
from services.controller.tracking import joint_limit_penalty
from services.robot_sim.scene import CameraConfig
from services.model.arm import load_arm
from services.model.kinematics import ArmKinematics

ARM = load_arm("j2s7s300")

T_EC = CameraConfig().camera_in_ee.matrix()
GOAL = np.array([[-0.1666, -0.1666], [0.1666, -0.1666], [0.1666, 0.1666], [-0.1666, 0.1666]])


def inp(q=None):
    points = GOAL * 0.6 + np.array([0.03, -0.02])
    return ServoInput(t_s=1.0, points=points, depths=np.full(4, 0.45), goal_points=GOAL,
                      goal_depths=np.full(4, 0.2888), q=ARM.home.copy() if q is None else q, camera_in_ee=T_EC)


def test_without_manipulability_cost_it_is_eq_17():
    law = make_law("manipulability", None, ArmKinematics(ARM), S=0.0, q=2.0, r_translation=0.5, r_rotation=0.1)
    x = inp()
    out = law.step(x)
    o = law.options
    B = o.period_s * law._L(x)
    e = min(1.0, o.approach_rate * o.period_s) * x.error
    expected = -np.linalg.solve(o.q * B.T @ B + np.diag([0.5] * 3 + [0.1] * 3), o.q * B.T @ e)
    assert np.allclose(out.camera_twist, expected)
    J_c = law._camera_jacobian(x.q, T_EC)[0]
    assert np.allclose(J_c @ out.joint_velocities, out.camera_twist, atol=1e-9)  # resolved through J_c⁺


def test_the_step_zeroes_the_gradient_of_the_linearised_objective():
    law = make_law("manipulability", None, ArmKinematics(ARM), S=1e-6, q=2.0, r_translation=0.5, r_rotation=0.1)
    x = inp()
    u = law.step(x).camera_twist
    o = law.options
    B = o.period_s * law._L(x)
    e = min(1.0, o.approach_rate * o.period_s) * x.error
    J_c = law._camera_jacobian(x.q, T_EC)[0]
    w = law.modified_manipulability(x.q)
    g = law.gradient(x.q, np.linalg.pinv(J_c), w)
    R = np.diag([0.5] * 3 + [0.1] * 3)
    grad_F = 2 * o.q * B.T @ (e + B @ u) + 2 * R @ u - (o.S / w**2) * g
    assert np.allclose(grad_F, 0.0, atol=1e-9)
    assert np.linalg.norm(g) > 0 and np.all(g[2:] == 0)  # avoidance on vx, vy only


def test_joint_limit_penalty():
    lower, upper = ARM.model_limits()
    q = ARM.home.copy()
    mid = q.copy()
    limited = np.isfinite(lower)
    mid[limited] = (lower[limited] + upper[limited]) / 2
    assert joint_limit_penalty(mid, 220.0, ARM) == pytest.approx(1 - math.exp(-220.0 / 4**3))
    at_limit = mid.copy()
    at_limit[1] = upper[1]
    assert joint_limit_penalty(at_limit, 220.0, ARM) == 0.0
    assert 0 < joint_limit_penalty(q, 220.0, ARM) < joint_limit_penalty(mid, 220.0, ARM) < 1


def test_manipulability_does_not_depend_on_the_frame_or_the_camera_mounting(rng):
    law = make_law("manipulability", None, ArmKinematics(ARM))
    q = ARM.home + rng.normal(scale=0.2, size=7)
    J_base = law.kin.jacobian_base(q)
    R, _ = law.kin.pose(q)
    J_ee = frames.rotation_motion_transform(R.T) @ J_base
    other_mount = PoseConfig(xyz=(0.1, -0.05, 0.03), rpy_deg=(10, -20, 45)).matrix()
    J_cam = frames.motion_transform_inv(other_mount[:3, :3], other_mount[:3, 3]) @ J_ee
    dets = [np.linalg.det(J @ J.T) for J in (J_base, J_ee, J_cam)]
    assert np.allclose(dets, dets[0], rtol=1e-9)
    assert law.manipulability(q) == pytest.approx(math.sqrt(dets[0]))


def test_cartesian_gradient_matches_the_joint_gradient_through_the_resolver():
    law = make_law("manipulability", None, ArmKinematics(ARM), S=1e-6, avoidance_axes=["vx", "vy", "vz", "wx", "wy", "wz"], h=1e-6)
    q = ARM.home.copy()
    J_pinv = np.linalg.pinv(law._camera_jacobian(q, T_EC)[0])
    w = law.modified_manipulability(q)
    g = law.gradient(q, J_pinv, w)
    grad_q = np.array([(law.modified_manipulability(q + 1e-6 * np.eye(7)[i]) -
                        law.modified_manipulability(q - 1e-6 * np.eye(7)[i])) / 2e-6 for i in range(7)])
    assert np.allclose(g, law.options.period_s * J_pinv.T @ grad_q, rtol=1e-3, atol=1e-12)


def test_a_step_along_the_avoidance_velocity_increases_w():
    law = make_law("manipulability", None, ArmKinematics(ARM), S=1e-6)
    x = inp()
    tracking_only = make_law("manipulability", None, ArmKinematics(ARM), S=0.0).step(x).camera_twist
    with_avoidance = law.step(x).camera_twist
    u_avoid = with_avoidance - tracking_only
    J_pinv = np.linalg.pinv(law._camera_jacobian(x.q, T_EC)[0])
    step = J_pinv @ (u_avoid / np.linalg.norm(u_avoid)) * 1e-3
    assert law.modified_manipulability(x.q + step) > law.modified_manipulability(x.q)


def test_axes_are_validated():
    with pytest.raises(ValueError):
        make_law("manipulability", None, ArmKinematics(ARM), tracking_axes=["vx", "spin"])
    with pytest.raises(ValueError):
        make_law("manipulability", None, ArmKinematics(ARM), tracking_axes=["vx", "vy"], avoidance_axes=["vz"])
