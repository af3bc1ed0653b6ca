"""Vision's front ends behind one interface, as ViSP's features are interchangeable ``vpBasicFeature``s behind one
``vpServo``: each takes a grayscale image, the camera and the goal, and says what it saw (:class:`Seen`): N points
in normalized image coordinates, each with a stable id (the goal's own for that point), a depth, a weight and its
pixel, and one view of its own (the tag's id and pose; the keypoints' inliers and errors). What the goal is and how
the error against it is measured is the same for every front end (:class:`Goal`, :func:`point_errors`).

- :class:`TagFrontEnd`: an AprilTag's four corners (ids 0-3, in detection order), depths from its pose;
- :class:`services.vision.keypoints.KeypointFrontEnd`: a taught view's keypoints matched in the image (markerless).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional, Protocol, Union

import numpy as np

from protocol.messages import FeatureStatus, FrontEnd, KeypointView, TagView
from services.model import frames
from services.model.point_features import feature_error, per_point_rms
from services.vision import features as F


@dataclass(frozen=True)
class Camera:
    """The camera an image came from: intrinsics, distortion and size (from its CameraInfo)."""

    K: np.ndarray
    distortion: np.ndarray
    width: int
    height: int

    @classmethod
    def from_info(cls, info) -> "Camera":
        return cls(F.camera_matrix(info.fx, info.fy, info.cx, info.cy), np.asarray(info.distortion, dtype=float),
                   info.width, info.height)


class Goal:
    """The goal: each point's desired normalized coordinates and depth, by id (a tag's corners 0-3; a taught
    view's keypoints by their index in it)."""

    def __init__(self, points: np.ndarray, depths: np.ndarray, description: str,
                 ids: Optional[np.ndarray] = None) -> None:
        self.points = np.asarray(points, dtype=float).reshape(-1, 2)
        self.depths = np.asarray(depths, dtype=float).reshape(-1)
        self.ids = np.arange(len(self.points)) if ids is None else np.asarray(ids, dtype=int).reshape(-1)
        if not (len(self.points) == len(self.depths) == len(self.ids)) or len(self.points) == 0:
            raise ValueError(f"a goal needs one depth and one id per point ({len(self.points)} points, "
                             f"{len(self.depths)} depths, {len(self.ids)} ids)")
        if len(np.unique(self.ids)) != len(self.ids):
            raise ValueError("a goal's point ids must be unique")
        self._row = {int(i): k for k, i in enumerate(self.ids)}
        self.description = description

    def rows(self, ids) -> np.ndarray:
        """Where each of ``ids`` is in the goal (KeyError naming an id the goal does not have)."""
        try:
            return np.array([self._row[int(i)] for i in ids], dtype=int)
        except KeyError as exc:
            raise KeyError(f"point id {exc.args[0]} is not in the goal ({self.description})") from None

    def for_ids(self, ids) -> tuple[np.ndarray, np.ndarray]:
        """(goal points, goal depths) of ``ids``, in their order."""
        rows = self.rows(ids)
        return self.points[rows], self.depths[rows]


def point_errors(points: np.ndarray, goal_points: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, float, float]:
    """(e = s − s* stacked (x0, y0, x1, y1, ...), ‖e‖, the weighted per-point RMS
    (:func:`services.model.point_features.per_point_rms`))."""
    e, norm = feature_error(points, goal_points)
    return e, norm, per_point_rms(e, weights)


View = Union[TagView, KeypointView]


@dataclass
class Seen:
    """What a front end says about one image: a status, why when it is not ``ok``, and for ``ok`` or ``partial``
    the points (normalized, n×2), their depths, ids, weights (0..1) and pixels, with its view."""

    status: FeatureStatus
    detail: str = ""
    #: the image was unusable or the measurement implausible (counted as a refusal), rather than the target out of
    #: view
    rejected: bool = False
    points: Optional[np.ndarray] = None
    depths: Optional[np.ndarray] = None
    ids: Optional[np.ndarray] = None
    weights: Optional[np.ndarray] = None
    pixels: Optional[np.ndarray] = None
    view: Optional[View] = None
    #: what the front end counts for this image (counter names, one each)
    counts: list[str] = field(default_factory=list)


class FrontEndProtocol(Protocol):
    kind: FrontEnd

    def measure(self, gray: np.ndarray, camera: Camera, goal: Goal) -> Seen: ...


#: the tag's corner ids, in its detection order
TAG_CORNER_IDS = np.arange(4)


class TagFrontEnd:
    """An AprilTag's corners: detected in a window around where they were (:class:`~features.TagTracker`),
    normalized, the tag's pose by IPPE_SQUARE on its known size, each corner's depth from it
    (:func:`services.vision.features.measure`)."""

    kind = FrontEnd.TAG

    def __init__(self, tag, detector: F.TagDetector, roi: F.RoiConfig, min_peak_brightness: int,
                 border_margin_px: float) -> None:
        self.tag = tag
        self.tracker = F.TagTracker(detector, roi)
        self.min_peak_brightness = min_peak_brightness
        self.border_margin_px = border_margin_px

    def measure(self, gray: np.ndarray, camera: Camera, goal: Goal) -> Seen:
        goal_points, _ = goal.for_ids(TAG_CORNER_IDS)
        m = F.measure(gray, self.tracker, self.tag.id, self.tag.size_m, camera.K, camera.distortion,
                      goal_points=goal_points, min_peak_brightness=self.min_peak_brightness,
                      border_margin_px=self.border_margin_px)
        search = self.tracker.take_last_search()
        seen = Seen(m.status, m.detail, rejected=m.rejected, counts=[f"detect.{search}"] if search else [])
        if m.points is not None:
            seen.points, seen.depths, seen.pixels = m.points, m.depths, m.corners_px
            seen.ids, seen.weights = TAG_CORNER_IDS, np.ones(4)
            seen.view = TagView(id=self.tag.id, pose_in_camera=frames.pose_message(*m.pose))
        return seen
