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

from protocol.conventions import ClockMode
from protocol.messages import (CameraInfo, FeatureStatus, FrontEnd, Image, ImageEncoding, RobotState, TeachPhase,
                               TeachReply, TeachRequest, VisionGoal)
from services.model import frames
from services.model.arm import ArmDescription, declared_arm
from services.model.kinematics import ArmKinematics
from services.runtime.state_history import StateHistory
from services.vision import features as F
from services.vision.front_end import Camera, FrontEndProtocol, Goal, Seen, TagFrontEnd, point_errors
from services.vision.keypoints import KeypointFrontEnd, taught_goal_points
from services.vision.taught import TaughtGoal, decode_goal, encode_goal
from services.vision.teach import TeachError, TeachSession


#: Sensors 2022 Table 2's desired square (±0.1666 at 0.2888 m), in this project's corner order
TABLE2_GOAL = ((-0.1666, -0.1666), (0.1666, -0.1666), (0.1666, 0.1666), (-0.1666, 0.1666))
TABLE2_DEPTH = 0.2888


def goal_from_camera_in_tag(camera_in_tag: np.ndarray, size_m: float) -> Goal:
    """What the camera would see of the tag with this pose (4×4) in the tag's frame."""
    points, depths = F.goal_from_camera_in_tag(camera_in_tag, size_m)
    return Goal(points, depths, "camera_in_tag")


def goal_from_features(features, depth_m: float) -> Goal:
    """Explicit points (normalized, ids in their order) at one depth, like Sensors 2022's Table 2."""
    points = np.array(features, dtype=float)
    return Goal(points, np.full(len(points), depth_m), "features")


