"""A taught goal: the view a person showed the arm once (``mfvs teach``), kept as a file they can keep and give again
(``mfvs task start --goal FILE``).

The file (MessagePack, :class:`TaughtGoalFile`, validated as it is read) holds what the keypoint front end needs to
find the object again and what the servo needs to go back to the view: the object's region in the taught image,
its keypoints and descriptors, each keypoint's 3D point in the taught camera's frame (its depth measured by the arm
itself: a small known motion and triangulation, services/vision/teach.py), the plane's normal where the object is
planar, the camera's intrinsics and resolution, and the arm and its pose at the teach. It is named by its name and
its digest (the file's SHA-256, 16 hex digits), as the robot names its arm: features measured against it say which
goal they were measured against, and a file whose camera, resolution or arm differ from the stack's is refused in
one line.
"""
from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Optional

import cv2
import msgspec
import numpy as np

from protocol.messages import CameraInfo, GoalName

#: what a taught-goal file says it is, and the version of its layout this build reads
FILE_FORMAT = "mfvs-taught-goal"
FILE_VERSION = 1
#: the contrast equalizations a goal's images may have had before the detector (services/vision/keypoints.py)
EQUALIZATIONS = ("none", "clahe")
#: the largest file read (a taught goal is tens to hundreds of kB: a few hundred descriptors and a small image)
MAX_FILE_BYTES = 16 * 1024 * 1024
#: the most keypoints a goal keeps (the strongest, spread over the region)
MAX_GOAL_KEYPOINTS = 2000

#: the camera's intrinsics must agree with the goal's within this (px): a goal taught through another lens, or a
#: camera recalibrated since, would put every point in the wrong place
INTRINSICS_TOLERANCE_PX = 0.5

Float = Annotated[float, msgspec.Meta(ge=-1e9, le=1e9)]


class TaughtCamera(msgspec.Struct, forbid_unknown_fields=True):
    width: Annotated[int, msgspec.Meta(ge=8, le=8192)]
    height: Annotated[int, msgspec.Meta(ge=8, le=8192)]
    fx: Annotated[float, msgspec.Meta(gt=0.0)]
    fy: Annotated[float, msgspec.Meta(gt=0.0)]
    cx: float
    cy: float
    distortion: Annotated[list[float], msgspec.Meta(max_length=14)] = []


class TaughtGoalFile(msgspec.Struct, forbid_unknown_fields=True, kw_only=True):
    """The file's contents, as they are written and read (a plain ``msgpack`` client reads them as a map)."""

    format: str
    version: int
    name: GoalName
    #: when it was taught (ns since the epoch, or the simulator's clock) and by whom
    taught_ns: Annotated[int, msgspec.Meta(ge=0)] = 0
    operator: Annotated[str, msgspec.Meta(max_length=64)] = ""
    #: sift or orb: the detector its descriptors are of
    detector: Annotated[str, msgspec.Meta(pattern="^(sift|orb)$")]
    #: the contrast equalization its images got before the detector (services/vision/keypoints.py: none, or CLAHE);
    #: a file without it was taught on the images as they came
    equalization: Annotated[str, msgspec.Meta(pattern=f"^({'|'.join(EQUALIZATIONS)})$")] = "none"
    camera: TaughtCamera
    arm: Annotated[str, msgspec.Meta(pattern=r"^[a-z0-9_]{1,32}$")]
    arm_digest: Annotated[str, msgspec.Meta(pattern=r"^[0-9a-f]{16}$")]
    #: the arm's model joint angles (rad) and the camera's pose in the base frame (4×4, row by row) at the teach
    joints: Annotated[list[Float], msgspec.Meta(min_length=1, max_length=7)]
    camera_in_base: Annotated[list[Float], msgspec.Meta(min_length=16, max_length=16)]
    #: the object's region in the taught image (px, a polygon)
    region_px: Annotated[list[tuple[Float, Float]], msgspec.Meta(min_length=3, max_length=64)]
    #: per keypoint: its pixel in the taught image, its 3D point in the taught camera's frame (m)
    keypoints_px: Annotated[list[tuple[Float, Float]], msgspec.Meta(max_length=MAX_GOAL_KEYPOINTS)]
    points_camera: Annotated[list[tuple[Float, Float, Float]], msgspec.Meta(max_length=MAX_GOAL_KEYPOINTS)]
    #: the descriptors, one row per keypoint: ``descriptor_dtype`` (float32 for sift, uint8 for orb) row-major
    descriptors: bytes
    descriptor_dtype: Annotated[str, msgspec.Meta(pattern="^(float32|uint8)$")]
    descriptor_size: Annotated[int, msgspec.Meta(ge=1, le=512)]
    #: a planar object: its plane in the taught camera's frame (unit normal toward the camera, distance m); the
    #: keypoint front end then rejects outliers with a homography, else with the epipolar constraint
    planar: bool
    plane_normal: Optional[tuple[Float, Float, Float]] = None
    plane_distance_m: Optional[Float] = None
    #: the camera's measured motion between the two views the depths were triangulated from (m, taught frame) and
    #: the triangulation's median reprojection error (px)
    probe_m: tuple[Float, Float, Float] = (0.0, 0.0, 0.0)
    triangulation_error_px: Float = 0.0
    #: the taught view (grey PNG): what the console shows, and the reference of the region
    image_png: bytes = b""


