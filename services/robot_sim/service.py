"""The robot_sim service: the simulation behind the same zenoh API a gateway to a real arm offers.

Inputs: robot commands (from safety) on ``…/robot/command``; the Kinova API on ``…/robot/api/<Function>``.
Outputs: robot state every DSP cycle (100 Hz), camera images at the camera rate with their capture stamp,
camera info (periodically and on query), and the simulation clock every cycle.

Clock modes (ARCHITECTURE.md):

* ``realtime``: the DSP cycle runs every 10 ms of wall time; stamps are wall time (simulated time is wall time
  since start plus the start epoch); frames render in their own thread so rendering does not delay the cycle.
* ``lockstep``: deterministic simulated time (from 1 s, so that a stamp of 0 always means "none"). Each cycle
  the simulator publishes a clock tick and, when someone listens to the clock, waits (at most
  ``cycle_timeout_s``) for a command stamped at or after the tick: the safety service answers every tick with its
  held command. When a frame was published, it also waits (at
  most ``frame_timeout_s``) for a command derived from that frame (``source_stamp_ns`` at or after its capture
  stamp): one iteration of the pipeline is one camera frame. With nobody listening it runs free.
"""
from __future__ import annotations

import queue
import threading
import time
from concurrent.futures import Future
from typing import Callable, Optional

import msgspec
import mujoco
import numpy as np
import zenoh

from protocol import kinova
from protocol.conventions import ClockMode
from protocol.messages import (
    CameraInfo,
    Header,
    Image,
    ImageEncoding,
    KinovaPose,
    ProtocolError,
    RobotCommand,
    RobotState,
    SimClock,
    decode,
    encode,
)
from services.common import frames, jaco2
from services.common.config import ConfigStruct
from services.common.dsp import CommandRefused, DSPConfig
from services.common.metrics import LoopTimer
from services.common.service import Service, ServiceConfig
from services.common.zones import zone_from_kinova, zone_to_kinova
from services.robot_sim import scene as scene_mod
from services.robot_sim.scene import SceneConfig
from services.robot_sim.sim import Simulation

#: simulated time in lockstep starts here, so that a stamp of 0 always means "none" (no source image)
LOCKSTEP_EPOCH_NS = 1_000_000_000


class LockstepConfig(ConfigStruct):
    #: wall time to wait for the answer to a clock tick before running the cycle without it
    cycle_timeout_s: float = 0.5
    #: wall time to wait for the pipeline's answer to a frame
    frame_timeout_s: float = 2.0
    #: publish the tick (and the frame) again after this long without an answer
    retry_s: float = 0.25


class RobotSimConfig(ServiceConfig):
    scene: SceneConfig = msgspec.field(default_factory=SceneConfig)
    dsp: DSPConfig = msgspec.field(default_factory=DSPConfig)
    lockstep: LockstepConfig = msgspec.field(default_factory=LockstepConfig)
    camera_info_period_s: float = 1.0
    #: stop after this much simulated time (0: run until stopped); for benchmarks and scripted runs
    max_sim_time_s: float = 0.0


