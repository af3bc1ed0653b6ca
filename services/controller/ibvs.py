"""Image-based visual servoing building blocks of Sensors 2022 (section 3), as plain functions.

Features are point features in normalized image coordinates; e = s − s* is stacked (x0, y0, x1, y1, ...).
The camera twist Vc = (v, ω) is expressed in the camera (OpenCV optical) frame.
"""
from __future__ import annotations

import math

import numpy as np

from protocol.conventions import DepthSource


def interaction_matrix(points, depths) -> np.ndarray:
    """L_s of eq. 16 for n points: (2n × 6), rows (ẋ, ẏ) = L·Vc for each point (x, y) at depth Z."""
    points = np.asarray(points, dtype=float).reshape(-1, 2)
    depths = np.asarray(depths, dtype=float).reshape(-1)
    if len(depths) != len(points):
        raise ValueError("one depth per point")
    if not (depths.min(initial=np.inf) > 0 and np.isfinite(depths).all()):
        raise ValueError("depths must be positive and finite")
    x, y, inv_z = points[:, 0], points[:, 1], 1.0 / depths
    L = np.zeros((2 * len(points), 6))
    L[0::2, 0] = -inv_z
    L[0::2, 2] = x * inv_z
    L[0::2, 3] = x * y
    L[0::2, 4] = -(1.0 + x * x)
    L[0::2, 5] = y
    L[1::2, 1] = -inv_z
    L[1::2, 2] = y * inv_z
    L[1::2, 3] = 1.0 + y * y
    L[1::2, 4] = -x * y
    L[1::2, 5] = -x
    return L


def approximate_interaction_matrix(points, depths, goal_points, goal_depths, source: DepthSource) -> np.ndarray:
    """L̂_s: at the current features and depths, at the goal, or the mean of the two (ViSP's CURRENT, DESIRED,
    MEAN)."""
    if source is not DepthSource.CURRENT:
        source = DepthSource(source)
    if source is DepthSource.CURRENT:
        return interaction_matrix(points, depths)
    if source is DepthSource.GOAL:
        return interaction_matrix(goal_points, goal_depths)
    return 0.5 * (interaction_matrix(points, depths) + interaction_matrix(goal_points, goal_depths))


def adaptive_gain(e_inf: float, lambda0: float, lambda_inf: float, slope0: float) -> float:
    """λ_adp(‖e‖∞) of eq. 20: λ0 at 0, λ∞ at infinity, slope −λ'0 at 0 (ViSP's adaptive gain)."""
    if not (lambda0 > lambda_inf >= 0.0) or slope0 < 0:
        raise ValueError("the adaptive gain needs λ0 > λ∞ ≥ 0 and λ'0 ≥ 0")
    span = lambda0 - lambda_inf
    return span * math.exp(-slope0 / span * e_inf) + lambda_inf


class ErrorRate:
    """ė estimated from successive errors, smoothed by a first-order low-pass filter with time constant ``tau_s``
    (0: the raw finite difference). Gaps longer than ``max_gap_s``, a reset (e.g. after the target was lost), or
    errors of other points than the last (their ids) restart it: the first sample after a restart gives ė = 0."""

    def __init__(self, tau_s: float = 0.05, max_gap_s: float = 0.2) -> None:
        self.tau_s = tau_s
        self.max_gap_s = max_gap_s
        self.reset()

    def reset(self) -> None:
        self._last_e = None
        self._last_t = None
        self._last_ids = None
        self.value = None

    def update(self, e, t_s: float, ids=None) -> np.ndarray:
        e = np.asarray(e, dtype=float)
        ids = None if ids is None else np.asarray(ids)
        same_points = (self._last_ids is None and ids is None) or (
            self._last_ids is not None and ids is not None and np.array_equal(self._last_ids, ids))
        if (self._last_e is None or self._last_e.shape != e.shape or not same_points
                or not (0 < t_s - self._last_t <= self.max_gap_s)):
            self._last_e, self._last_t, self._last_ids = e.copy(), t_s, ids
            self.value = np.zeros_like(e)
            return self.value
        dt = t_s - self._last_t
        raw = (e - self._last_e) / dt
        alpha = 1.0 if self.tau_s <= 0 else dt / (self.tau_s + dt)
        self.value = self.value + alpha * (raw - self.value)
        self._last_e, self._last_t = e.copy(), t_s
        return self.value


