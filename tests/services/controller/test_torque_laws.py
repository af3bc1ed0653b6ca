"""The JACO thesis's torque laws and references (services/controller/torque_laws.py) against hand computations, and the
model the controllers use against MuJoCo's arm."""
import math

import mujoco
import numpy as np
import pytest

from services.controller import torque_laws as laws
from services.model import frames
from services.model.arm import load_arm

ARM6 = load_arm("j2n6s300")
ARM7 = load_arm("j2s7s300")


# ------------------------------------------------------------------------------------------------ references
def test_cubic_is_eq_5_1_with_its_derivatives_held_at_both_ends():
    x0, xf, tf = np.zeros(3), np.array([1.0, -2.0, 0.5]), 2.0
    x, dx, ddx = laws.cubic(x0, xf, tf, 0.5)
    # X(t) = X0 + 3(Xf − X0)t²/tf² − 2(Xf − X0)t³/tf³ at t = 0.5, tf = 2: 3/16 − 2/64 = 0.15625
    assert x == pytest.approx(0.15625 * xf)
    assert dx == pytest.approx((6 * 0.5 / 4 - 6 * 0.25 / 8) * xf)
    assert ddx == pytest.approx((6 / 4 - 12 * 0.5 / 8) * xf)
    assert laws.cubic(x0, xf, tf, -1.0)[0] == pytest.approx(x0)
    end = laws.cubic(x0, xf, tf, 5.0)
    assert end[0] == pytest.approx(xf) and not end[1].any() and not end[2].any()  # held at Xf after tf
    h = 1e-6
    for t in (0.3, 1.0, 1.7):
        assert (laws.cubic(x0, xf, tf, t + h)[0] - laws.cubic(x0, xf, tf, t - h)[0]) / (2 * h) == \
            pytest.approx(laws.cubic(x0, xf, tf, t)[1], abs=1e-6)
        assert (laws.cubic(x0, xf, tf, t + h)[1] - laws.cubic(x0, xf, tf, t - h)[1]) / (2 * h) == \
            pytest.approx(laws.cubic(x0, xf, tf, t)[2], abs=1e-5)


def test_eq_5_2_is_the_thesis_motion():
    """+0.100, −0.150, +0.200 m and +45°, −60°, +30° of XYZ Euler angles in 16 s (L2415-2417)."""
    d = laws.THESIS_DISPLACEMENT
    assert d[:3] == pytest.approx([0.100, -0.150, 0.200], abs=2e-4)
    assert np.degrees(d[3:]) == pytest.approx([45.0, -60.0, 30.0], abs=0.05)
    assert laws.THESIS_TF_S == 16.0


def test_pose_reference_turns_the_euler_spline_into_a_rotation_and_an_angular_velocity():
    x0 = laws.THESIS_X0
    xf = laws.THESIS_XF
    ref = laws.pose_reference(x0, xf, 16.0, 8.0)
    assert ref.x == pytest.approx(x0 + 0.5 * (xf - x0))  # halfway at tf/2
    assert ref.R == pytest.approx(frames.rot_x(ref.x[3]) @ frames.rot_y(ref.x[4]) @ frames.rot_z(ref.x[5]))
    # ω is the rotation's rate: R(t + h) ≈ exp([ω h]×) R(t)
    h = 1e-5
    after = laws.pose_reference(x0, xf, 16.0, 8.0 + h)
    assert frames.rotation_log(after.R @ ref.R.T) / h == pytest.approx(ref.omega, abs=1e-6)
    assert ref.v == pytest.approx(1.5 * (xf[:3] - x0[:3]) / 16.0)  # the spline's peak speed, 1.5·Δ/tf


def test_sinusoid_is_eq_5_3_about_the_start():
    q0 = np.array([0.1, -0.2, 0.3])
    q, dq, ddq = laws.sinusoid(q0, math.radians(20), 8.0, 2.0)  # a quarter period: the crest
    assert q == pytest.approx(q0 + math.radians(20))
    assert dq == pytest.approx(0.0, abs=1e-12)
    assert ddq == pytest.approx(-math.radians(20) * (2 * math.pi / 8) ** 2)
    assert laws.sinusoid(q0, math.radians(20), 8.0, 0.0)[1] == pytest.approx(math.radians(20) * 2 * math.pi / 8)


# ------------------------------------------------------------------------------------------------ orientation error
def test_orientation_error_is_the_angle_axis_in_the_current_frame():
    R_c = frames.rot_z(0.7) @ frames.rot_x(0.3)
    R_d = R_c @ frames.rot_y(0.2)  # 0.2 rad about the current frame's y
    theta, axis = laws.orientation_error(R_c, R_d)
    assert theta == pytest.approx(0.2) and axis == pytest.approx([0.0, 1.0, 0.0])
    # eq. 4.6 by hand on R = R_cᵀR_d
    R = R_c.T @ R_d
    assert math.acos((np.trace(R) - 1) / 2) == pytest.approx(theta)
    assert np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / (2 * math.sin(theta)) == \
        pytest.approx(axis)