class _Api:
    """Kinova API calls, executed by the simulation thread between cycles."""

    def __init__(self, sim: Simulation) -> None:
        self.sim = sim
        self.dsp = sim.dsp
        self.builtin_zones = list(sim.dsp.zones)
        self.kinova_zones: list = []
        self.last_command = np.zeros(jaco2.N_JOINTS)

    def call(self, function: str, argument) -> kinova.ApiReply:
        handler: Callable = getattr(self, f"_{function}")
        return handler(argument)

    def _InitAPI(self, _):
        return kinova.ApiReply()

    _CloseAPI = _SetCartesianControl = _SetAngularControl = _InitAPI

    def _MoveHome(self, _):
        self.dsp.move_home()
        return kinova.ApiReply()

    def _SendBasicTrajectory(self, point: kinova.TrajectoryPoint):
        code = self.dsp.send_basic_trajectory(point)
        message = "" if code == kinova.ErrorCode.NO_ERROR_KINOVA else "point refused (FIFO full, target outside " \
                                                                       "the joint limits, or unsupported type)"
        return kinova.ApiReply(code=int(code), message=message)

    def _EraseAllTrajectories(self, _):
        self.dsp.erase_all_trajectories()
        return kinova.ApiReply()

    def _GetGlobalTrajectoryInfo(self, _):
        n = self.dsp.fifo_count
        return kinova.TrajectoryFIFOReply(result=kinova.TrajectoryFIFO(
            TrajectoryCount=n, UsedPercentage=100.0 * n / kinova.TRAJECTORY_FIFO_SIZE))

    def _angular(self, values_deg) -> kinova.AngularPositionReply:
        return kinova.AngularPositionReply(result=kinova.AngularPosition(
            Actuators=kinova.AngularInfo.from_list(values_deg)))

    def _GetAngularPosition(self, _):
        return self._angular(jaco2.model_to_physical_deg(self.sim.q))

    def _GetAngularVelocity(self, _):
        return self._angular(jaco2.model_rate_to_physical(self.sim.dq))

    def _GetAngularForce(self, _):
        return self._angular(jaco2.SIGN * self.sim.actuators.read().tau)

    def _GetAngularCommand(self, _):
        return self._angular(jaco2.model_to_physical_deg(self.sim.actuators.q_ref))

    def _cartesian(self, T) -> kinova.CartesianPositionReply:
        euler = frames.matrix_to_euler_xyz(T[:3, :3])
        return kinova.CartesianPositionReply(result=kinova.CartesianPosition(Coordinates=kinova.CartesianInfo(
            X=T[0, 3], Y=T[1, 3], Z=T[2, 3], ThetaX=euler[0], ThetaY=euler[1], ThetaZ=euler[2])))

    def _GetCartesianPosition(self, _):
        return self._cartesian(self.sim.ee_pose())

    def _GetCartesianCommand(self, _):
        return self._cartesian(jaco2.dh_forward_kinematics(self.sim.actuators.q_ref))

    def _SetProtectionZone(self, zones: kinova.ZoneList):
        try:
            boxes = [zone_from_kinova(z) for z in zones.Zones]
        except ValueError as exc:
            return kinova.ApiReply(code=int(kinova.ErrorCode.ERROR_INVALID_PARAM), message=str(exc))
        self.kinova_zones = boxes
        self.dsp.zones = self.builtin_zones + boxes
        return kinova.ApiReply()

    def _GetProtectionZone(self, _):
        zones = [zone_to_kinova(box, i + 1) for i, box in enumerate(self.kinova_zones)]
        return kinova.ZoneListReply(result=kinova.ZoneList(NbZones=len(zones), Zones=zones))

    def _EraseAllProtectionZones(self, _):
        self.kinova_zones = []
        self.dsp.zones = list(self.builtin_zones)
        return kinova.ApiReply()

    def _GetClientConfigurations(self, _):
        cfg = self.dsp.config
        return kinova.ClientConfigurationsReply(result=kinova.ClientConfigurations(
            MaxTranslationVelocity=self.dsp.max_linear, MaxOrientationVelocity=self.dsp.max_angular,
            MaxTranslationAcceleration=cfg.linear_accel_mps2, MaxOrientationAcceleration=cfg.angular_accel_rps2))

    def _SetClientConfigurations(self, conf: kinova.ClientConfigurations):
        try:
            self.dsp.set_max_velocities(conf.MaxTranslationVelocity, conf.MaxOrientationVelocity)
        except CommandRefused as exc:
            return kinova.ApiReply(code=int(kinova.ErrorCode.ERROR_INVALID_PARAM), message=str(exc))
        return kinova.ApiReply()


class _StampClock:
    """The clock of robot_sim's stamps: wall time in realtime (so latencies across services are measured in one
    clock), simulated time in lockstep."""

    def __init__(self, service: "RobotSimService") -> None:
        self._service = service
        self.mode = ClockMode(service.config.clock)

    def now_ns(self) -> int:
        return self._service._now_ns() if self.mode is ClockMode.LOCKSTEP else time.time_ns()

    def now_s(self) -> float:
        return self.now_ns() * 1e-9


