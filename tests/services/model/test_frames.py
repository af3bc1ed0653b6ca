"""Mixed-frame math (Sensors 2022 eq. 9-12, 22-25) against independent references: finite differences of the arm's
pose through Pinocchio, Pinocchio's SE(3) exponential and logarithm, and the seed's formulas."""
import itertools
import math

import numpy as np
import pinocchio as pin
import pytest

from protocol.conventions import AngularConvention
from services.model import frames as f
from tests.helpers import PinArm, random_q
from services.model.arm import load_arm

ARM = load_arm("j2s7s300")

CONVENTIONS = list(AngularConvention)
H = 1e-6


@pytest.fixture(scope="module")
def arm():
    return PinArm()


def random_euler(rng, max_pitch_deg=80.0):
    return np.array([rng.uniform(-math.pi, math.pi), math.radians(rng.uniform(-max_pitch_deg, max_pitch_deg)),
                     rng.uniform(-math.pi, math.pi)])


def random_rotation(rng):
    return f.euler_xyz_to_matrix(random_euler(rng))


def configurations(rng, arm, n=60):
    """Random arm configurations whose end-effector Euler pitch is away from ±90° (B(Γ) invertible)."""
    out = []
    while len(out) < n:
        q = random_q(rng)
        R, _ = arm.pose(q)
        if abs(f.matrix_to_euler_xyz(R)[1]) < math.radians(80):
            out.append(q)
    return out


# ----------------------------------------------------------------------------------------- rotations


def test_euler_xyz_is_rx_ry_rz(rng):
    r, p, y = random_euler(rng)
    expected = pin.utils.rotate("x", r) @ pin.utils.rotate("y", p) @ pin.utils.rotate("z", y)
    assert np.allclose(f.euler_xyz_to_matrix((r, p, y)), expected, atol=1e-14)


def test_euler_round_trip(rng):
    for _ in range(500):
        e = random_euler(rng, 89.9)
        assert np.allclose(f.matrix_to_euler_xyz(f.euler_xyz_to_matrix(e)), e, atol=1e-9)


def test_euler_at_gimbal_lock_still_reproduces_the_rotation():
    for p in (math.pi / 2, -math.pi / 2):
        R = f.euler_xyz_to_matrix((0.3, p, 0.2))
        assert np.allclose(f.euler_xyz_to_matrix(f.matrix_to_euler_xyz(R)), R, atol=1e-12)


def test_tag_facing_camera_convention():
    # docs/contracts.md: a tag squarely facing the camera has rpy_deg [180, 0, 0] in the camera frame
    T = f.pose_from_xyz_rpy_deg([0, 0, 0.5], [180, 0, 0])
    assert np.allclose(T[:3, 2], [0, 0, -1])  # the tag's z (out of its face) points back at the camera


def test_quaternion_round_trip(rng):
    for _ in range(200):
        R = random_rotation(rng)
        q = f.matrix_to_quat_wxyz(R)
        assert q[0] >= 0 and np.allclose(f.quat_wxyz_to_matrix(q), R, atol=1e-12)
        reference = pin.Quaternion(R).coeffs()[[3, 0, 1, 2]]  # pinocchio stores (x, y, z, w)
        assert abs(np.dot(q, reference)) == pytest.approx(1.0, abs=1e-9)  # same rotation, up to sign


def test_rotation_log_matches_pinocchio(rng):
    for _ in range(200):
        R = random_rotation(rng)
        assert np.allclose(f.rotation_log(R), pin.log3(R), atol=1e-9)
    R = pin.exp3(np.array([0.0, math.pi - 1e-6, 0.0]))
    assert np.allclose(f.rotation_log(R), pin.log3(R), atol=1e-6)


# ----------------------------------------------------------------------------------------- B(Γ), eq. 12


