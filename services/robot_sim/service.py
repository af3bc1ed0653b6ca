"""robot_sim: the simulated JACO-2 behind the same zenoh API a gateway to a real arm offers, plus its eye-in-hand
camera and the simulation clock. Two modes (``mode``):

* ``api`` (:class:`RobotSimService`): the robot node (:mod:`services.robot.node`: DSP, Kinova API, low-level
  control, the 500/100 Hz loop) on the simulated arm in this process (:class:`SimulatedHardware`);
* ``actuator_bus`` (:class:`ArmOnBusService`): only the arm, its actuators answering RS-485 frames on ``bus``
  (:class:`~services.robot_sim.bus_device.ActuatorBusDevice`); robot_gateway is the robot node in front of them.

Both publish camera images at the camera rate with their capture stamp, camera info (periodically and on query),
and the clock at every DSP tick (10 ms of the arm's time), with the stamp of the frame taken at that tick.

Time is the arm's own timeline (:class:`~services.robot_sim.sim.Simulation`), advanced in fixed 2 ms bus cycles:

* ``realtime``: the timeline is paced by the wall clock and stamped like wall time (the wall clock at start plus
  the arm's time). In ``actuator_bus`` mode the cycle boundaries lock to the host's frames (a host sending every
  2 ms sees its frames taken half a cycle after they arrive), like actuators synchronised to their bus master;
  replies go out as each frame arrives, with the values of the current cycle;
* ``lockstep``: deterministic, from 1 s (so that a stamp of 0 always means "none"). In ``api`` mode the robot node
  waits for the pipeline at every DSP tick (services.robot.node). In ``actuator_bus`` mode a cycle ends when every
  actuator has its command (the robot node in robot_gateway waits for the pipeline before sending it), or after
  ``lockstep.cycle_timeout_s`` without one.
"""
from __future__ import annotations

import threading
import time
from typing import Literal, Optional

import msgspec
import zenoh

from protocol.conventions import LOCKSTEP_EPOCH_NS, ClockMode
from protocol.messages import CameraInfo, Image, ObjectPose, RobotState, SimClock, SimObjects, encode
from services.model import frames
from services.robot.arm_check import ArmCheckConfig
from services.robot.rs485_bus import BusConfig, RS485Bus
from services.runtime.ports import Port, Ports
from services.runtime.service import Service
from services.robot.hardware import CYCLE_NS, CYCLE_S, DEFAULT_TIMING, DSP_CYCLE_NS, ActuatorValues
from protocol.keys import ROBOT_SERVICES
from services.robot.node import RobotNode, RobotNodeConfig
from services.robot_sim import usb_base
from services.robot_sim.arm_on_bus import ArmOnBus, ArmOnBusConfig, BusSyncConfig
from services.robot_sim.camera import RENDERER_REALTIME_PRIORITY, LoopCamera, SimCamera
from services.model.arm import load_arm
from services.robot_sim.firmware import ActuatorConfig, check_actuators
from services.robot_sim.hardware import SimulatedHardware
from services.robot_sim.scene import DEFAULT_TRIGGER_MS, TRIGGER_OFFSETS_MS, SceneConfig, check_joints_deg, \
    trigger_offset
from services.robot_sim.trigger_phase import TriggerPhase
from services.robot_sim.sim import Simulation

class RobotSimConfig(RobotNodeConfig):
    #: a simulated arm is its description (MuJoCo builds it from the same one): the check is waived unless its
    #: actuators are told to disagree (actuators.mirrored_joints)
    arm_check: ArmCheckConfig = msgspec.field(default_factory=lambda: ArmCheckConfig(waived=True))
    scene: SceneConfig = msgspec.field(default_factory=SceneConfig)
    #: the emulated actuators' firmware
    actuators: ActuatorConfig = msgspec.field(default_factory=ActuatorConfig)
    camera_info_period_s: float = 1.0
    #: stop after this much simulated time (0: run until stopped); for benchmarks and scripted runs
    max_sim_time_s: float = 0.0
    #: api: the robot node (DSP, Kinova API, low-level API) on the simulated arm; actuator_bus: only the arm,
    #: its actuators answering RS-485 frames on ``bus`` (a robot_gateway drives them), plus the camera and clock
    mode: Literal["api", "actuator_bus"] = "api"
    bus: BusConfig = msgspec.field(default_factory=BusConfig)
    bus_sync: BusSyncConfig = msgspec.field(default_factory=BusSyncConfig)

    def __post_init__(self) -> None:
        super().__post_init__()
        arm = load_arm(self.arm)
        if self.scene.initial_joints_deg is not None:
            check_joints_deg(arm, self.scene.initial_joints_deg, "scene.initial_joints_deg")
        check_actuators(self.actuators, arm)
        if self.bus.timing != DEFAULT_TIMING and ClockMode(self.clock) is ClockMode.LOCKSTEP:
            raise ValueError(f"bus.period_ms {self.bus.period_ms:g}: in lockstep the host exchanges once per "
                             f"{DEFAULT_TIMING.period_ms:g} ms cycle of the emulated actuators; a longer period is "
                             "realtime's")
        if self.actuators.mirrored_joints and self.arm_check.waived:
            raise ValueError("actuators.mirrored_joints makes the arm disagree with its description: the check "
                             "cannot be waived (arm_check.waived: false)")


