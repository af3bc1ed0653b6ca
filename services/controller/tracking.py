"""Nelson 1995 (Nelson & Khosla): visual tracking that also keeps the arm away from singularities and joint
limits, by minimising, each camera period,

    F(k+1) = [x(k+1) − x_D]ᵀ Q [x(k+1) − x_D] + uᵀ R u + S / w'(q(k+1))

over the commanded camera twist u on the tracking axes, with x(k+1) = x(k) + B u, B = T·L_s[:, axes] (eq. 12-15,
28, 33). Linearising 1/w' in u gives the closed form of eq. 29/40:

    u = −(BᵀQB + R)⁻¹ [ BᵀQ (x(k) − x_D) − (S / (2 w'²)) ∇_u w' ]

w'(q) = P(q)·det(J Jᵀ) is the manipulability (Yoshikawa's measure squared; eq. 25-26 for a square J, the same
quantity for the 6×7 JACO-2) times the joint-limit penalty P(q) = 1 − exp(−k Π (q_i − q_i,min)(q_i,max − q_i) /
(q_i,max − q_i,min)²) over the limited joints (eq. 27). ∇_u w' is the Cartesian manipulability gradient by forward
differences (eq. 31): each avoidance axis a is displaced by h, mapped to joints through J_c⁺, and
g_a = T·(w'(q + J_c⁺ h e_a) − w'(q))/h. R, Q and S choose which axes track and which avoid (``tracking_axes``,
``avoidance_axes``). The twist is resolved into joint velocities through J_c⁺ (the resolver the gradient assumes).

Paper notes (reconstructed where the text is garbled): eq. 37's S is S/2; eq. 31's T multiplies; eq. 27's k is not
given (k ≈ 200-250 suits the JACO-2's three limited joints); Q and R are retuned for normalized coordinates.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from services.model.arm import ArmDescription
from services.model.kinematics import manipulability
from services.controller.law import Law, LawConfig, LawOutput, ServoInput

AXES = {"vx": 0, "vy": 1, "vz": 2, "wx": 3, "wy": 4, "wz": 5}


@dataclass
class TrackingOptions:
    tracking_axes: list = field(default_factory=lambda: ["vx", "vy", "vz", "wx", "wy", "wz"])
    avoidance_axes: list = field(default_factory=lambda: ["vx", "vy"])
    #: feature-error weight Q = q·I and control-cost weights R = diag(r_translation ×3, r_rotation ×3)
    q: float = 1.0
    r_translation: float = 1e-8
    r_rotation: float = 1e-8
    #: weight of the manipulability cost S / w'
    S: float = 1e-12
    #: joint-limit penalty constant k of eq. 27
    k: float = 220.0
    #: finite-difference step of eq. 31 (m for translations, rad for rotations)
    h: float = 1e-3
    #: sample period T (s)
    period_s: float = 1.0 / 30.0
    #: the desired features of the next period, x_D(k+1), approach the goal exponentially at this rate (1/s):
    #: x_D(k+1) = x(k) − λT (x(k) − x*). The paper lets x_D vary; a fixed x_D = x* (λT = 1) asks for the whole
    #: error in one period, which a loop with a period of latency cannot take
    approach_rate: float = 1.5
    #: w' below this is treated as this (keeps 1/w'² finite at a singularity)
    w_floor: float = 1e-12

    def __post_init__(self) -> None:
        unknown = [a for a in (*self.tracking_axes, *self.avoidance_axes) if a not in AXES]
        if unknown:
            raise ValueError(f"unknown axes {unknown}; axes are {list(AXES)}")
        if not set(self.avoidance_axes) <= set(self.tracking_axes):
            raise ValueError("avoidance axes must be tracking axes")
        if self.q < 0 or self.r_translation <= 0 or self.r_rotation <= 0 or self.S < 0:
            raise ValueError("tracking weights need q ≥ 0, r > 0, S ≥ 0")


def joint_limit_penalty(q, k: float, arm: ArmDescription) -> float:
    """P(q) of eq. 27 over ``arm``'s limited joints: 0 at any limit, 1 − exp(−k/4ⁿ) at mid-range."""
    lower, upper = arm.model_limits()
    limited = np.isfinite(lower)
    q = np.asarray(q, dtype=float)
    lo, hi = lower[limited], upper[limited]
    factors = np.clip((q[limited] - lo) * (hi - q[limited]), 0.0, None) / (hi - lo) ** 2
    return 1.0 - math.exp(-k * float(np.prod(factors)))


class ManipulabilityLaw(Law):
    name = "manipulability"

    def __init__(self, config: LawConfig | None = None, kinematics=None, **options) -> None:
        super().__init__(config, kinematics)
        self.options = TrackingOptions(**options)
        self.axes = [AXES[a] for a in self.options.tracking_axes]
        self.avoid = [self.axes.index(AXES[a]) for a in self.options.avoidance_axes]
        o = self.options
        r = [o.r_translation if a < 3 else o.r_rotation for a in self.axes]
        self.R = np.diag(r)

    def manipulability(self, q) -> float:
        """Yoshikawa's w at q (frame-independent)."""
        return manipulability(self.kin.jacobian_base(q))

    def modified_manipulability(self, q) -> float:
        """w'(q) = P(q)·det(J Jᵀ) (eq. 26 with the penalty of eq. 27)."""
        J = self.kin.jacobian_base(q)
        return joint_limit_penalty(q, self.options.k, self.arm) * max(0.0, float(np.linalg.det(J @ J.T)))

    def gradient(self, q, J_c_pinv: np.ndarray, w: float) -> np.ndarray:
        """∇_u w' on the tracking axes (zero off the avoidance axes), eq. 31."""
        o = self.options
        g = np.zeros(len(self.axes))
        for index in self.avoid:
            delta = np.zeros(6)
            delta[self.axes[index]] = o.h
            g[index] = o.period_s * (self.modified_manipulability(q + J_c_pinv @ delta) - w) / o.h
        return g

    def step(self, inp: ServoInput) -> LawOutput:
        o = self.options
        q = np.asarray(inp.q, dtype=float)
        L = self._L(inp)
        B = o.period_s * L[:, self.axes]
        e = min(1.0, o.approach_rate * o.period_s) * inp.error  # x(k) − x_D(k+1)
        J_c, _, _ = self._camera_jacobian(q, inp.camera_in_ee)
        J_c_pinv = np.linalg.pinv(J_c)
        w = max(self.modified_manipulability(q), o.w_floor)
        g = self.gradient(q, J_c_pinv, w) if o.S > 0 and self.avoid else np.zeros(len(self.axes))
        M = o.q * (B.T @ B) + self.R
        u_track = -np.linalg.solve(M, o.q * (B.T @ e))
        u_avoid = np.linalg.solve(M, (o.S / (2.0 * w * w)) * g)
        u6 = np.zeros(6)
        u6[self.axes] = u_track + u_avoid
        dq = J_c_pinv @ u6
        notes = {"w": self.manipulability(q), "w_prime": w, "penalty": joint_limit_penalty(q, o.k, self.arm),
                 "avoid_speed": float(np.linalg.norm(u_avoid))}
        return LawOutput(joint_velocities=dq, camera_twist=u6, gain=o.q, notes=notes)