def test_orientation_error_threshold_and_the_clamp_near_pi():
    R_c = np.eye(3)
    assert laws.orientation_error(R_c, frames.rot_x(0.029)) == (0.0, pytest.approx(np.zeros(3)))
    assert laws.orientation_error(R_c, frames.rot_x(0.031))[0] == pytest.approx(0.031)
    theta, axis = laws.orientation_error(R_c, frames.rot_z(math.pi - 0.01))
    assert theta == pytest.approx(math.pi - 0.03) and axis == pytest.approx([0.0, 0.0, 1.0])


def test_orientation_integral_is_eq_8_projected_on_the_current_axis():
    integral = laws.OrientationIntegral()
    x, y = np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])
    assert integral.step(0.5, x, 0.1) == pytest.approx([0.05, 0.0, 0.0])
    assert integral.step(0.5, x, 0.1) == pytest.approx([0.10, 0.0, 0.0])
    diagonal = (x + y) / math.sqrt(2)
    # (r·ν + θΔt)ν: 0.1/√2 + 0.05 along the new axis
    assert integral.step(0.5, diagonal, 0.1) == pytest.approx((0.1 / math.sqrt(2) + 0.05) * diagonal)
    before = integral.value.copy()
    assert integral.step(0.0, np.zeros(3), 0.1) == pytest.approx(before)  # no error: unchanged


# ------------------------------------------------------------------------------------------------ the model
def test_model_without_rotors_is_the_links_alone_and_with_them_mujocos_arm(rng):
    """M̂ without rotor inertia (the thesis's CAD model) is the arm's less the description's armature on the
    diagonal; with it, the model's inverse dynamics is MuJoCo's own (the emulated arm)."""
    q, dq = ARM6.home + rng.normal(scale=0.2, size=6), rng.normal(scale=0.3, size=6)
    cad, full = laws.DynamicsModel(ARM6), laws.DynamicsModel(ARM6, rotor_inertia=True, friction=True)
    assert full.mass(q) - cad.mass(q) == pytest.approx(np.diag(ARM6.armature))
    assert cad.gravity(q) == pytest.approx(full.gravity(q))
    assert ARM6.load_pinocchio().model.armature == pytest.approx(ARM6.armature)  # the shared model kept its own
    w = rng.normal(size=6)
    tau = full.mass(q) @ w + full.gravity(q) + full.coriolis(q, dq) + full.friction * dq
    model = ARM6.load_mujoco()
    data = mujoco.MjData(model)
    data.qpos[:], data.qvel[:], data.qfrc_applied[:] = q, dq, tau
    mujoco.mj_forward(model, data)
    assert data.qacc == pytest.approx(w, abs=1e-6)


def test_kinematics_is_in_the_thesis_mixed_frame(rng):
    """J_v in the base frame, J_ω in the end effector's (eq. 3.12); the pose is the DH table's."""
    model = laws.DynamicsModel(ARM6)
    q, dq = ARM6.home + rng.normal(scale=0.3, size=6), rng.normal(size=6)
    kin = model.kinematics(q)
    T = ARM6.dh_forward_kinematics(q)
    assert kin.p == pytest.approx(T[:3, 3], abs=1e-9) and kin.R == pytest.approx(T[:3, :3], abs=1e-9)
    h = 1e-6
    after = model.kinematics(q + h * dq)
    assert (after.p - kin.p) / h == pytest.approx(kin.J_v @ dq, abs=1e-5)
    assert frames.rotation_log(kin.R.T @ after.R) / h == pytest.approx(kin.J_w @ dq, abs=1e-5)


# ------------------------------------------------------------------------------------------------ the laws
def _kin(rng, arm=ARM6):
    return laws.DynamicsModel(arm).kinematics(arm.home + rng.normal(scale=0.2, size=arm.n_joints))


def test_jacobian_transpose_is_virtual_work(rng):
    """Eq. 4.1-4.3: τᵀδq = Fᵀ(J δq), the force in the base frame and the moment in the end effector's."""
    kin = _kin(rng)
    f, mu, dq = rng.normal(size=3), rng.normal(size=3), rng.normal(size=6)
    tau = laws.jacobian_transpose(kin, f, mu)
    assert tau @ dq == pytest.approx(f @ (kin.J_v @ dq) + mu @ (kin.J_w @ dq))


@pytest.mark.parametrize("arm", [ARM6, ARM7], ids=["6-dof", "7-dof"])
@pytest.mark.parametrize("weighted", [False, True], ids=["W=I", "W=M"])
def test_null_space_torque_leaves_the_position_task_alone(rng, arm, weighted):
    """Eq. 4.13: the orientation's torque is filtered so that it makes no force at the end effector's position
    (J^#ᵀ of the filtered part is zero): with W = M, no acceleration of the position task (J_v M⁻¹ τ_N = 0)."""
    model = laws.DynamicsModel(arm)
    q = arm.home + rng.normal(scale=0.2, size=arm.n_joints)
    kin = model.kinematics(q)
    W = model.mass(q) if weighted else None
    f, mu = rng.normal(size=3), rng.normal(size=3)
    tau = laws.null_space_torque(kin, f, mu, W)
    tau_n = tau - kin.J_v.T @ f
    J_sharp = laws.generalized_inverse(kin.J_v, W)
    assert kin.J_v @ J_sharp == pytest.approx(np.eye(3), abs=1e-9)
    assert J_sharp.T @ tau_n == pytest.approx(np.zeros(3), abs=1e-9)
    if weighted:
        assert kin.J_v @ np.linalg.solve(W, tau_n) == pytest.approx(np.zeros(3), abs=1e-9)
    else:
        assert J_sharp == pytest.approx(np.linalg.pinv(kin.J_v))  # eq. 4.12


