"""The JACO thesis's torque control (chapter 4) and its references (chapter 5) as pure functions: no zenoh, no clock, no
threads. Equation numbers are the thesis's; ``docs/torque.md`` says where the code departs from it and why.

References
    :func:`cubic`           eq. 5.1, the cubic spline X(t) = X0 + 3(Xf − X0)t²/tf² − 2(Xf − X0)t³/tf³ (held after tf)
    :func:`pose_reference`  eq. 5.1 componentwise on [p; XYZ Euler], R_d from the Euler angles (eq. 4.4)
    :func:`sinusoid`        eq. 5.3, q_d = q_start + A·sin(2πt/T) on every joint
    ``THESIS_X0/XF``        eq. 5.2 (the HOME pose the thesis read from its arm, and the final pose), tf = 16 s

Orientation error
    :func:`orientation_error`   eq. 4.5-4.7, the angle-axis of (R_c)ᵀR_d in the current end-effector frame, zero
                                below 0.03 rad and clamped below π − 0.03 rad
    :class:`OrientationIntegral` eq. 4.8, the integral projected on the current axis

Laws (τ in model sign, N·m)
    :func:`jacobian_transpose`  eq. 4.3, τ = Jᵀ[f_c; μ_c] with the mixed Jacobian (eq. 3.12)
    :func:`null_space_torque`   eq. 4.9-4.13, τ = J_vᵀf_c + (I − J_vᵀJ^#ᵀ)J_ωᵀμ_c, J^# of eq. 4.11 with W = I or M(q)
    :func:`computed_torque`     eq. 4.16-4.18, τ = M̂(q)w + ĝ(q) with w = Kp(q_d − q) − Kd·q̇ (optionally the
                                feed-forward and Ĉ the thesis leaves out)
    :func:`joint_velocity_reference`, :func:`velocity_torque`   eq. 4.20-4.23

The model the controllers use (:class:`DynamicsModel`, services/model/dynamics.py) is Pinocchio on the arm's
description, as the thesis's was its CAD model: by default the links alone (``rotor_inertia=False``, ``friction=False``), which is what eq. 3.35
holds; the emulated arm adds the motors' rotor inertia reflected through the gears and viscous friction.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import numpy as np

from services.model import frames
from services.model.arm import ArmDescription
from services.model.dynamics import DynamicsModel, Kinematics

# ------------------------------------------------------------------------------------------------ the thesis's numbers

#: eq. 5.2: the HOME pose the thesis read from its j2n6s300 (x, y, z in m; XYZ Euler angles in rad) and the final
#: pose, reached in tf = 16 s
THESIS_X0 = np.array([0.212444, -0.257293, 0.506643, 1.65789, 1.11875, 0.113634])
THESIS_XF = np.array([0.312452, -0.407218, 0.706502, 2.44364, 0.0715527, 0.637327])
THESIS_TF_S = 16.0
#: the motion of eq. 5.2 (+0.100, −0.150, +0.200 m; +45°, −60°, +30° of XYZ Euler angles), for arms other than the
#: thesis's
THESIS_DISPLACEMENT = THESIS_XF - THESIS_X0
#: eq. 5.3: 20° on every joint, period 8 s
SINUSOID_AMPLITUDE_RAD = math.radians(20.0)
SINUSOID_PERIOD_S = 8.0
#: eq. 4.6-4.7: below this angle the orientation error is zero, and it is kept this far from π (L1976-1984)
ORIENTATION_THRESHOLD_RAD = 0.03


@dataclass(frozen=True)
class TaskGains:
    """The task-space PID of eq. 4.3 (and of the outer loop of eq. 4.20-4.22): the same gain on every axis
    (L2141-2149). Position on the error in m, orientation on the angle-axis error in rad; integrals over time (s)."""

    kp_position: float
    ki_position: float
    kd_position: float
    kp_orientation: float
    ki_orientation: float
    kd_orientation: float


#: Table 5.2 (controllers a-c): f_c in N from m, μ_c in N·m from rad
TABLE_5_2 = TaskGains(400.0, 150.0, 25.0, 20.0, 8.0, 1.5)
#: Table 5.5 (controller e's outer loop): a linear velocity in m/s from m, an angular one in rad/s from rad
TABLE_5_5 = TaskGains(80.0, 20.0, 5.0, 25.0, 10.0, 3.5)
#: Table 5.3 (controller d), per joint of the j2n6s300: Kp in 1/s², Kd in 1/s
TABLE_5_3_KP = (32.5, 40.5, 55.0, 65.0, 70.0, 850.0)
TABLE_5_3_KD = (12.25, 15.25, 22.5, 28.5, 30.5, 150.0)
#: Table 5.4 (controller e's inner loop), per joint of the j2n6s300: K in 1/s
TABLE_5_4_KV = (60.5, 70.5, 87.5, 90.0, 90.0, 600.0)


def per_joint_gains(table, n_joints: int) -> np.ndarray:
    """A per-joint gain table of the 6-DoF thesis on an arm of ``n_joints``: the shoulder's three gains, then the
    wrist's. On the 7-DoF the extra joint is the upper arm's rotation (joint 3 of 7, a K-75+ like the thesis's joints
    1-3) and takes joint 3's gain; the last three joints take the thesis's joints 4-6 (K-58 on both arms)."""
    table = np.asarray(table, dtype=float)
    if n_joints == len(table):
        return table.copy()
    if n_joints == 7 and len(table) == 6:
        return np.concatenate([table[:3], table[2:3], table[3:]])
    raise ValueError(f"no mapping of a {len(table)}-joint gain table onto {n_joints} joints")


# ------------------------------------------------------------------------------------------------ references


def cubic(x0, xf, tf: float, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Eq. 5.1 and its first two derivatives at time t, componentwise; before 0 it is at x0, after tf at xf."""
    x0, xf = np.asarray(x0, dtype=float), np.asarray(xf, dtype=float)
    if not tf > 0:
        raise ValueError("the spline's tf must be positive")
    moving = 0.0 <= t < tf
    t = min(max(t, 0.0), tf)
    d = xf - x0
    return (x0 + d * (3 * t**2 / tf**2 - 2 * t**3 / tf**3), d * (6 * t / tf**2 - 6 * t**2 / tf**3),
            d * (6 / tf**2 - 12 * t / tf**3) if moving else np.zeros_like(d))


