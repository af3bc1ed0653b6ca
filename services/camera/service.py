"""The camera service: a real camera (or a video file, or a folder of images) on the keys robot_sim's simulated
camera publishes, so that vision and the controller cannot tell them apart.

Outputs: Image on ``…/camera/image`` for every frame, stamped with its capture time (header ``stamp_ns`` and
``source_stamp_ns``: the trace starts here); CameraInfo on ``…/camera/info`` every ``camera_info_period_s`` and on
query: the calibration file's intrinsics and distortion (vision undistorts the corner points with them), and the
camera's mounting on the end effector (``camera_in_ee`` or a hand-eye file from ``mfvs calibrate hand-eye``).

The service runs in realtime only: a camera cannot be paused for a lockstep simulation (lockstep images come from
robot_sim's renderer). Frames of another size than the calibration's are refused (``rejected.frame``), never
published with intrinsics that do not describe them. A camera that stops giving frames is reopened every
``reopen_after_s`` (``errors.capture``); the service keeps running and says so in its health.
"""
from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Literal, Optional, Union

import msgspec
import numpy as np
import zenoh

from protocol.conventions import ClockMode
from protocol.messages import CameraInfo, Image, ImageEncoding, encode
from services.camera import core
from services.camera.calibration import Intrinsics, read_camera_in_ee, read_intrinsics
from services.camera.sources import DeviceSource, FrameSource, ImageFolderSource, SourceError, VideoFileSource
from services.runtime.pacing import CyclePacer
from services.runtime.config import ConfigStruct
from services.model.frames import PoseConfig
from services.runtime.service import Service, ServiceConfig
from services.runtime.threads import start_thread
from services.runtime.ports import Port, Ports


class SourceConfig(ConfigStruct):
    #: device: a camera through OpenCV (V4L2/UVC); video: a video file; images: a folder of images, in name order
    kind: Literal["device", "video", "images"] = "device"
    #: device: its index (0 for /dev/video0) or path
    device: Union[int, str] = 0
    #: video or images: the file or folder (relative paths from the service's working directory)
    path: Optional[str] = None
    #: device: the size asked of the camera, which must be the calibration's
    width: int = 640
    height: int = 480
    #: device: the frame rate asked of the camera; video, images: the playback rate (null: a video's own rate)
    rate_hz: Optional[float] = 30.0
    #: device: a manual exposure in the driver's units (V4L2: 100 µs) where the camera allows; null: automatic
    exposure: Optional[float] = None
    #: device: exposure to the driver's buffer stamp (s), as measured for the camera (readout, USB transfer)
    capture_latency_s: float = 0.0
    #: video, images: start again at the end (otherwise the service stops publishing there and says so)
    loop: bool = True

    def __post_init__(self) -> None:
        if self.kind != "device" and not self.path:
            raise ValueError(f"a {self.kind} source needs a path")
        if self.rate_hz is not None and not 0 < self.rate_hz <= 240:
            raise ValueError("rate_hz must be within (0, 240]")
        if not 0.0 <= self.capture_latency_s < 1.0:
            raise ValueError("capture_latency_s must be within [0, 1) s")


class CameraConfig(ServiceConfig):
    source: SourceConfig = msgspec.field(default_factory=SourceConfig)
    #: the calibration file: OpenCV FileStorage YAML/XML or ROS camera_info YAML (`mfvs calibrate intrinsics`
    #: writes one); required: without it vision would measure with intrinsics that are not this camera's
    calibration: Optional[str] = None
    #: where the camera sits on the end effector; a hand-eye file (`mfvs calibrate hand-eye`) replaces it
    camera_in_ee: PoseConfig = msgspec.field(
        default_factory=lambda: PoseConfig(xyz=(0.065, 0.0, -0.02), rpy_deg=(0.0, 0.0, 90.0)))
    hand_eye: Optional[str] = None
    #: what is published: mono8 (what vision reads: a third of the bytes) or rgb8
    encoding: ImageEncoding = ImageEncoding.MONO8
    camera_info_period_s: float = 1.0
    #: a device that gives no frame is reopened after this long
    reopen_after_s: float = 1.0

    def __post_init__(self) -> None:
        if ClockMode(self.clock) is ClockMode.LOCKSTEP:
            raise ValueError("the camera service runs in realtime only: a camera cannot wait for a lockstep "
                             "simulation (lockstep images come from robot_sim)")
        if self.encoding is ImageEncoding.BGR8:
            raise ValueError("encoding must be mono8 or rgb8")


