"""Vision's rules, without zenoh, locks or clocks (the Drake shape: the service decodes, calls, counts and
publishes). For each image, in turn: is it newer than the last one taken, young enough, described by the camera
info it came with and of that size; then the front end measures the points (:mod:`services.vision.front_end`) and
the error against the goal is taken point by point, by id. The goal (set, taught from the current view, or from
the config) and the last features seen live here too.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from protocol.messages import CameraInfo, FeatureStatus, Image, ImageEncoding, VisionGoal
from services.model import frames
from services.vision import features as F
from services.vision.front_end import Camera, FrontEndProtocol, Goal, Seen, TagFrontEnd, point_errors


def goal_from_camera_in_tag(camera_in_tag: np.ndarray, size_m: float) -> Goal:
    """What the camera would see of the tag with this pose (4×4) in the tag's frame."""
    points, depths = F.goal_from_camera_in_tag(camera_in_tag, size_m)
    return Goal(points, depths, "camera_in_tag")


def goal_from_features(features, depth_m: float) -> Goal:
    """Explicit points (normalized, ids in their order) at one depth, like Sensors 2022's Table 2."""
    points = np.array(features, dtype=float)
    return Goal(points, np.full(len(points), depth_m), "features")


def goal_from_config(goal, size_m: float) -> Goal:
    if goal.camera_in_tag is not None:
        return goal_from_camera_in_tag(goal.camera_in_tag.matrix(), size_m)
    return goal_from_features(goal.features, goal.depth_m)


@dataclass
class Outcome:
    """What vision says about one image: the status and reason, what the front end saw, the error against the goal
    when it saw the target, and what the service counts (``refusal``: a refused input; ``counts``: counter names,
    one each)."""

    status: FeatureStatus
    detail: str = ""
    seen: Optional[Seen] = None
    goal_points: Optional[np.ndarray] = None
    goal_depths: Optional[np.ndarray] = None
    error: Optional[np.ndarray] = None
    error_norm: float = 0.0
    error_rms: float = 0.0
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
        detector = F.TagDetector(config.tag.family, config.refinement, layout=config.tag.layout,
                                 backend=config.detector, apriltag_corrected_bits=config.apriltag_corrected_bits)
        self.front_end: FrontEndProtocol = TagFrontEnd(config.tag, detector, config.roi, config.min_peak_brightness,
                                                       config.border_margin_px)
        self.goal = goal_from_config(config.goal, config.tag.size_m)
        #: the last features seen in a usable image (what a goal taught from the current view takes)
        self.last_points: Optional[np.ndarray] = None
        self.last_depths: Optional[np.ndarray] = None
        self.last_ids: Optional[np.ndarray] = None
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
        seen = self.front_end.measure(gray_of(image), Camera.from_info(info), self.goal)
        outcome = Outcome(seen.status, seen.detail, seen=seen, counts=list(seen.counts))
        if seen.rejected:
            outcome.refusal = seen.detail
        elif seen.status is FeatureStatus.TARGET_LOST:
            outcome.counts.append("frames.target_lost")
        if seen.points is not None:
            outcome.goal_points, outcome.goal_depths = self.goal.for_ids(seen.ids)
            outcome.error, outcome.error_norm, outcome.error_rms = point_errors(seen.points, outcome.goal_points,
                                                                                seen.weights)
        if not seen.rejected:  # an unusable image says nothing about the view
            self.last_points, self.last_depths, self.last_ids = seen.points, seen.depths, seen.ids
        return outcome

    def goal_from(self, goal: VisionGoal) -> Goal:
        """The goal a VisionGoal asks for (raises ValueError with the reason when it cannot be had)."""
        if goal.teach:
            if self.last_points is None:
                raise ValueError("teach needs the target in view: no current features")
            return Goal(self.last_points, self.last_depths, "teach", ids=self.last_ids)
        if goal.camera_in_tag is not None:
            pose = goal.camera_in_tag
            return goal_from_camera_in_tag(frames.homogeneous(frames.quat_wxyz_to_matrix(pose.quat_wxyz), pose.xyz),
                                           self.config.tag.size_m)
        if len(goal.features) != 4:
            raise ValueError(f"the tag gives 4 points, the goal has {len(goal.features)}")
        return goal_from_features(goal.features, goal.depth_m)
