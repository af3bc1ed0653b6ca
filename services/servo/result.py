"""What a servo task leaves: one :class:`Iteration` per controller iteration (the trajectory log, one JSON line
each) and the :class:`ServoResult` (docs/contracts.md)."""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Optional

from services.runtime.jsonsafe import json_safe


def write_log(records: list[Iteration], path) -> Path:
    """The trajectory log: one strict-JSON object per iteration (a missing measurement is null)."""
    path = Path(path)
    with path.open("w") as f:
        for record in records:
            fields_ = record.__dict__ if record.keypoints is not None else {
                k: v for k, v in record.__dict__.items() if k != "keypoints"}
            f.write(json.dumps(json_safe(fields_), allow_nan=False) + "\n")
    return path


def read_log(path) -> list[dict]:
    """A run's trajectory log (one JSON object per iteration), with the null of a missing measurement (no arm
    state, no error: JSON has no NaN) read back as NaN in the float fields, so the numbers stay numbers."""
    floats = [f.name for f in fields(Iteration) if f.type == "float"]
    records = []
    for line in Path(path).read_text().splitlines():
        record = json.loads(line)
        for name in floats:
            if record.get(name, 0.0) is None:
                record[name] = math.nan
        records.append(record)
    return records


def error_rms(record) -> float:
    """An iteration's per-point RMS error (what convergence is judged on), from its record (an :class:`Iteration` or
    its logged dict): a keypoint target's, as its view gave it (``keypoints.error_rms``: its points are weighted);
    else ‖e‖/√n over its n points, every weight 1 (a tag's: ‖e‖/2)."""
    get = record.get if isinstance(record, dict) else lambda name, default=None: getattr(record, name, default)
    keypoints = get("keypoints")
    if keypoints:
        return float(keypoints["error_rms"])
    n = len(get("points") or ()) or 4
    return float(get("error_norm")) / math.sqrt(n)


@dataclass
class Iteration:
    """One controller iteration as the run log records it."""

    iteration: int
    t_s: float
    #: the stamp of the camera frame this iteration answers
    stamp_ns: int
    status: str
    error_norm: float
    points: list
    error: list
    command: list
    command_kind: str
    q: list
    gain: float
    saturated: bool
    camera_twist: Optional[list]
    manipulability: float
    ee_speed_mps: float
    notes: dict = field(default_factory=dict)
    #: the end effector's measured angular speed (rad/s) at the frame's tick
    ee_angular_speed_rps: float = 0.0
    #: what shaped the arm's motion at the frame's tick (the robot state's faults: the DSP's active limits, e.g.
    #: joint_limit, singularity, zone:base, dead_band, speed)
    robot_faults: list = field(default_factory=list)
    #: the end effector's signed distance to the nearest protection zone of the arm's DSP (m; inside: negative)
    zone_distance_m: Optional[float] = None
    #: safety's answer to the law's command for this frame, when it refused it: why (empty: approved, or no command)
    safety_refusal: str = ""
    #: a keypoint target's figures at this frame (ids, weights, inliers, median error in px, per-point RMS error);
    #: None for a tag, whose log lines then carry no such key
    keypoints: Optional[dict] = None


@dataclass
class ServoResult:
    converged: bool
    iterations: int
    #: the last error the law acted on; None when the tag was never seen (``detail`` says why)
    final_error_norm: Optional[float]
    status: str
    min_manipulability: float
    max_joint_limit_violation_deg: float
    max_linear_speed_mps: float
    trajectory_log: Optional[str] = None
    plots: list = field(default_factory=list)
    law: str = ""
    wall_time_s: float = 0.0
    #: from the first frame the law acted on to the last frame answered (the arm's clock): with
    #: ``frames_answered``, what separates a loop that moves differently from one that sees fewer frames
    servo_time_s: float = 0.0
    #: frames the controller answered in that time, whatever the answer (stale, lost and converged included)
    frames_answered: int = 0
    #: frames that never became an iteration, by where they were lost (the services' counters over the run):
    #: ``camera.dropped`` (the renderer still busy with the last one), ``vision.skipped`` (a newer frame came
    #: before vision took it), ``vision.stale`` (older than vision's image budget)
    frames_lost: dict = field(default_factory=dict)
    #: the largest of each law figure over the run (e.g. smc's max_phi.fov, and its band)
    law_figures: dict = field(default_factory=dict)
    #: why the run ended as it did, in words (empty when it converged)
    detail: str = ""
    #: the first and the largest error the law acted on
    initial_error_norm: Optional[float] = None
    max_error_norm: Optional[float] = None
    #: iterations at whose tick each of the arm's limits shaped its motion (robot state faults)
    robot_limits_hit: dict = field(default_factory=dict)
    #: the closest the end effector came to a protection zone (m; negative: inside)
    min_zone_distance_m: Optional[float] = None
    #: why safety refused the last frame's command it refused (per frame, as ``Iteration.safety_refusal``)
    last_refusal: str = ""
    #: what safety's status said over the run (published at its own rate, so counts vary run to run): its states
    #: seen, the limits it named, its last refusal, a protective stop's reason
    safety: dict = field(default_factory=dict)
    #: the speed limits the robot declared (MotionLimits as a dict)
    robot_limits: Optional[dict] = None
    #: ticks at which the robot node's lockstep wait for the pipeline ran out and the arm went on without its
    #: answer: a host too loaded for the wait (``lockstep.frame_timeout_s``); the run is then not a function of its
    #: scenario alone, and a rerun may differ
    lockstep_timeouts: int = 0
    #: how its stack ran: ``composed`` (the services in the runner's process, :mod:`services.stack.composed`) or
    #: ``processes`` (each service a process of its own, as deployed)
    stack: str = ""
    #: a keypoint target's front end: its wall time a frame (ms: median, 95th percentile, largest, frames), and the
    #: share of frames it detected (the others tracked); None for a tag
    front_end: Optional[dict] = None

    def to_json(self) -> dict:
        return {
            "converged": self.converged, "iterations": self.iterations,
            "final_error_norm": self.final_error_norm, "status": self.status,
            "min_manipulability": self.min_manipulability,
            "max_joint_limit_violation_deg": self.max_joint_limit_violation_deg,
            "max_linear_speed_mps": self.max_linear_speed_mps, "trajectory_log": self.trajectory_log,
            "plots": self.plots, "law": self.law, "wall_time_s": self.wall_time_s,
            "servo_time_s": self.servo_time_s, "frames_answered": self.frames_answered,
            "frames_lost": self.frames_lost, "law_figures": self.law_figures, "detail": self.detail,
            "initial_error_norm": self.initial_error_norm, "max_error_norm": self.max_error_norm,
            "robot_limits_hit": self.robot_limits_hit, "min_zone_distance_m": self.min_zone_distance_m,
            "last_refusal": self.last_refusal, "safety": self.safety, "robot_limits": self.robot_limits,
            "lockstep_timeouts": self.lockstep_timeouts, "stack": self.stack,
            **({"front_end": self.front_end} if self.front_end is not None else {}),
        }
