"""Starts nobody tuned: the target placed at random in front of the camera, for Sensors 2022's Table 3 over many
starts (``mfvs experiment table3 --random-starts N``), the markerless experiment (the same draws, the tag replaced by
the object) and the realtime-against-lockstep comparison (``mfvs bench swap --random-starts N``).

A start is a scenario (:class:`services.servo.Scenario`) whose ``target.pose_in_camera`` is drawn from the ranges of
Table 2's kind of task (:data:`TABLE2_LIKE`), kept only when every point of the target's outline (a tag's corners, a
plane's, a cup's silhouette: services/robot_sim/scene.py ``target_outline``) is in the image at the start; the arm,
the goal, the law and the camera are the base scenario's. Each start is written out as a scenario file, so any one
of them can be run again with ``--scenario``.
"""
from __future__ import annotations

import random
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from services.model.frames import PoseConfig
from services.robot_sim.scene import target_outline


@dataclass(frozen=True)
class StartRanges:
    """Where a start puts the tag, in the camera frame at the arm's start (OpenCV optical frame: z ahead)."""

    #: distance ahead of the camera (m)
    ahead_m: tuple[float, float]
    #: off the optical axis, sideways (x) and up or down (y), each within ± this (m)
    off_centre_m: float
    #: turned away from facing the camera: roll (about x, from 180°) and pitch (about y), each within ± (deg)
    roll_deg: float
    pitch_deg: float
    #: turned about the optical axis within ± (deg)
    yaw_deg: float
    #: every corner at least this far inside the image (px), so the detector sees the whole tag
    margin_px: float = 10.0


#: issue 34's Table-2-like starts: the tag 0.48-0.65 m ahead, off-centre up to ±7 cm, roll within ±15° of facing,
#: pitch ±12°, turned ±40° about the optical axis (Table 2's own start: 0.52 m, 6 and 4 cm off, 172°, −6°, 30°)
TABLE2_LIKE = StartRanges(ahead_m=(0.48, 0.65), off_centre_m=0.07, roll_deg=15.0, pitch_deg=12.0, yaw_deg=40.0)
#: draws before a generator gives up on ranges whose tag never fits in the image
MAX_DRAWS = 1000


def corners_in_image(pose: PoseConfig, outline: np.ndarray, camera) -> np.ndarray:
    """The target's outline points (n×3 in its frame) in pixels, seen by ``camera`` (a
    :class:`~services.robot_sim.scene.CameraConfig`) with the target at ``pose`` in the camera frame."""
    T = pose.matrix()
    corners = outline @ T[:3, :3].T + T[:3, 3]
    cx, cy = camera.principal_point
    return np.column_stack([camera.fx * corners[:, 0] / corners[:, 2] + cx,
                            camera.fy * corners[:, 1] / corners[:, 2] + cy])


def all_corners_visible(pose: PoseConfig, outline: np.ndarray, camera, margin_px: float) -> bool:
    T = pose.matrix()
    if np.any(outline @ T[:3, :3].T[:, 2] + T[2, 3] <= 0.0):
        return False  # behind the camera
    pixels = corners_in_image(pose, outline, camera)
    return bool(np.all(pixels[:, 0] >= margin_px) and np.all(pixels[:, 0] <= camera.width - 1 - margin_px)
                and np.all(pixels[:, 1] >= margin_px) and np.all(pixels[:, 1] <= camera.height - 1 - margin_px))


def random_start(rng: random.Random, ranges: StartRanges, outline: np.ndarray, camera) -> PoseConfig:
    """A target pose in the camera frame from ``ranges`` with every point of its ``outline`` (n×3, its frame) in the
    image (drawn again until it is)."""
    for _ in range(MAX_DRAWS):
        off = ranges.off_centre_m
        pose = PoseConfig(
            xyz=(round(rng.uniform(-off, off), 4), round(rng.uniform(-off, off), 4),
                 round(rng.uniform(*ranges.ahead_m), 4)),
            rpy_deg=(round(180.0 + rng.uniform(-ranges.roll_deg, ranges.roll_deg), 2),
                     round(rng.uniform(-ranges.pitch_deg, ranges.pitch_deg), 2),
                     round(rng.uniform(-ranges.yaw_deg, ranges.yaw_deg), 2)))
        if all_corners_visible(pose, outline, camera, ranges.margin_px):
            return pose
    raise ValueError(f"no target pose within {ranges} keeps its whole outline in a {camera.width}×{camera.height} "
                     "image")


@dataclass(frozen=True)
class Start:
    """One drawn start: which (seed, index), the tag's pose, and the scenario file that runs it."""

    seed: int
    index: int
    pose_in_camera: PoseConfig
    scenario: Path

    def to_json(self) -> dict:
        return {"seed": self.seed, "index": self.index, "scenario": str(self.scenario),
                "pose_in_camera": {"xyz": list(self.pose_in_camera.xyz),
                                   "rpy_deg": list(self.pose_in_camera.rpy_deg)}}


def write_starts(base: Path, count: int, seed: int, out_dir: Path, ranges: StartRanges = TABLE2_LIKE,
                 command: str = "mfvs experiment table3 --random-starts", arm: str | None = None) -> list[Start]:
    """``count`` starts from ``seed``: copies of the ``base`` scenario file (on ``arm``, when given) with the tag
    placed at random, written to ``out_dir`` (``<base>_seed<S>_start<i>.yaml``). The same seed gives the same
    starts."""
    from services.servo.scenario import load_scenario, on_arm

    if count < 1:
        raise ValueError("the number of random starts must be at least 1")
    rng = random.Random(seed)
    scenario = on_arm(load_scenario(base), arm, str(base))
    document = yaml.safe_load(Path(base).read_text()) or {}
    if arm is not None:
        document.setdefault("robot", {})["arm"] = arm
    out_dir.mkdir(parents=True, exist_ok=True)
    starts = []
    for index in range(count):
        pose = random_start(rng, ranges, target_outline(scenario.target), scenario.camera)
        target = document.setdefault("target", {})
        target.pop("pose_in_base", None)
        target["pose_in_camera"] = {"xyz": list(pose.xyz), "rpy_deg": list(pose.rpy_deg)}
        stem = Path(base).stem if arm is None or arm in Path(base).stem else f"{Path(base).stem}_{arm}"
        path = out_dir / f"{stem}_seed{seed}_start{index}.yaml"
        path.write_text(f"# {Path(base).name} from a random start ({command} {count} --seed {seed}: start {index})\n"
                        + yaml.safe_dump(document, sort_keys=False))
        starts.append(Start(seed, index, pose, path))
    return starts


def quartiles(values: list[float]) -> dict:
    """Median and quartiles (the 25th and 75th percentiles, linear interpolation), or nulls for no values."""
    if not values:
        return {"n": 0, "q1": None, "median": None, "q3": None, "min": None, "max": None}
    q1, median, q3 = (float(np.percentile(values, p)) for p in (25, 50, 75))
    return {"n": len(values), "q1": q1, "median": median, "q3": q3, "min": min(values), "max": max(values)}
