"""Seed 002: robust fulfilment of constraints in visual servoing by sliding mode, at the acceleration level.

Two priority levels (eq. 15): level 1 holds the active constraints on their sliding surfaces, level 2 tracks the
features in what freedom is left:

    q̈_c = A1⁺ b1 + (A2 N1)⁺ (b2 − A2 A1⁺ b1),   N1 = I − A1⁺ A1

Each constraint σ_i(q) ≤ 0 becomes φ_i = σ_i + K_i ∇σ_iᵀ q̇ ≤ 0 (eq. 19); it is active when φ_i ≥ 0 and then
contributes the row K_i ∇σ_iᵀ (∇φ_iᵀ w.r.t. q̇ for speed constraints) with right-hand side −u⁺_i (eq. 10-11,
40). Level 2 is the tracking law of eq. 41-42 with the exponential gain K_T,p(‖e‖) = K0·exp(−(K̇0/K0)‖e‖) and
K_T,v = 3√K_T,p. The acceleration is integrated into the joint velocity command (the arm takes velocities).
With sampling time T_s, φ chatters within the band T_s·u⁺ around 0 (eq. 43).

Constraints implemented (following the spec of Appendix B): field of view (hyperellipse per point, eq. 20-24, in
normalized coordinates), joint range (eq. 25-27, exact gradient), joint speed (eq. 28-29, exact gradient),
forbidden spheres for the end effector (eq. 30-31). Gradient error injection (eq. 49) for robustness runs.
When the active constraints leave no freedom (more than n, or rank-deficient), the law aborts (ConstraintAbort).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from services.model import jaco2
from services.controller.law import ConstraintAbort, Law, LawConfig, LawOutput, ServoInput


@dataclass
class FovConstraint:
    """Hyperellipse |x/a|^n + |y/b|^n ≤ 1 in normalized coordinates, a = (W/2)(1−margin)/fx, b likewise."""

    width: int = 640
    height: int = 480
    fx: float = 615.0
    fy: float = 615.0
    margin: float = 0.05
    exponent: float = 16.0
    K: float = 0.1
    u_plus: float = 2.0

    @property
    def semi_axes(self) -> tuple[float, float]:
        return (self.width / 2.0) * (1 - self.margin) / self.fx, (self.height / 2.0) * (1 - self.margin) / self.fy


@dataclass
class JointRangeConstraint:
    """σ = −1 + |q̃| + margin, q̃ = (q − q_mid)/(Δq/2), for the given joints (model rad limits)."""

    joints: dict = field(default_factory=dict)  # index → (lower, upper) in rad
    margin: float = 0.0
    K: float = 0.1
    u_plus: float = 2.0


@dataclass
class JointSpeedConstraint:
    """φ = −1 + |q̇_i|/q̇_max,i + margin. ``u_plus`` None: 1.25× the largest normalized acceleration the task
    levels may ask for (max_task_accel / min q̇_max), so the switching gain dominates them."""

    max_speed: np.ndarray = field(default_factory=lambda: jaco2.MAX_SPEED * 0.8)
    margin: float = 0.0
    u_plus: Optional[float] = None


@dataclass
class SphereConstraint:
    """The end effector stays out of a sphere (base frame): σ = r − ‖p − c‖ + margin."""

    centre: tuple = (0.0, 0.0, 0.0)
    radius: float = 0.05
    margin: float = 0.0
    K: float = 0.1
    u_plus: float = 0.2




@dataclass
class SmcOptions:
    fov: Optional[FovConstraint] = field(default_factory=FovConstraint)
    joint_range: Optional[JointRangeConstraint] = None
    joint_speed: Optional[JointSpeedConstraint] = field(default_factory=JointSpeedConstraint)
    spheres: list = field(default_factory=list)
    #: tracking gain K_T,p(0) and its slope magnitude at 0
    K0: float = 4.0
    Kdot0: float = 10.0
    #: sampling time T_s (s); None: from the features' timestamps
    Ts: Optional[float] = None
    #: gradient error injection (eq. 49): relative error c_e on the FOV gradients, 0 to disable
    gradient_error: float = 0.0
    #: singular values of A1 below rcond·σ_max count as zero (rank test and pseudo-inverses)
    rcond: float = 1e-6
    #: level 2's pseudo-inverse ignores singular values below task_rcond·σ_max: blocking a joint by an active
    #: constraint can leave A2·N1 with a tiny singular value that would otherwise be amplified into a jump
    task_rcond: float = 1e-4
    #: bound on the task levels' joint accelerations (rad/s²; the JACO-2 DSP's 200 deg/s²)
    max_task_accel: float = math.radians(200.0)
    #: damping (1/s) of the joint motion left in the null space of both levels: the 7-DoF arm's self-motion,
    #: which neither level sees (the paper's 6R arm has none)
    null_damping: float = 3.0

    @classmethod
    def from_dict(cls, options: dict) -> "SmcOptions":
        """Options as a scenario writes them; joint ranges are given per joint number (1-7) in physical degrees,
        like ``joint_range: {joints_deg: {6: [200, 240]}, K: 0.1, u_plus: 2}``."""
        options = {k: (dict(v) if isinstance(v, dict) else v) for k, v in options.items()}
        out = cls()
        if "fov" in options:
            out.fov = None if options["fov"] is None else FovConstraint(**options.pop("fov"))
        if "joint_range" in options:
            spec = options.pop("joint_range")
            if spec is not None:
                joints = {}
                for number, limits in spec.pop("joints_deg", {}).items():
                    index = int(number) - 1
                    if not 0 <= index < jaco2.N_JOINTS or len(limits) != 2:
                        raise ValueError(f"joint_range: joint {number} needs two limits, joints are 1-7")
                    ends = sorted(jaco2.SIGN[index] * math.radians(v) for v in limits)
                    joints[index] = (ends[0], ends[1])
                if not joints:
                    lower, upper = jaco2.model_limits()
                    joints = {i: (lower[i], upper[i]) for i in range(jaco2.N_JOINTS) if np.isfinite(lower[i])}
                out.joint_range = JointRangeConstraint(joints=joints, **spec)
        else:
            lower, upper = jaco2.model_limits()
            out.joint_range = JointRangeConstraint(
                joints={i: (lower[i], upper[i]) for i in range(jaco2.N_JOINTS) if np.isfinite(lower[i])}, margin=0.05)
        if "joint_speed" in options:
            spec = options.pop("joint_speed")
            if spec is None:
                out.joint_speed = None
            else:
                scale = spec.pop("speed_scale", 0.8)
                out.joint_speed = JointSpeedConstraint(max_speed=jaco2.MAX_SPEED * scale, **spec)
        if "spheres" in options:
            out.spheres = [SphereConstraint(**s) for s in options.pop("spheres")]
        for key, value in options.items():
            if not hasattr(out, key):
                raise ValueError(f"unknown smc option {key!r}")
            setattr(out, key, value)
        return out


#: eq. 49's sign pattern for a 6R arm, with a seventh sign chosen for the 7-DoF arm
GRADIENT_ERROR_SIGNS = np.array([-1.0, 1.0, 1.0, 1.0, -1.0, -1.0, 1.0])


class SlidingModeLaw(Law):
    name = "smc"

    def __init__(self, config: LawConfig | None = None, kinematics=None, **options) -> None:
        super().__init__(config, kinematics)
        self.options = SmcOptions.from_dict(options)
        if self.options.joint_range is not None:
            joints = self.options.joint_range.joints
            idx = np.array(sorted(joints), dtype=int)
            lo = np.array([joints[j][0] for j in idx])
            hi = np.array([joints[j][1] for j in idx])
            self._range_arrays = (idx, (lo + hi) / 2.0, (hi - lo) / 2.0)
        speed = self.options.joint_speed
        if speed is not None and speed.u_plus is None:
            speed.u_plus = 1.25 * self.options.max_task_accel / float(np.min(speed.max_speed))
        self.reset()

    def reset(self) -> None:
        super().reset()
        self.dq_c = np.zeros(jaco2.N_JOINTS)
        self._Js_prev: Optional[np.ndarray] = None
        self._t_prev: Optional[float] = None

    # ------------------------------------------------------------------ constraints
    def constraints(self, inp: ServoInput, Js: np.ndarray, J_base: np.ndarray, p: np.ndarray, dq: np.ndarray):
        """(rows, rhs, phis, names): every constraint's φ, and the level-1 row (K∇σᵀ, or ∂φ/∂q̇ for speeds) and
        right-hand side (−u⁺) it contributes when active. Arrays, one entry per constraint, in a fixed order."""
        opt = self.options
        n_joints = jaco2.N_JOINTS
        rows, rhs, phis = [], [], []
        if opt.fov is not None:
            fov = opt.fov
            a, b = fov.semi_axes
            n = fov.exponent
            pts = np.asarray(inp.points)
            x, y = pts[:, 0], pts[:, 1]
            ax, ay = np.abs(x / a), np.abs(y / b)
            sigma = ax**n + ay**n - 1.0
            d_sigma = np.empty((len(pts), 2))
            d_sigma[:, 0] = n * np.sign(x) * ax ** (n - 1) / a
            d_sigma[:, 1] = n * np.sign(y) * ay ** (n - 1) / b
            grads = np.einsum("pk,pkj->pj", d_sigma, Js.reshape(-1, 2, n_joints))
            if opt.gradient_error:
                grads = grads + opt.gradient_error * GRADIENT_ERROR_SIGNS * np.abs(grads)
            rows.append(fov.K * grads)
            rhs.append(np.full(len(pts), -fov.u_plus))
            phis.append(sigma + fov.K * (grads @ dq))
        if opt.joint_range is not None:
            jr = opt.joint_range
            idx, mid, half = self._range_arrays
            q_t = (np.asarray(inp.q)[idx] - mid) / half
            block = np.zeros((len(idx), n_joints))
            block[np.arange(len(idx)), idx] = jr.K * np.sign(q_t) / half
            rows.append(block)
            rhs.append(np.full(len(idx), -jr.u_plus))
            phis.append(-1.0 + np.abs(q_t) + jr.margin + block[np.arange(len(idx)), idx] * dq[idx])
        if opt.joint_speed is not None:
            js = opt.joint_speed
            rows.append(np.diag(np.sign(dq) / js.max_speed))
            rhs.append(np.full(n_joints, -js.u_plus))
            phis.append(-1.0 + np.abs(dq) / js.max_speed + js.margin)
        for sphere in opt.spheres:
            offset = p - np.asarray(sphere.centre)
            dist = float(np.linalg.norm(offset))
            grad = J_base[:3].T @ (-offset / max(dist, 1e-12))
            rows.append((sphere.K * grad)[None, :])
            rhs.append(np.array([-sphere.u_plus]))
            phis.append(np.array([sphere.radius - dist + sphere.margin + sphere.K * grad @ dq]))
        if not rows:
            return np.zeros((0, n_joints)), np.zeros(0), np.zeros(0), []
        return np.vstack(rows), np.concatenate(rhs), np.concatenate(phis), self._names(len(inp.points))

    def _names(self, n_points: int) -> list[str]:
        cached = getattr(self, "_names_cache", None)
        if cached is None or cached[0] != n_points:
            opt = self.options
            names = [f"fov:{i}" for i in range(n_points)] if opt.fov is not None else []
            if opt.joint_range is not None:
                names += [f"joint_range:{j + 1}" for j in opt.joint_range.joints]
            if opt.joint_speed is not None:
                names += [f"joint_speed:{j + 1}" for j in range(jaco2.N_JOINTS)]
            names += [f"sphere:{k}" for k in range(len(opt.spheres))]
            self._names_cache = cached = (n_points, names)
        return cached[1]

    def band(self, name: str) -> float:
        """The chattering band T_s·u⁺ of the constraint called ``name`` (for the nominal sampling time)."""
        opt = self.options
        kind = name.split(":")[0]
        u_plus = {"fov": opt.fov.u_plus if opt.fov else 0.0,
                  "joint_range": opt.joint_range.u_plus if opt.joint_range else 0.0,
                  "joint_speed": opt.joint_speed.u_plus if opt.joint_speed else 0.0}.get(kind)
        if u_plus is None:
            u_plus = opt.spheres[int(name.split(":")[1])].u_plus
        return self._Ts_nominal * u_plus

    def _kinds(self, names: list[str]) -> dict:
        """kind → (indices of its constraints, its band); the constraint list is fixed for a law, so cached."""
        if getattr(self, "_kinds_cache", None) is None or self._kinds_cache[0] != len(names):
            kinds: dict = {}
            for i, name in enumerate(names):
                kind = name.split(":")[0]
                kinds.setdefault(kind, ([], self.band(name)))[0].append(i)
            self._kinds_cache = (len(names), {k: (np.array(v[0]), v[1]) for k, v in kinds.items()})
        return self._kinds_cache[1]

    # ------------------------------------------------------------------ the step
    def step(self, inp: ServoInput) -> LawOutput:
        opt = self.options
        Ts = opt.Ts
        if Ts is None:
            Ts = (inp.t_s - self._t_prev) if self._t_prev is not None and inp.t_s > self._t_prev else 1.0 / 30.0
        self._Ts_nominal = opt.Ts or 1.0 / 30.0
        J_c, R_be, J_base = self._camera_jacobian(inp.q, inp.camera_in_ee)
        p = self.kin.data.oMf[self.kin.ee_frame_id].translation.copy()  # computed with the Jacobian above
        L = self._L(inp)
        Js = L @ J_c
        dq = self.dq_c
        e = inp.error
        e_dot = Js @ dq  # ṡ of the noise-free model (static target, static reference)
        s_ddot, K_p = tracking_acceleration(e, e_dot, opt.K0, opt.Kdot0)
        Js_dot = np.zeros_like(Js) if self._Js_prev is None else (Js - self._Js_prev) / Ts
        rows, rhs, phis, names = self.constraints(inp, Js, J_base, p, dq)
        active = np.flatnonzero(phis >= 0.0).tolist()
        try:
            ddq = prioritized_acceleration(rows[active], rhs[active], Js, s_ddot - Js_dot @ dq, dq, opt)
        except ConstraintAbort as exc:
            raise ConstraintAbort(f"{exc}: {', '.join(names[i] for i in active)}") from None
        #: the last step's level-1 system, acceleration and active constraint indices (into ``_names``), for
        #: inspection: A1·q̈ = b1 holds when A1 has full rank
        self.last_level1 = (rows[active], rhs[active], ddq, active)
        self.dq_c = dq + Ts * ddq
        self._Js_prev = Js
        self._t_prev = inp.t_s
        notes = {"max_phi": float(np.max(phis)) if len(phis) else -math.inf, "active": len(active),
                 "gain": K_p}
        for kind, (indices, band) in self._kinds(names).items():
            notes[f"max_phi.{kind}"] = float(np.max(phis[indices]))
            notes[f"band.{kind}"] = band
        return LawOutput(joint_velocities=self.dq_c.copy(), camera_twist=J_c @ self.dq_c, gain=K_p, notes=notes)


def tracking_acceleration(e: np.ndarray, e_dot: np.ndarray, K0: float, Kdot0: float) -> tuple[np.ndarray, float]:
    """Eq. 41-42: the features' desired acceleration s̈ = −K_T,p e − K_T,v ė, with the exponential gain
    K_T,p(‖e‖) = K0·exp(−(K̇0/K0)‖e‖) and K_T,v = 3√K_T,p; (s̈, K_T,p)."""
    K_p = K0 * math.exp(-(Kdot0 / K0) * math.sqrt(float(e @ e)))
    return -K_p * e - 3.0 * math.sqrt(K_p) * e_dot, K_p


def prioritized_acceleration(A1: np.ndarray, b1: np.ndarray, A2: np.ndarray, b2: np.ndarray, dq: np.ndarray,
                             opt: "SmcOptions") -> np.ndarray:
    """Eq. 15: q̈ = A1⁺ b1 + (A2 N1)⁺ (b2 − A2 A1⁺ b1), N1 = I − A1⁺ A1 — level 1 the active constraints (rows of
    A1, none if it is empty), level 2 the features' task — plus a third level that damps the self-motion left in
    the null space of both. The task's part is bounded by ``opt.max_task_accel`` (what the arm can do); level 1
    never is, so the switching gains dominate the task's push on every constraint (the condition behind the
    chattering band of eq. 43). Raises ConstraintAbort when the constraints leave no freedom."""
    n = dq.shape[0]
    if len(A1):
        U, s1, Vt = np.linalg.svd(A1, full_matrices=False)
        rank = int(np.sum(s1 > opt.rcond * max(s1[0], 1e-12)))
        if len(A1) > n or rank < len(A1):
            raise ConstraintAbort(f"{len(A1)} active constraints (rank {rank}) leave no freedom for the task")
        A1_pinv = (Vt.T / s1) @ U.T
        N1 = np.eye(n) - A1_pinv @ A1
        first = A1_pinv @ b1
        A2N1 = A2 @ N1
        b2 = b2 - A2 @ first
    else:
        N1, first, A2N1 = None, 0.0, A2
    U2, s2, Vt2 = np.linalg.svd(A2N1, full_matrices=False)
    keep = s2 > opt.task_rcond * s2[0]
    V2 = Vt2[keep]
    second = (V2.T / s2[keep]) @ (U2[:, keep].T @ b2)
    # level 3: damp the self-motion in the null space of both levels (V2 spans A2N1's row space)
    damping = -opt.null_damping * dq
    damping = damping - V2.T @ (V2 @ damping)
    second = second + (damping if N1 is None else N1 @ damping)
    peak = float(np.abs(second).max())
    if peak > opt.max_task_accel:
        second *= opt.max_task_accel / peak
    return second + first
