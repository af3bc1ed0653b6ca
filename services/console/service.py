"""The console's side toward the stack: a service like the others (liveliness, health with its counters, every
input decoded and validated) that follows what the page shows, encodes the camera's frames to JPEG in a thread of
its own (the newest frame, and only when a page is ready to draw one: a page that cannot keep up is sent fewer
frames, they never queue, and no frame is encoded that no page would draw), and carries
out the page's requests with the functions `mfvs task` and `mfvs estop` use, as the identity of its zenoh config
(the operator's, behind authority). It publishes nothing the robot acts on: its only writes are the e-stop (the
operator's key) and its own health; the task is asked of the controller."""
from __future__ import annotations

import threading
from pathlib import Path
import time
from typing import Callable, Optional

import cv2
import numpy as np

from protocol import messages as m
from protocol.conventions import ClockMode
import msgspec

from services.console.core import Action, Command, ConsoleModel, FrameSize, frame_packet
from services.console.jog import ConsoleJog, ConsoleJogConfig, JogRefused, JogSnapshot
from services.runtime.pacing import CyclePacer
from services.runtime.transport import GuardedPublisher, ZenohConfig, open_session, publisher_options
from services.controller.task_client import TaskUnavailable, call_task
from services.safety.estop_sender import EStopSender
from services.controller.task_client import describe_task
from services.observe.foxglove_view import jpeg, pixels
from services.vision.taught import write_goal_bytes
from services.runtime.service import Service, ServiceConfig, query_health
from services.runtime.threads import start_thread
from services.runtime.ports import Port, Ports