def test_b_maps_euler_rates_to_base_angular_velocity(rng):
    for _ in range(100):
        e, rates = random_euler(rng), rng.normal(size=3)
        R_plus, R_minus = f.euler_xyz_to_matrix(e + H * rates), f.euler_xyz_to_matrix(e - H * rates)
        omega_base = pin.log3(R_plus @ R_minus.T) / (2 * H)  # Ṙ·Rᵀ = [ω_b]×
        assert np.allclose(f.euler_rates_matrix(e) @ rates, omega_base, atol=1e-6)


def test_b_matches_the_seed_formula():
    r, p = 0.3, -0.7
    B = f.euler_rates_matrix((r, p, 1.1))
    seed = np.array([[1, 0, math.sin(p)], [0, math.cos(r), -math.cos(p) * math.sin(r)],
                     [0, math.sin(r), math.cos(p) * math.cos(r)]])
    assert np.array_equal(B, seed)


def test_b_inverse(rng):
    for _ in range(200):
        e = random_euler(rng, 89.0)
        assert np.allclose(f.euler_rates_matrix_inv(e) @ f.euler_rates_matrix(e), np.eye(3), atol=1e-9)


@pytest.mark.parametrize("pitch_deg", [90.0, -90.0, 89.99, -89.999])
def test_b_inverse_refuses_pitch_near_90(pitch_deg):
    with pytest.raises(f.EulerSingularityError, match="pitch"):
        f.euler_rates_matrix_inv((0.1, math.radians(pitch_deg), 0.2))


def test_b_inverse_threshold_is_configurable():
    e = (0.0, math.radians(89.9), 0.0)
    f.euler_rates_matrix_inv(e)  # cos(89.9°) = 1.7e-3 > default 1e-3
    with pytest.raises(f.EulerSingularityError):
        f.euler_rates_matrix_inv(e, min_cos_pitch=0.01)


# ----------------------------------------------------------------------------------------- twists, eq. 22-23


def test_camera_to_ee_transform_moves_the_camera_as_commanded(rng):
    """Eq. 22: an end-effector twist X·V_c moves a camera rigidly mounted at T_ec with the camera twist V_c."""
    for _ in range(50):
        T_ec = pin.SE3(random_rotation(rng), rng.normal(size=3) * 0.1)
        V_c = rng.normal(size=6)
        V_e = f.ee_twist_from_camera(V_c, T_ec.rotation, T_ec.translation)
        T_be = pin.SE3(random_rotation(rng), rng.normal(size=3))
        dt = 1e-6
        # the end effector moves with body twist V_e; where does the camera go?
        T_bc_next = T_be * pin.exp6(pin.Motion(V_e * dt)) * T_ec
        T_bc = T_be * T_ec
        V_c_observed = pin.log6(T_bc.inverse() * T_bc_next).vector / dt
        assert np.allclose(V_c_observed, V_c, atol=1e-5)
        assert np.allclose(f.camera_twist_from_ee(V_e, T_ec.rotation, T_ec.translation), V_c, atol=1e-12)


def test_motion_transform_matches_pinocchio_action(rng):
    T = pin.SE3(random_rotation(rng), rng.normal(size=3))
    assert np.allclose(f.motion_transform(T.rotation, T.translation), T.action, atol=1e-12)
    assert np.allclose(f.motion_transform_inv(T.rotation, T.translation), T.inverse().action, atol=1e-12)


def test_eq23_re_expresses_in_the_base(rng):
    R = random_rotation(rng)
    V = rng.normal(size=6)
    assert np.allclose(f.rotation_motion_transform(R) @ V, np.concatenate([R @ V[:3], R @ V[3:]]))


# ----------------------------------------------------------------------------------------- Jacobians vs FD


def fd_pose_rates(arm, q, dq):
    """Finite differences of the end-effector pose along dq: (ṗ in base, ω in base, ω in EE, Euler rates)."""
    R_p, p_p = arm.pose(q + H * dq)
    R_m, p_m = arm.pose(q - H * dq)
    v_base = (p_p - p_m) / (2 * H)
    omega_base = pin.log3(R_p @ R_m.T) / (2 * H)
    omega_ee = pin.log3(R_m.T @ R_p) / (2 * H)
    euler_rates = (f.matrix_to_euler_xyz(R_p) - f.matrix_to_euler_xyz(R_m)) / (2 * H)
    euler_rates = (euler_rates + math.pi / H) % (2 * math.pi / H) - math.pi / H  # unwrap ±π jumps
    return v_base, omega_base, omega_ee, euler_rates


