"""Joint-space computed-torque control (seed 003, chapter 4) and its reference: the cubic of seed 003 eq. 5.1,
X(t) = X0 + (3/tf²)(Xf − X0)t² − (2/tf³)(Xf − X0)t³, here between two joint configurations.

    τ = M̂(q)·(q̈_d + Kp (q_d − q) + Kd (q̇_d − q̇)) + Ĉ(q, q̇)q̇ + ĝ(q)        (eq. 4.16-4.18 with feedforward)

computed with Pinocchio's recursive Newton-Euler algorithm on the shared JACO-2 model. With the actuators' own
gravity compensation on (as on the real DSP), ĝ(q) is left out of the command.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from services.model.arm import ArmDescription


def cubic(q0, qf, tf: float, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Position, velocity and acceleration of eq. 5.1 at time t (held at qf after tf)."""
    q0, qf = np.asarray(q0, dtype=float), np.asarray(qf, dtype=float)
    t = min(max(t, 0.0), tf)
    d = qf - q0
    return (q0 + d * (3 * t**2 / tf**2 - 2 * t**3 / tf**3), d * (6 * t / tf**2 - 6 * t**2 / tf**3),
            d * (6 / tf**2 - 12 * t / tf**3))


@dataclass
class ComputedTorque:
    arm: ArmDescription
    #: per joint (1/s², 1/s); None: 100 and 20 for every joint
    kp: np.ndarray = None
    kd: np.ndarray = None
    #: leave ĝ(q) out: the actuators add it themselves
    actuator_gravity_compensation: bool = True

    def __post_init__(self) -> None:
        n = self.arm.n_joints
        self.kp = np.full(n, 100.0) if self.kp is None else np.asarray(self.kp, dtype=float)
        self.kd = np.full(n, 20.0) if self.kd is None else np.asarray(self.kd, dtype=float)
        self.model = self.arm.load_pinocchio().model
        self.data = self.model.createData()

    def torque(self, q, dq, q_d, dq_d, ddq_d) -> np.ndarray:
        """Joint torques (model sign, N·m): M̂(q)·w + Ĉ(q, q̇)q̇ + ĝ(q) + friction (Pinocchio's CRBA includes the
        rotors' inertia, model.armature)."""
        q, dq = np.asarray(q, dtype=float), np.asarray(dq, dtype=float)
        w = np.asarray(ddq_d) + self.kp * (np.asarray(q_d) - q) + self.kd * (np.asarray(dq_d) - dq)
        M = pin.crba(self.model, self.data, q)
        M = np.triu(M) + np.triu(M, 1).T
        tau = M @ w + pin.nonLinearEffects(self.model, self.data, q, dq) + self.model.damping * dq
        if self.actuator_gravity_compensation:
            tau = tau - pin.computeGeneralizedGravity(self.model, self.data, q)
        return tau
