"""The vision service: camera images → AprilTag point features, depths and error against the goal.

Inputs: images and camera info (``…/camera/*``); goals on ``…/vision/goal`` or through the queryables
``…/vision/api/set_goal`` (VisionGoal → VisionGoalReply) and ``…/vision/api/get_goal``.
Output: Features on ``…/vision/features`` for every image processed, carrying the image's capture stamp and
trace. The status says at once when the tag is lost; an image older than ``max_image_age_s`` when its turn
comes is answered with ``stale`` and no features; unusable images with ``invalid_image``.

Images are processed in a worker thread, newest first: if images arrive faster than they are processed, the
older waiting one is dropped (counted as ``frames.skipped``), so features are never late by a queue.
"""
from __future__ import annotations

import threading
from typing import Optional

import msgspec
import numpy as np
import zenoh

from protocol.messages import (
    CameraInfo,
    Features,
    FeatureStatus,
    Image,
    ImageEncoding,
    Pose,
    ProtocolError,
    VisionGoal,
    VisionGoalReply,
    decode,
    encode,
)
from services.model import frames
from services.model import tag as tags
from services.runtime.config import ConfigStruct, PoseConfig
from services.runtime.service import Service, ServiceConfig, query_argument
from services.runtime.threads import start_thread
from services.vision import features as F

#: seed 000 Table 2's desired square (±0.1666 at 0.2888 m), in this project's corner order
TABLE2_GOAL = ((-0.1666, -0.1666), (0.1666, -0.1666), (0.1666, 0.1666), (-0.1666, 0.1666))
TABLE2_DEPTH = 0.2888


class TagConfig(ConfigStruct):
    family: str = "tag36h11"
    id: int = 0
    #: edge of the black square (m)
    size_m: float = 0.0962

    def __post_init__(self) -> None:
        if self.family not in tags.FAMILIES:
            raise ValueError(f"unknown tag family {self.family!r}; known: {sorted(tags.FAMILIES)}")
        if not 0.005 <= self.size_m <= 1.0:
            raise ValueError("tag size_m must be within 0.005..1 m")


class GoalConfig(ConfigStruct):
    """One of: features (normalized, corner order as detected) with depth_m; or camera_in_tag."""

    features: Optional[list[tuple[float, float]]] = msgspec.field(default_factory=lambda: list(TABLE2_GOAL))
    depth_m: Optional[float] = TABLE2_DEPTH
    camera_in_tag: Optional[PoseConfig] = None

    def __post_init__(self) -> None:
        if (self.features is None) == (self.camera_in_tag is None):
            raise ValueError("give the goal as features (with depth_m) or as camera_in_tag, exactly one")
        if self.features is not None and (self.depth_m is None or self.depth_m <= 0 or len(self.features) != 4):
            raise ValueError("goal features need 4 points and a positive depth_m")


class VisionConfig(ServiceConfig):
    tag: TagConfig = msgspec.field(default_factory=TagConfig)
    goal: GoalConfig = msgspec.field(default_factory=GoalConfig)
    refinement: F.Refinement = F.Refinement.APRILTAG_SUBPIX
    roi: F.RoiConfig = msgspec.field(default_factory=F.RoiConfig)
    #: an image older than this (capture to processing, in the service's clock) gets status stale
    max_image_age_s: float = 0.25
    #: a tag whose corners come closer than this to the image border is reported as partial
    border_margin_px: float = 2.0
    #: an image whose brightest pixel is below this is refused as all black (lens covered, camera fault)
    min_peak_brightness: int = 16


class Goal:
    """The current goal: desired points and depths (4 each)."""

    def __init__(self, points: np.ndarray, depths: np.ndarray, description: str) -> None:
        self.points = np.asarray(points, dtype=float).reshape(-1, 2)
        self.depths = np.asarray(depths, dtype=float).reshape(-1)
        self.description = description

    @classmethod
    def from_config(cls, goal: GoalConfig, size_m: float) -> "Goal":
        if goal.camera_in_tag is not None:
            points, depths = F.goal_from_camera_in_tag(goal.camera_in_tag.matrix(), size_m)
            return cls(points, depths, "camera_in_tag")
        return cls(np.array(goal.features), np.full(4, goal.depth_m), "features")