@dataclass
class TaughtGoal:
    """A taught goal, read and checked: its file's contents as arrays, its name and digest."""

    file: TaughtGoalFile
    digest: str
    keypoints_px: np.ndarray
    points_camera: np.ndarray
    descriptors: np.ndarray

    @property
    def name(self) -> str:
        return self.file.name

    @property
    def camera_matrix(self) -> np.ndarray:
        c = self.file.camera
        return np.array([[c.fx, 0.0, c.cx], [0.0, c.fy, c.cy], [0.0, 0.0, 1.0]])

    def normalized(self) -> np.ndarray:
        """The keypoints where they were taught, in normalized image coordinates (the goal's points): the view
        itself, not its triangulated points' projection, so that seeing the taught view again is a zero error."""
        c = self.file.camera
        dist = np.asarray(c.distortion, dtype=float) if any(c.distortion) else None
        return cv2.undistortPoints(self.keypoints_px.reshape(-1, 1, 2), self.camera_matrix, dist).reshape(-1, 2)

    def region(self) -> np.ndarray:
        return np.asarray(self.file.region_px, dtype=float)

    def image(self) -> Optional[np.ndarray]:
        if not self.file.image_png:
            return None
        return cv2.imdecode(np.frombuffer(self.file.image_png, np.uint8), cv2.IMREAD_GRAYSCALE)

    def mismatch(self, info: CameraInfo, arm: Optional[str] = None) -> str:
        """Why this goal does not fit the camera ``info`` describes (and ``arm``, when given), in one line; "" when
        it does."""
        c = self.file.camera
        if (info.width, info.height) != (c.width, c.height):
            return (f"goal {self.name} was taught at {c.width}x{c.height}; the camera gives {info.width}x"
                    f"{info.height}")
        off = max(abs(info.fx - c.fx), abs(info.fy - c.fy), abs(info.cx - c.cx), abs(info.cy - c.cy))
        if off > INTRINSICS_TOLERANCE_PX:
            return (f"goal {self.name} was taught through another camera (intrinsics differ by {off:.1f} px: fx "
                    f"{c.fx:g} fy {c.fy:g} cx {c.cx:g} cy {c.cy:g}, the camera's {info.fx:g} {info.fy:g} {info.cx:g} "
                    f"{info.cy:g})")
        dist = list(info.distortion) + [0.0] * 14
        if any(abs(a - b) > 1e-6 for a, b in zip(list(c.distortion) + [0.0] * 14, dist)):
            return f"goal {self.name} was taught through a lens of other distortion"
        if arm is not None and arm != self.file.arm:
            return f"goal {self.name} was taught on the {self.file.arm}; this stack runs the {arm}"
        return ""


def digest_of(payload: bytes) -> str:
    return hashlib.sha256(payload).hexdigest()[:16]


def encode_goal(goal: TaughtGoalFile) -> bytes:
    return msgspec.msgpack.encode(goal)


_decoder = msgspec.msgpack.Decoder(TaughtGoalFile)