def sinusoid(q_start, amplitude: float, period_s: float, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Eq. 5.3 about the starting posture: q_d = q_start + A·sin(ωt), ω = 2π/T, and its derivatives."""
    q_start = np.asarray(q_start, dtype=float)
    w = 2.0 * math.pi / period_s
    s, c = math.sin(w * t), math.cos(w * t)
    return q_start + amplitude * s, np.full_like(q_start, amplitude * w * c), np.full_like(q_start, -amplitude * w * w * s)


@dataclass(frozen=True)
class PoseReference:
    """The desired pose at one instant: position (m) and rotation in the base frame, their velocities (the linear
    one and the angular one, both in base coordinates), and the 6-vector [p; XYZ Euler] it was made of."""

    p: np.ndarray
    R: np.ndarray
    v: np.ndarray
    omega: np.ndarray
    x: np.ndarray


def pose_vector(R, p) -> np.ndarray:
    """[x, y, z, α, β, γ]: a pose as GetCartesianPosition reports it (XYZ Euler angles, eq. 4.4)."""
    return np.concatenate([np.asarray(p, dtype=float), frames.matrix_to_euler_xyz(R)])


def pose_reference(x0, xf, tf: float, t: float) -> PoseReference:
    """Eq. 5.1 on [p; XYZ Euler] (as the thesis applies it, L2317-2328), R_d = Rx(α)Ry(β)Rz(γ) (eq. 4.4); the angular
    velocity from the Euler rates, ω = B(Γ)Γ̇."""
    x, dx, _ = cubic(x0, xf, tf, t)
    return PoseReference(p=x[:3], R=frames.euler_xyz_to_matrix(x[3:]), v=dx[:3],
                         omega=frames.euler_rates_matrix(x[3:]) @ dx[3:], x=x)


# ------------------------------------------------------------------------------------------------ orientation error


def orientation_error(R_c, R_d, threshold: float = ORIENTATION_THRESHOLD_RAD) -> tuple[float, np.ndarray]:
    """Eq. 4.5-4.7: (θ, ν) of the rotation from the current to the desired orientation, R = R_cᵀR_d, expressed in the
    current end-effector frame. θ below ``threshold`` counts as no error (θ = 0: the axis is undefined there, eq.
    4.6 divides by sin θ); above π − threshold it is clamped to π − threshold. The error vector is r = θν."""
    rotation = frames.rotation_log(np.asarray(R_c, dtype=float).T @ np.asarray(R_d, dtype=float))
    theta = float(np.linalg.norm(rotation))
    if theta < threshold:
        return 0.0, np.zeros(3)
    axis = rotation / theta
    return min(theta, math.pi - threshold), axis


class OrientationIntegral:
    """Eq. 4.8: the integral of the orientation error, r_k = (r_{k−1}·ν_k + θ_k·Δt)·ν_k — the accumulated vector
    projected on the current axis, plus this step's angle, along that axis. The thesis writes no Δt (its loop ran at a
    fixed 10 ms); here each step is weighed by its duration, so that the gain K_i,o means the same at any rate. A step
    without error (θ below the threshold) leaves the integral as it is."""

    def __init__(self) -> None:
        self.value = np.zeros(3)

    def step(self, theta: float, axis, dt: float) -> np.ndarray:
        if theta > 0.0:
            axis = np.asarray(axis, dtype=float)
            self.value = (float(self.value @ axis) + theta * dt) * axis
        return self.value


# ------------------------------------------------------------------------------------------------ the model


# ------------------------------------------------------------------------------------------------ the task PID


class TaskPID:
    """The PID of eq. 4.3 on the task errors: f_c on the position error (base frame), μ_c on the orientation error r
    (end-effector frame), the integrals of eq. 4.8 and of the position error over time, the D term on the errors'
    rates (the reference's velocity less the measured one, J·q̇: the thesis does not say which; this is the error's
    derivative without differencing noisy samples)."""

    def __init__(self, gains: TaskGains, threshold: float = ORIENTATION_THRESHOLD_RAD) -> None:
        self.gains = gains
        self.threshold = threshold
        self.position_integral = np.zeros(3)
        self.orientation_integral = OrientationIntegral()

    def step(self, kin: Kinematics, dq, ref: PoseReference, dt: float) -> tuple[np.ndarray, np.ndarray]:
        """(f_c, μ_c) for this step of ``dt`` seconds."""
        g = self.gains
        dq = np.asarray(dq, dtype=float)
        e_p = ref.p - kin.p
        self.position_integral = self.position_integral + e_p * dt
        theta, axis = orientation_error(kin.R, ref.R, self.threshold)
        r = theta * axis
        integral_o = self.orientation_integral.step(theta, axis, dt)
        de_p = ref.v - kin.J_v @ dq
        de_o = kin.R.T @ ref.omega - kin.J_w @ dq  # ω_d − ω, both in the current end-effector frame
        f = g.kp_position * e_p + g.ki_position * self.position_integral + g.kd_position * de_p
        mu = g.kp_orientation * r + g.ki_orientation * integral_o + g.kd_orientation * de_o
        return f, mu


# ------------------------------------------------------------------------------------------------ the laws


def jacobian_transpose(kin: Kinematics, f, mu) -> np.ndarray:
    """Eq. 4.3: τ = Jᵀ[f_c; μ_c], J the mixed Jacobian (a force in the base frame, a moment in the end effector's)."""
    return kin.J_v.T @ np.asarray(f, dtype=float) + kin.J_w.T @ np.asarray(mu, dtype=float)


#: the inner inverse of eq. 4.11 drops directions this much weaker than the strongest (at a singularity of J_v the
#: thesis's inverse does not exist; elsewhere this is the inverse itself)
INVERSE_RCOND = 1e-6


def generalized_inverse(J_v, W: Optional[np.ndarray] = None) -> np.ndarray:
    """Eq. 4.11: J^# = W⁻¹J_vᵀ(J_v W⁻¹ J_vᵀ)⁻¹; W = I (None) gives the Moore-Penrose pseudo-inverse of eq. 4.12,
    W = M(q) the dynamically consistent inverse."""
    J_v = np.asarray(J_v, dtype=float)
    W_inv_Jt = J_v.T if W is None else np.linalg.solve(W, J_v.T)
    return W_inv_Jt @ np.linalg.pinv(J_v @ W_inv_Jt, rcond=INVERSE_RCOND, hermitian=True)


def null_space_torque(kin: Kinematics, f, mu, W: Optional[np.ndarray] = None) -> np.ndarray:
    """Eq. 4.13: τ = J_vᵀf_c + (I − J_vᵀJ^#ᵀ)J_ωᵀμ_c — position first, the orientation's torque filtered into the
    null space of the position task (eq. 4.9-4.10), J^# of eq. 4.11 with weight W (None: W = I)."""
    J_v = kin.J_v
    n = J_v.shape[1]
    projector = np.eye(n) - J_v.T @ generalized_inverse(J_v, W).T
    return J_v.T @ np.asarray(f, dtype=float) + projector @ (kin.J_w.T @ np.asarray(mu, dtype=float))


def computed_torque(M, g, q, dq, q_d, kp, kd, dq_d=None, ddq_d=None, coriolis=None) -> np.ndarray:
    """Eq. 4.17-4.18: τ = M̂(q)·w + ĝ(q), w = Kp(q_d − q) − Kd·q̇. The thesis has no feed-forward and drops Ĉ; given
    ``dq_d``, ``ddq_d`` or ``coriolis`` (Ĉq̇), w = q̈_d + Kp(q_d − q) + Kd(q̇_d − q̇) and Ĉq̇ is added."""
    q, dq = np.asarray(q, dtype=float), np.asarray(dq, dtype=float)
    w = np.asarray(kp) * (np.asarray(q_d, dtype=float) - q) - np.asarray(kd) * dq
    if dq_d is not None:
        w = w + np.asarray(kd) * np.asarray(dq_d, dtype=float)
    if ddq_d is not None:
        w = w + np.asarray(ddq_d, dtype=float)
    tau = np.asarray(M) @ w + np.asarray(g)
    return tau if coriolis is None else tau + np.asarray(coriolis)


def joint_velocity_reference(kin: Kinematics, v_d, omega_d) -> np.ndarray:
    """Eq. 4.20-4.22: q̇_d = J_v^#·Ẋ_d + (I − J_v^#J_v)·q̇_0 with q̇_0 = J_ω^+·Ẋ_ω; both inverses Moore-Penrose (eq.
    4.12; the thesis's "J_ω⁻¹" of a 3×n matrix can only be a pseudo-inverse)."""
    J_v_pinv = generalized_inverse(kin.J_v)
    n = kin.J_v.shape[1]
    dq_0 = np.linalg.pinv(kin.J_w) @ np.asarray(omega_d, dtype=float)
    return J_v_pinv @ np.asarray(v_d, dtype=float) + (np.eye(n) - J_v_pinv @ kin.J_v) @ dq_0


def velocity_torque(M, g, dq, dq_d, kv) -> np.ndarray:
    """Eq. 4.23 in eq. 4.17: τ = M̂(q)·K(q̇_d − q̇) + ĝ(q) (K per joint, Table 5.4; the thesis dropped the D and I
    terms, L2203-2209, L2682-2690)."""
    return np.asarray(M) @ (np.asarray(kv) * (np.asarray(dq_d, dtype=float) - np.asarray(dq, dtype=float))) + \
        np.asarray(g)


# ------------------------------------------------------------------------------------------------ reachability

#: how :func:`nearest_pose` weighs orientation against position: 1 rad counts as this many metres (1° ≈ 1.7 mm)
ORIENTATION_WEIGHT_M = 0.1


@dataclass(frozen=True)
class NearestPose:
    """The pose within the arm's joint limits nearest a target: how far it is (m, deg), the joints there, and the
    smallest singular values there of J (6×n) and J_v (3×n): near zero, the arm is stretched or folded."""

    position_error_m: float
    orientation_error_deg: float
    q: np.ndarray
    sigma_min: float
    sigma_min_position: float

    @property
    def reachable(self) -> bool:
        return self.position_error_m < 1e-4 and self.orientation_error_deg < 0.01


def nearest_pose(arm: ArmDescription, x_target, q_start, starts: int = 16, seed: int = 0) -> NearestPose:
    """The nearest pose to ``x_target`` ([p; XYZ Euler]) the arm reaches within its joint limits (least squares
    from ``q_start`` and ``starts`` − 1 random configurations, orientation weighted by ORIENTATION_WEIGHT_M):
    whether a reference's end is reachable, and if not, the floor under any controller's final error."""
    from scipy.optimize import least_squares

    model = DynamicsModel(arm)
    x_target = np.asarray(x_target, dtype=float)
    R_t = frames.euler_xyz_to_matrix(x_target[3:])
    lower, upper = arm.model_limits()
    q_start = np.asarray(q_start, dtype=float)
    lower = np.where(np.isfinite(lower), lower, q_start - 2 * math.pi)
    upper = np.where(np.isfinite(upper), upper, q_start + 2 * math.pi)

    def residual(q):
        kin = model.kinematics(q)
        return np.concatenate([kin.p - x_target[:3], ORIENTATION_WEIGHT_M * frames.rotation_log(kin.R.T @ R_t)])

    def jacobian(q):  # d(log(Rᵀ R_t))/dq ≈ −J_ω (end-effector frame) near the target
        kin = model.kinematics(q)
        return np.vstack([kin.J_v, -ORIENTATION_WEIGHT_M * kin.J_w])

    rng = np.random.default_rng(seed)
    best = None
    for k in range(max(1, starts)):
        q0 = np.clip(q_start, lower, upper) if k == 0 else rng.uniform(lower, upper)
        result = least_squares(residual, q0, jac=jacobian, bounds=(lower, upper), max_nfev=300)
        if best is None or result.cost < best.cost:
            best = result
    kin = model.kinematics(best.x)
    return NearestPose(
        position_error_m=float(np.linalg.norm(kin.p - x_target[:3])),
        orientation_error_deg=math.degrees(float(np.linalg.norm(frames.rotation_log(kin.R.T @ R_t)))),
        q=best.x, sigma_min=float(np.linalg.svd(kin.J, compute_uv=False)[-1]),
        sigma_min_position=float(np.linalg.svd(kin.J_v, compute_uv=False)[-1]))
