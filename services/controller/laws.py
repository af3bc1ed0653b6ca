"""The control laws, by the names the scenario file and the controller service use (docs/contracts.md):

=====================  ======================================================================  ============
name                   law                                                                     output
=====================  ======================================================================  ============
p-joint                Sensors 2022 eq. 17-18, constant gain λ, secondary task in the null space joint vel.
adaptive-p-joint       the same with the adaptive gain of eq. 20                               joint vel.
adaptive-pd-joint      adaptive PD in the joint law                                            joint vel.
adaptive-pd-mixed      eq. 21 → eq. 22 → eq. 23-25: the mixed twist (the proposed law)          mixed twist
ee-frame               eq. 21 → eq. 22, the end-effector twist sent as if it were mixed        mixed twist
                       (the conventional mistake of Sensors 2022 Part A; it diverges)
mixed-jacobian-joint   eq. 26: q̇ = Jm⁺·V_m + (I − Jm⁺Jm)·ξ with V_m from eq. 21-25           joint vel.
manipulability         Nelson 1995 eq. 29/40 (services.controller.tracking)                    joint vel.
smc                    Muñoz 2018 eq. 15, 41-42 (services.controller.smc)                       joint vel.
=====================  ======================================================================  ============

A law is an object with ``step(ServoInput) -> LawOutput`` and ``reset()``; it keeps only its own memory (error
rate filter, previous output). It runs without zenoh: the controller service is a thin adapter around it.
"""
from __future__ import annotations

import numpy as np

from protocol.conventions import AngularConvention
from services.controller import ibvs
from services.controller.law import Law, LawConfig, LawOutput, ServoInput
from services.controller.smc import SlidingModeLaw
from services.controller.tracking import ManipulabilityLaw
from services.model import frames
from services.model.kinematics import ArmKinematics

JOINT_LAWS = ("p-joint", "adaptive-p-joint", "adaptive-pd-joint", "mixed-jacobian-joint", "manipulability", "smc")
TWIST_LAWS = ("adaptive-pd-mixed", "ee-frame")
LAW_NAMES = TWIST_LAWS + JOINT_LAWS


class CameraTwistLaw(Law):
    """Eq. 21 adaptive PD in Cartesian space, then to the robot: mixed (eq. 22-25) or, wrongly, end-effector."""

    def __init__(self, *args, mixed: bool = True, **kw) -> None:
        super().__init__(*args, **kw)
        self.mixed = mixed
        self.name = "adaptive-pd-mixed" if mixed else "ee-frame"

    def camera_twist(self, inp: ServoInput) -> tuple[np.ndarray, float]:
        e = inp.error
        L = self._L(inp)
        e_dot, measured_e_dot = self._error_rates(inp, L)
        gain = self._gain(e, adaptive=True)
        Vc = ibvs.pd_camera_twist(L, e, gain, self.config.gains.kd, e_dot, self._target_term(L, measured_e_dot))
        self._last_camera_twist = Vc
        return Vc, gain

    def step(self, inp: ServoInput) -> LawOutput:
        Vc, gain = self.camera_twist(inp)
        T_ec = inp.camera_in_ee
        V_e = frames.ee_twist_from_camera(Vc, T_ec[:3, :3], T_ec[:3, 3])
        if self.mixed:
            R_be, _ = self.kin.pose(inp.q)
            twist = frames.mixed_from_ee_twist(V_e, R_be, self.config.robot_convention)
        else:
            twist = V_e.copy()  # end-effector numbers, declared mixed: the conventional mistake
        return LawOutput(twist=twist, camera_twist=Vc, gain=gain)


class JointLaw(Law):
    """Eq. 17-18 (with the adaptive gain and the PD term as configured)."""

    def __init__(self, *args, adaptive: bool, derivative: bool, name: str, **kw) -> None:
        super().__init__(*args, **kw)
        self.adaptive = adaptive
        self.derivative = derivative
        self.name = name

    def step(self, inp: ServoInput) -> LawOutput:
        e = inp.error
        L = self._L(inp)
        gain = self._gain(e, self.adaptive)
        J_c, _, _ = self._camera_jacobian(inp.q, inp.camera_in_ee)
        e_dot, measured_e_dot = self._error_rates(inp, L, J_c)
        xi = ibvs.joint_limit_task(inp.q, self.lower, self.upper, self.config.joint_limit_gain)
        kd = self.config.gains.kd if self.derivative else 0.0
        drive_e = e
        target = self._target_term(L, measured_e_dot)
        if target is not None:
            drive_e = e + target / gain
        dq = ibvs.joint_law(L, J_c, drive_e, gain, kd, e_dot, xi)
        self._last_camera_twist = J_c @ dq
        return LawOutput(joint_velocities=dq, camera_twist=self._last_camera_twist, gain=gain)


class MixedJacobianJointLaw(CameraTwistLaw):
    """Eq. 26: the seed000 mixed twist of eq. 21-25, realised in joint space through Jm⁺, with ξ in the null
    space of Jm."""

    def __init__(self, *args, **kw) -> None:
        super().__init__(*args, mixed=True, **kw)
        self.name = "mixed-jacobian-joint"

    def step(self, inp: ServoInput) -> LawOutput:
        Vc, gain = self.camera_twist(inp)
        T_ec = inp.camera_in_ee
        V_e = frames.ee_twist_from_camera(Vc, T_ec[:3, :3], T_ec[:3, 3])
        R_be, _, J_base = self.kin.pose_and_jacobian(inp.q)
        V_m = frames.mixed_from_ee_twist(V_e, R_be, AngularConvention.SEED000)
        xi = ibvs.joint_limit_task(inp.q, self.lower, self.upper, self.config.joint_limit_gain)
        dq = ibvs.mixed_jacobian_joint_velocity(frames.mixed_jacobian(J_base, R_be), V_m, xi)
        return LawOutput(joint_velocities=dq, camera_twist=Vc, gain=gain)


def make_law(name: str, config: LawConfig | None, kinematics: ArmKinematics, **options) -> Law:
    """The law called ``name`` (see the module table), on the arm of ``kinematics``."""
    if name == "adaptive-pd-mixed":
        return CameraTwistLaw(config, kinematics, mixed=True)
    if name == "ee-frame":
        return CameraTwistLaw(config, kinematics, mixed=False)
    if name == "p-joint":
        return JointLaw(config, kinematics, adaptive=False, derivative=False, name=name)
    if name == "adaptive-p-joint":
        return JointLaw(config, kinematics, adaptive=True, derivative=False, name=name)
    if name == "adaptive-pd-joint":
        return JointLaw(config, kinematics, adaptive=True, derivative=True, name=name)
    if name == "mixed-jacobian-joint":
        return MixedJacobianJointLaw(config, kinematics)
    if name == "manipulability":
        return ManipulabilityLaw(config, kinematics, **options)
    if name == "smc":
        return SlidingModeLaw(config, kinematics, **options)
    raise ValueError(f"unknown law {name!r}; known: {', '.join(LAW_NAMES)}")
