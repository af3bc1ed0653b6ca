"""The vision service: camera images → AprilTag point features, depths and error against the goal.

Inputs: images and camera info (``…/camera/*``); goals on ``…/vision/goal`` or through the queryables
``…/vision/api/set_goal`` (VisionGoal → VisionGoalReply) and ``…/vision/api/get_goal``.
Output: Features on ``…/vision/features`` for every image processed, carrying the image's capture stamp and
trace. The status says at once when the tag is lost; an image older than ``max_image_age_s`` when its turn
comes is answered with ``stale`` and no features; unusable images with ``invalid_image``.

Images are processed in a worker thread, newest first: if images arrive faster than they are processed, the
older waiting one is dropped (counted as ``frames.skipped``), so features are never late by a queue. The same
image again (robot_sim's lockstep retry) is answered with the features it got the first time
(``frames.repeated``): one frame, one answer, however often it is delivered.

The rules (order, age, camera info, size, then detect → normalise → pose → error; the goal) are
:class:`services.vision.core.VisionCore`'s; this service decodes, hands it the image with the time, counts what it
says and publishes.
"""
from __future__ import annotations

import threading
from typing import Annotated, Optional

import msgspec
import zenoh

from protocol.conventions import IMAGE_AGE_BUDGET_S
from protocol.messages import (
    CameraInfo,
    Features,
    MAX_FEATURE_POINTS,
    Image,
    KeypointView,
    ProtocolError,
    RobotState,
    TagView,
    TeachPhase,
    TeachReply,
    TeachRequest,
    VisionGoal,
    VisionGoalReply,
    decode,
    encode,
)
from services.model import tag as tags
from services.runtime.clock import SimulatedClock
from services.runtime.config import ConfigStruct
from services.model.frames import PoseConfig
from services.runtime.service import Service, ServiceConfig, query_argument
from services.runtime.threads import start_thread
from services.vision import features as F
from services.vision.core import TABLE2_DEPTH, TABLE2_GOAL, VisionCore, goal_from_config
from services.vision.keypoints import KeypointConfig
from services.vision.taught import read_goal
from services.vision.teach import TeachConfig
from services.runtime.ports import Port, Ports

#: lockstep: how long the first frame without camera info waits for it (the robot's own wait for a frame's answer)
CAMERA_INFO_WAIT_S = 2.0



class TagConfig(ConfigStruct):
    family: str = "tag36h11"
    id: int = 0
    #: edge of the black square (m)
    size_m: float = 0.0962
    #: which image is printed: official (AprilRobotics/apriltag-imgs, the one to print) or opencv (OpenCV's
    #: drawing, turned); the corners and the tag's pose follow that image's upright
    layout: tags.TagLayout = tags.TagLayout.OFFICIAL

    def __post_init__(self) -> None:
        if self.family not in tags.FAMILIES:
            raise ValueError(f"unknown tag family {self.family!r}; known: {sorted(tags.FAMILIES)}")
        if not 0.005 <= self.size_m <= 1.0:
            raise ValueError("tag size_m must be within 0.005..1 m")


class GoalConfig(ConfigStruct):
    """One of: features (normalized, corner order as detected) with depth_m; camera_in_tag; or a taught goal's file
    (``taught``: `mfvs teach`'s, found by the keypoint front end). None: Sensors 2022 Table 2's square (±0.1666 at
    0.2888 m)."""

    features: Optional[list[tuple[float, float]]] = None
    #: the goal's depth, with features (default: Table 2's 0.2888 m); a camera_in_tag goal has its own depths
    depth_m: Optional[float] = None
    camera_in_tag: Optional[PoseConfig] = None
    #: a taught goal's file (services/vision/taught.py), read when vision starts
    taught: Optional[str] = None

    def __post_init__(self) -> None:
        if sum(v is not None for v in (self.features, self.camera_in_tag, self.taught)) > 1:
            raise ValueError("give the goal as features, camera_in_tag or taught, one of them (features: null to use "
                             "another)")
        if self.taught is not None:
            if self.depth_m is not None:
                raise ValueError("a taught goal has its own depths: give no depth_m with it")
            return
        if self.camera_in_tag is not None:
            if self.depth_m is not None:
                raise ValueError("a camera_in_tag goal has its own depths: give no depth_m with it")
            return
        if self.features is None:
            self.features = list(TABLE2_GOAL)
        if self.depth_m is None:
            self.depth_m = TABLE2_DEPTH
        if self.depth_m <= 0 or len(self.features) != 4:
            raise ValueError("goal features need 4 points and a positive depth_m")


