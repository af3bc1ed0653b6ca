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
from typing import Literal, Optional

import msgspec
import mujoco
import numpy as np
import zenoh

from protocol import rs485
from protocol.conventions import ClockMode
from protocol.messages import (
    CameraInfo,
    Image,
    ImageEncoding,
    SimClock,
    encode,
)
from services.common import jaco2
from services.common.clock import PeriodicSchedule
from services.common.config import ConfigStruct
from services.common.dsp import DSPConfig
from services.common.lowlevel import LowLevelConfig
from services.common.metrics import LoopTimer
from services.common.robot_frontend import RobotFrontEnd
from services.common.rs485_bus import BusConfig, RS485Bus
from services.common.service import Service, ServiceConfig
from services.robot_sim import scene as scene_mod
from services.robot_sim.actuator_bus import (
    ACTUATOR_TEMPERATURE_C,
    TORQUE_PER_AMPERE,
    ActuatorBusConfig,
    ActuatorBusEmulator,
)
from services.robot_sim.scene import SceneConfig
from services.robot_sim.sim import Simulation

#: simulated time in lockstep starts here, so that a stamp of 0 always means "none" (no source image)
LOCKSTEP_EPOCH_NS = 1_000_000_000


#: actuator-bus mode: after a stall, physics catches up this many 2 ms cycles at most (0.1 s), then drops time
MAX_CATCH_UP_CYCLES = 50


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
    #: api: the emulated DSP and the robot's zenoh API; actuator_bus: only the actuators, answering RS-485 frames
    #: on ``bus`` (a robot_gateway drives them), plus the camera (realtime only)
    mode: Literal["api", "actuator_bus"] = "api"
    bus: BusConfig = msgspec.field(default_factory=BusConfig)
    actuators: ActuatorBusConfig = msgspec.field(default_factory=ActuatorBusConfig)
    #: api mode: the low-level torque API (robot/lowlevel/*, realtime) with its watchdog and release
    lowlevel: LowLevelConfig = msgspec.field(default_factory=LowLevelConfig)

    def __post_init__(self) -> None:
        if self.mode == "actuator_bus" and ClockMode(self.clock) is not ClockMode.REALTIME:
            raise ValueError("the actuator_bus mode runs in realtime only")


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