class RobotSimService(Service):
    name = "robot_sim"
    follows_sim_clock = False  # it is the clock

    def __init__(self, config: RobotSimConfig | None = None, **kw) -> None:
        config = config or RobotSimConfig()
        self.config = config
        self._epoch_ns = 0
        self.sim = Simulation(config.scene, config.dsp, render=True)
        super().__init__(config, clock=_StampClock(self), **kw)
        self.config: RobotSimConfig = config
        self.lockstep = ClockMode(config.clock) is ClockMode.LOCKSTEP
        self.api = _Api(self.sim)
        self._command: Optional[tuple[RobotCommand, int]] = None
        self._command_cond = threading.Condition()
        self._api_calls: queue.Queue = queue.Queue()
        self._thread: Optional[threading.Thread] = None
        self._last_refusal = ""
        self._refusal_cycles = 0
        self._render_queue: queue.Queue = queue.Queue(maxsize=1)
        self._render_thread: Optional[threading.Thread] = None
        self._render_data = mujoco.MjData(self.sim.model)
        self._last_image: Optional[Image] = None
        self.finished = threading.Event()
        #: wall-clock periods of the DSP cycle loop (realtime: the 100 Hz loop's rate and jitter)
        self.loop_timer = LoopTimer(self.sim.cycle_ns * 1e-9)

    # ------------------------------------------------------------------ lifecycle
    def on_start(self) -> None:
        keys = self.keys
        self.state_pub = self.publisher(keys.robot_state, "state")
        self.image_pub = self.publisher(keys.camera_image, "image")
        self.info_pub = self.publisher(keys.camera_info, "camera_info")
        self.clock_pub = self.publisher(keys.clock, "clock")
        self.subscribe(keys.robot_command, RobotCommand, self._on_command, "command")
        self.queryable(keys.robot_api_all, self._on_api)
        self.queryable(keys.camera_info, self._on_camera_info_query)
        self._epoch_ns = LOCKSTEP_EPOCH_NS if self.lockstep else time.time_ns()
        self._render_thread = threading.Thread(target=self._render_loop, name="robot_sim-render", daemon=True)
        self._render_thread.start()
        self._thread = threading.Thread(target=self._run, name="robot_sim-loop", daemon=True)
        self._thread.start()

    def on_stop(self) -> None:
        with self._command_cond:
            self._command_cond.notify_all()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
        self._render_queue.put(None)
        if self._render_thread is not None:
            self._render_thread.join(timeout=5.0)

    def check_health(self) -> tuple[bool, str]:
        alive = self._thread is not None and self._thread.is_alive()
        if not alive:
            return False, "simulation loop stopped"
        stats = self.loop_timer.stats()
        return True, (f"sim_time_s={self.sim.time_ns * 1e-9:.3f} cycle_rate_hz={stats['rate_hz']:.1f} "
                      f"jitter_ms_p99={stats['jitter_ms_p99']:.2f}")

    # ------------------------------------------------------------------ inputs (zenoh threads)
    def _on_command(self, command: RobotCommand, recv_ns: int) -> None:
        with self._command_cond:
            self._command = (command, recv_ns)
            self._command_cond.notify_all()

    def _on_api(self, query: zenoh.Query) -> None:
        function = str(query.key_expr).rsplit("/", 1)[-1]
        spec = kinova.API_FUNCTIONS.get(function)
        if spec is None:
            self.refuse("api", f"unknown Kinova API function {function!r}")
            reply = kinova.ApiReply(code=int(kinova.ErrorCode.ERROR_INVALID_PARAM),
                                    message=f"unknown function {function}")
            query.reply(query.key_expr, encode(reply))
            return
        argument_type, _ = spec
        argument = None
        if argument_type is not None:
            payload = query.payload.to_bytes() if query.payload is not None else b""
            try:
                argument = decode(payload, argument_type)
            except ProtocolError as exc:
                self.refuse("api", str(exc))
                query.reply(query.key_expr, encode(kinova.ApiReply(
                    code=int(kinova.ErrorCode.ERROR_INVALID_PARAM), message=str(exc))))
                return
        future: Future = Future()
        self._api_calls.put((function, argument, future))
        with self._command_cond:
            self._command_cond.notify_all()
        try:
            reply = future.result(timeout=5.0)
        except Exception as exc:  # the loop died or timed out: the caller gets Kinova's unknown error
            reply = kinova.ApiReply(code=int(kinova.ErrorCode.UNKNOWN_ERROR), message=f"not executed: {exc}")
        query.reply(query.key_expr, encode(reply))

    def _on_camera_info_query(self, query: zenoh.Query) -> None:
        query.reply(self.keys.camera_info, encode(self._camera_info()))

    # ------------------------------------------------------------------ the loop (simulation thread)
    def _now_ns(self) -> int:
        """Simulated time (in realtime offset by the wall-clock epoch at start, so it reads like wall time)."""
        return self._epoch_ns + self.sim.time_ns

    def _run(self) -> None:
        try:
            if self.lockstep:
                self._run_lockstep()
            else:
                self._run_realtime()
        except Exception:
            self.log.exception("simulation loop failed")
            self.counters.inc("errors.loop")
        finally:
            self.finished.set()

    def _done(self) -> bool:
        limit = self.config.max_sim_time_s
        return self.stop_requested or (limit > 0 and self.sim.time_ns >= limit * 1e9)

    def _run_realtime(self) -> None:
        period = self.sim.cycle_ns * 1e-9
        next_info = 0.0
        start = time.monotonic()
        cycle = 0
        while not self._done():
            deadline = start + cycle * period
            delay = deadline - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            elif delay < -5 * period:  # fell far behind (a stall): skip ahead rather than burst
                self.counters.inc("overruns")
                cycle = int((time.monotonic() - start) / period)
            self.rates.tick("cycle")
            self.loop_timer.tick()
            self._run_api_calls()
            if self.sim.frame_due():
                self._capture_frame(wait=False)
            if time.monotonic() >= next_info:
                self.info_pub.put(self._camera_info())
                next_info = time.monotonic() + self.config.camera_info_period_s
            self.clock_pub.put(SimClock(header=self.header("clock"), sim_time_ns=self._now_ns(),
                                        mode=ClockMode.REALTIME.value))
            taken = self._take_command()
            self._cycle(taken)
            cycle += 1

    def _run_lockstep(self) -> None:
        cfg = self.config.lockstep
        self.info_pub.put(self._camera_info())
        frames_since_info = 0
        while not self._done():
            self.rates.tick("cycle")
            tick = self._now_ns()
            awaiting_frame = None
            self._publish_tick(tick)  # before the frame, so services know the time the frame was captured at
            if self.sim.frame_due() and self._capture_frame(wait=True):
                awaiting_frame = tick
                frames_since_info += 1
                if frames_since_info * self.sim.frame_period_ns >= self.config.camera_info_period_s * 1e9:
                    self.info_pub.put(self._camera_info())
                    frames_since_info = 0
            listening = self.clock_pub.matching or awaiting_frame is not None
            timeout = cfg.frame_timeout_s if awaiting_frame is not None else cfg.cycle_timeout_s
            taken = self._wait_for_answer(tick, awaiting_frame, timeout) if listening else self._take_command()
            self._cycle(taken)

    def _answered(self, tick: int, frame_stamp: Optional[int]) -> bool:
        if self._command is None:
            return False
        header = self._command[0].header
        if header.stamp_ns < tick:
            return False
        return frame_stamp is None or header.source_stamp_ns >= frame_stamp

    def _publish_tick(self, tick: int) -> None:
        self.clock_pub.put(SimClock(header=self.header("clock", stamp_ns=tick), sim_time_ns=tick,
                                    mode=ClockMode.LOCKSTEP.value))

    def _wait_for_answer(self, tick: int, frame_stamp: Optional[int], timeout_s: float):
        """Wait for the answer to this tick (and frame). A message can be lost while routes are still being set
        up (a service that just joined), so the tick, and the frame, are published again every ``retry_s``."""
        cfg = self.config.lockstep
        start = time.monotonic()
        deadline, next_retry = start + timeout_s, start + cfg.retry_s
        with self._command_cond:
            while not self._answered(tick, frame_stamp) and not self.stop_requested:
                self._run_api_calls_locked()
                now = time.monotonic()
                if now >= deadline:
                    self.counters.inc("lockstep.timeouts.frame" if frame_stamp is not None else
                                      "lockstep.timeouts.cycle")
                    break
                if now >= next_retry:
                    self.counters.inc("lockstep.retries")
                    self._command_cond.release()
                    try:
                        if frame_stamp is not None and self._last_image is not None:
                            self.image_pub.put(self._last_image)
                        self._publish_tick(tick)
                    finally:
                        self._command_cond.acquire()
                    next_retry = now + cfg.retry_s
                self._command_cond.wait(min(deadline, next_retry) - now)
        return self._take_command()

    def _run_api_calls_locked(self) -> None:
        self._command_cond.release()
        try:
            self._run_api_calls()
        finally:
            self._command_cond.acquire()

    def _run_api_calls(self) -> None:
        while True:
            try:
                function, argument, future = self._api_calls.get_nowait()
            except queue.Empty:
                return
            try:
                future.set_result(self.api.call(function, argument))
            except Exception as exc:
                self.counters.inc("errors.api")
                future.set_exception(exc)

    def _take_command(self) -> Optional[tuple[RobotCommand, int]]:
        with self._command_cond:
            taken, self._command = self._command, None
        return taken

    def _cycle(self, taken: Optional[tuple[RobotCommand, int]]) -> None:
        self._run_api_calls()
        applied: Optional[Header] = None
        if taken is not None:
            command, recv_ns = taken
            try:
                self.sim.dsp.submit(command)
                applied = command.header.with_hop(self.name, recv_ns, self.clock.now_ns())
            except CommandRefused as exc:
                self.refuse("command", str(exc))
                self.counters.inc("refused.convention")
                self._last_refusal, self._refusal_cycles = str(exc), 100
        self.sim.step_cycle()
        self._publish_state(applied)

    def _publish_state(self, applied: Optional[Header]) -> None:
        sim = self.sim
        T = sim.ee_pose()
        euler = frames.matrix_to_euler_xyz(T[:3, :3])
        status = sim.dsp.status
        faults = list(status.active_limits)
        if self._refusal_cycles > 0:
            faults.append(f"refused: {self._last_refusal}"[:120])
            self._refusal_cycles -= 1
        joint = sim.actuators.read()
        state = RobotState(
            header=self.header("state"),
            q=joint.q.tolist(), dq=joint.dq.tolist(), tau=joint.tau.tolist(),
            pose=KinovaPose(X=T[0, 3], Y=T[1, 3], Z=T[2, 3], ThetaX=euler[0], ThetaY=euler[1], ThetaZ=euler[2]),
            control_mode=status.mode, fifo_count=sim.dsp.fifo_count, faults=faults,
            watchdog_tripped=status.watchdog_tripped, angular_convention=sim.dsp.config.angular_convention,
            applied_command=applied,
        )
        self.state_pub.put(state)

    # ------------------------------------------------------------------ camera
    def _capture_frame(self, wait: bool) -> bool:
        """Snapshot the state at the frame time and render it in the render thread. Returns whether a frame is
        (being) published."""
        stamp = self.clock.now_ns()
        self.sim.mark_frame()
        if not self.image_pub.matching:  # nobody looks: rendering is read-only, so skipping changes nothing else
            self.counters.inc("frames.unobserved")
            return False
        mujoco.mj_copyData(self._render_data, self.sim.model, self.sim.data)
        done = threading.Event()
        try:
            self._render_queue.put_nowait((stamp, done))
        except queue.Full:
            self.counters.inc("frames.dropped")
            return False
        if wait:
            done.wait(timeout=10.0)
        return True

    def _render_loop(self) -> None:
        renderer = None
        cam = self.config.scene.camera
        try:
            while True:
                item = self._render_queue.get()
                if item is None:
                    return
                stamp, done = item
                try:
                    if renderer is None:
                        renderer = mujoco.Renderer(self.sim.model, cam.height, cam.width)
                    mujoco.mj_forward(self.sim.model, self._render_data)
                    renderer.update_scene(self._render_data, camera=self.sim.camera_id)
                    pixels = renderer.render()
                    header = self.header("image", stamp_ns=stamp, source_stamp_ns=stamp)
                    image = Image(header=header, width=cam.width, height=cam.height, encoding=ImageEncoding.RGB8,
                                  data=pixels.tobytes())
                    self._last_image = image
                    self.image_pub.put(image)
                except Exception:
                    self.counters.inc("errors.render")
                    self.limited_log.error("render", "rendering failed")
                    self.log.debug("render failure", exc_info=True)
                finally:
                    done.set()
        finally:
            if renderer is not None:
                renderer.close()

    def _camera_info(self) -> CameraInfo:
        return scene_mod.camera_info(self.config.scene.camera, self.header("camera_info"))


