"""Rotation, twist and mixed-frame math of Sensors 2022 (eq. 9-12, 22-25), as plain numpy functions.

Notation: ``R_be`` is the rotation of the end-effector frame in the base frame (the seed's ᵇₑR), so a vector
expressed in the end-effector frame maps to the base frame as ``v_b = R_be @ v_e``. Twists are 6-vectors
(linear; angular). Γ = (r, p, y) are XYZ Euler angles: R = Rx(r)·Ry(p)·Rz(y), as GetCartesianPosition reports.

The three angular conventions (protocol.conventions.AngularConvention) of the rotational part of a mixed twist:

* ``omega``:            ω_e, the angular velocity expressed in the end-effector frame;
* ``euler_xyz_rates``:  Γ̇ = B(Γ)⁻¹·ω_b = B(Γ)⁻¹·R_be·ω_e, the true rate of the reported Euler angles
                        (B of eq. 12 maps Euler rates to the base-frame angular velocity);
* ``seed000``:          B(Γ)⁻¹·ω_e, exactly what eq. 11, 24 and 25 compute.
"""
from __future__ import annotations

import math

import numpy as np

from protocol.conventions import AngularConvention
from protocol.messages import Pose
from services.runtime.config import ConfigStruct

#: |cos(pitch)| below this makes B(Γ) numerically singular (pitch within ≈0.06° of ±90°).
MIN_COS_PITCH = 1e-3


class EulerSingularityError(ArithmeticError):
    """B(Γ) is not invertible: the XYZ Euler pitch is at (or too near) ±90°."""


# --------------------------------------------------------------------------------------------- rotations


def rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def euler_xyz_to_matrix(euler) -> np.ndarray:
    """R = Rx(r)·Ry(p)·Rz(y)."""
    r, p, y = (float(v) for v in euler)
    return rot_x(r) @ rot_y(p) @ rot_z(y)


def kinova_pose(R, p) -> dict[str, float]:
    """A pose as Kinova's GetCartesianPosition reports it: X, Y, Z (m) and ThetaX, ThetaY, ThetaZ, the XYZ Euler
    angles of ``R`` (rad): the one place a rotation becomes Kinova's six numbers (the API's reply, the robot's
    state, ``mfvs model fk``)."""
    theta = matrix_to_euler_xyz(R)
    return {"X": float(p[0]), "Y": float(p[1]), "Z": float(p[2]),
            "ThetaX": float(theta[0]), "ThetaY": float(theta[1]), "ThetaZ": float(theta[2])}


def matrix_to_euler_xyz(R) -> np.ndarray:
    """(r, p, y) with p ∈ [−π/2, π/2] such that R = Rx(r)·Ry(p)·Rz(y).

    At p = ±90° only r ± y is defined; then y = 0 is returned.
    """
    R = np.asarray(R, dtype=float)
    sin_p = float(np.clip(R[0, 2], -1.0, 1.0))
    cos_p = math.hypot(R[1, 2], R[2, 2])
    p = math.atan2(sin_p, cos_p)
    if cos_p > 1e-12:
        r = math.atan2(-R[1, 2], R[2, 2])
        y = math.atan2(-R[0, 1], R[0, 0])
    else:  # gimbal lock: R = Rx(r ± y)·Ry(±90°)
        r = math.atan2(R[2, 1], R[1, 1])
        y = 0.0
    return np.array([r, p, y])


