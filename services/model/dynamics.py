"""The arm's dynamics as its description says it: M̂(q), Ĉ(q, q̇)q̇ and ĝ(q) by Pinocchio (the model both the torque
controllers and safety's and the robot's contact monitor use; one model, in the layer every service may use), and
the end effector's kinematics in the mixed frame of the JACO thesis (eq. 3.12)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from services.model.arm import ArmDescription


@dataclass(frozen=True)
class Kinematics:
    """The end effector at one configuration, in the thesis's mixed frame (eq. 3.12): J_v (3×n) in the base frame,
    J_ω (3×n) in the end-effector frame."""

    R: np.ndarray
    p: np.ndarray
    J_v: np.ndarray
    J_w: np.ndarray

    @property
    def J(self) -> np.ndarray:
        return np.vstack([self.J_v, self.J_w])


class DynamicsModel:
    """The arm as a torque controller knows it: Pinocchio on the description (kinematics, M̂(q) by CRBA, ĝ(q)).

    ``rotor_inertia``: M̂ includes the motors' rotor inertia reflected through the gears (the description's
    ``armature``, which the emulated arm has); without it M̂ is the links' alone, as the thesis's eq. 3.35 built it
    from the CAD model. ``friction``: the description's viscous friction is known (the thesis neglects friction,
    L2094). Not thread-safe: one per loop."""

    def __init__(self, arm: ArmDescription, rotor_inertia: bool = False, friction: bool = False) -> None:
        self.arm = arm
        shared = arm.load_pinocchio()
        self.model = pin.Model(shared.model)  # a copy: the shared model keeps its armature
        if not rotor_inertia:
            self.model.armature = np.zeros(self.model.nv)
        self.friction = arm.damping.copy() if friction else np.zeros(arm.n_joints)
        self.rotor_inertia = rotor_inertia
        self.ee_frame_id = shared.ee_frame_id
        self.data = self.model.createData()

    def kinematics(self, q) -> Kinematics:
        q = np.asarray(q, dtype=float)
        pin.computeJointJacobians(self.model, self.data, q)
        pin.updateFramePlacements(self.model, self.data)
        placement = self.data.oMf[self.ee_frame_id]
        J = pin.getFrameJacobian(self.model, self.data, self.ee_frame_id, pin.LOCAL_WORLD_ALIGNED)
        R = placement.rotation.copy()
        return Kinematics(R=R, p=placement.translation.copy(), J_v=J[:3].copy(), J_w=R.T @ J[3:])

    def mass(self, q) -> np.ndarray:
        M = pin.crba(self.model, self.data, np.asarray(q, dtype=float))
        return np.triu(M) + np.triu(M, 1).T

    def gravity(self, q) -> np.ndarray:
        return pin.computeGeneralizedGravity(self.model, self.data, np.asarray(q, dtype=float)).copy()

    def coriolis(self, q, dq) -> np.ndarray:
        """Ĉ(q, q̇)q̇ (without gravity)."""
        q, dq = np.asarray(q, dtype=float), np.asarray(dq, dtype=float)
        return pin.nonLinearEffects(self.model, self.data, q, dq) - self.gravity(q)
