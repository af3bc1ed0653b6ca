"""What every control law is: its gains and configuration, its input (``ServoInput``: the features, their goal
and the arm's configuration at the frame) and output (``LawOutput``), the base class with the pieces the laws share
(the interaction matrix, the gain, the camera Jacobian), and ``ConstraintAbort``. The laws themselves live in
:mod:`services.controller.laws` (Sensors 2022), :mod:`~services.controller.smc` (Muñoz 2018) and
:mod:`~services.controller.tracking` (Nelson 1995); they import this module and nothing imports them back but the
registry (:func:`services.controller.laws.make_law`)."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import msgspec
import numpy as np

from protocol.conventions import AngularConvention, DepthSource, ErrorRateSource
from protocol.messages import FingerCommand
from services.controller import ibvs
from services.model import frames
from services.model.kinematics import ArmKinematics
from services.runtime.config import ConfigStruct


class ConstraintAbort(RuntimeError):
    """A law gives up: its active constraints leave no freedom for the task (Muñoz 2018)."""


class Gains(ConfigStruct):
    """Gains of Sensors 2022 (Table 3's proposed-law values by default). ``lambda`` is the constant gain of p-joint;
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
    #: where the derivative term's ė comes from (see ErrorRateSource). The frame difference lags by its filter and
    #: by the frames' spacing: in realtime, with frames arriving unevenly, it sustained a limit cycle near
    #: convergence (easy.yaml in realtime: 93, 258 and 96 iterations; with camera_motion 81, 79 and 79, lockstep 86)
    error_rate: ErrorRateSource = ErrorRateSource.CAMERA_MOTION
    #: time constant of the frame-difference filter (s); 0 uses the raw difference of successive errors. About
    #: three camera frames: the derivative term's gain on frame-to-frame corner noise (kd/τ) then stays near the
    #: proportional gain λ0; with one frame (0.03 s) a realtime loop limit-cycles at ~1e-3 on 0.05 px of noise.
    #: The frame difference also estimates a moving target's own motion (``target_motion``)
    derivative_tau_s: float = 0.1
    #: estimate and compensate the target's own motion (∂ê/∂t of eq. 19/21) for moving targets
    target_motion: bool = False
    #: gain of the joint-limit avoidance task ξ in the null space (joint laws)
    joint_limit_gain: float = 0.5
    #: the angular convention the robot reads (twist laws express their output in it)
    robot_convention: AngularConvention = AngularConvention.SEED000


@dataclass
class ServoInput:
    """One frame's points against their goal (row i of each array is the same point: its id ``ids[i]``, its weight
    ``weights[i]``), with the arm's configuration at the frame. The laws see the task weighted: the error and the
    interaction matrix with each point's rows scaled by its weight, D·e and D·L̂ (Comport, Marchand and Chaumette,
    "Statistically robust 2-D visual servoing", IEEE T-RO 22(2), 2006, eq. 12: ė = −λ(D̂L̂)⁺De), so that a point
    fading in or out (weight between 0 and 1) changes the command gradually; with every weight 1 (a tag) it is
    Sensors 2022's law exactly."""

    t_s: float
    points: np.ndarray
    depths: np.ndarray
    goal_points: np.ndarray
    goal_depths: np.ndarray
    #: model joint angles (rad)
    q: np.ndarray
    #: the camera's pose in the end-effector frame (4×4)
    camera_in_ee: np.ndarray
    #: model joint velocities (rad/s) at the frame, as the arm measured them; None: not known (the PD laws then
    #: difference successive frames for ė whatever ``error_rate`` says)
    dq: Optional[np.ndarray] = None
    #: each point's id (the goal's): a law's memory of the error follows the same points (None: 0..n-1)
    ids: Optional[np.ndarray] = None
    #: each point's weight in [0, 1] (None: all 1)
    weights: Optional[np.ndarray] = None

    @property
    def row_weights(self) -> Optional[np.ndarray]:
        """The weight of each row of e and L (each point's, twice), or None when every weight is 1."""
        if self.weights is None or np.all(np.asarray(self.weights) == 1.0):
            return None
        return np.repeat(np.asarray(self.weights, dtype=float), 2)

    @property
    def error(self) -> np.ndarray:
        """D·e: the error e = s − s* stacked, each point's rows scaled by its weight."""
        e = (np.asarray(self.points) - np.asarray(self.goal_points)).reshape(-1)
        rows = self.row_weights
        return e if rows is None else rows * e


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
    #: the hand's part of the command (a task's grasp or release: services/controller/phases.py); None: the fingers
    #: keep their targets
    fingers: Optional[FingerCommand] = None


class Law:
    name = "law"

    def __init__(self, config: LawConfig | None, kinematics: ArmKinematics) -> None:
        """``kinematics``: of the arm the law runs on (its description: ``kinematics.arm``)."""
        self.config = config or LawConfig()
        self.kin = kinematics
        self.arm = kinematics.arm
        self.rate = ibvs.ErrorRate(self.config.derivative_tau_s)
        self._last_camera_twist: Optional[np.ndarray] = None
        self.lower, self.upper = self.arm.model_limits()

    def reset(self) -> None:
        self.rate.reset()
        self._last_camera_twist = None

    def step(self, inp: ServoInput) -> LawOutput:
        raise NotImplementedError

    # ---- shared pieces
    def _L(self, inp: ServoInput) -> np.ndarray:
        """D·L̂: the interaction matrix with the configured depth source, each point's rows scaled by its weight."""
        L = ibvs.approximate_interaction_matrix(inp.points, inp.depths, inp.goal_points, inp.goal_depths,
                                                self.config.depth)
        rows = inp.row_weights
        return L if rows is None else rows[:, None] * L

    def _error_rates(self, inp: ServoInput, L: np.ndarray, J_c: Optional[np.ndarray] = None
                     ) -> tuple[np.ndarray, np.ndarray]:
        """(ė for the derivative term of eq. 21, ė differenced from the frames). The first is the change of the
        error due to the camera's own motion, L̂·J_c(q)·q̇, when the configuration asks for it and the input
        carries the arm's joint velocities; the second is what a moving target's estimate needs (eq. 19's ∂ê/∂t
        is the measured rate less the camera's part), so it is kept up to date either way."""
        measured = self.rate.update(inp.error, inp.t_s, inp.ids)
        if self.config.error_rate is not ErrorRateSource.CAMERA_MOTION or inp.dq is None:
            return measured, measured
        if J_c is None:
            J_c = self._camera_jacobian(inp.q, inp.camera_in_ee)[0]
        return ibvs.camera_motion_error_rate(L, J_c, inp.dq), measured

    def _gain(self, e: np.ndarray, adaptive: bool) -> float:
        g = self.config.gains
        return ibvs.adaptive_gain(float(np.max(np.abs(e))), g.lambda0, g.lambda_inf, g.slope0) if adaptive \
            else g.lambda_

    def _target_term(self, L: np.ndarray, measured_e_dot: np.ndarray) -> Optional[np.ndarray]:
        if not self.config.target_motion or self._last_camera_twist is None:
            return None
        return ibvs.target_motion_term(measured_e_dot, L, self._last_camera_twist)

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
