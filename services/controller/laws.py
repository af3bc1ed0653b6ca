"""The control laws, by the names the scenario file and the controller service use (ARCHITECTURE.md):

=====================  ======================================================================  ============
name                   law                                                                     output
=====================  ======================================================================  ============
p-joint                seed 000 eq. 17-18, constant gain λ, secondary task in the null space   joint vel.
adaptive-p-joint       the same with the adaptive gain of eq. 20                               joint vel.
adaptive-pd-joint      adaptive PD in the joint law                                            joint vel.
adaptive-pd-mixed      eq. 21 → eq. 22 → eq. 23-25: the mixed twist (the proposed law)          mixed twist
ee-frame               eq. 21 → eq. 22, the end-effector twist sent as if it were mixed        mixed twist
                       (the conventional mistake of seed 000 Part A; it diverges)
mixed-jacobian-joint   eq. 26: q̇ = Jm⁺·V_m + (I − Jm⁺Jm)·ξ with V_m from eq. 21-25           joint vel.
manipulability         seed 004 eq. 29/40 (services.controller.tracking)                       joint vel.
smc                    seed 002 eq. 15, 41-42 (services.controller.smc)                         joint vel.
=====================  ======================================================================  ============

A law is an object with ``step(ServoInput) -> LawOutput`` and ``reset()``; it keeps only its own memory (error
rate filter, previous output). It runs without zenoh: the controller service is a thin adapter around it.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import msgspec
import numpy as np

from protocol.conventions import AngularConvention, DepthSource
from services.common import frames, jaco2
from services.common.config import ConfigStruct
from services.common.kinematics import ArmKinematics
from services.controller import ibvs

JOINT_LAWS = ("p-joint", "adaptive-p-joint", "adaptive-pd-joint", "mixed-jacobian-joint", "manipulability", "smc")
TWIST_LAWS = ("adaptive-pd-mixed", "ee-frame")
LAW_NAMES = TWIST_LAWS + JOINT_LAWS


class Gains(ConfigStruct):
    """Gains of seed 000 (Table 3's proposed-law values by default). ``lambda`` is the constant gain of p-joint;
    the adaptive laws use λ0, λ∞ and the slope λ'0 at 0 (eq. 20); kd is the derivative gain (eq. 21)."""

    lambda_: float = msgspec.field(default=1.2, name="lambda")
    lambda0: float = 4.5
    lambda_inf: float = 0.5
    slope0: float = 30.0
    kd: float = 0.55

    def __post_init__(self) -> None:
        if not (self.lambda_ > 0 and self.lambda0 > self.lambda_inf >= 0 and self.slope0 >= 0 and self.kd >= 0):
            raise ValueError("gains need lambda > 0, lambda0 > lambda_inf >= 0, slope0 >= 0, kd >= 0")


class LawConfig(ConfigStruct):
    gains: Gains = msgspec.field(default_factory=Gains)
    depth: DepthSource = DepthSource.CURRENT
    #: time constant of the error-rate filter (s); 0 uses the raw difference of successive errors. About three
    #: camera frames: the derivative term's gain on frame-to-frame corner noise (kd/τ) then stays near the
    #: proportional gain λ0; with one frame (0.03 s) a realtime loop limit-cycles at ~1e-3 on 0.05 px of noise
    derivative_tau_s: float = 0.1
    #: estimate and compensate the target's own motion (∂ê/∂t of eq. 19/21) for moving targets
    target_motion: bool = False
    #: gain of the joint-limit avoidance task ξ in the null space (joint laws)
    joint_limit_gain: float = 0.5
    #: the angular convention the robot reads (twist laws express their output in it)
    robot_convention: AngularConvention = AngularConvention.SEED000


@dataclass
class ServoInput:
    t_s: float
    points: np.ndarray
    depths: np.ndarray
    goal_points: np.ndarray
    goal_depths: np.ndarray
    #: model joint angles (rad)
    q: np.ndarray
    #: the camera's pose in the end-effector frame (4×4)
    camera_in_ee: np.ndarray

    @property
    def error(self) -> np.ndarray:
        return (np.asarray(self.points) - np.asarray(self.goal_points)).reshape(-1)


@dataclass
class LawOutput:
    #: mixed twist (linear base frame; angular in the robot's convention) for twist laws
    twist: Optional[np.ndarray] = None
    #: joint velocities (model, rad/s) for joint laws
    joint_velocities: Optional[np.ndarray] = None
    #: the camera twist the law asked for (camera frame), for logs
    camera_twist: Optional[np.ndarray] = None
    gain: float = 0.0
    notes: dict = field(default_factory=dict)


class Law:
    name = "law"

    def __init__(self, config: LawConfig | None = None, kinematics: ArmKinematics | None = None) -> None:
        self.config = config or LawConfig()
        self.kin = kinematics or ArmKinematics()
        self.rate = ibvs.ErrorRate(self.config.derivative_tau_s)
        self._last_camera_twist: Optional[np.ndarray] = None
        self.lower, self.upper = jaco2.model_limits()

    def reset(self) -> None:
        self.rate.reset()
        self._last_camera_twist = None

    def step(self, inp: ServoInput) -> LawOutput:
        raise NotImplementedError

    # ---- shared pieces
    def _L(self, inp: ServoInput) -> np.ndarray:
        return ibvs.approximate_interaction_matrix(inp.points, inp.depths, inp.goal_points, inp.goal_depths,
                                                   self.config.depth)

    def _gain(self, e: np.ndarray, adaptive: bool) -> float:
        g = self.config.gains
        return ibvs.adaptive_gain(float(np.max(np.abs(e))), g.lambda0, g.lambda_inf, g.slope0) if adaptive \
            else g.lambda_

    def _target_term(self, L: np.ndarray, e_dot: np.ndarray) -> Optional[np.ndarray]:
        if not self.config.target_motion or self._last_camera_twist is None:
            return None
        return ibvs.target_motion_term(e_dot, L, self._last_camera_twist)

    def _camera_jacobian(self, q, camera_in_ee) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(J_c, R_be, J_base): J_c maps joint velocities to the camera twist in the camera frame."""
        R_be, _, J_base = self.kin.pose_and_jacobian(q)
        key = camera_in_ee.tobytes()
        if getattr(self, "_camera_key", None) != key:  # the mount rarely changes: keep its motion transform
            self._camera_key = key
            self._X_ce = frames.motion_transform_inv(camera_in_ee[:3, :3], camera_in_ee[:3, 3])
        J_ee = np.empty_like(J_base)
        J_ee[:3] = R_be.T @ J_base[:3]
        J_ee[3:] = R_be.T @ J_base[3:]
        return self._X_ce @ J_ee, R_be, J_base


class CameraTwistLaw(Law):
    """Eq. 21 adaptive PD in Cartesian space, then to the robot: mixed (eq. 22-25) or, wrongly, end-effector."""

    def __init__(self, *args, mixed: bool = True, **kw) -> None:
        super().__init__(*args, **kw)
        self.mixed = mixed
        self.name = "adaptive-pd-mixed" if mixed else "ee-frame"

    def camera_twist(self, inp: ServoInput) -> tuple[np.ndarray, float]:
        e = inp.error
        L = self._L(inp)
        e_dot = self.rate.update(e, inp.t_s)
        gain = self._gain(e, adaptive=True)
        Vc = ibvs.pd_camera_twist(L, e, gain, self.config.gains.kd, e_dot, self._target_term(L, e_dot))
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
        e_dot = self.rate.update(e, inp.t_s)
        gain = self._gain(e, self.adaptive)
        J_c, _, _ = self._camera_jacobian(inp.q, inp.camera_in_ee)
        xi = ibvs.joint_limit_task(inp.q, self.lower, self.upper, self.config.joint_limit_gain)
        kd = self.config.gains.kd if self.derivative else 0.0
        drive_e = e
        target = self._target_term(L, e_dot)
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
        Jm = frames.mixed_jacobian(J_base, R_be)
        Jm_pinv = np.linalg.pinv(Jm)
        xi = ibvs.joint_limit_task(inp.q, self.lower, self.upper, self.config.joint_limit_gain)
        dq = Jm_pinv @ V_m + (np.eye(jaco2.N_JOINTS) - Jm_pinv @ Jm) @ xi
        return LawOutput(joint_velocities=dq, camera_twist=Vc, gain=gain)


def make_law(name: str, config: LawConfig | None = None, kinematics: ArmKinematics | None = None, **options) -> Law:
    """The law called ``name`` (see the module table)."""
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
        from services.controller.tracking import ManipulabilityLaw

        return ManipulabilityLaw(config, kinematics, **options)
    if name == "smc":
        from services.controller.smc import SlidingModeLaw

        return SlidingModeLaw(config, kinematics, **options)
    raise ValueError(f"unknown law {name!r}; known: {', '.join(LAW_NAMES)}")