class VisionService(Service):
    name = "vision"

    def __init__(self, config: VisionConfig | None = None, **kw) -> None:
        config = config or VisionConfig()
        super().__init__(config, **kw)
        self.config: VisionConfig = config
        self.detector = F.TagDetector(config.tag.family, config.refinement)
        self.tracker = F.TagTracker(self.detector, config.roi)
        self.goal = Goal.from_config(config.goal, config.tag.size_m)
        self._lock = threading.Lock()
        self._info: Optional[CameraInfo] = None
        self._pending: Optional[tuple[Image, int]] = None
        self._wake = threading.Condition(self._lock)
        self._last_points: Optional[np.ndarray] = None
        self._last_depths: Optional[np.ndarray] = None
        self._last_capture_ns = -1
        self._worker: Optional[threading.Thread] = None

    # ------------------------------------------------------------------ lifecycle
    def on_start(self) -> None:
        keys = self.keys
        self.features_pub = self.publisher(keys.features, "features")
        self.subscribe(keys.camera_info, CameraInfo, self._on_camera_info, "camera_info")
        self.subscribe(keys.camera_image, Image, self._on_image, "image", sim_stamped=True)
        self.subscribe(keys.vision_goal, VisionGoal, lambda goal, _: self.set_goal(goal), "goal")
        self.queryable(keys.vision_api("set_goal"), self._on_set_goal_query)
        self.queryable(keys.vision_api("get_goal"), self._on_get_goal_query)
        self._worker = start_thread(self._work, "vision-worker")
        self._request_camera_info()

    def on_stop(self) -> None:
        with self._wake:
            self._wake.notify_all()
        if self._worker is not None:
            self._worker.join(timeout=5.0)

    def check_health(self) -> tuple[bool, str]:
        if self._worker is None or not self._worker.is_alive():
            return False, "worker stopped"
        if self._info is None:
            return False, "no camera info yet"
        return True, f"goal from {self.goal.description}"

    # ------------------------------------------------------------------ inputs
    def _request_camera_info(self) -> None:
        """Ask the camera (robot_sim answers on the camera-info key) rather than wait for its next broadcast."""
        try:
            for reply in self.session.get(self.keys.camera_info, timeout=2.0):
                if reply.ok is not None:
                    self._on_camera_info_payload(reply.ok.payload.to_bytes())
        except Exception:
            self.limited_log.warning("camera_info_query", "camera info query failed; waiting for its broadcast")

    def _on_camera_info_payload(self, payload: bytes) -> None:
        try:
            info = decode(payload, CameraInfo)
        except ProtocolError as exc:
            self.refuse("camera_info", str(exc))
            return
        self._on_camera_info(info, 0)

    def _on_camera_info(self, info: CameraInfo, _recv_ns: int) -> None:
        with self._lock:
            self._info = info

    def _on_image(self, image: Image, recv_ns: int) -> None:
        with self._wake:
            if self._pending is not None:
                self.counters.inc("frames.skipped")
            self._pending = (image, recv_ns)
            self._wake.notify()

    # ------------------------------------------------------------------ goal
    def set_goal(self, goal: VisionGoal) -> VisionGoalReply:
        try:
            if goal.teach:
                with self._lock:
                    points, depths = self._last_points, self._last_depths
                if points is None:
                    raise ValueError("teach needs the tag in view: no current features")
                new = Goal(points, depths, "teach")
            elif goal.camera_in_tag is not None:
                T = frames.homogeneous(frames.quat_wxyz_to_matrix(goal.camera_in_tag.quat_wxyz),
                                       goal.camera_in_tag.xyz)
                points, depths = F.goal_from_camera_in_tag(T, self.config.tag.size_m)
                new = Goal(points, depths, "camera_in_tag")
            else:
                if len(goal.features) != 4:
                    raise ValueError(f"the tag gives 4 points, the goal has {len(goal.features)}")
                new = Goal(np.array(goal.features), np.full(4, goal.depth_m), "features")
        except ValueError as exc:
            self.refuse("goal", str(exc))
            return VisionGoalReply(ok=False, message=str(exc))
        with self._lock:
            self.goal = new
        self.log.info("goal set from %s", new.description)
        return VisionGoalReply(ok=True, goal_points=[tuple(p) for p in new.points], goal_depths=new.depths.tolist())

    def _on_set_goal_query(self, query: zenoh.Query) -> None:
        try:
            reply = self.set_goal(query_argument(query, "set_goal", VisionGoal))
        except ProtocolError as exc:
            self.refuse("goal", str(exc))
            reply = VisionGoalReply(ok=False, message=str(exc)[:256])
        query.reply(query.key_expr, encode(reply))

    def _on_get_goal_query(self, query: zenoh.Query) -> None:
        try:
            query_argument(query, "get_goal", None)
        except ProtocolError as exc:
            self.refuse("api", str(exc))
            query.reply(query.key_expr, encode(VisionGoalReply(ok=False, message=str(exc)[:256])))
            return
        with self._lock:
            goal = self.goal
        query.reply(query.key_expr, encode(VisionGoalReply(
            ok=True, message=goal.description, goal_points=[tuple(p) for p in goal.points],
            goal_depths=goal.depths.tolist())))

    # ------------------------------------------------------------------ processing
    def _work(self) -> None:
        while True:
            with self._wake:
                while self._pending is None and not self.stop_requested:
                    self._wake.wait(0.2)
                if self.stop_requested:
                    return
                image, recv_ns = self._pending
                self._pending = None
            try:
                self.features_pub.put(self.process(image, recv_ns))
            except Exception:
                self.counters.inc("errors.processing")
                self.limited_log.error("processing", "vision: processing an image failed")
                self.log.debug("processing failure", exc_info=True)

    def _answer(self, image: Image, recv_ns: int, status: FeatureStatus, detail: str = "", **fields) -> Features:
        header = self.header("features", source=image.header, recv_ns=recv_ns)
        with self._lock:
            goal = self.goal
        return Features(header=header, status=status, tag_id=self.config.tag.id, detail=detail,
                        goal_points=[tuple(p) for p in goal.points], goal_depths=goal.depths.tolist(), **fields)

    def process(self, image: Image, recv_ns: int) -> Features:
        """Features for one image (also usable without zenoh: ``recv_ns`` is when the image arrived)."""
        cfg = self.config
        capture = image.header.source_stamp_ns or image.header.stamp_ns
        with self._lock:
            info = self._info
        if capture <= self._last_capture_ns:
            self.refuse("image", f"image captured at {capture} is not newer than the last one processed")
            return self._answer(image, recv_ns, FeatureStatus.STALE, "out-of-order image")
        self._last_capture_ns = capture
        age_s = (self.clock.now_ns() - capture) * 1e-9
        if age_s > cfg.max_image_age_s:
            self.counters.inc("frames.stale")
            return self._answer(image, recv_ns, FeatureStatus.STALE, f"image is {age_s * 1e3:.0f} ms old")
        if info is None:
            self.refuse("image", "no camera info yet")
            return self._answer(image, recv_ns, FeatureStatus.INVALID_IMAGE, "no camera info yet")
        if (image.width, image.height) != (info.width, info.height):
            reason = f"image is {image.width}x{image.height}, the camera info says {info.width}x{info.height}"
            self.refuse("image", reason)
            return self._answer(image, recv_ns, FeatureStatus.INVALID_IMAGE, reason)
        measurement = F.measure(self._gray(image), self.tracker, cfg.tag.id, cfg.tag.size_m,
                                F.camera_matrix(info.fx, info.fy, info.cx, info.cy),
                                np.asarray(info.distortion, dtype=float), goal_points=self._goal_points(),
                                min_peak_brightness=cfg.min_peak_brightness, border_margin_px=cfg.border_margin_px)
        status = measurement.status
        search = self.tracker.take_last_search()
        if search:
            self.counters.inc(f"detect.{search}")
        if measurement.rejected:
            self.refuse("image", measurement.detail)
        elif status is FeatureStatus.TAG_LOST:
            self.counters.inc("frames.tag_lost")
        if not measurement.rejected:  # an unusable image says nothing about the view
            with self._lock:  # the last features seen (a goal taught from the current view uses them)
                self._last_points, self._last_depths = measurement.points, measurement.depths
        if measurement.points is None:
            return self._answer(image, recv_ns, status, measurement.detail)
        R, t = measurement.pose
        return self._answer(
            image, recv_ns, status, measurement.detail, points=[tuple(p) for p in measurement.points],
            depths=measurement.depths.tolist(), error=measurement.error.tolist(), error_norm=measurement.error_norm,
            tag_pose_in_camera=Pose(xyz=tuple(t), quat_wxyz=tuple(frames.matrix_to_quat_wxyz(R))),
            corners_px=[tuple(c) for c in measurement.corners_px],
        )

    def _goal_points(self) -> np.ndarray:
        with self._lock:
            return self.goal.points

    @staticmethod
    def _gray(image: Image) -> np.ndarray:
        import cv2

        pixels = np.frombuffer(image.data, dtype=np.uint8)
        if image.encoding is ImageEncoding.MONO8:
            return pixels.reshape(image.height, image.width)
        rgb = pixels.reshape(image.height, image.width, 3)
        code = cv2.COLOR_RGB2GRAY if image.encoding is ImageEncoding.RGB8 else cv2.COLOR_BGR2GRAY
        return cv2.cvtColor(rgb, code)