def test_base_jacobian_against_finite_differences(arm, rng):
    for q in configurations(rng, arm):
        dq = rng.normal(size=7)
        v, w_b, _, _ = fd_pose_rates(arm, q, dq)
        V = arm.jacobian_base(q) @ dq
        assert np.allclose(V[:3], v, atol=1e-6) and np.allclose(V[3:], w_b, atol=1e-6)


def test_end_effector_velocity_and_speed_against_finite_differences(arm, rng):
    for q in configurations(rng, arm):
        dq = rng.normal(size=7)
        v, _, _, _ = fd_pose_rates(arm, q, dq)
        assert np.allclose(arm.ee_velocity(q, dq), v, atol=1e-6)
        assert arm.ee_speed(q, dq) == pytest.approx(np.linalg.norm(v), abs=1e-6)


def test_euler_rate_jacobian_against_euler_angle_derivative(arm, rng):
    for q in configurations(rng, arm):
        dq = rng.normal(size=7)
        v, _, _, rates = fd_pose_rates(arm, q, dq)
        R, _ = arm.pose(q)
        Ja = f.euler_rate_jacobian(arm.jacobian_base(q), R)
        assert np.allclose(Ja @ dq, np.concatenate([v, rates]), atol=1e-6)


def test_mixed_jacobian_eq_10_11_against_b_inverse_of_ee_angular_velocity(arm, rng):
    for q in configurations(rng, arm):
        dq = rng.normal(size=7)
        v, _, w_e, _ = fd_pose_rates(arm, q, dq)
        R, _ = arm.pose(q)
        Jm = f.mixed_jacobian(arm.jacobian_base(q), R)
        B_inv = f.euler_rates_matrix_inv(f.matrix_to_euler_xyz(R))
        assert np.allclose(Jm @ dq, np.concatenate([v, B_inv @ w_e]), atol=1e-6)


def test_mixed_jacobian_equals_eq25_applied_to_the_body_jacobian(arm, rng):
    """Eq. 11 (J(Γ)·Jb) and eq. 25 (ᵐX_e·V_e) describe the same map."""
    for q in configurations(rng, arm, n=20):
        R, _ = arm.pose(q)
        Jb = arm.jacobian_base(q)
        J_ee = f.rotation_motion_transform(R.T) @ Jb
        assert np.allclose(f.mixed_jacobian(Jb, R), f.mixed_transform(R) @ J_ee, atol=1e-12)


def test_jm_is_the_euler_rate_jacobian_only_in_special_poses(arm, rng):
    q = configurations(rng, arm, n=1)[0]
    R, _ = arm.pose(q)
    Jb = arm.jacobian_base(q)
    assert not np.allclose(f.mixed_jacobian(Jb, R), f.euler_rate_jacobian(Jb, R), atol=1e-3)
    # with the end effector aligned with the base, ω_e = ω_b and the two agree
    assert np.allclose(f.mixed_jacobian(Jb, np.eye(3)), f.euler_rate_jacobian(Jb, np.eye(3)))


# ----------------------------------------------------------------------------------------- conventions


def test_every_convention_pair_round_trips(rng):
    for _ in range(50):
        R = random_rotation(rng)
        a = rng.normal(size=3)
        for src, dst in itertools.product(CONVENTIONS, CONVENTIONS):
            there = f.convert_angular(a, R, src, dst)
            assert np.allclose(f.convert_angular(there, R, dst, src), a, atol=1e-9), (src, dst)
            if src == dst:
                assert np.allclose(there, a, atol=1e-12)