def test_computed_torque_is_eq_4_17_4_18_by_hand():
    M, g = np.diag([2.0, 3.0]), np.array([1.0, -1.0])
    q, dq, q_d = np.array([0.1, 0.2]), np.array([0.5, -0.5]), np.array([0.3, 0.0])
    kp, kd = np.array([10.0, 20.0]), np.array([4.0, 5.0])
    # w = Kp(q_d − q) − Kd q̇ = [2 − 2, −4 + 2.5]; τ = M w + g
    assert laws.computed_torque(M, g, q, dq, q_d, kp, kd) == pytest.approx([1.0, -5.5])
    with_feed_forward = laws.computed_torque(M, g, q, dq, q_d, kp, kd, dq_d=np.array([1.0, 1.0]),
                                             ddq_d=np.array([0.5, 0.0]), coriolis=np.array([0.1, 0.2]))
    assert with_feed_forward == pytest.approx([1.0 + 2 * (4.0 + 0.5) + 0.1, -5.5 + 3 * 5.0 + 0.2])


def test_joint_velocity_reference_is_eq_4_20_4_22(rng):
    kin = _kin(rng)
    v, w = rng.normal(size=3), rng.normal(size=3)
    dq = laws.joint_velocity_reference(kin, v, w)
    assert kin.J_v @ dq == pytest.approx(v, abs=1e-9)  # the primary task exactly
    J_pinv = np.linalg.pinv(kin.J_v)
    assert dq == pytest.approx(J_pinv @ v + (np.eye(6) - J_pinv @ kin.J_v) @ np.linalg.pinv(kin.J_w) @ w)
    assert laws.velocity_torque(np.diag([2.0] * 6), np.ones(6), np.zeros(6), dq, np.full(6, 3.0)) == \
        pytest.approx(6.0 * dq + 1.0)


def test_task_pid_by_hand():
    """f = Kp e + Ki ∫e + Kd ė on the position; μ the same on r = θν, its integral eq. 4.8's."""
    gains = laws.TaskGains(400.0, 150.0, 25.0, 20.0, 8.0, 1.5)
    pid = laws.TaskPID(gains)
    kin = laws.Kinematics(R=np.eye(3), p=np.zeros(3), J_v=np.eye(3, 6), J_w=np.eye(3, 6, 3))
    ref = laws.PoseReference(p=np.array([0.01, 0.0, 0.0]), R=frames.rot_z(0.1), v=np.array([0.0, 0.02, 0.0]),
                             omega=np.zeros(3), x=np.zeros(6))
    dq = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.05])
    f, mu = pid.step(kin, dq, ref, 0.002)
    assert f == pytest.approx(400 * np.array([0.01, 0, 0]) + 150 * np.array([0.01, 0, 0]) * 0.002 +
                              25 * np.array([0.0, 0.02, 0.0]))
    assert mu == pytest.approx(20 * np.array([0, 0, 0.1]) + 8 * np.array([0, 0, 0.1 * 0.002]) +
                               1.5 * np.array([0, 0, -0.05]))


def test_per_joint_gains_map_the_thesis_tables_onto_the_seven_joints():
    assert laws.per_joint_gains(laws.TABLE_5_3_KP, 6) == pytest.approx(laws.TABLE_5_3_KP)
    assert laws.per_joint_gains(laws.TABLE_5_3_KP, 7) == pytest.approx([32.5, 40.5, 55, 55, 65, 70, 850])
    with pytest.raises(ValueError):
        laws.per_joint_gains(laws.TABLE_5_3_KP, 5)


def test_xf_of_eq_5_2_is_just_out_of_reach_of_the_six_dof():
    """Fact sheet §6.0: no configuration reaches Xf exactly; the nearest is a few millimetres away, the arm
    stretched at a singularity of J."""
    nearest = laws.nearest_pose(ARM6, laws.THESIS_XF, ARM6.home)
    assert not nearest.reachable
    assert 0.2e-3 < nearest.position_error_m < 4e-3 and nearest.orientation_error_deg < 1.0
    assert nearest.sigma_min < 1e-3 < nearest.sigma_min_position


def test_a_pose_the_arm_is_at_is_reachable():
    model = laws.DynamicsModel(ARM6)
    q = ARM6.home + 0.1
    kin = model.kinematics(q)
    assert laws.nearest_pose(ARM6, laws.pose_vector(kin.R, kin.p), ARM6.home, starts=2).reachable