def quat_wxyz_to_matrix(q) -> np.ndarray:
    w, x, y, z = (float(v) for v in q)
    n = math.sqrt(w * w + x * x + y * y + z * z)
    if n == 0.0:
        raise ValueError("zero quaternion")
    w, x, y, z = w / n, x / n, y / n, z / n
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def matrix_to_quat_wxyz(R) -> np.ndarray:
    """Unit quaternion (w ≥ 0) of a rotation matrix (Shepperd's method)."""
    R = np.asarray(R, dtype=float)
    tr = R[0, 0] + R[1, 1] + R[2, 2]
    if tr > 0:
        s = 2.0 * math.sqrt(tr + 1.0)
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = 2.0 * math.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        q = [(R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s]
    elif R[1, 1] > R[2, 2]:
        s = 2.0 * math.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        q = [(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s]
    else:
        s = 2.0 * math.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        q = [(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s]
    q = np.array(q)
    q /= np.linalg.norm(q)
    return -q if q[0] < 0 else q


def rotation_log(R) -> np.ndarray:
    """The rotation vector θ·u of R (so R = exp([θu]×)), θ ∈ [0, π]."""
    R = np.asarray(R, dtype=float)
    cos_t = float(np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0))
    theta = math.acos(cos_t)
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if theta < 1e-6:
        return 0.5 * w
    if math.pi - theta < 1e-4:
        # near π the antisymmetric part vanishes; take the axis from the symmetric part
        axis = np.sqrt(np.clip((np.diag(R) + 1.0) / 2.0, 0.0, None))
        k = int(np.argmax(axis))
        axis = (R[:, k] + np.eye(3)[:, k]) / 2.0
        axis /= np.linalg.norm(axis)
        if np.dot(axis, w) < 0:
            axis = -axis
        return theta * axis
    return theta / (2.0 * math.sin(theta)) * w


def skew(t) -> np.ndarray:
    x, y, z = (float(v) for v in t)
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def homogeneous(R, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def pose_from_xyz_rpy_deg(xyz, rpy_deg) -> np.ndarray:
    """4×4 transform from a file-style pose {xyz, rpy_deg} (XYZ Euler, degrees)."""
    return homogeneous(euler_xyz_to_matrix(np.radians(np.asarray(rpy_deg, dtype=float))), np.asarray(xyz, float))


# --------------------------------------------------------------------------------------------- B(Γ), eq. 12


def euler_rates_matrix(euler) -> np.ndarray:
    """B(Γ) of Sensors 2022 eq. 12: ω_b = B(Γ)·Γ̇ for XYZ Euler angles Γ = (r, p, y)."""
    r, p, _ = (float(v) for v in euler)
    sr, cr, sp, cp = math.sin(r), math.cos(r), math.sin(p), math.cos(p)
    return np.array([[1.0, 0.0, sp], [0.0, cr, -cp * sr], [0.0, sr, cp * cr]])


def euler_rates_matrix_inv(euler, min_cos_pitch: float = MIN_COS_PITCH) -> np.ndarray:
    """B(Γ)⁻¹ in closed form; raises :class:`EulerSingularityError` when |cos p| < ``min_cos_pitch``."""
    r, p, _ = (float(v) for v in euler)
    cp = math.cos(p)
    if abs(cp) < min_cos_pitch:
        raise EulerSingularityError(
            f"B(Γ) is singular: XYZ Euler pitch {math.degrees(p):.4f}° is within "
            f"{math.degrees(math.asin(min(1.0, min_cos_pitch))):.3f}° of ±90°"
        )
    sr, cr, tp = math.sin(r), math.cos(r), math.tan(p)
    return np.array([[1.0, sr * tp, -cr * tp], [0.0, cr, sr], [0.0, -sr / cp, cr / cp]])


# --------------------------------------------------------------------------------------------- twists, eq. 22-25


def motion_transform(R, t) -> np.ndarray:
    """The 6×6 spatial motion transform of eq. 22, ᵉX_c = [[R, [t]×R], [0, R]].

    With R = ᵉ_cR and t = ᵉt_c (the camera pose in the end-effector frame) it maps a camera twist expressed in the
    camera frame to the end-effector twist expressed in the end-effector frame.
    """
    R = np.asarray(R, dtype=float)
    X = np.zeros((6, 6))
    X[:3, :3] = R
    X[:3, 3:] = skew(t) @ R
    X[3:, 3:] = R
    return X


def motion_transform_inv(R, t) -> np.ndarray:
    """Inverse of :func:`motion_transform`: [[Rᵀ, −Rᵀ[t]×], [0, Rᵀ]]."""
    R = np.asarray(R, dtype=float)
    X = np.zeros((6, 6))
    X[:3, :3] = R.T
    X[:3, 3:] = -R.T @ skew(t)
    X[3:, 3:] = R.T
    return X


def rotation_motion_transform(R) -> np.ndarray:
    """ᵇX_e of eq. 23: blockdiag(R, R) re-expresses a twist in a rotated frame (same reference point)."""
    X = np.zeros((6, 6))
    X[:3, :3] = R
    X[3:, 3:] = R
    return X


def mixed_transform(R_be, euler=None, min_cos_pitch: float = MIN_COS_PITCH) -> np.ndarray:
    """ᵐX_e of eq. 25, blockdiag(ᵇₑR, B(Γ)⁻¹): end-effector twist (in the end-effector frame) → mixed twist with
    the ``seed000`` angular part. Γ defaults to the Euler angles of R_be."""
    R_be = np.asarray(R_be, dtype=float)
    euler = matrix_to_euler_xyz(R_be) if euler is None else euler
    X = np.zeros((6, 6))
    X[:3, :3] = R_be
    X[3:, 3:] = euler_rates_matrix_inv(euler, min_cos_pitch)
    return X


def mixed_jacobian_transform(R_be, euler=None, min_cos_pitch: float = MIN_COS_PITCH) -> np.ndarray:
    """J(Γ) of eq. 11, blockdiag(I, B(Γ)⁻¹·ᵉ_bR), with ᵉ_bR = R_beᵀ."""
    R_be = np.asarray(R_be, dtype=float)
    euler = matrix_to_euler_xyz(R_be) if euler is None else euler
    X = np.eye(6)
    X[3:, 3:] = euler_rates_matrix_inv(euler, min_cos_pitch) @ R_be.T
    return X


def mixed_jacobian(J_base, R_be, min_cos_pitch: float = MIN_COS_PITCH) -> np.ndarray:
    """Jm = J(Γ)·Jb (eq. 10), Jb the geometric Jacobian in the base frame at the end-effector origin
    (rows: linear velocity, angular velocity, both in base coordinates)."""
    return mixed_jacobian_transform(R_be, min_cos_pitch=min_cos_pitch) @ np.asarray(J_base, dtype=float)


def euler_rate_jacobian(J_base, R_be, min_cos_pitch: float = MIN_COS_PITCH) -> np.ndarray:
    """The analytical Jacobian of (position, XYZ Euler angles): rows 4-6 are B(Γ)⁻¹·Jω,b."""
    J = np.array(J_base, dtype=float, copy=True)
    J[3:] = euler_rates_matrix_inv(matrix_to_euler_xyz(R_be), min_cos_pitch) @ J[3:]
    return J


# --------------------------------------------------------------------------------------------- conventions


def _as_convention(c) -> AngularConvention:
    try:
        return AngularConvention(c)
    except ValueError:
        raise ValueError(f"unknown angular convention {c!r}; known: {[m.value for m in AngularConvention]}") from None


def angular_from_omega_ee(omega_ee, R_be, convention, min_cos_pitch: float = MIN_COS_PITCH) -> np.ndarray:
    """The rotational part of a mixed twist in ``convention``, from ω expressed in the end-effector frame."""
    convention = _as_convention(convention)
    omega_ee = np.asarray(omega_ee, dtype=float)
    if convention is AngularConvention.OMEGA:
        return omega_ee.copy()
    R_be = np.asarray(R_be, dtype=float)
    B_inv = euler_rates_matrix_inv(matrix_to_euler_xyz(R_be), min_cos_pitch)
    if convention is AngularConvention.SEED000:
        return B_inv @ omega_ee
    return B_inv @ (R_be @ omega_ee)


def omega_ee_from_angular(angular, R_be, convention) -> np.ndarray:
    """ω in the end-effector frame from the rotational part of a mixed twist in ``convention``."""
    convention = _as_convention(convention)
    angular = np.asarray(angular, dtype=float)
    if convention is AngularConvention.OMEGA:
        return angular.copy()
    R_be = np.asarray(R_be, dtype=float)
    B = euler_rates_matrix(matrix_to_euler_xyz(R_be))
    if convention is AngularConvention.SEED000:
        return B @ angular
    return R_be.T @ (B @ angular)


def convert_angular(angular, R_be, source, target, min_cos_pitch: float = MIN_COS_PITCH) -> np.ndarray:
    """Re-express the rotational part of a mixed twist from one convention in another at orientation R_be."""
    return angular_from_omega_ee(omega_ee_from_angular(angular, R_be, source), R_be, target, min_cos_pitch)


def mixed_from_ee_twist(twist_ee, R_be, convention, min_cos_pitch: float = MIN_COS_PITCH) -> np.ndarray:
    """Mixed twist from an end-effector twist (both parts in the end-effector frame). With ``seed000`` this is
    exactly ᵐX_e·V_e of eq. 25."""
    twist_ee = np.asarray(twist_ee, dtype=float)
    R_be = np.asarray(R_be, dtype=float)
    out = np.empty(6)
    out[:3] = R_be @ twist_ee[:3]
    out[3:] = angular_from_omega_ee(twist_ee[3:], R_be, convention, min_cos_pitch)
    return out


def ee_twist_from_mixed(twist_mixed, R_be, convention) -> np.ndarray:
    """End-effector twist (in the end-effector frame) from a mixed twist in ``convention``."""
    twist_mixed = np.asarray(twist_mixed, dtype=float)
    R_be = np.asarray(R_be, dtype=float)
    out = np.empty(6)
    out[:3] = R_be.T @ twist_mixed[:3]
    out[3:] = omega_ee_from_angular(twist_mixed[3:], R_be, convention)
    return out


def base_twist_from_mixed(twist_mixed, R_be, convention) -> np.ndarray:
    """Base-frame twist (linear and angular velocity in base coordinates, at the end-effector origin)."""
    twist_mixed = np.asarray(twist_mixed, dtype=float)
    R_be = np.asarray(R_be, dtype=float)
    return np.concatenate([twist_mixed[:3], R_be @ omega_ee_from_angular(twist_mixed[3:], R_be, convention)])


def mixed_from_base_twist(twist_base, R_be, convention, min_cos_pitch: float = MIN_COS_PITCH) -> np.ndarray:
    twist_base = np.asarray(twist_base, dtype=float)
    R_be = np.asarray(R_be, dtype=float)
    return np.concatenate(
        [twist_base[:3], angular_from_omega_ee(R_be.T @ twist_base[3:], R_be, convention, min_cos_pitch)]
    )


def ee_twist_from_camera(twist_cam, R_ec, t_ec) -> np.ndarray:
    """Eq. 22: the end-effector twist that moves the camera (mounted at pose (R_ec, t_ec) in the end-effector
    frame) with ``twist_cam`` (expressed in the camera frame)."""
    return motion_transform(R_ec, t_ec) @ np.asarray(twist_cam, dtype=float)


def camera_twist_from_ee(twist_ee, R_ec, t_ec) -> np.ndarray:
    return motion_transform_inv(R_ec, t_ec) @ np.asarray(twist_ee, dtype=float)


class PoseConfig(ConfigStruct):
    """A pose as files write it: position (m) and XYZ Euler angles in degrees (R = Rx·Ry·Rz)."""

    xyz: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rpy_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        if not all(math.isfinite(v) for v in (*self.xyz, *self.rpy_deg)):
            raise ValueError("pose values must be finite")

    def matrix(self) -> np.ndarray:
        """The 4×4 homogeneous transform."""
        return pose_from_xyz_rpy_deg(self.xyz, self.rpy_deg)


def pose_message(R: np.ndarray, t) -> Pose:
    """A rotation and a translation as the wire's Pose (position, unit quaternion w, x, y, z)."""
    return Pose(xyz=tuple(float(v) for v in np.asarray(t, dtype=float).ravel()),
                quat_wxyz=tuple(matrix_to_quat_wxyz(R)))