class RobotSimService(RobotFrontEnd, Service):
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
        self.bus_mode = config.mode == "actuator_bus"
        self.bus: Optional[RS485Bus] = None
        if self.bus_mode:
            self.bus = RS485Bus(config.bus, self.counters)
            self.sim.actuators = ActuatorBusEmulator(self.sim.model, self.sim.data, self.bus, config.actuators,
                                                     self.counters)
        else:
            self.init_frontend(self.sim, self.sim.dsp)
        self._thread: Optional[threading.Thread] = None
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
        if not self.bus_mode:
            self.declare_frontend()
            self.declare_lowlevel(self.sim.actuators, self.config.lowlevel, self.sim.dsp.kin.gravity,
                                  unavailable="low-level torque control runs in realtime only" if self.lockstep
                                  else "")
        self.image_pub = self.publisher(keys.camera_image, "image")
        self.info_pub = self.publisher(keys.camera_info, "camera_info")
        self.clock_pub = self.publisher(keys.clock, "clock")
        self.queryable(keys.camera_info, self._on_camera_info_query)
        self._epoch_ns = LOCKSTEP_EPOCH_NS if self.lockstep else time.time_ns()
        self._render_thread = threading.Thread(target=self._render_loop, name="robot_sim-render", daemon=True)
        self._render_thread.start()
        self._thread = threading.Thread(target=self._run, name="robot_sim-loop", daemon=True)
        self._thread.start()

    def on_stop(self) -> None:
        if not self.bus_mode:
            with self.command_cond:
                self.command_cond.notify_all()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
        self._render_queue.put(None)
        if self._render_thread is not None:
            self._render_thread.join(timeout=5.0)
        if self.bus is not None:
            self.bus.close()

    def check_health(self) -> tuple[bool, str]:
        alive = self._thread is not None and self._thread.is_alive()
        if not alive:
            return False, "simulation loop stopped"
        stats = self.loop_timer.stats()
        return True, (f"sim_time_s={self.sim.time_ns * 1e-9:.3f} cycle_rate_hz={stats['rate_hz']:.1f} "
                      f"jitter_ms_p99={stats['jitter_ms_p99']:.2f}")

    # ------------------------------------------------------------------ inputs (zenoh threads)
    def _on_camera_info_query(self, query: zenoh.Query) -> None:
        query.reply(self.keys.camera_info, encode(self._camera_info()))

    # ------------------------------------------------------------------ the loop (simulation thread)
    def _now_ns(self) -> int:
        """Simulated time (in realtime offset by the wall-clock epoch at start, so it reads like wall time)."""
        return self._epoch_ns + self.sim.time_ns

    def _run(self) -> None:
        try:
            if self.bus_mode:
                self._run_bus()
            elif self.lockstep:
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
        """The actuators' 2 ms cycle on wall time: low-level torque control and state every cycle, the DSP (robot
        commands, Kinova API, state) every fifth, frames when due. After a stall the missed cycles run back to
        back (up to MAX_CATCH_UP_CYCLES), so simulated time keeps up with the wall-time stamps of everyone else."""
        schedule = PeriodicSchedule(rs485.CYCLE_S)
        last = -1
        self._next_info = 0.0
        self._applied = None
        while not self._done():
            cycle, skipped = schedule.wait()
            if skipped:
                self.counters.inc("overruns")
            first = cycle if last < 0 else max(last + 1, cycle - MAX_CATCH_UP_CYCLES + 1)
            if first > last + 1 and last >= 0:
                self.counters.inc("physics.dropped_cycles", first - last - 1)
            for slot in range(first, cycle + 1):
                self._actuator_cycle(slot)
            last = cycle

    def _actuator_cycle(self, slot: int) -> None:
        per_dsp_cycle = max(1, round(self.sim.cycle_ns * 1e-9 / rs485.CYCLE_S))
        phase = slot % per_dsp_cycle
        if phase == 0:
            self.rates.tick("cycle")
            self.loop_timer.tick()
            self.run_api_calls()
            if self.sim.frame_due():
                self._capture_frame(wait=False)
            if time.monotonic() >= self._next_info:
                self.info_pub.put(self._camera_info())
                self._next_info = time.monotonic() + self.config.camera_info_period_s
            self.clock_pub.put(SimClock(header=self.header("clock"), sim_time_ns=self._now_ns(),
                                        mode=ClockMode.REALTIME.value))
            self._applied = self.apply_command(self.take_command())
            self.sim.dsp_cycle()
        self.lowlevel_cycle(self.sim.q)
        self.sim.step_physics(max(1, round(rs485.CYCLE_S / self.sim.model.opt.timestep)))
        self._publish_lowlevel()
        if phase == per_dsp_cycle - 1:
            self.publish_state(self._applied)
            self._applied = None

    def _publish_lowlevel(self) -> None:
        data = self.sim.data
        tau = data.actuator_force[: jaco2.N_JOINTS]
        self.publish_lowlevel(data.qpos[: jaco2.N_JOINTS], data.qvel[: jaco2.N_JOINTS], tau,
                              tau / TORQUE_PER_AMPERE, np.full(jaco2.N_JOINTS, ACTUATOR_TEMPERATURE_C))

    def _run_bus(self) -> None:
        """Actuator-bus mode: the actuators' 500 Hz cycle and physics on wall time, the camera and the clock."""
        schedule = PeriodicSchedule(rs485.CYCLE_S)  # the actuators' cycle (500 Hz)
        steps = max(1, round(rs485.CYCLE_S / self.sim.model.opt.timestep))
        self.loop_timer = LoopTimer(rs485.CYCLE_S)
        next_info = 0.0
        last = -1
        while not self._done():
            cycle, skipped = schedule.wait()
            if skipped:
                self.counters.inc("overruns")
            self.loop_timer.tick()
            # physics keeps up with wall time even when the loop stalled (rendering, a busy machine): the
            # gateway's position targets are wall-time trajectories, and a simulation that dropped time would
            # run them faster than commanded (and stamp its images behind the robot's state)
            cycles = 1 if last < 0 else min(cycle - last, MAX_CATCH_UP_CYCLES)
            if last >= 0 and cycle - last > MAX_CATCH_UP_CYCLES:
                self.counters.inc("physics.dropped_cycles", cycle - last - MAX_CATCH_UP_CYCLES)
            last = cycle
            self.sim.actuators.process(schedule.elapsed_s())
            self.sim.step_physics(steps * cycles)
            if self.sim.frame_due():
                self._capture_frame(wait=False)
            if cycle % 5 == 0:
                self.rates.tick("cycle")
                self.clock_pub.put(SimClock(header=self.header("clock"), sim_time_ns=self._now_ns(),
                                            mode=ClockMode.REALTIME.value))
            if time.monotonic() >= next_info:
                self.info_pub.put(self._camera_info())
                next_info = time.monotonic() + self.config.camera_info_period_s

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
            taken = self._wait_for_answer(tick, awaiting_frame, timeout) if listening else self.take_command()
            self._cycle(taken)

    def _answered(self, tick: int, frame_stamp: Optional[int]) -> bool:
        pending = self.peek_command()
        if pending is None:
            return False
        header = pending[0].header
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
        with self.command_cond:
            while not self._answered(tick, frame_stamp) and not self.stop_requested:
                self._run_api_calls_locked()
                now = time.monotonic()
                if now >= deadline:
                    self.counters.inc("lockstep.timeouts.frame" if frame_stamp is not None else
                                      "lockstep.timeouts.cycle")
                    break
                if now >= next_retry:
                    self.counters.inc("lockstep.retries")
                    self.command_cond.release()
                    try:
                        if frame_stamp is not None and self._last_image is not None:
                            self.image_pub.put(self._last_image)
                        self._publish_tick(tick)
                    finally:
                        self.command_cond.acquire()
                    next_retry = now + cfg.retry_s
                self.command_cond.wait(min(deadline, next_retry) - now)
        return self.take_command()

    def _run_api_calls_locked(self) -> None:
        self.command_cond.release()
        try:
            self.run_api_calls()
        finally:
            self.command_cond.acquire()

    def _cycle(self, taken) -> None:
        applied = self.apply_command(taken)
        self.sim.step_cycle()
        self.publish_state(applied)

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