def goal_from_config(goal, size_m: float) -> Goal:
    """The configured goal; a taught one's points come with its file (the service reads it: VisionCore.set_taught),
    and until then the goal is Table 2's."""
    if goal.taught is not None:
        return goal_from_features(TABLE2_GOAL, TABLE2_DEPTH)
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
    front_end: FrontEnd = FrontEnd.TAG


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
        self._tag_detector = F.TagDetector(config.tag.family, config.refinement, layout=config.tag.layout,
                                           backend=config.detector,
                                           apriltag_corrected_bits=config.apriltag_corrected_bits)
        self.front_end: FrontEndProtocol = self._tag_front_end()
        #: a taught goal (the keypoint front end's), when the goal is one
        self.taught: Optional[TaughtGoal] = None
        self.goal = goal_from_config(config.goal, config.tag.size_m)
        #: the last features seen in a usable image (what a goal taught from the current view takes)
        self.last_points: Optional[np.ndarray] = None
        self.last_depths: Optional[np.ndarray] = None
        self.last_ids: Optional[np.ndarray] = None
        self._last_capture_ns = -1
        #: the last usable image (grey), its capture stamp and camera info: what a teach takes its views from
        self.last_gray: Optional[np.ndarray] = None
        self.last_gray_ns = 0
        self.last_info: Optional[CameraInfo] = None
        #: the robot's states (a teach takes the arm's pose at each view) and its arm's kinematics
        self.states: StateHistory[RobotState] = StateHistory()
        self.arm: Optional[ArmDescription] = None
        self.kinematics: Optional[ArmKinematics] = None
        self.teach = TeachSession(config.teach)

    def _tag_front_end(self) -> TagFrontEnd:
        cfg = self.config
        return TagFrontEnd(cfg.tag, self._tag_detector, cfg.roi, cfg.min_peak_brightness, cfg.border_margin_px)

    # ------------------------------------------------------------------ the goal
    def set_taught(self, taught: TaughtGoal, info: Optional[CameraInfo]) -> Goal:
        """A taught goal as the goal: the keypoint front end finds it (ValueError, in one line, when it does not fit
        the camera or the arm)."""
        if info is not None:
            problem = taught.mismatch(info, self.arm.name if self.arm is not None else None)
            if problem:
                raise ValueError(problem)
        self._close_front_end()
        self.front_end = KeypointFrontEnd(taught, self.config.keypoints, self.config.min_peak_brightness,
                                          self.config.border_margin_px,
                                          background=ClockMode(self.config.clock) is ClockMode.REALTIME)
        self.taught = taught
        return taught_goal_points(taught)

    def use_tag(self) -> None:
        if self.front_end.kind is not FrontEnd.TAG:
            self._close_front_end()
            self.front_end, self.taught = self._tag_front_end(), None

    def _close_front_end(self) -> None:
        close = getattr(self.front_end, "close", None)
        if close is not None:
            close()

    # ------------------------------------------------------------------ the arm (for a teach)
    def robot_state(self, state: RobotState) -> str:
        """A robot state: kept for the teach's poses; "" or why its arm is not one this host describes."""
        arm, why = declared_arm(state.arm, state.arm_digest, len(state.q), None, self.arm)
        if arm is None:
            return why
        if self.arm is None:
            self.arm, self.kinematics = arm, ArmKinematics(arm)
        self.states.add(state.header.stamp_ns, state)
        return ""

    def state_at(self, capture_ns: int) -> Optional[RobotState]:
        """The arm's state when the frame ``capture_ns`` was taken (the nearest before it)."""
        return self.states.at_capture(capture_ns)

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
        gray = gray_of(image)
        seen = self.front_end.measure(gray, Camera.from_info(info), self.goal)
        outcome = Outcome(seen.status, seen.detail, seen=seen, counts=list(seen.counts), front_end=self.front_end.kind)
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
            self.last_gray, self.last_gray_ns, self.last_info = gray, capture, info
        return outcome

    def goal_from(self, goal: VisionGoal, info: Optional[CameraInfo] = None) -> Goal:
        """The goal a VisionGoal asks for, its front end made ready (raises ValueError with the reason when it cannot
        be had); ``info``: the camera's, which a taught goal must fit (None: the last image's)."""
        if goal.taught_file is not None:
            return self.set_taught(decode_goal(goal.taught_file), info or self.last_info)
        if goal.teach:
            if self.last_points is None:
                raise ValueError("teach needs the target in view: no current features")
            return Goal(self.last_points, self.last_depths, "teach", ids=self.last_ids)
        if goal.camera_in_tag is not None:
            pose = goal.camera_in_tag
            made = goal_from_camera_in_tag(frames.homogeneous(frames.quat_wxyz_to_matrix(pose.quat_wxyz), pose.xyz),
                                           self.config.tag.size_m)
        else:
            if len(goal.features) != 4:
                raise ValueError(f"the tag gives 4 points, the goal has {len(goal.features)}")
            made = goal_from_features(goal.features, goal.depth_m)
        self.use_tag()  # a tag's goal: the tag front end measures it
        return made

    # ------------------------------------------------------------------ teach by showing
    def teach_step(self, request: TeachRequest, now_ns: int) -> TeachReply:
        """One step of a teach (services/vision/teach.py), on the last usable image and the arm's state when it was
        taken; the reply says what was done, or why not."""
        phase = request.phase
        try:
            if phase is TeachPhase.CANCEL:
                self.teach = TeachSession(self.config.teach)
                return TeachReply(ok=True, phase=phase, message="teach cancelled")
            gray, info, stamp = self.last_gray, self.last_info, self.last_gray_ns
            if phase is not TeachPhase.FINISH:
                if gray is None or info is None:
                    raise TeachError("no image yet: the camera is not seen")
                age = (now_ns - stamp) * 1e-9
                if age > self.config.max_image_age_s:
                    raise TeachError(f"the last image is {age * 1e3:.0f} ms old: the camera is not keeping up")
            if phase is TeachPhase.BEGIN:
                region = np.asarray(request.region_px, dtype=float).reshape(-1, 2)
                found = self.teach.begin(gray, info, self.state_at(stamp), self.kinematics, region,
                                         request.detector or self.config.keypoints.detector, request.operator,
                                         self.config.keypoints.equalization)
                return TeachReply(ok=True, phase=phase, keypoints=found,
                                  message=f"{found} keypoints in the region; now move the camera by the probe")
            if phase is TeachPhase.SECOND_VIEW:
                t = self.teach.second_view(gray, self.state_at(stamp), self.kinematics)
                shape = "planar" if t.planar else "not planar"
                return TeachReply(ok=True, phase=phase, keypoints=len(t.points), planar=t.planar,
                                  triangulation_error_px=t.error_px, probe_m=tuple(float(v) for v in t.probe_m),
                                  message=(f"{len(t.points)} keypoints triangulated over a "
                                           f"{np.linalg.norm(t.probe_m) * 1e3:.1f} mm baseline (median error "
                                           f"{t.error_px:.2f} px); the object is {shape}"))
            file = self.teach.finish(request.name, now_ns)
            payload = encode_goal(file)
            taught = decode_goal(payload, "the taught goal")
            self.goal = self.set_taught(taught, info)
            self.teach = TeachSession(self.config.teach)
            return TeachReply(ok=True, phase=phase, goal=taught.name, goal_digest=taught.digest, goal_file=payload,
                              keypoints=len(taught.points_camera),
                              message=f"goal {taught.name} ({taught.digest}) taught: {len(taught.points_camera)} "
                                      "keypoints; vision now servos to it")
        except (TeachError, ValueError) as exc:
            return TeachReply(ok=False, phase=phase, message=str(exc)[:512])
