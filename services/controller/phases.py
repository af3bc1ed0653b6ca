"""A task's phases, as a small pure machine: each phase names its motion and the input that drives it, and says
when it is done. The controller runs the phase the task is in at every frame (:mod:`services.controller.core`);
what it commands goes to safety named ``controller/<phase>`` (services/safety/sources.py).

==========  ==================================================================  ===================  ==========
phase       motion                                                              driven by            done when
==========  ==================================================================  ===================  ==========
servo       the visual servo law (Sensors 2022) toward vision's goal             the features         never (the
                                                                                                     task runs
                                                                                                     until
                                                                                                     stopped), or
                                                                                                     converged
move        the end effector by a displacement in the camera, tool or base      the arm's state      arrived and
            frame from where it was when the phase began, its orientation held  (forward kinematics) at rest
grasp       the arm still, the fingers closing                                  the fingers          the hand
                                                                                (services/model/     holds it
                                                                                grasp.py)            (grasped)
hold        the arm still, the fingers as they are (no finger part: holding)    the fingers          never: until
                                                                                                     a release
release     the arm still, the fingers opening                                  the fingers          open
==========  ==================================================================  ===================  ==========

A plan (``TaskRequest.plan``) is a list of phases (:func:`phases_for`): ``servo`` is [servo], ``move`` is [move],
``grasp`` is [servo until converged, move along the tool's axis (the approach), grasp, move up in the base frame (the
lift), hold], ``release`` is [release] (a release during a grasp task's hold replaces what is left of it). The grasp
fails when the hand closes on nothing (empty) or does not hold within its time; the hold fails when the object slips.
A failed or stopped task outputs nothing more: the fingers keep their targets (safety never opens the hand), so a
cup held stays held; only a release opens it.
Every phase's command is checked by safety as any other (limits, zones, joint horizons, convention) and derives
from the frame at which it was computed (its image stamp), so a move stops like a servo when vision stops.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import msgspec
import numpy as np
import pinocchio as pin

from protocol.messages import FingerCommand, FingerMode, FingerState, GraspVerdict, MoveFrame, TaskPlan, TaskRequest
from services.model.arm import HandDescription
from services.model.grasp import GraspDetector, GraspThresholds
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


class GraspConfig(ConfigStruct):
    """How a grasp task reaches, grasps and lifts (our choices where the issue's task does not say)."""

    #: the approach: how far the end effector moves along its tool axis from the pre-grasp view (m). The taught view
    #: is this far back from where the hand holds the object: our choice, far enough back for the eye-in-hand
    #: camera to see the object whole and some table around it
    approach_m: float = 0.2
    #: the lift: how far up (m): the task's 10 cm (robosuite's lift counts 0.04 m above the table as lifted) and a
    #: centimetre more, our choice, for what the grip gives under the load (the move arrives within 0.5 mm)
    lift_m: float = 0.11
    #: the reach has converged when the features' per-point RMS error is below this: mfvs's choice, 1e-3 (0.6 px at
    #: 615 px, 0.2 mm across and 3 mm in depth at a 3 cm tag 0.2 m away: well inside what the open hand takes in).
    #: Sensors 2022's 2.5e-5 is the tag's noiseless floor; the emulated DSP's velocity dead-band held a reach at 1.7e-4
    reach_error_rms: float = 1e-3
    #: the approach's and the lift's speed (m/s): mfvs's choice, slow beside the JACO-2's assistive 0.05-0.2 m/s, as
    #: a hand near an object and a person should be
    speed_mps: float = 0.04
    #: the grasp fails if the hand does not hold within the fingers' closing time plus this (s)
    grasp_grace_s: float = 1.0
    #: what the grasp detector judges by
    detector: GraspThresholds = msgspec.field(default_factory=GraspThresholds)

    def __post_init__(self) -> None:
        if not (0.0 < self.approach_m <= 0.3 and 0.0 < self.lift_m <= 0.3):
            raise ValueError("grasp.approach_m and grasp.lift_m must be within 0..0.3 m")
        if not (math.isfinite(self.grasp_grace_s) and self.grasp_grace_s > 0):
            raise ValueError("grasp.grasp_grace_s must be positive")
        if not (math.isfinite(self.reach_error_rms) and 0.0 < self.reach_error_rms <= 0.05):
            raise ValueError("grasp.reach_error_rms must be within 0..0.05")
        if not (math.isfinite(self.speed_mps) and 0.005 <= self.speed_mps <= 0.2):
            raise ValueError("grasp.speed_mps must be within 0.005..0.2 m/s")

    def move(self, move: "MoveConfig") -> "MoveConfig":
        """The task's move settings at the grasp's speed."""
        return msgspec.structs.replace(move, speed_mps=self.speed_mps, min_speed_mps=min(move.min_speed_mps,
                                                                                          self.speed_mps))


class ServoPhase:
    """The visual servo: the controller's law on the features (its computation is the core's). ``until_converged``:
    the phase is done when the servo converges (a grasp's reach, below ``error_rms``), else it runs until the task is
    stopped."""

    name = "servo"
    driven_by = "features"

    def __init__(self, until_converged: bool = False, error_rms: Optional[float] = None) -> None:
        self.until_converged = until_converged
        #: converged below this per-point RMS error (None: the controller's threshold)
        self.error_rms = error_rms

    def restart(self) -> None:
        """A resumed servo goes on from the view it has (the core resets the law's memory)."""


@dataclass
class HandStep:
    """One frame of a hand phase: the arm still, the fingers' command (None: they keep their targets), the grasp's
    verdict, and whether the phase is done or failed (why)."""

    fingers: Optional[FingerCommand]
    verdict: GraspVerdict
    done: bool = False
    failure: str = ""
    detail: str = ""


class HandPhase:
    """A phase of the hand with the arm still, judged by the task's grasp detector, which the core feeds every
    fresh state of the fingers through the whole task (the lift between grasp and hold included)."""

    name = "hand"
    driven_by = "fingers"
    #: the detector starts afresh when the phase begins (a new grasp, a release), or goes on (the hold)
    fresh_detector = True

    def __init__(self, detector: GraspDetector) -> None:
        self.detector = detector
        self.hand = detector.hand
        self.started_s: Optional[float] = None

    def restart(self) -> None:
        """Resumed after a pause: its time allowed starts again (a fresh detector, where it has one)."""
        self.started_s = None

    def step(self, t_s: float) -> HandStep:
        """A frame of the phase at ``t_s`` (the state's stamp, s), on the detector's verdict now."""
        if self.started_s is None:
            self.started_s = t_s
        return self.judge(self.detector.verdict, t_s - self.started_s)

    def judge(self, verdict: GraspVerdict, elapsed_s: float) -> HandStep:
        raise NotImplementedError


class GraspPhase(HandPhase):
    """Close the fingers until the hand holds something; fail on nothing between them, or after the closing time
    and ``grace_s`` without a hold."""

    name = "grasp"

    def __init__(self, detector: GraspDetector, grace_s: float) -> None:
        super().__init__(detector)
        hand = self.hand
        self.allowed_s = hand.closing_time_s + grace_s
        self.command = FingerCommand(mode=FingerMode.POSITION, values=[hand.closed_angle] * hand.n_fingers)

    def judge(self, verdict: GraspVerdict, elapsed_s: float) -> HandStep:
        if verdict is GraspVerdict.GRASPED:
            return HandStep(self.command, verdict, done=True, detail="the hand holds it")
        if verdict is GraspVerdict.EMPTY:
            return HandStep(None, verdict, failure="the hand closed on nothing (empty)")
        if elapsed_s > self.allowed_s:
            return HandStep(None, verdict, failure=f"the hand did not hold within {self.allowed_s:.1f} s "
                                                    f"({verdict.value})")
        return HandStep(self.command, verdict, detail=f"closing ({verdict.value})")


class HoldPhase(HandPhase):
    """Hold: the arm still, the fingers as they are (no finger part), until a release."""

    name = "hold"
    fresh_detector = False

    def judge(self, verdict: GraspVerdict, elapsed_s: float) -> HandStep:
        return HandStep(None, verdict, detail=f"holding for {elapsed_s:.1f} s")


class ReleasePhase(HandPhase):
    """Open the fingers; done when they are open (reached)."""

    name = "release"

    def __init__(self, detector: GraspDetector) -> None:
        super().__init__(detector)
        self.command = FingerCommand(mode=FingerMode.POSITION, values=[0.0] * self.hand.n_fingers)
        #: the fingers' full travel, and as long again (mfvs's choice)
        self.allowed_s = 2.0 * self.hand.closing_time_s

    def judge(self, verdict: GraspVerdict, elapsed_s: float) -> HandStep:
        if verdict is GraspVerdict.REACHED:
            return HandStep(self.command, verdict, done=True, detail="the hand is open")
        if elapsed_s > self.allowed_s:
            return HandStep(None, verdict, failure=f"the hand did not open within {self.allowed_s:.1f} s")
        return HandStep(self.command, verdict, detail="opening")


def release_phases(hand: HandDescription, grasp: GraspConfig) -> list:
    """What a release is: the hand opened, judged by a detector of its own."""
    return [ReleasePhase(GraspDetector(hand, grasp.detector))]


class MovePhase:
    """Move the end effector by ``displacement_m`` in ``frame`` (as it is when the phase begins), holding its
    orientation: a straight line at ``speed_mps``, slowing as gain × the remaining distance near the end, closed on
    the arm's measured configuration (forward kinematics of the description)."""

    name = "move"
    driven_by = "state"

    def __init__(self, displacement_m, frame: MoveFrame, config: MoveConfig, name: str = "move",
                 detector: Optional[GraspDetector] = None, needs_previous: bool = False) -> None:
        #: what the phase is called (a grasp's approach and lift are moves); the grasp detector that watches the
        #: hand while it moves (a lift), if any
        self.name = name
        self.detector = detector
        #: its displacement is meant from where the previous phase ended (a grasp's approach, from the converged
        #: pre-grasp view): resumed after a pause, the task goes back to that phase (services.controller.task)
        self.needs_previous = needs_previous
        self.displacement = np.asarray(displacement_m, dtype=float).reshape(3)
        self.frame = MoveFrame(frame)
        self.config = config
        self.target_p: Optional[np.ndarray] = None
        self.target_R: Optional[np.ndarray] = None
        self.started_s: Optional[float] = 0.0
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

    def restart(self) -> None:
        """Resumed after a pause: toward the same target (a lift to where it was going), its time allowed anew from
        where the arm is then; a move that needs its previous phase is begun anew after it."""
        if self.needs_previous:
            self.target_p = self.target_R = None
        self.started_s = None

    def resume_at(self, p: np.ndarray, t_s: float) -> None:
        """The time allowed for what is left of the way, from ``p`` at ``t_s``."""
        cfg = self.config
        self.started_s = t_s
        self.allowed_s = cfg.time_factor * float(np.linalg.norm(self.target_p - p)) / cfg.speed_mps + cfg.grace_s

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


def phases_for(request: TaskRequest, move: MoveConfig, grasp: Optional[GraspConfig] = None,
               hand: Optional[HandDescription] = None) -> list:
    """The phases of a task started by ``request`` (a grasp or a release needs the arm's ``hand``)."""
    if request.plan is TaskPlan.MOVE:
        if not np.any(request.move_m):
            raise ValueError("a move needs a displacement (move_m)")
        return [MovePhase(request.move_m, request.move_frame, move)]
    if request.plan in (TaskPlan.GRASP, TaskPlan.RELEASE):
        if hand is None:
            raise ValueError(f"a {request.plan.value} needs a hand, and the arm carries none")
        grasp = grasp or GraspConfig()
        if request.plan is TaskPlan.RELEASE:
            return release_phases(hand, grasp)
        detector = GraspDetector(hand, grasp.detector)  # one for the grasp, the lift and the hold
        moving = grasp.move(move)
        return [ServoPhase(until_converged=True, error_rms=grasp.reach_error_rms),
                MovePhase((0.0, 0.0, grasp.approach_m), MoveFrame.TOOL, moving, name="approach", needs_previous=True),
                GraspPhase(detector, grasp.grasp_grace_s),
                MovePhase((0.0, 0.0, grasp.lift_m), MoveFrame.BASE, moving, name="lift", detector=detector),
                HoldPhase(detector)]
    return [ServoPhase()]


def twist_from_move(step: MoveStep, kin: ArmKinematics, q) -> tuple[np.ndarray, np.ndarray]:
    """(end-effector twist in its own frame, base-frame geometric twist) of a move step at configuration ``q``."""
    R_be, _ = kin.pose(q)
    twist_ee = np.concatenate([R_be.T @ step.linear_base, step.omega_ee])
    return twist_ee, np.concatenate([step.linear_base, R_be @ step.omega_ee])