def test_conventions_mean_what_they_say(arm, rng):
    for q in configurations(rng, arm, n=30):
        dq = rng.normal(size=7)
        _, w_b, w_e, rates = fd_pose_rates(arm, q, dq)
        R, _ = arm.pose(q)
        B_inv = f.euler_rates_matrix_inv(f.matrix_to_euler_xyz(R))
        assert np.allclose(f.angular_from_omega_ee(w_e, R, "omega"), w_e)
        assert np.allclose(f.angular_from_omega_ee(w_e, R, "euler_xyz_rates"), rates, atol=1e-6)
        assert np.allclose(f.angular_from_omega_ee(w_e, R, "seed000"), B_inv @ w_e, atol=1e-12)
        assert np.allclose(f.omega_ee_from_angular(rates, R, "euler_xyz_rates"), w_e, atol=1e-6)


def test_seed000_and_euler_rates_differ_except_in_special_poses(rng):
    R = random_rotation(rng)
    w = np.array([0.0, 0.0, 1.0])
    assert not np.allclose(f.angular_from_omega_ee(w, R, "seed000"), f.angular_from_omega_ee(w, R, "euler_xyz_rates"))
    assert np.allclose(f.angular_from_omega_ee(w, np.eye(3), "seed000"),
                       f.angular_from_omega_ee(w, np.eye(3), "euler_xyz_rates"))


def test_unknown_convention_is_a_clear_error():
    with pytest.raises(ValueError, match="unknown angular convention 'quat'"):
        f.angular_from_omega_ee(np.zeros(3), np.eye(3), "quat")


def test_eq25_is_the_seed000_mixed_twist(rng):
    for _ in range(50):
        R = random_rotation(rng)
        V_e = rng.normal(size=6)
        X = f.mixed_transform(R)
        assert np.allclose(X[:3, :3], R) and np.allclose(X[3:, 3:], f.euler_rates_matrix_inv(f.matrix_to_euler_xyz(R)))
        assert np.allclose(f.mixed_from_ee_twist(V_e, R, "seed000"), X @ V_e, atol=1e-12)


@pytest.mark.parametrize("convention", CONVENTIONS, ids=lambda c: c.value)
def test_camera_to_ee_to_mixed_and_back(convention, rng):
    for _ in range(50):
        T_ec = (random_rotation(rng), rng.normal(size=3) * 0.1)
        R_be = random_rotation(rng)
        V_c = rng.normal(size=6)
        V_e = f.ee_twist_from_camera(V_c, *T_ec)
        V_m = f.mixed_from_ee_twist(V_e, R_be, convention)
        assert np.allclose(f.camera_twist_from_ee(f.ee_twist_from_mixed(V_m, R_be, convention), *T_ec), V_c, atol=1e-9)
        V_b = f.base_twist_from_mixed(V_m, R_be, convention)
        assert np.allclose(V_b, f.rotation_motion_transform(R_be) @ V_e, atol=1e-9)
        assert np.allclose(f.mixed_from_base_twist(V_b, R_be, convention), V_m, atol=1e-9)


def test_mixed_twist_drives_the_arm_as_declared(arm, rng):
    """Joint velocities from Jm⁺ (eq. 13) realise the commanded seed000 mixed twist; the base-frame linear part and
    ω_e are what the frame math says they are."""
    for q in configurations(rng, arm, n=20):
        R, _ = arm.pose(q)
        V_m = rng.normal(size=6) * 0.1
        dq = np.linalg.pinv(f.mixed_jacobian(arm.jacobian_base(q), R)) @ V_m
        v, _, w_e, _ = fd_pose_rates(arm, q, dq)
        assert np.allclose(v, V_m[:3], atol=1e-6)
        assert np.allclose(w_e, f.omega_ee_from_angular(V_m[3:], R, "seed000"), atol=1e-6)


def test_home_pose_has_an_invertible_b():
    arm = PinArm()
    R, _ = arm.pose(ARM.home)
    f.mixed_transform(R)  # does not raise