class VisionConfig(ServiceConfig):
    tag: TagConfig = msgspec.field(default_factory=TagConfig)
    goal: GoalConfig = msgspec.field(default_factory=GoalConfig)
    #: the detector: apriltag (the AprilTag project's quads: a quarter of aruco's time, never lost to 3 m) or aruco
    #: (OpenCV's)
    detector: F.Backend = F.Backend.APRILTAG
    #: apriltag_subpix: either detector's quads, then OpenCV's sub-pixel corner search (the same corners from both,
    #: within 0.002 px); none (apriltag) / apriltag (aruco): as detected; see features.Refinement
    refinement: F.Refinement = F.Refinement.APRILTAG_SUBPIX
    #: the apriltag detector's error correction: a tag read with up to this many wrong cells still decodes (0-2; 2
    #: is the AprilTag library's default). For tag36h11 its table holds 36 MB of vision's memory at 2, 1 MB at 1;
    #: at 1 about one detection in twenty of small, blurred, noisy tags is lost (features.APRILTAG_CORRECTED_BITS)
    apriltag_corrected_bits: Annotated[int, msgspec.Meta(ge=0, le=F.APRILTAG_CORRECTED_BITS)] = \
        F.APRILTAG_CORRECTED_BITS
    roi: F.RoiConfig = msgspec.field(default_factory=F.RoiConfig)
    #: an image older than this (capture to processing, in the service's clock) gets status stale
    max_image_age_s: float = IMAGE_AGE_BUDGET_S
    #: a tag whose corners come closer than this to the image border is reported as partial
    border_margin_px: float = 2.0
    #: an image whose brightest pixel is below this is refused as all black (lens covered, camera fault)
    min_peak_brightness: int = 16
    #: the keypoint front end (a taught goal's: services/vision/keypoints.py)
    keypoints: KeypointConfig = msgspec.field(default_factory=KeypointConfig)
    #: teach by showing (services/vision/teach.py)
    teach: TeachConfig = msgspec.field(default_factory=TeachConfig)


def goal_in_message(goal) -> dict:
    """The goal's points and depths as a message carries them: its first MAX_FEATURE_POINTS (a taught goal's are
    strongest first), for a taught view may hold more keypoints than a message may (a photograph's print gave 600, and
    every frame without the object in it was refused by each subscriber)."""
    return dict(goal_points=[tuple(p) for p in goal.points[:MAX_FEATURE_POINTS]],
                goal_depths=goal.depths[:MAX_FEATURE_POINTS].tolist())