#: what the simulation's outputs use (:class:`_SimulationOutputs`): the clock, the camera (published and its info
#: answered), where the free objects are, and the robot's state, whose trace places the camera's trigger (``trigger_offset_ms: auto``)
SIMULATION_PORTS = Ports(consumes=(Port("robot_state", RobotState),),
                         produces=(Port("clock", SimClock), Port("camera_image", Image),
                                   Port("camera_info", CameraInfo), Port("sim_objects", SimObjects)),
                         answers=(Port("camera_info"),))


class _SimulationOutputs:
    """What both modes publish besides the robot: camera images and info, and the clock with its frame stamps."""

    def __init__(self, service: Service, sim: Simulation, config: RobotSimConfig, epoch_ns: int,
                 render_in_loop: bool = False) -> None:
        """``render_in_loop``: in lockstep, the thread that runs the arm's cycles (and calls :meth:`at_boundary`,
        :meth:`tick`) renders the frames itself (:class:`~services.robot_sim.camera.LoopCamera`); it must then
        call :meth:`loop_ended` as it ends."""
        self.service, self.sim, self.config = service, sim, config
        self.lockstep = ClockMode(config.clock) is ClockMode.LOCKSTEP
        self.render_in_loop = render_in_loop and self.lockstep
        self.epoch_ns = epoch_ns
        #: realtime: frames are taken this long after a DSP tick (the camera's trigger: fixed, or moved to where the
        #: commands' measured paths are applied soonest); lockstep: at the tick
        offset = trigger_offset(config.scene.camera, config.mode)
        auto = offset == "auto" and not self.lockstep
        self.trigger = TriggerPhase(0 if self.lockstep else DEFAULT_TRIGGER_MS[config.mode] if auto else offset,
                                    TRIGGER_OFFSETS_MS, auto, cycle_ms=DSP_CYCLE_NS / 1e6)
        self.camera: Optional[SimCamera | LoopCamera] = None
        #: the frame taken at the last DSP tick: (capture stamp, what the camera delivers it by)
        self.frame: Optional[tuple[int, object]] = None
        self._next_info = 0.0

    @property
    def renders(self) -> bool:
        """Whether this camera publishes at all (``scene.camera.enabled``; false: a camera service does)."""
        return self.config.scene.camera.enabled

    def declare(self) -> None:
        service, keys = self.service, self.service.keys
        self.clock_pub = service.publisher(keys.clock, "clock")
        self.objects_pub = service.publisher(keys.sim_objects, "objects") if self.sim.free_objects else None
        if not self.renders:
            return
        self.image_pub = service.publisher(keys.camera_image, "image")
        self.info_pub = service.publisher(keys.camera_info, "camera_info")
        service.queryable(keys.camera_info, self._on_info_query)
        if self.trigger.auto:
            # whichever robot node applies the commands (this process's, or robot_gateway's): the trace says when
            # each reached it; decisions are made on this thread, the loop only reads the offset
            service.subscribe(keys.robot_state, RobotState, self._on_robot_state, "robot_state")
        if self.render_in_loop:
            self.camera = LoopCamera(self.sim, self.image_pub.put, service.header, self._render_failed)
        else:
            self.camera = SimCamera(self.sim, self.image_pub.put, service.header, self._render_failed,
                                    realtime_priority=RENDERER_REALTIME_PRIORITY
                                    if self.config.realtime_priority > 0 and not self.lockstep else 0)
        self.camera.start()
        self._camera_info_now_and_then()  # before the first frame: vision cannot use a frame without it

    def loop_ended(self) -> None:
        """The thread that rendered the frames ends (``render_in_loop``): its renderer goes with it."""
        if isinstance(self.camera, LoopCamera):
            self.camera.close_renderer()

    def stop(self) -> None:
        if self.camera is not None:
            self.camera.stop()

    def _render_failed(self) -> None:
        self.service.counters.inc("errors.render")
        self.service.limited_log.error("render", "rendering failed")

    def _on_robot_state(self, state: RobotState, recv_ns: int) -> None:
        applied = state.applied_command
        if applied is None or not applied.source_stamp_ns or not applied.trace:
            return
        robot_hop = applied.trace[-1]
        if robot_hop.service not in ROBOT_SERVICES or not self.trigger.observe(
                applied.source_stamp_ns, robot_hop.recv_ns, robot_hop.pub_ns):
            return
        change = self.trigger.update(time.monotonic_ns())
        if change is not None:
            self.service.counters.inc("camera.trigger_moves")
            self.service.log.info(
                "camera trigger moved from %d to %d ms after the DSP tick: capture to applied predicted %.1f ms "
                "(median) at the old offset, %.1f ms at the new one (%d commands; the robot takes commands %.1f ms "
                "after its tick)", change.from_ms, change.to_ms, change.predicted_from_ms, change.predicted_to_ms,
                change.samples, change.lag_ms)

    def trigger_detail(self) -> str:
        """The camera's trigger, for the health's detail (``mfvs status``, the latency benchmark)."""
        if not self.trigger.auto:
            return f"camera_trigger_ms={self.trigger.offset_ms} (fixed)"
        return (f"camera_trigger_ms={self.trigger.offset_ms} (auto, moved {self.trigger.moves}x, "
                f"{self.trigger.inconsistent} decisions left to a model that missed)")

    def _on_info_query(self, query: zenoh.Query) -> None:
        query.reply(self.service.keys.camera_info, encode(self.camera.info(self.service.header("camera_info"))))

    def at_boundary(self, sim_time_ns: int) -> None:
        """A cycle boundary, before physics moves on: take the camera frame due at this DSP tick."""
        if not self.renders or (sim_time_ns - self.trigger.offset_ns) % DSP_CYCLE_NS or not self.sim.frame_due():
            return
        self.sim.mark_frame()
        stamp = self.epoch_ns + sim_time_ns
        if not self.image_pub.matching:  # nobody looks: rendering is read-only, so skipping changes nothing else
            self.service.counters.inc("frames.unobserved")
            return
        taken = self.camera.capture(stamp)
        if taken is None:
            self.service.counters.inc("frames.dropped")
            return
        self.frame = (stamp, taken)

    def tick(self, tick_ns: int) -> Optional[int]:
        """A DSP tick: the clock (with this tick's frame stamp) and, now and then, the camera info; in lockstep
        the frame is rendered and out before this returns. The frame's stamp, if one was taken at this tick."""
        frame_stamp = None
        if self.frame is not None and self.frame[0] == tick_ns:
            frame_stamp, taken = self.frame
            if self.lockstep:
                self.camera.deliver(taken, timeout_s=10.0)
        self.clock_pub.put(SimClock(header=self.service.header("clock", stamp_ns=tick_ns), sim_time_ns=tick_ns,
                                    mode=ClockMode(self.config.clock).value, frame_stamp_ns=frame_stamp or 0))
        if self.objects_pub is not None:
            self.objects_pub.put(SimObjects(header=self.service.header("objects", stamp_ns=tick_ns), objects=[
                ObjectPose(name=name, pose=frames.pose_message(T[:3, :3], T[:3, 3]))
                for name, T in ((n, self.sim.object_pose(n)) for n in self.sim.free_objects)]))
        self._camera_info_now_and_then()
        return frame_stamp

    def retry(self, tick_ns: int) -> None:
        """The answer to this tick is late: the frame and the tick again."""
        image = self.camera.last_image if self.camera is not None else None
        if self.frame is not None and self.frame[0] == tick_ns and image is not None:
            self.image_pub.put(image)
        self.clock_pub.put(SimClock(header=self.service.header("clock", stamp_ns=tick_ns), sim_time_ns=tick_ns,
                                    mode=ClockMode(self.config.clock).value,
                                    frame_stamp_ns=self.frame[0] if self.frame and self.frame[0] == tick_ns else 0))

    def _camera_info_now_and_then(self) -> None:
        now = time.monotonic()
        if self.renders and now >= self._next_info:
            self.info_pub.put(self.camera.info(self.service.header("camera_info")))
            self._next_info = now + self.config.camera_info_period_s


