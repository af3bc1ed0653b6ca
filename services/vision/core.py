"""Vision's rules, without zenoh, locks or clocks (the Drake shape: the service decodes, calls, counts and
publishes). For each image, in turn: is it newer than the last one taken, young enough, described by the camera
info it came with and of that size; then detect → normalise → pose → error (:func:`features.measure`). The
goal (set, taught from the current view, or from the config) and the last features seen live here too.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from protocol.messages import CameraInfo, FeatureStatus, Image, ImageEncoding, VisionGoal
from services.model import frames
from services.vision import features as F


class Goal:
    """The current goal: desired points and depths (4 each)."""

    def __init__(self, points: np.ndarray, depths: np.ndarray, description: str) -> None:
        self.points = np.asarray(points, dtype=float).reshape(-1, 2)
        self.depths = np.asarray(depths, dtype=float).reshape(-1)
        self.description = description

    @classmethod
    def from_camera_in_tag(cls, camera_in_tag: np.ndarray, size_m: float) -> "Goal":
        """What the camera would see with this pose (4×4) in the tag's frame."""
        points, depths = F.goal_from_camera_in_tag(camera_in_tag, size_m)
        return cls(points, depths, "camera_in_tag")

    @classmethod
    def from_features(cls, features, depth_m: float) -> "Goal":
        return cls(np.array(features), np.full(4, depth_m), "features")

    @classmethod
    def from_config(cls, goal, size_m: float) -> "Goal":
        if goal.camera_in_tag is not None:
            return cls.from_camera_in_tag(goal.camera_in_tag.matrix(), size_m)
        return cls.from_features(goal.features, goal.depth_m)


@dataclass
class Outcome:
    """What vision says about one image: the status and reason, the measurement when the tag was seen, and what
    the service counts (``refusal``: a refused input; ``counts``: counter names, one each)."""

    status: FeatureStatus
    detail: str = ""
    measurement: Optional[F.Measurement] = None
    refusal: str = ""
    counts: list[str] = field(default_factory=list)


def gray_of(image: Image) -> np.ndarray:
    """The image as grayscale pixels (mono8 as it is; rgb8/bgr8 converted as OpenCV does)."""
    import cv2

    pixels = np.frombuffer(image.data, dtype=np.uint8)
    if image.encoding is ImageEncoding.MONO8:
        return pixels.reshape(image.height, image.width)
    rgb = pixels.reshape(image.height, image.width, 3)
    code = cv2.COLOR_RGB2GRAY if image.encoding is ImageEncoding.RGB8 else cv2.COLOR_BGR2GRAY
    return cv2.cvtColor(rgb, code)


class VisionCore:
    def __init__(self, config) -> None:
        self.config = config
        self.detector = F.TagDetector(config.tag.family, config.refinement, layout=config.tag.layout,
                                      backend=config.detector, apriltag_corrected_bits=config.apriltag_corrected_bits)
        self.tracker = F.TagTracker(self.detector, config.roi)
        self.goal = Goal.from_config(config.goal, config.tag.size_m)
        #: the last features seen in a usable image (what a taught goal takes)
        self.last_points: Optional[np.ndarray] = None
        self.last_depths: Optional[np.ndarray] = None
        self._last_capture_ns = -1

    def process(self, image: Image, info: Optional[CameraInfo], now_ns: int) -> Outcome:
        """One image, with the camera info at hand and the time now (the service's clock)."""
        cfg = self.config
        capture = image.header.source_stamp_ns or image.header.stamp_ns
        if capture <= self._last_capture_ns:
            reason = f"image captured at {capture} is not newer than the last one processed"
            return Outcome(FeatureStatus.STALE, "out-of-order image", refusal=reason)
        self._last_capture_ns = capture
        age_s = (now_ns - capture) * 1e-9
        if age_s > cfg.max_image_age_s:
            return Outcome(FeatureStatus.STALE, f"image is {age_s * 1e3:.0f} ms old", counts=["frames.stale"])
        if info is None:
            return Outcome(FeatureStatus.INVALID_IMAGE, "no camera info yet", refusal="no camera info yet")
        if (image.width, image.height) != (info.width, info.height):
            reason = f"image is {image.width}x{image.height}, the camera info says {info.width}x{info.height}"
            return Outcome(FeatureStatus.INVALID_IMAGE, reason, refusal=reason)
        measurement = F.measure(gray_of(image), self.tracker, cfg.tag.id, cfg.tag.size_m,
                                F.camera_matrix(info.fx, info.fy, info.cx, info.cy),
                                np.asarray(info.distortion, dtype=float), goal_points=self.goal.points,
                                min_peak_brightness=cfg.min_peak_brightness, border_margin_px=cfg.border_margin_px)
        outcome = Outcome(measurement.status, measurement.detail, measurement=measurement)
        search = self.tracker.take_last_search()
        if search:
            outcome.counts.append(f"detect.{search}")
        if measurement.rejected:
            outcome.refusal = measurement.detail
        elif measurement.status is FeatureStatus.TAG_LOST:
            outcome.counts.append("frames.tag_lost")
        if not measurement.rejected:  # an unusable image says nothing about the view
            self.last_points, self.last_depths = measurement.points, measurement.depths
        return outcome

    def goal_from(self, goal: VisionGoal) -> Goal:
        """The goal a VisionGoal asks for (raises ValueError with the reason when it cannot be had)."""
        if goal.teach:
            if self.last_points is None:
                raise ValueError("teach needs the tag in view: no current features")
            return Goal(self.last_points, self.last_depths, "teach")
        if goal.camera_in_tag is not None:
            pose = goal.camera_in_tag
            return Goal.from_camera_in_tag(frames.homogeneous(frames.quat_wxyz_to_matrix(pose.quat_wxyz), pose.xyz),
                                           self.config.tag.size_m)
        if len(goal.features) != 4:
            raise ValueError(f"the tag gives 4 points, the goal has {len(goal.features)}")
        return Goal.from_features(goal.features, goal.depth_m)
