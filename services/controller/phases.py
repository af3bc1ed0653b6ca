"""A task's phases, as a small pure machine: each phase names its motion and the input that drives it, and says
when it is done. The controller runs the phase the task is in at every frame (:mod:`services.controller.core`);
what it commands goes to safety named ``controller/<phase>`` (services/safety/sources.py).

==========  ==================================================================  ===================  ==========
phase       motion                                                              driven by            done when
==========  ==================================================================  ===================  ==========
servo       the visual servo law (Sensors 2022) toward vision's goal             the features         never: the
                                                                                                     task runs
                                                                                                     until stopped
move        the end effector by a displacement in the camera, tool or base      the arm's state      arrived and
            frame from where it was when the phase began, its orientation held  (forward kinematics) at rest
==========  ==================================================================  ===================  ==========

A plan (``TaskRequest.plan``) is a list of phases (:func:`phases_for`): ``servo`` is [servo], ``move`` is [move].
Every phase's command is checked by safety as any other (limits, zones, joint horizons, convention) and derives
from the frame at which it was computed (its image stamp), so a move stops like a servo when vision stops.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import numpy as np
import pinocchio as pin

from protocol.messages import MoveFrame, TaskPlan, TaskRequest
from services.model.kinematics import ArmKinematics
from services.runtime.config import ConfigStruct


class MoveConfig(ConfigStruct):
    """How a move phase moves (our choices: a probe or an approach is a short, slow, precise motion)."""

    #: the end effector's speed along the way (m/s): slow, well inside the JACO-2's assistive 0.05-0.2 m/s
    speed_mps: float = 0.02
    #: the slowest it is told to go before it arrives (m/s): above the emulated arm's velocity dead-band (2 mm/s,
    #: services/robot/dsp.py DeadBand), below which it would creep; a real arm's dead-band may be higher (docs/robot.md)
    min_speed_mps: float = 0.004
    #: proportional gain on the remaining distance near the end (1/s): speed = gain × distance, within the two above
    gain_per_s: float = 2.0
    #: arrived within this distance of the target and this angle of the orientation held (m, rad)
    tolerance_m: float = 5e-4
    tolerance_rad: float = 2e-3
    #: gain of the orientation hold (1/s)
    angular_gain_per_s: float = 2.0
    #: ... and at rest: the end effector slower than this (m/s)
    rest_speed_mps: float = 1e-3
    #: the move fails if it has not arrived after this multiple of its distance at ``speed_mps``, plus ``grace_s``
    time_factor: float = 3.0
    grace_s: float = 3.0

    def __post_init__(self) -> None:
        for name in ("speed_mps", "min_speed_mps", "gain_per_s", "tolerance_m", "tolerance_rad",
                     "angular_gain_per_s", "rest_speed_mps", "time_factor", "grace_s"):
            value = getattr(self, name)
            if not (value > 0 and math.isfinite(value)):
                raise ValueError(f"move.{name} must be positive")
        if self.min_speed_mps > self.speed_mps:
            raise ValueError("move.min_speed_mps must not exceed move.speed_mps")


@dataclass
class MoveStep:
    """One frame of a move: the end effector's linear velocity (base frame) and angular velocity (its own frame),
    or that it is done (``done``) or failed (``failure``: why); ``remaining_m``: how far it still is."""

    linear_base: np.ndarray
    omega_ee: np.ndarray
    remaining_m: float
    done: bool = False
    failure: str = ""


class ServoPhase:
    """The visual servo: the controller's law on the features (its computation is the core's)."""

    name = "servo"
    driven_by = "features"


class MovePhase:
    """Move the end effector by ``displacement_m`` in ``frame`` (as it is when the phase begins), holding its
    orientation: a straight line at ``speed_mps``, slowing as gain × the remaining distance near the end, closed on
    the arm's measured configuration (forward kinematics of the description)."""

    name = "move"
    driven_by = "state"

    def __init__(self, displacement_m, frame: MoveFrame, config: MoveConfig) -> None:
        self.displacement = np.asarray(displacement_m, dtype=float).reshape(3)
        self.frame = MoveFrame(frame)
        self.config = config
        self.target_p: Optional[np.ndarray] = None
        self.target_R: Optional[np.ndarray] = None
        self.started_s = 0.0
        self.allowed_s = 0.0

    def begin(self, R_be: np.ndarray, p: np.ndarray, camera_in_ee: np.ndarray, t_s: float) -> None:
        """The target: the displacement from the end effector's pose now (``R_be``, ``p``)."""
        if self.frame is MoveFrame.BASE:
            offset = self.displacement
        elif self.frame is MoveFrame.TOOL:
            offset = R_be @ self.displacement
        else:  # the camera's displacement, carried by the end effector as mounted (a pure translation of the hand)
            offset = R_be @ (camera_in_ee[:3, :3] @ self.displacement)
        self.target_p, self.target_R = p + offset, np.array(R_be, dtype=float)
        self.started_s = t_s
        cfg = self.config
        self.allowed_s = cfg.time_factor * float(np.linalg.norm(offset)) / cfg.speed_mps + cfg.grace_s

    def step(self, R_be: np.ndarray, p: np.ndarray, ee_speed_mps: float, t_s: float) -> MoveStep:
        cfg = self.config
        error = self.target_p - p
        distance = float(np.linalg.norm(error))
        rotation = pin.log3(R_be.T @ self.target_R)  # the hold's error, in the end effector's frame
        arrived = distance <= cfg.tolerance_m and float(np.linalg.norm(rotation)) <= cfg.tolerance_rad
        if arrived and ee_speed_mps <= cfg.rest_speed_mps:
            return MoveStep(np.zeros(3), np.zeros(3), distance, done=True)
        if t_s - self.started_s > self.allowed_s:
            return MoveStep(np.zeros(3), np.zeros(3), distance, failure=(
                f"the move did not arrive within {self.allowed_s:.1f} s ({distance * 1e3:.1f} mm away)"))
        linear = np.zeros(3)
        if distance > cfg.tolerance_m:
            linear = error / distance * min(cfg.speed_mps, max(cfg.min_speed_mps, cfg.gain_per_s * distance))
        return MoveStep(linear, cfg.angular_gain_per_s * rotation, distance)


def phases_for(request: TaskRequest, move: MoveConfig) -> list:
    """The phases of a task started by ``request``."""
    if request.plan is TaskPlan.MOVE:
        if not np.any(request.move_m):
            raise ValueError("a move needs a displacement (move_m)")
        return [MovePhase(request.move_m, request.move_frame, move)]
    return [ServoPhase()]


def twist_from_move(step: MoveStep, kin: ArmKinematics, q) -> tuple[np.ndarray, np.ndarray]:
    """(end-effector twist in its own frame, base-frame geometric twist) of a move step at configuration ``q``."""
    R_be, _ = kin.pose(q)
    twist_ee = np.concatenate([R_be.T @ step.linear_base, step.omega_ee])
    return twist_ee, np.concatenate([step.linear_base, R_be @ step.omega_ee])