class CameraService(Service):
    name = "camera"
    PORTS = Ports(produces=(Port("camera_image", Image), Port("camera_info", CameraInfo)),
                  answers=(Port("camera_info"),))
    follows_sim_clock = False

    def __init__(self, config: CameraConfig | None = None, **kw) -> None:
        config = config or CameraConfig()
        super().__init__(config, **kw)
        self.config: CameraConfig = config
        if not config.calibration:
            raise ValueError("the camera service needs a calibration file (calibration: ...; `mfvs calibrate "
                             "intrinsics` writes one)")
        self.intrinsics: Intrinsics = read_intrinsics(config.calibration)
        mounting = read_camera_in_ee(config.hand_eye) if config.hand_eye else config.camera_in_ee
        self.T_ee_camera: np.ndarray = mounting.matrix()
        source = config.source
        if source.kind == "device" and (source.width, source.height) != (self.intrinsics.width,
                                                                          self.intrinsics.height):
            raise ValueError(f"the camera is asked for {source.width}x{source.height}, the calibration "
                             f"{config.calibration} is for {self.intrinsics.width}x{self.intrinsics.height}")
        #: opened now: a source that cannot be had stops the service before it joins the network, with the reason
        self._source: FrameSource = self.open_source()
        self._thread: Optional[threading.Thread] = None
        #: why frames stopped, for health ("" while they flow)
        self._stopped_reason = ""
        self._next_info = 0.0

    # ------------------------------------------------------------------ lifecycle
    def open_source(self) -> FrameSource:
        source = self.config.source
        if source.kind == "video":
            return VideoFileSource(Path(source.path), loop=source.loop)
        if source.kind == "images":
            return ImageFolderSource(Path(source.path), loop=source.loop)
        return DeviceSource(source.device, source.width, source.height, source.rate_hz, source.exposure,
                            source.capture_latency_s)

    def on_start(self) -> None:
        keys = self.keys
        self.image_pub = self.publisher(keys.camera_image, "image")
        self.info_pub = self.publisher(keys.camera_info, "camera_info")
        self.queryable(keys.camera_info, self._on_info_query)
        self._publish_info_now_and_then()  # before the first frame: vision cannot use a frame without it
        rate = self.playback_rate_hz()
        self.declare_loop("pub.image", rate, ("frames.late",))
        self._thread = start_thread(self._capture_loop, "camera-capture")

    def on_stop(self) -> None:
        if self._thread is not None:
            self._thread.join(timeout=5.0)
        self._source.close()

    def playback_rate_hz(self) -> float:
        source = self.config.source
        if source.kind != "device" and source.rate_hz is None:
            return self._source.native_rate_hz or 30.0
        return source.rate_hz or 30.0

    def check_health(self) -> tuple[bool, str]:
        if self._stopped_reason:
            return False, self._stopped_reason
        if self._thread is None or not self._thread.is_alive():
            return False, "capture stopped"
        stamp = getattr(self._source, "stamp_source", "publication")
        return True, f"{self.config.source.kind} {self.intrinsics.width}x{self.intrinsics.height}, stamps: {stamp}"

    # ------------------------------------------------------------------ camera info
    def info(self):
        return core.camera_info(self.intrinsics, self.T_ee_camera, self.header("camera_info"))

    def _on_info_query(self, query: zenoh.Query) -> None:
        query.reply(self.keys.camera_info, encode(self.info()))

    def _publish_info_now_and_then(self) -> None:
        now = time.monotonic()
        if now >= self._next_info:
            self.info_pub.put(self.info())
            self._next_info = now + self.config.camera_info_period_s

    # ------------------------------------------------------------------ frames
    def _capture_loop(self) -> None:
        pacer = CyclePacer(1.0 / self.playback_rate_hz(), catch_up_cycles=0) if self._source.paced else None
        while not self.stop_requested:
            if pacer is not None:
                slot = pacer.wait()
                if slot.late:
                    self.counters.inc("frames.late")
                if slot.missed:
                    self.counters.inc("frames.missed", slot.missed)
            try:
                frame = self._source.read()
            except SourceError as exc:
                self.counters.inc("errors.capture")
                self.limited_log.error("capture", "camera: %s", exc)
                if self.config.source.kind == "device":
                    self._reopen()
                continue
            if frame is None:
                self._stopped_reason = f"the {self.config.source.kind} source ended (loop: false)"
                self.log.info("camera: %s", self._stopped_reason)
                return
            self.publish_frame(frame.pixels, frame.capture_ns)
            self._publish_info_now_and_then()

    def publish_frame(self, pixels: np.ndarray, capture_ns: int) -> bool:
        """Publish one captured frame (False, counted and logged, when it is refused)."""
        try:
            converted = core.pixels_for(pixels, self.config.encoding, self.intrinsics)
        except ValueError as exc:
            self.refuse("frame", str(exc))
            return False
        # the trace starts with the camera's hop: capture to publication (decoding, conversion) is its share
        header = self.header("image", stamp_ns=capture_ns, source_stamp_ns=capture_ns, recv_ns=capture_ns)
        self.image_pub.put(core.image_message(converted, self.config.encoding, header))
        return True

    def _reopen(self) -> None:
        self._source.close()
        deadline = time.monotonic() + self.config.reopen_after_s
        while not self.stop_requested and time.monotonic() < deadline:
            time.sleep(0.05)
        try:
            self._source = self.open_source()
            self.log.info("camera: reopened")
        except SourceError as exc:
            self.limited_log.error("reopen", "camera: cannot reopen: %s", exc)