class VisionService(Service):
    name = "vision"
    PORTS = Ports(consumes=(Port("camera_image", Image), Port("camera_info", CameraInfo),
                            Port("vision_goal", VisionGoal), Port("robot_state", RobotState)),
                  produces=(Port("features", Features),),
                  answers=(Port("vision_api"),))
    clock_from_inputs = True  # the images

    def __init__(self, config: VisionConfig | None = None, **kw) -> None:
        config = config or VisionConfig()
        super().__init__(config, **kw)
        self.config: VisionConfig = config
        self.core = VisionCore(config)
        if config.goal.taught is not None:  # the person's goal file: read now, a bad one refused before anything runs
            taught, _ = read_goal(config.goal.taught)
            self.core.goal = self.core.set_taught(taught, None)
        #: the core's: held while it processes an image or changes the goal (queries wait one frame at most)
        self._core_lock = threading.Lock()
        self._lock = threading.Lock()
        self._info: Optional[CameraInfo] = None
        self._pending: Optional[tuple[Image, int]] = None
        #: the last image's capture stamp and the answer it got: the same image again (robot_sim's lockstep
        #: retry, published while an answer down the pipeline is late) gets that answer again, not a second one
        self._last_answer: Optional[tuple[int, Features]] = None
        self._wake = threading.Condition(self._lock)
        self._worker: Optional[threading.Thread] = None
        #: lockstep: the first frame without camera info waits for it (CAMERA_INFO_WAIT_S at most, once)
        self._await_info = True

    # ------------------------------------------------------------------ lifecycle
    def on_start(self) -> None:
        keys = self.keys
        self.features_pub = self.publisher(keys.features, "features")
        self.subscribe(keys.camera_info, CameraInfo, self._on_camera_info, "camera_info")
        self.subscribe(keys.camera_image, Image, self._on_image, "image", sim_stamped=True)
        self.subscribe(keys.vision_goal, VisionGoal, lambda goal, _: self.set_goal(goal), "goal")
        self.subscribe(keys.robot_state, RobotState, self._on_state, "robot_state")
        self.queryable(keys.vision_api("set_goal"), self._on_set_goal_query)
        self.queryable(keys.vision_api("get_goal"), self._on_get_goal_query)
        self.queryable(keys.vision_api("teach"), self._on_teach_query)
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
        return True, f"goal from {self.core.goal.description}"

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
        with self._core_lock:
            taught = self.core.taught
            problem = taught.mismatch(info, self.core.arm.name if self.core.arm else None) if taught else ""
            if problem:  # a goal file taught through another camera: refused, and nothing is servoed to
                self.core.use_tag()
                self.core.goal = goal_from_config(self.config.goal if self.config.goal.taught is None
                                                  else GoalConfig(), self.config.tag.size_m)
        if problem:
            self.refuse("goal", problem)
        with self._wake:
            self._info = info
            self._wake.notify_all()

    def _on_state(self, state: RobotState, _recv_ns: int) -> None:
        with self._core_lock:
            why = self.core.robot_state(state)
        if why:
            self.refuse("robot_state", why)

    def _on_image(self, image: Image, recv_ns: int) -> None:
        with self._wake:
            if self._pending is not None:
                self.counters.inc("frames.skipped")
            self._pending = (image, recv_ns)
            self._wake.notify()

    # ------------------------------------------------------------------ goal
    def set_goal(self, goal: VisionGoal) -> VisionGoalReply:
        try:
            with self._lock:
                info = self._info
            with self._core_lock:
                new = self.core.goal_from(goal, info)
                self.core.goal = new
                reply = self._goal_reply(new)
        except ValueError as exc:
            self.refuse("goal", str(exc))
            return VisionGoalReply(ok=False, message=str(exc)[:256])
        self.log.info("goal set from %s", new.description)
        return reply

    def _goal_reply(self, goal, message: str = "") -> VisionGoalReply:
        """The goal as a reply (call with the core's lock held): its points and depths, front end, and name."""
        taught = self.core.taught
        return VisionGoalReply(ok=True, message=message[:256], **goal_in_message(goal),
                               front_end=self.core.front_end.kind, goal=taught.name if taught else None,
                               goal_digest=taught.digest if taught else None)

    def teach(self, request: TeachRequest) -> TeachReply:
        with self._core_lock:
            reply = self.core.teach_step(request, self.clock.now_ns())
        if reply.ok:
            self.log.info("teach %s (%s): %s", request.phase.value, request.operator, reply.message)
        else:
            self.refuse("teach", reply.message)
        return reply

    def _on_teach_query(self, query: zenoh.Query) -> None:
        try:
            reply = self.teach(query_argument(query, "teach", TeachRequest))
        except ProtocolError as exc:
            self.refuse("teach", str(exc))
            reply = TeachReply(ok=False, phase=TeachPhase.CANCEL, message=str(exc)[:512])
        query.reply(query.key_expr, encode(reply))

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
        with self._core_lock:
            reply = self._goal_reply(self.core.goal, self.core.goal.description)
        query.reply(query.key_expr, encode(reply))

    # ------------------------------------------------------------------ processing
    def _work(self) -> None:
        while True:
            with self._wake:
                while self._pending is None and not self.stop_requested:
                    self._wake.wait(0.2)
                if self.stop_requested:
                    return
                if self._info is None and self._await_info and isinstance(self.clock, SimulatedClock):
                    # lockstep: a frame waits for the camera info rather than being refused, once. The info and
                    # the frame come on subscribers of their own, in the host's order: a replay that sent the
                    # info first had its first frame refused now and then.
                    self._wake.wait_for(lambda: self._info is not None or self.stop_requested,
                                        timeout=CAMERA_INFO_WAIT_S)
                    self._await_info = False
                image, recv_ns = self._pending
                self._pending = None
            try:
                self.features_pub.put(self.process(image, recv_ns))
            except Exception:
                self.counters.inc("errors.processing")
                self.limited_log.error("processing", "vision: processing an image failed")
                self.log.debug("processing failure", exc_info=True)

    def process(self, image: Image, recv_ns: int) -> Features:
        """Features for one image (also usable without zenoh: ``recv_ns`` is when the image arrived); the answer
        already given when it is the last image again."""
        capture = image.header.source_stamp_ns or image.header.stamp_ns
        if self._last_answer is not None and self._last_answer[0] == capture:
            self.counters.inc("frames.repeated")
            return self._last_answer[1]
        features = self._answer(image, recv_ns)
        self._last_answer = (capture, features)
        return features

    def _answer(self, image: Image, recv_ns: int) -> Features:
        with self._lock:
            info = self._info
        with self._core_lock:
            outcome = self.core.process(image, info, self.clock.now_ns())
            goal = self.core.goal
        if outcome.refusal:
            self.refuse("image", outcome.refusal)
        for name in outcome.counts:
            self.counters.inc(name)
        header = self.header("features", source=image.header, recv_ns=recv_ns)
        answer = dict(header=header, status=outcome.status, front_end=outcome.front_end, detail=outcome.detail)
        seen = outcome.seen
        if seen is None or seen.points is None:
            return Features(**answer, **goal_in_message(goal))
        view = seen.view
        return Features(
            **answer, points=[tuple(p) for p in seen.points], depths=seen.depths.tolist(), ids=seen.ids.tolist(),
            weights=seen.weights.tolist(), pixels=[tuple(c) for c in seen.pixels],
            goal_points=[tuple(p) for p in outcome.goal_points], goal_depths=outcome.goal_depths.tolist(),
            error=outcome.error.tolist(), error_norm=outcome.error_norm, error_rms=outcome.error_rms,
            tag=view if isinstance(view, TagView) else None, keypoints=view if isinstance(view, KeypointView) else None,
        )
