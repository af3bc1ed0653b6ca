"""Muñoz 2018: robust fulfilment of constraints in visual servoing by sliding mode, at the acceleration level.

Two priority levels (eq. 15): level 1 holds the active constraints on their sliding surfaces, level 2 tracks the
features in what freedom is left:

    q̈_c = A1⁺ b1 + (A2 N1)⁺ (b2 − A2 A1⁺ b1),   N1 = I − A1⁺ A1

Each constraint σ_i(q) ≤ 0 becomes φ_i = σ_i + K_i ∇σ_iᵀ q̇ ≤ 0 (eq. 19); it is active when φ_i ≥ 0 and then
contributes the row K_i ∇σ_iᵀ (∇φ_iᵀ w.r.t. q̇ for speed constraints) with right-hand side −u⁺_i (eq. 10-11,
40). Level 2 is the tracking law of eq. 41-42 with the exponential gain K_T,p(‖e‖) = K0·exp(−(K̇0/K0)‖e‖) and
K_T,v = 3√K_T,p. The acceleration is integrated into the joint velocity command (the arm takes velocities).
With sampling time T_s, φ chatters within the band T_s·u⁺ around 0 (eq. 43).

Constraints implemented (following the spec of Appendix B): field of view (hyperellipse per point, eq. 20-24, in
normalized coordinates), occlusion (a forbidden hyperellipse in the image per region and point, section 4.3.3;
the region is declared, not detected: the paper's vision finds the obstacle, ours is told where it is), joint range
(eq. 25-27, exact gradient), joint speed (eq. 28-29, exact gradient), forbidden spheres for the end effector
(eq. 30-31). Gradient error injection (eq. 49) on every constraint's gradient, for robustness runs: the law acts on
the erroneous gradients (its rows, and the φ it slides on); σ itself is measured, not modelled, so it stays exact,
and the law reports it beside φ: a constraint held is σ within the band, whatever the law believed.
When the active constraints leave no freedom (more than n, or rank-deficient), the law aborts (ConstraintAbort).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from services.model.arm import ArmDescription
from services.controller.law import ConstraintAbort, Law, LawConfig, LawOutput, ServoInput


@dataclass
class FovConstraint:
    """Every point inside the hyperellipse h = |x/a|^n + |y/b|^n ≤ 1 in normalized coordinates,
    a = (W/2)(1−margin)/fx, b likewise. ``form``: ``radius`` (default) σ = h^(1/n) − 1, the boundary of eq. 20 with
    a gradient of the image's scale; ``polynomial`` σ = h − 1, eq. 20 as written, whose gradient grows as the
    n-th power near the boundary (n = 16): at a 10-ms sample its switching action asks accelerations no arm
    gives, and it jolts every other constraint (the paper's case study samples at 2 ms)."""

    width: int = 640
    height: int = 480
    fx: float = 615.0
    fy: float = 615.0
    margin: float = 0.05
    exponent: float = 16.0
    K: float = 0.1
    u_plus: float = 2.0
    form: str = "radius"

    def __post_init__(self) -> None:
        if self.form not in ("radius", "polynomial"):
            raise ValueError(f"fov form {self.form!r}: radius or polynomial")

    @property
    def semi_axes(self) -> tuple[float, float]:
        return (self.width / 2.0) * (1 - self.margin) / self.fx, (self.height / 2.0) * (1 - self.margin) / self.fy


@dataclass
class OcclusionConstraint:
    """A forbidden region of the image bounded by the hyperellipse h = |(x − x_c)/a|^n + |(y − y_c)/b|^n = 1, in
    normalized coordinates: σ = 1 − h^(1/n) + margin ≤ 0 for every point (section 4.3.3 leaves the function to
    the user; the experiment of section 10.2.2 uses n = 4, K = 3, u⁺ = 1 at T_s = 0.1 s)."""

    centre: tuple = (0.0, 0.0)
    semi_axes: tuple = (0.05, 0.05)
    exponent: float = 4.0
    margin: float = 0.0
    K: float = 0.1
    u_plus: float = 2.0

    def __post_init__(self) -> None:
        if len(self.centre) != 2 or len(self.semi_axes) != 2 or min(self.semi_axes) <= 0 or self.exponent < 2:
            raise ValueError("occlusion needs a centre (x, y), semi_axes (a, b) > 0 and an exponent ≥ 2")


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

    #: each joint's (rad/s; the law fills in 0.8× the arm's rated speeds when none is given)
    max_speed: Optional[np.ndarray] = None
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
    occlusions: list = field(default_factory=list)
    #: tracking gain K_T,p(0) and its slope magnitude at 0
    K0: float = 4.0
    Kdot0: float = 10.0
    #: sampling time T_s (s); None: from the features' timestamps
    Ts: Optional[float] = None
    #: gradient error injection (eq. 49): relative error c_e on every constraint's gradient, 0 to disable
    gradient_error: float = 0.0
    #: singular values of A1 below rcond·σ_max count as zero (rank test and pseudo-inverses)
    rcond: float = 1e-6
    #: level 2's pseudo-inverse ignores singular values below task_rcond·σ_max: blocking a joint by an active
    #: constraint can leave A2·N1 with a tiny singular value that would otherwise be amplified into a jump
    task_rcond: float = 1e-4
    #: bound on the task levels' joint accelerations (rad/s²; the JACO-2 DSP's 200 deg/s²)
    max_task_accel: float = math.radians(200.0)
    #: discrete-time look-ahead: rounds of activating the constraints this step's acceleration would carry past
    #: φ = 0 by the next sample (0: the paper's test φ ≥ 0 alone)
    lookahead_rounds: int = 3
    #: ... unless their switching actions ask a joint for more than this (rad/s²; the JACO-2 DSP's 200 deg/s²)
    lookahead_max_accel: float = math.radians(200.0)
    #: the sampling time assumed at the first step, before two frames give it (s; the camera's period)
    nominal_period_s: float = 1.0 / 30.0
    #: damping (1/s) of the joint motion left in the null space of both levels: the 7-DoF arm's self-motion,
    #: which neither level sees (the paper's 6R arm has none)
    null_damping: float = 3.0

    @classmethod
    def from_dict(cls, options: dict, arm: ArmDescription) -> "SmcOptions":
        """Options as a scenario writes them, for ``arm``; joint ranges are given per joint number (1-n) in physical
        degrees, like ``joint_range: {joints_deg: {6: [200, 240]}, K: 0.1, u_plus: 2}``."""
        options = {k: (dict(v) if isinstance(v, dict) else v) for k, v in options.items()}
        n = arm.n_joints
        out = cls(joint_speed=JointSpeedConstraint(max_speed=arm.max_speed * 0.8))
        if "fov" in options:
            out.fov = None if options["fov"] is None else FovConstraint(**options.pop("fov"))
        if "joint_range" in options:
            spec = options.pop("joint_range")
            if spec is not None:
                joints = {}
                for number, limits in spec.pop("joints_deg", {}).items():
                    index = int(number) - 1
                    if not 0 <= index < n or len(limits) != 2:
                        raise ValueError(f"joint_range: joint {number} needs two limits, joints are 1-{n}")
                    ends = sorted(arm.sign[index] * math.radians(v) + arm.offset[index] for v in limits)
                    joints[index] = (ends[0], ends[1])
                if not joints:
                    lower, upper = arm.model_limits()
                    joints = {i: (lower[i], upper[i]) for i in range(n) if np.isfinite(lower[i])}
                out.joint_range = JointRangeConstraint(joints=joints, **spec)
        else:
            lower, upper = arm.model_limits()
            out.joint_range = JointRangeConstraint(
                joints={i: (lower[i], upper[i]) for i in range(n) if np.isfinite(lower[i])}, margin=0.05)
        if "joint_speed" in options:
            spec = options.pop("joint_speed")
            if spec is None:
                out.joint_speed = None
            else:
                scale = spec.pop("speed_scale", 0.8)
                out.joint_speed = JointSpeedConstraint(max_speed=arm.max_speed * scale, **spec)
        if "spheres" in options:
            out.spheres = [SphereConstraint(**s) for s in options.pop("spheres")]
        if "occlusions" in options:
            out.occlusions = [OcclusionConstraint(**{k: tuple(v) if isinstance(v, list) else v
                                                     for k, v in o.items()}) for o in options.pop("occlusions")]
        for key, value in options.items():
            if not hasattr(out, key):
                raise ValueError(f"unknown smc option {key!r}")
            setattr(out, key, value)
        return out


@dataclass
class ConstraintSet:
    """Every constraint at one step, one entry per constraint in a fixed order (``names``): its φ as the law
    computes it (with the injected gradient error, if any), the level-1 row (K∇σᵀ, or ∂φ/∂q̇ for speeds) and
    right-hand side (−u⁺) it contributes when active, the part of φ̇ that does not depend on q̈ (∇σᵀq̇ through
    the law's gradient; 0 for speeds) and σ itself (measured: no gradient in it, so exact whatever the gradient
    error)."""

    rows: np.ndarray
    rhs: np.ndarray
    phis: np.ndarray
    drifts: np.ndarray
    sigmas: np.ndarray
    names: list


#: eq. 49's sign pattern for a 6R arm, with a seventh sign chosen for the 7-DoF arm (an arm's first n of them)
GRADIENT_ERROR_SIGNS = np.array([-1.0, 1.0, 1.0, 1.0, -1.0, -1.0, 1.0])


class SlidingModeLaw(Law):
    name = "smc"

    def __init__(self, config: LawConfig | None = None, kinematics=None, **options) -> None:
        super().__init__(config, kinematics)
        self.options = SmcOptions.from_dict(options, self.arm)
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
        self.dq_c = np.zeros(self.arm.n_joints)
        self._Js_prev: Optional[np.ndarray] = None
        self._t_prev: Optional[float] = None

    # ------------------------------------------------------------------ constraints
    def constraints(self, inp: ServoInput, Js: np.ndarray, J_base: np.ndarray, p: np.ndarray,
                    dq: np.ndarray) -> ConstraintSet:
        """Every constraint at this step (eq. 19-31, 40)."""
        opt = self.options
        n_joints = self.arm.n_joints
        # per kind: σ, the gradient ∇σ (w.r.t. q; for speeds ∂φ/∂q̇), the approach gain K (None: a speed, whose φ
        # is σ itself) and the switching gain u⁺
        parts: list[tuple[np.ndarray, np.ndarray, Optional[float], float]] = []
        pts = np.asarray(inp.points)
        Js_points = Js.reshape(-1, 2, n_joints)
        if opt.fov is not None:
            fov = opt.fov
            if fov.form == "polynomial":  # eq. 20 as written
                h, d_h = _hyperellipse(pts, (0.0, 0.0), fov.semi_axes, fov.exponent)
                parts.append((h - 1.0, np.einsum("pk,pkj->pj", d_h, Js_points), fov.K, fov.u_plus))
            else:
                radius, d_radius = _hyperellipse_radius(pts, (0.0, 0.0), fov.semi_axes, fov.exponent)
                parts.append((radius - 1.0, np.einsum("pk,pkj->pj", d_radius, Js_points), fov.K, fov.u_plus))
        for occlusion in opt.occlusions:
            radius, d_radius = _hyperellipse_radius(pts, occlusion.centre, occlusion.semi_axes, occlusion.exponent)
            parts.append((1.0 - radius + occlusion.margin, -np.einsum("pk,pkj->pj", d_radius, Js_points),
                          occlusion.K, occlusion.u_plus))
        if opt.joint_range is not None:
            jr = opt.joint_range
            idx, mid, half = self._range_arrays
            q_t = (np.asarray(inp.q)[idx] - mid) / half
            grad = np.zeros((len(idx), n_joints))
            grad[np.arange(len(idx)), idx] = np.sign(q_t) / half
            parts.append((-1.0 + np.abs(q_t) + jr.margin, grad, jr.K, jr.u_plus))
        if opt.joint_speed is not None:
            js = opt.joint_speed
            parts.append((-1.0 + np.abs(dq) / js.max_speed + js.margin, np.diag(np.sign(dq) / js.max_speed), None,
                          js.u_plus))
        for sphere in opt.spheres:
            offset = p - np.asarray(sphere.centre)
            dist = float(np.linalg.norm(offset))
            grad = J_base[:3].T @ (-offset / max(dist, 1e-12))
            parts.append((np.array([sphere.radius - dist + sphere.margin]), grad[None, :], sphere.K, sphere.u_plus))
        if not parts:
            empty = np.zeros(0)
            return ConstraintSet(np.zeros((0, n_joints)), empty, empty, empty, empty, [])
        rows, rhs, phis, drifts, sigmas = [], [], [], [], []
        for sigma, grad, K, u_plus in parts:
            if opt.gradient_error:  # eq. 49
                grad = grad + opt.gradient_error * GRADIENT_ERROR_SIGNS[:n_joints] * np.abs(grad)
            if K is None:
                rows.append(grad)
                phis.append(sigma)
                drifts.append(np.zeros(len(sigma)))
            else:
                rate = grad @ dq
                rows.append(K * grad)
                phis.append(sigma + K * rate)
                drifts.append(rate)
            sigmas.append(sigma)
            rhs.append(np.full(len(sigma), -u_plus))
        return ConstraintSet(np.vstack(rows), np.concatenate(rhs), np.concatenate(phis), np.concatenate(drifts),
                             np.concatenate(sigmas), self._names(len(pts)))

    def _names(self, n_points: int) -> list[str]:
        cached = getattr(self, "_names_cache", None)
        if cached is None or cached[0] != n_points:
            opt = self.options
            names = [f"fov:{i}" for i in range(n_points)] if opt.fov is not None else []
            names += [f"occlusion:{k}.{i}" for k in range(len(opt.occlusions)) for i in range(n_points)]
            if opt.joint_range is not None:
                names += [f"joint_range:{j + 1}" for j in opt.joint_range.joints]
            if opt.joint_speed is not None:
                names += [f"joint_speed:{j + 1}" for j in range(self.arm.n_joints)]
            names += [f"sphere:{k}" for k in range(len(opt.spheres))]
            self._names_cache = cached = (n_points, names)
        return cached[1]

    def switching_gain(self, name: str) -> float:
        """u⁺ of the constraint called ``name``."""
        opt = self.options
        kind, _, index = name.partition(":")
        if kind == "sphere":
            return opt.spheres[int(index)].u_plus
        if kind == "occlusion":
            return opt.occlusions[int(index.split(".")[0])].u_plus
        return {"fov": opt.fov, "joint_range": opt.joint_range, "joint_speed": opt.joint_speed}[kind].u_plus

    def _kinds(self, names: list[str]) -> dict:
        """kind → (indices of its constraints, their switching gains u⁺); the constraint list is fixed for a law,
        so cached."""
        if getattr(self, "_kinds_cache", None) is None or self._kinds_cache[0] != len(names):
            kinds: dict = {}
            for i, name in enumerate(names):
                kinds.setdefault(name.split(":")[0], []).append(i)
            self._kinds_cache = (len(names), {
                kind: (np.array(indices), np.array([self.switching_gain(names[i]) for i in indices]))
                for kind, indices in kinds.items()})
        return self._kinds_cache[1]

    def _solve(self, cs: ConstraintSet, Js: np.ndarray, b2: np.ndarray, dq: np.ndarray,
               Ts: float) -> tuple[list[int], np.ndarray]:
        """The active set and the acceleration of eq. 15. Active: φ ≥ 0 (eq. 10), and, with ``lookahead``, also a
        constraint that this step's acceleration would carry past 0 by the next sample (φ + T_s·φ̇ ≥ 0): the
        discrete-time law otherwise finds a constraint only after it has crossed, by up to T_s·φ̇ — more than the
        band T_s·u⁺ whenever another constraint's switching action jolts it. Constraints added by looking ahead
        that would leave no freedom, or ask more than ``lookahead_max_accel`` (nearly dependent rows), are left
        out (and found at the next sample, as without look-ahead)."""
        opt = self.options
        active = np.flatnonzero(cs.phis >= 0.0).tolist()

        def solve(indices):
            indices = one_row_per_joint(cs, indices)
            return prioritized_acceleration(cs.rows[indices], cs.rhs[indices], Js, b2, dq, opt)

        try:
            ddq = solve(active)
        except ConstraintAbort as exc:
            raise ConstraintAbort(f"{exc}: {', '.join(cs.names[i] for i in active)}") from None
        for _ in range(opt.lookahead_rounds):
            predicted = cs.phis + Ts * (cs.drifts + cs.rows @ ddq)
            crossing = [i for i in np.flatnonzero(predicted >= 0.0).tolist() if i not in active]
            if not crossing:
                break
            rows = one_row_per_joint(cs, active + crossing)
            if np.abs(np.linalg.pinv(cs.rows[rows]) @ cs.rhs[rows]).max() > opt.lookahead_max_accel:
                break  # nearly dependent rows: an acceleration no arm gives, worse than the overshoot it avoids
            try:
                ddq, active = solve(active + crossing), active + crossing
            except ConstraintAbort:
                break
        return sorted(active), ddq

    # ------------------------------------------------------------------ the step
    def step(self, inp: ServoInput) -> LawOutput:
        opt = self.options
        Ts = opt.Ts
        if Ts is None:
            Ts = (inp.t_s - self._t_prev) if self._t_prev is not None and inp.t_s > self._t_prev \
                else opt.nominal_period_s
        J_c, R_be, J_base = self._camera_jacobian(inp.q, inp.camera_in_ee)
        p = self.kin.data.oMf[self.kin.ee_frame_id].translation.copy()  # computed with the Jacobian above
        L = self._L(inp)
        Js = L @ J_c
        dq = self.dq_c
        e = inp.error
        e_dot = Js @ dq  # ṡ of the noise-free model (static target, static reference)
        s_ddot, K_p = tracking_acceleration(e, e_dot, opt.K0, opt.Kdot0)
        Js_dot = np.zeros_like(Js) if self._Js_prev is None else (Js - self._Js_prev) / Ts
        cs = self.constraints(inp, Js, J_base, p, dq)
        active, ddq = self._solve(cs, Js, s_ddot - Js_dot @ dq, dq, Ts)
        #: the last step's level-1 system, acceleration and active constraint indices (into ``_names``), for
        #: inspection: A1·q̈ = b1 holds when A1 has full rank
        self.last_level1 = (cs.rows[active], cs.rhs[active], ddq, active)
        self.dq_c = dq + Ts * ddq
        self._Js_prev = Js
        self._t_prev = inp.t_s
        # per kind: the φ nearest its band (T_s·u⁺ of this step, eq. 43), that band, the largest σ (the
        # constraint itself, exact even when the law's gradients are not), and how many are active
        notes = {"max_phi": float(np.max(cs.phis)) if len(cs.phis) else -math.inf, "active": len(active),
                 "gain": K_p, "Ts": Ts}
        is_active = np.zeros(len(cs.phis), dtype=bool)
        is_active[active] = True
        for kind, (indices, u_plus) in self._kinds(cs.names).items():
            worst = int(np.argmax(cs.phis[indices] / u_plus))
            notes[f"max_phi.{kind}"] = float(cs.phis[indices][worst])
            notes[f"band.{kind}"] = Ts * float(u_plus[worst])
            notes[f"max_sigma.{kind}"] = float(np.max(cs.sigmas[indices]))
            notes[f"active.{kind}"] = int(np.count_nonzero(is_active[indices]))
        return LawOutput(joint_velocities=self.dq_c.copy(), camera_twist=J_c @ self.dq_c, gain=K_p, notes=notes)


def one_row_per_joint(cs: ConstraintSet, indices: list[int]) -> list[int]:
    """The active rows without the redundant ones: a joint's range and its speed constraints (rows on that
    joint alone) each prescribe that joint's acceleration, and both active at once would be two parallel rows
    (rank-deficient: the paper aborts, section 5.2). Keep the one asking the larger deceleration when they push
    the same way (it satisfies both φ̇ ≤ −u⁺), the speed's when they do not (the range's φ already falls while
    the joint moves away from its limit)."""
    kept: dict[int, int] = {}
    out = []
    for i in indices:
        row = cs.rows[i]
        nonzero = np.flatnonzero(row)
        if len(nonzero) != 1:
            out.append(i)
            continue
        joint = int(nonzero[0])
        if joint not in kept:
            kept[joint] = i
            continue
        other = kept[joint]
        demand_i, demand_other = cs.rhs[i] / row[joint], cs.rhs[other] / cs.rows[other][joint]  # q̈_j each asks
        if np.sign(demand_i) == np.sign(demand_other):
            kept[joint] = i if abs(demand_i) > abs(demand_other) else other
        elif cs.names[i].startswith("joint_speed"):
            kept[joint] = i
    return sorted(out + list(kept.values()))


def _hyperellipse(points: np.ndarray, centre, semi_axes, exponent: float) -> tuple[np.ndarray, np.ndarray]:
    """h = |(x − x_c)/a|^n + |(y − y_c)/b|^n per point (eq. 20's hyperellipse) and ∂h/∂(x, y) (eq. 22-23)."""
    (xc, yc), (a, b) = centre, semi_axes
    ux, uy = (points[:, 0] - xc) / a, (points[:, 1] - yc) / b
    ax, ay = np.abs(ux), np.abs(uy)
    d = np.empty((len(points), 2))
    d[:, 0] = exponent * np.sign(ux) * ax ** (exponent - 1) / a
    d[:, 1] = exponent * np.sign(uy) * ay ** (exponent - 1) / b
    return ax**exponent + ay**exponent, d


def _hyperellipse_radius(points: np.ndarray, centre, semi_axes, exponent: float) -> tuple[np.ndarray, np.ndarray]:
    """r = h^(1/n), the hyperellipse's own "radius" (1 on its boundary, growing like the distance away from it),
    and ∂r/∂(x, y): the same boundary as h = 1, with a gradient that keeps the image's scale where h's grows as
    the n-th power."""
    h, d_h = _hyperellipse(points, centre, semi_axes, exponent)
    radius = h ** (1.0 / exponent)
    return radius, d_h * (radius / (exponent * np.maximum(h, 1e-300)))[:, None]


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