def _epoch(config: RobotSimConfig) -> int:
    """Stamps are this plus the arm's time: wall-like in realtime, from 1 s in lockstep."""
    return LOCKSTEP_EPOCH_NS if ClockMode(config.clock) is ClockMode.LOCKSTEP else time.time_ns()


class RobotSimService(RobotNode):
    """The robot node on the simulated arm in this process (``mode: api``)."""

    name = "robot_sim"
    PORTS = RobotNode.PORTS | SIMULATION_PORTS
    follows_sim_clock = False  # it is the clock

    def __init__(self, config: RobotSimConfig | None = None, **kw) -> None:
        config = config or RobotSimConfig()
        if config.mode != "api":
            raise ValueError("RobotSimService is robot_sim's api mode; use robot_sim_service() for any mode")
        super().__init__(config, **kw)
        self.config: RobotSimConfig = config
        self.sim = Simulation(config.scene, config.actuators, render=True, counters=self.counters, arm=self.arm)
        self.outputs: Optional[_SimulationOutputs] = None
        #: the simulated arm as the node's hardware (its stamps' epoch moves with the wall clock in realtime)
        self.sim_hardware: Optional[SimulatedHardware] = None

    def open_hardware(self):
        epoch = _epoch(self.config)
        if self.lockstep:
            self.clock.advance_to(epoch)
        self.outputs = _SimulationOutputs(self, self.sim, self.config, epoch, render_in_loop=True)
        self.sim_hardware = SimulatedHardware(self.sim, epoch, on_boundary=self._at_boundary)
        return self.sim_hardware, self.sim_hardware.read()

    def _at_boundary(self, values: ActuatorValues) -> None:
        self.outputs.at_boundary(values.stamp_ns)

    def declare_outputs(self) -> None:
        self.outputs.declare()

    def frame_at_tick(self, tick_ns: int) -> Optional[int]:
        return self.outputs.tick(tick_ns)

    def on_lockstep_retry(self, tick_ns: int) -> None:
        self.outputs.retry(tick_ns)

    def on_lockstep_end(self) -> None:
        self.outputs.loop_ended()

    def lockstep_outputs_matched(self) -> bool:
        return not self.outputs.renders or self.outputs.image_pub.matching

    def on_loop_start(self) -> None:
        self.sim_hardware.epoch_ns = time.time_ns() - self.sim.time_ns  # the arm's time starts now, as wall time
        self.outputs.epoch_ns = self.sim_hardware.epoch_ns

    def cycles_dropped(self, n: int) -> None:
        super().cycles_dropped(n)
        self.sim_hardware.epoch_ns += n * CYCLE_NS  # the arm did not run them: its stamps skip them, as wall time did
        self.outputs.epoch_ns = self.sim_hardware.epoch_ns

    def done(self) -> bool:
        limit = self.config.max_sim_time_s
        return self.stop_requested or (limit > 0 and self.sim.time_ns >= limit * 1e9)

    def on_stop(self) -> None:
        super().on_stop()
        if self.outputs is not None:
            self.outputs.stop()

    def check_health(self) -> tuple[bool, str]:
        ok, detail = super().check_health()
        trigger = self.outputs.trigger_detail() if self.outputs is not None else ""
        arm, _, rest = detail.partition("; ")  # the arm first, as every robot node's detail starts
        return ok, f"{arm}; sim_time_s={self.sim.time_ns * 1e-9:.3f} {trigger} {rest}"