def decode_goal(payload: bytes, where: str = "the goal") -> TaughtGoal:
    """A taught goal from its file's bytes; ValueError naming what is wrong, in one line."""
    if len(payload) > MAX_FILE_BYTES:
        raise ValueError(f"{where}: {len(payload)} bytes, more than a taught goal's {MAX_FILE_BYTES}")
    try:
        goal = _decoder.decode(payload)
    except msgspec.ValidationError as exc:
        raise ValueError(f"{where}: not a valid taught goal ({exc})") from None
    except (msgspec.DecodeError, UnicodeDecodeError, ValueError, TypeError, OverflowError, RecursionError):
        raise ValueError(f"{where}: not a taught goal file (malformed MessagePack)") from None
    if goal.format != FILE_FORMAT:
        raise ValueError(f"{where}: not a taught goal file (format {goal.format!r})")
    if goal.version != FILE_VERSION:
        raise ValueError(f"{where}: a taught goal of version {goal.version}; this build reads {FILE_VERSION}")
    n = len(goal.keypoints_px)
    if n < 4 or len(goal.points_camera) != n:
        raise ValueError(f"{where}: {n} keypoints and {len(goal.points_camera)} 3D points (at least 4, one each)")
    dtype = np.dtype(goal.descriptor_dtype)
    if len(goal.descriptors) != n * goal.descriptor_size * dtype.itemsize:
        raise ValueError(f"{where}: descriptors hold {len(goal.descriptors)} bytes, {n} rows of "
                         f"{goal.descriptor_size} {goal.descriptor_dtype} need {n * goal.descriptor_size * dtype.itemsize}")
    if (goal.detector == "sift") != (goal.descriptor_dtype == "float32"):
        raise ValueError(f"{where}: {goal.detector} descriptors are not {goal.descriptor_dtype}")
    points = np.asarray(goal.points_camera, dtype=float)
    keypoints = np.asarray(goal.keypoints_px, dtype=float)
    descriptors = np.frombuffer(goal.descriptors, dtype=dtype).reshape(n, goal.descriptor_size)
    if not (np.all(np.isfinite(points)) and np.all(np.isfinite(keypoints)) and np.all(np.isfinite(descriptors))):
        raise ValueError(f"{where}: a keypoint, 3D point or descriptor is not finite")
    if not np.all(points[:, 2] > 0.01):
        raise ValueError(f"{where}: a 3D point is not in front of the taught camera (depth ≤ 1 cm)")
    if len(goal.joints) and not all(math.isfinite(v) for v in goal.joints + goal.camera_in_base):
        raise ValueError(f"{where}: the arm's pose at the teach is not finite")
    if goal.planar and (goal.plane_normal is None or goal.plane_distance_m is None):
        raise ValueError(f"{where}: a planar goal needs its plane_normal and plane_distance_m")
    c = goal.camera
    if not np.all((keypoints >= -0.5) & (keypoints <= [c.width - 0.5, c.height - 0.5])):
        raise ValueError(f"{where}: a keypoint is outside the taught {c.width}x{c.height} image")
    return TaughtGoal(goal, digest_of(payload), keypoints, points, descriptors.copy())


def read_goal(path: str | Path) -> tuple[TaughtGoal, bytes]:
    """The taught goal in file ``path`` and the file's bytes; ValueError naming the file, in one line."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"goal file {path}: no such file")
    if path.stat().st_size > MAX_FILE_BYTES:
        raise ValueError(f"goal file {path}: larger than a taught goal ({MAX_FILE_BYTES} bytes at most)")
    payload = path.read_bytes()
    return decode_goal(payload, f"goal file {path}"), payload


def write_goal(goal: TaughtGoalFile, path: str | Path) -> str:
    """Write the file (atomically: a reader never sees half of it); its digest."""
    return write_goal_bytes(encode_goal(goal), path)


def write_goal_bytes(payload: bytes, path: str | Path) -> str:
    """Write a taught goal's file from its bytes (atomically: a reader never sees half of it); its digest."""
    decode_goal(payload, "the goal written")  # what is written is readable: the same checks as a reader's
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_suffix(path.suffix + ".partial")
    partial.write_bytes(payload)
    partial.replace(path)
    return digest_of(payload)