def halved(image: m.Image) -> m.Image:
    """The frame at half its width and height (OpenCV's area average): what the console sends while the pages are
    behind. The header keeps the whole frame's size, which the overlays' pixels refer to."""
    width, height = max(1, image.width // 2), max(1, image.height // 2)
    small = np.ascontiguousarray(cv2.resize(pixels(image), (width, height), interpolation=cv2.INTER_AREA))
    return m.Image(header=image.header, width=width, height=height, encoding=image.encoding, data=small.tobytes())



#: the page's task requests: the controller's function and the task's plan
TASK_ACTIONS = {Action.TASK_START: (m.START_TASK, m.TaskPlan.SERVO),
                Action.TASK_STOP: (m.STOP_TASK, m.TaskPlan.SERVO),
                Action.GRASP: (m.START_TASK, m.TaskPlan.GRASP),
                Action.OPEN_HAND: (m.START_TASK, m.TaskPlan.RELEASE),
                Action.TASK_RESUME: (m.RESUME_TASK, m.TaskPlan.SERVO)}

#: why the page's stick is off when the console runs behind authority with no jog identity's config
JOG_NEEDS_IDENTITY = ("the console runs as the operator, who may not put on jog/request behind authority: start it "
                      "with --jog-zenoh-config FILE (the jog identity's client config, written by `mfvs authority "
                      "init`) to drive the arm from this page")

class ConsoleConfig(ServiceConfig):
    #: the page's JPEG quality (the viewer's copy; vision gets the raw frame)
    jpeg_quality: int = 80
    #: how long an action waits for the controller's answer or safety's confirmation (s)
    action_timeout_s: float = 5.0
    #: where the goals taught from the page are kept (a person gives one again: mfvs task start --goal FILE)
    goals_dir: str = "~/.local/share/mfvs/goals"
    #: how often each service's health and the task are asked (s)
    poll_period_s: float = 1.0
    #: the page's stick and gamepad (services/console/jog.py)
    jog: ConsoleJogConfig = msgspec.field(default_factory=ConsoleJogConfig)


class ConsoleService(Service):
    name = "console"
    PORTS = Ports(consumes=(Port("camera_image", m.Image), Port("camera_info", m.CameraInfo),
                            Port("features", m.Features), Port("robot_state", m.RobotState), Port("controller_status", m.ControllerStatus),
                            Port("safety_status", m.SafetyStatus), Port("estop", m.EStop), Port("clock", m.SimClock)),
                  # the page's stick: on the jog identity's session where one is given (behind authority)
                  produces=(Port("desired_jog", m.Jog),))

    def __init__(self, config: Optional[ConsoleConfig] = None, **kwargs) -> None:
        super().__init__(config or ConsoleConfig(), **kwargs)
        self.config: ConsoleConfig
        self.model = ConsoleModel()
        #: guards the model: zenoh's callback threads write it, the web side reads it
        self.lock = threading.Lock()
        #: where encoded frames and overlays go (the web side sets them); whether anyone watches now
        self.on_frame: Callable[[bytes], None] = lambda packet: None
        self.on_overlay: Callable[[dict], None] = lambda overlay: None
        self.wants_frames: Callable[[], bool] = lambda: False
        #: pages open and shown the stack now (the web side keeps it)
        self.pages_open = 0
        self._newest_image: Optional[tuple[m.Image, int]] = None
        self._image_arrived = threading.Condition()
        #: whether capture stamps are wall time (realtime) or the simulator's (lockstep): the page reads a frame's
        #: delay off its stamp only for the first
        self.wall_stamps = True
        self._estop: Optional[EStopSender] = None
        self._threads: list[threading.Thread] = []
        #: from a frame's sending to the page's word that it drew it, the last one (s); the last frame's encoding
        self.page_draw_s = 0.0
        self.encode_s = 0.0
        #: whole frames, or halved while the pages are behind (written by the web side's loop, read by the encoder)
        self.frame_size = FrameSize()
        #: the page's stick (its own lock: the web side's loop offers snapshots, the stream's thread sends)
        self.jog = ConsoleJog(self.config.jog, enabled=False, why="the console is starting")
        self.jog_lock = threading.Lock()
        self._jog_session = None
        self._jog_publisher: Optional[GuardedPublisher] = None

    # ------------------------------------------------------------------ lifecycle
    def on_start(self) -> None:
        k = self.keys
        self.subscribe(k.camera_image, m.Image, self._on_image, "image")
        self.subscribe(k.camera_info, m.CameraInfo, self._locked(self.model.on_camera_info, timed=False),
                       "camera_info")
        self.subscribe(k.features, m.Features, self._on_features, "features")
        self.subscribe(k.robot_state, m.RobotState, self._on_state, "robot_state")
        self.subscribe(k.controller_status, m.ControllerStatus, self._locked(self.model.on_controller),
                       "controller_status")
        self.subscribe(k.safety_status, m.SafetyStatus, self._locked(self.model.on_safety), "safety_status")
        self.subscribe(k.estop, m.EStop, self._locked(self.model.on_estop), "estop")
        self.subscribe(k.clock, m.SimClock, self._on_clock, "sim_clock")
        self._start_jog()  # before the e-stop's sender process: a jog config that fails leaves nothing running
        self._estop = EStopSender.for_service(self)
        self._threads = [start_thread(self._encode_frames, "console-jpeg"),
                         start_thread(self._poll, "console-poll")]
        if self._jog_publisher is not None:
            self._threads.append(start_thread(self._stream_jog, "console-jog"))

    def on_stop(self) -> None:
        with self._image_arrived:
            self._image_arrived.notify_all()
        for thread in self._threads:
            thread.join(timeout=5.0)
        self._stop_jog()
        if self._estop is not None:
            self._estop.close()

    # ------------------------------------------------------------------ the page's stick
    def _start_jog(self) -> None:
        """The stick's publisher: on the jog identity's session where its config is given, on the console's own
        where there is no authority (no zenoh config file); behind authority with no jog config, none (the page's
        stick is off and says why)."""
        config = self.config.jog
        if config.zenoh_config:
            self._jog_session = open_session(ZenohConfig(connect=list(self.config.zenoh.connect),
                                                         config_file=config.zenoh_config))
            session, how = self._jog_session, f"as the jog identity ({config.zenoh_config})"
        elif self.config.zenoh.config_file:
            self.jog = ConsoleJog(config, enabled=False, why=JOG_NEEDS_IDENTITY)
            return
        else:
            session, how = self.session, "on the console's own session (no access control)"
        key = self.keys.desired_jog
        try:
            self._jog_publisher = GuardedPublisher.declare(session, key, **publisher_options(key))
        except Exception:
            self._stop_jog()
            raise
        self.jog = ConsoleJog(config, enabled=True, why=how)

    def _stream_jog(self) -> None:
        """One request per slot while a page's snapshot is fresh (services/console/jog.py's rules), on an absolute
        schedule: a slot the host was late for is skipped and counted, never sent late."""
        pacer = CyclePacer(1.0 / self.config.jog.rate_hz, catch_up_cycles=0)
        while not self.stop_requested:
            slot = pacer.wait()
            if slot.missed:
                self.counters.inc("jog.missed_slots", slot.missed)
            with self.jog_lock:
                stale_before = self.jog.counts.stale
                message = self.jog.tick(time.time_ns())
                stale = self.jog.counts.stale > stale_before
            if message is not None:
                self._put_jog(message)
                if stale:
                    self.counters.inc("jog.stale")

    def _put_jog(self, message: m.Jog) -> None:
        try:
            self._jog_publisher.put(m.encode(message))
            self.rates.tick("jog.sent")
        except Exception as exc:  # the jog session closing, or refused: counted, the stream goes on
            self.counters.inc("errors.jog")
            self.limited_log.warning("jog", "console: could not send a jog request: %s", exc)

    def _stop_jog(self) -> None:
        if self._jog_publisher is not None:
            with self.jog_lock:
                released = self.jog.release(time.time_ns())
            if released is not None:
                self._put_jog(released)
            self._jog_publisher.undeclare()
            self._jog_publisher = None
        if self._jog_session is not None:
            self._jog_session.close()
            self._jog_session = None

    def jog_snapshot(self, page: int, snapshot: JogSnapshot) -> None:
        """A page's stick (the web side, from its loop): taken, or JogRefused (counted by the caller's refusal)."""
        with self.jog_lock:
            self.jog.offer(page, snapshot, time.time_ns())

    def jog_page_gone(self, page: int) -> None:
        with self.jog_lock:
            self.jog.page_gone(page)

    def jog_status(self) -> dict:
        with self.jog_lock:
            return self.jog.status(time.time_ns())

    def jog_refused(self, refusal: JogRefused) -> None:
        """A snapshot not taken: counted each time, logged and shown in the page's log at most once per 10 s (they
        come 50 a second)."""
        self.counters.inc(f"refused.{refusal.reason}")
        self.limited_log.warning(f"refused:{refusal.reason}", "console: stick refused (%s): %s", refusal.reason,
                                 refusal.message)
        with self.lock:
            self.model.note_once("console", "warning", f"stick refused: {refusal.message}", time.time())

    def check_health(self) -> tuple[bool, str]:
        rates = self.rates.snapshot()
        with self.lock:
            arm = self.model.arm
        robot = ("no robot state yet" if arm is None else f"arm {arm.name}" if arm.description is not None
                 else f"arm {arm.name} not described here")
        estop_ok, estop = self._estop.health() if self._estop is not None else (False, "no e-stop sender")
        return estop_ok, (f"{estop}; pages={self.pages_open} frames {rates.get('frames.sent', 0.0):.1f}/s "
                      f"(encoded {rates.get('frames.encoded', 0.0):.1f}/s, drawn {rates.get('frames.drawn', 0.0):.1f}/s"
                      f" {1e3 * self.page_draw_s:.0f} ms after sending) {robot}")

    # ------------------------------------------------------------------ inputs
    def _locked(self, update, timed: bool = True):
        def handler(message, _recv_ns: int) -> None:
            with self.lock:
                if timed:
                    update(message, time.time())
                else:
                    update(message)
        return handler

    def _on_image(self, image: m.Image, _recv_ns: int) -> None:
        with self._image_arrived:
            self._newest_image = (image, time.time_ns())  # an older one not yet encoded is dropped
            self._image_arrived.notify()

    def _on_features(self, features: m.Features, _recv_ns: int) -> None:
        with self.lock:
            overlay = self.model.on_features(features, time.time())
        if self.wants_frames():
            self.on_overlay(overlay)

    def _on_state(self, state: m.RobotState, _recv_ns: int) -> None:
        with self.lock:
            problem = self.model.on_state(state, time.time())
        if problem:  # shown without the arm's ranges and limits; counted each state, as safety counts its refusals
            self.counters.inc("arm.not_described")
            self.limited_log.warning("arm", "console: the robot's arm: %s", problem)

    def _on_clock(self, tick: m.SimClock, _recv_ns: int) -> None:
        self.wall_stamps = ClockMode(tick.mode) is ClockMode.REALTIME

    # ------------------------------------------------------------------ threads
    def frame_wanted(self) -> None:
        """A page is ready for a frame (the web side, from its loop): the newest image is encoded now."""
        with self._image_arrived:
            self._image_arrived.notify()

    def frame_drawn(self, seconds: float) -> None:
        """A page drew a frame ``seconds`` after it was sent (the web side, from its loop)."""
        self.rates.tick("frames.drawn")
        self.page_draw_s = seconds
        camera_hz = self.rates.snapshot().get("image", 0.0)
        before = self.frame_size.scale
        after = self.frame_size.on_drawn(self.encode_s, seconds, 1.0 / camera_hz if camera_hz > 0 else 1 / 30)
        if after != before:
            self.counters.inc("frames.halved" if after > before else "frames.whole")

    def _encode_frames(self) -> None:
        while not self.stop_requested:
            with self._image_arrived:
                # the newest image waits for a page ready to draw it (an image nobody would draw is not encoded)
                self._image_arrived.wait_for(lambda: (self._newest_image is not None and self.wants_frames())
                                             or self.stop_requested, timeout=0.5)
                if not self.wants_frames():
                    continue
                newest, self._newest_image = self._newest_image, None
            if newest is None:
                continue
            image, received_ns = newest
            scale = self.frame_size.scale
            started = time.perf_counter()
            try:
                encoded = jpeg(image if scale == 1 else halved(image), self.config.jpeg_quality)
            except Exception as exc:  # an image OpenCV cannot encode: not shown, counted, the next one may be
                self.counters.inc("errors.encode")
                self.limited_log.warning("encode", "console: could not encode a frame: %s", exc)
                continue
            self.encode_s = time.perf_counter() - started
            header = {"seq": image.header.seq, "capture_ns": image.header.source_stamp_ns or image.header.stamp_ns,
                      "received_ns": received_ns, "encoded_ns": time.time_ns(), "wall_stamps": self.wall_stamps,
                      "width": image.width, "height": image.height, "scale": scale}
            self.rates.tick("frames.encoded")
            self.on_frame(frame_packet(encoded, header))

    def _poll(self) -> None:
        """Each service's health and the task, every poll period (what `mfvs status` and `mfvs task status` ask)."""
        while not self._stop_event.wait(self.config.poll_period_s):
            session = self.session
            if session is None:
                return
            try:
                found = query_health(session, self.keys, timeout_s=0.8 * self.config.poll_period_s)
                task: Optional[m.TaskStatus] = call_task(session, self.keys, m.GET_TASK,
                                                         timeout_s=0.8 * self.config.poll_period_s)
            except TaskUnavailable:
                task = None
            except Exception:  # the session is closing
                if self.stop_requested:
                    return
                self.limited_log.warning("poll", "console: could not ask the stack's health and task")
                continue
            now = time.time()
            with self.lock:
                self.model.on_health(found, now)
                self.model.on_task(task, now)

    # ------------------------------------------------------------------ the page's requests
    def refused(self, reason: str, message: str) -> None:
        """A request of the page's that the console did not carry out: counted, logged, shown in its log."""
        self.counters.inc(f"refused.{reason}")
        self.limited_log.warning(f"refused:{reason}", "console: refused (%s): %s", reason, message)
        with self.lock:
            self.model.note("console", "warning", f"refused: {message}", time.time())

    def _teach(self, command: Command) -> tuple[bool, str]:
        """The whole teach (its two moves included), its goal kept in the goals folder."""
        from services.vision.teach_client import TeachFailed, teach

        def said(line: str) -> None:
            with self.lock:
                self.model.note("teach", "info", line, time.time())

        try:
            result = teach(self.session, self.keys, command.name, command.operator, region_px=command.region_px,
                           confirm=lambda _: True, say=said)  # (confirmed on the page: decide() checked it)
        except TeachFailed as exc:
            return False, str(exc)
        path = Path(self.config.goals_dir).expanduser() / f"{result.goal}.mfvsgoal"
        write_goal_bytes(result.file, path)  # (atomically: the page's reader, or a person's, never sees half of it)
        with self.lock:
            self.model.on_taught(result.goal, result.digest, str(path), time.time())
        return True, (f"taught {result.goal} ({result.digest}): {result.keypoints} keypoints, "
                      f"{'planar' if result.planar else 'not planar'}; kept in {path}")

    def perform(self, command: Command) -> tuple[bool, str]:
        """Carry out a request the rules let through (blocking: up to the action timeout); (done, what happened)."""
        self.counters.inc(f"actions.{command.action.value}")
        with self.lock:
            self.model.note("console", "info", f"{command.operator} asks: {command.action.value.replace('_', ' ')}"
                            + (f" ({command.reason})" if command.reason else ""), time.time())
        if command.action is Action.TEACH:
            return self._teach(command)
        if command.action in TASK_ACTIONS:
            function, plan = TASK_ACTIONS[command.action]
            try:
                status = call_task(self.session, self.keys, function,
                                   m.TaskRequest(operator=command.operator, reason=command.reason, plan=plan),
                                   self.config.action_timeout_s)
            except TaskUnavailable as exc:
                return False, f"{exc} (is the controller up? may this identity ask it?)"
            with self.lock:
                self.model.on_task(status, time.time())
            return status.ok, describe_task(status)
        reset = command.action is Action.ESTOP_RELEASE
        assert self._estop is not None
        status = self._estop.send(reset, command.operator, command.reason, self.config.action_timeout_s)
        if status is None:
            return False, (f"e-stop {'release' if reset else 'request'} sent, but safety did not confirm it within "
                           f"{self.config.action_timeout_s:g} s")
        with self.lock:
            self.model.on_safety(status, time.time())
        return True, f"e-stop {'released' if reset else 'engaged'}: safety reports {status.state.value}"