class ArmOnBusService(Service):
    """The simulated arm's actuators on an RS-485 bus (:class:`~services.robot_sim.arm_on_bus.ArmOnBus`), plus
    its camera and clock (``mode: actuator_bus``)."""

    name = "robot_sim"
    PORTS = SIMULATION_PORTS
    follows_sim_clock = False

    def __init__(self, config: RobotSimConfig | None = None, **kw) -> None:
        config = config or RobotSimConfig(mode="actuator_bus")
        super().__init__(config, **kw)
        self.config: RobotSimConfig = config
        self.lockstep = ClockMode(config.clock) is ClockMode.LOCKSTEP
        #: the arm simulated (its description)
        self.arm = load_arm(config.arm)
        self.sim = Simulation(config.scene, config.actuators, render=True, counters=self.counters, arm=self.arm)
        epoch = _epoch(config)
        self.outputs = _SimulationOutputs(self, self.sim, config, epoch)
        self.arm_on_bus: Optional[ArmOnBus] = None

    def on_start(self) -> None:
        cfg = self.config
        if self.lockstep:
            self.clock.advance_to(self.outputs.epoch_ns)
        bus = self._open_bus()
        try:
            self.outputs.declare()
        except BaseException:
            bus.close()
            raise
        # the host's cycle (bus.period_ms): the actuators keep their own 2 ms one and spread each target over it
        self.arm_on_bus = ArmOnBus(self.sim, bus, ArmOnBusConfig(
            lockstep=self.lockstep, epoch_ns=self.outputs.epoch_ns, sync=cfg.bus_sync, timing=cfg.lockstep,
            host_period_s=cfg.bus.timing.period_s,
            realtime_priority=cfg.realtime_priority, max_sim_time_s=cfg.max_sim_time_s), self.counters,
            on_boundary=self._on_boundary, on_tick=self._on_tick, on_retry=self.outputs.retry,
            on_epoch=self._on_epoch, log=self.log)
        if not self.lockstep:
            self.declare_loop("bus_cycle", 1.0 / CYCLE_S, ("cycles.late", "cycles.dropped"))
        self.arm_on_bus.start()

    def _open_bus(self):
        """The actuators' bus: python-can's (the emulation's CAN stand-in), or behind an emulated base on USB that
        a host reaches with Kinova's own comm layer (``interface: kinova_usb_base``, the channel the socket's
        path: services.robot_sim.usb_base)."""
        cfg = self.config
        if cfg.bus.interface != usb_base.INTERFACE:
            return RS485Bus(cfg.bus, self.counters)
        firmware = self.sim.firmware

        fingers, hand = self.sim.fingers, self.arm.hand

        def angles() -> list[float]:  # what Kinova's high-level API reads before RS-485 is activated
            joints = [firmware.position_deg(i) for i in range(self.arm.n_joints)]
            units = [] if fingers is None else hand.angle_to_units(fingers.position).tolist()
            return (joints + [0.0] * (usb_base.ANGULAR_ACTUATORS - len(joints))
                    + units + [0.0] * (usb_base.ANGULAR_FINGERS - len(units)))

        return usb_base.UsbBaseBus(cfg.bus.channel, model=self.arm.name, counters=self.counters,
                                   device_type=self.arm.robot_type, angular_position=angles)

    def _on_boundary(self, sim_time_ns: int) -> None:
        self.rates.tick("bus_cycle")
        self.outputs.at_boundary(sim_time_ns)

    def _on_tick(self, tick_ns: int) -> None:
        self.rates.tick("cycle")
        self.outputs.tick(tick_ns)

    def _on_epoch(self, epoch_ns: int) -> None:
        self.outputs.epoch_ns = epoch_ns

    @property
    def finished(self) -> threading.Event:
        return self.arm_on_bus.finished

    def on_stop(self) -> None:
        if self.arm_on_bus is not None:
            self.arm_on_bus.stop()
        self.outputs.stop()

    def check_health(self) -> tuple[bool, str]:
        if self.arm_on_bus is None or not self.arm_on_bus.alive:
            return False, "actuator loop stopped"
        stats, phase = self.arm_on_bus.loop_timer.stats(), self.arm_on_bus.phase_error.stats()
        return True, (f"sim_time_s={self.sim.time_ns * 1e-9:.3f} bus_cycle_rate_hz={stats['rate_hz']:.1f} "
                      f"jitter_ms_p99={stats['jitter_ms_p99']:.2f} host_phase_error_ms_p50={phase['p50_ms']:.2f} "
                      f"p99={phase['p99_ms']:.2f} {self.outputs.trigger_detail()}")


def robot_sim_service(config: RobotSimConfig | None = None, **kw) -> Service:
    """robot_sim in its configured mode."""
    config = config or RobotSimConfig()
    return (ArmOnBusService if config.mode == "actuator_bus" else RobotSimService)(config, **kw)


robot_sim_service.name = "robot_sim"