def features_after_camera_motion(points, depths, camera_b_in_a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The normalised points and depths that camera pose A saw, as seen from pose B (``camera_b_in_a``: B's pose
    in A's frame, 4×4) for a static scene: P_B = R_abᵀ (P_A − t_ab), reprojected."""
    points = np.asarray(points, dtype=float).reshape(-1, 2)
    depths = np.asarray(depths, dtype=float).reshape(-1)
    P_a = np.column_stack([points * depths[:, None], depths])
    R, t = camera_b_in_a[:3, :3], camera_b_in_a[:3, 3]
    P_b = (P_a - t) @ R
    return P_b[:, :2] / P_b[:, 2:3], P_b[:, 2].copy()


def camera_motion_error_rate(L_hat: np.ndarray, J_camera: np.ndarray, dq) -> np.ndarray:
    """ė due to the camera's own motion (Sensors 2022 eq. 21's ė; eq. 2 with the camera twist J_c·q̇): L̂·J_c·q̇."""
    return L_hat @ (J_camera @ np.asarray(dq, dtype=float))


def pd_camera_twist(L_hat: np.ndarray, e, gain: float, kd: float, e_dot=None, target_term=None) -> np.ndarray:
    """Eq. 21 (eq. 19 with kd = 0): Vc = −λ L̂⁺ (e + (kd/λ) ė) − L̂⁺ ∂ê/∂t."""
    L_pinv = np.linalg.pinv(L_hat)
    e = np.asarray(e, dtype=float)
    drive = gain * e
    if e_dot is not None and kd:
        drive = drive + kd * np.asarray(e_dot, dtype=float)
    Vc = -L_pinv @ drive
    if target_term is not None:
        Vc = Vc - L_pinv @ np.asarray(target_term, dtype=float)
    return Vc


def target_motion_term(e_dot, L_hat: np.ndarray, Vc_applied) -> np.ndarray:
    """∂ê/∂t: the part of the measured error rate that the camera's own motion does not explain (ė − L̂·Vc)."""
    return np.asarray(e_dot, dtype=float) - L_hat @ np.asarray(Vc_applied, dtype=float)


def joint_law(L_hat: np.ndarray, J_camera: np.ndarray, e, gain: float, kd: float = 0.0, e_dot=None,
              secondary=None) -> np.ndarray:
    """Eq. 17-18 with the PD term: q̇ = −(L̂·J_c)⁺ (λ e + kd ė) + (I − (L̂J_c)⁺(L̂J_c)) ξ, where J_c maps joint
    velocities to the camera twist in the camera frame (J_c = ᶜX_e·J_e = ᶜX_m·J_m)."""
    task = L_hat @ J_camera
    task_pinv = np.linalg.pinv(task)
    drive = gain * np.asarray(e, dtype=float)
    if e_dot is not None and kd:
        drive = drive + kd * np.asarray(e_dot, dtype=float)
    dq = -task_pinv @ drive
    if secondary is not None:
        dq = dq + (np.eye(task.shape[1]) - task_pinv @ task) @ np.asarray(secondary, dtype=float)
    return dq


def mixed_jacobian_joint_velocity(Jm: np.ndarray, V_m, xi) -> np.ndarray:
    """Eq. 26: q̇ = Jm⁺·V_m + (I − Jm⁺Jm)·ξ, the mixed twist V_m (eq. 21-25) realised in joint space through the
    mixed Jacobian Jm, with the secondary task ξ in its null space."""
    Jm_pinv = np.linalg.pinv(Jm)
    return Jm_pinv @ np.asarray(V_m, dtype=float) + (np.eye(Jm.shape[1]) - Jm_pinv @ Jm) @ np.asarray(xi, dtype=float)


def joint_limit_task(q, lower, upper, gain: float = 1.0) -> np.ndarray:
    """ξ of eq. 13/26: a gradient step away from the joint limits (toward each limited joint's mid-range);
    continuous joints (infinite limits) get nothing."""
    q = np.asarray(q, dtype=float)
    xi = np.zeros_like(q)
    limited = np.isfinite(lower) & np.isfinite(upper)
    mid = (lower[limited] + upper[limited]) / 2.0
    half = (upper[limited] - lower[limited]) / 2.0
    xi[limited] = -gain * (q[limited] - mid) / half**2
    return xi
