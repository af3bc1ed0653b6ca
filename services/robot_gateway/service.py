"""robot_gateway: the robot's zenoh API (state, commands, the Kinova API queryables, the low-level torque API)
backed by a real arm. It is the robot node (services.robot.node) that robot_sim runs in its ``api`` mode, on other
hardware, so every other service sees the same robot:

* ``rs485`` backend: the actuators on an RS-485 bus carried by python-can (:class:`LinkHardware`); the gateway runs
  the emulated DSP itself at 100 Hz on top of its 500 Hz exchanges with the actuators. In lockstep it drives
  robot_sim's emulated actuators (``mode: actuator_bus``) cycle by cycle, and learns from the simulator's clock
  which tick carries a camera frame;
* ``kinova_sdk`` backend (:class:`SdkGatewayService`): the arm through Kinova's own SDK library (USB, or
  Ethernet) loaded with ctypes (services.robot_gateway.kinova_sdk); the arm's own DSP interprets the commands, so
  the gateway forwards them every 10 ms (services.robot_gateway.sdk_driver); no low-level torque API; realtime
  only. It opens the arm before it connects to the router: a gateway that cannot reach its arm says so first
  (one line, exit 2).

Bus failures (timeouts, NACKs, missing replies, garbled frames) are counted; the arm is held at its last measured
angles, and after ``max_bus_errors`` consecutive failures the gateway reports itself unhealthy and refuses motion
until the bus answers again.
"""
from __future__ import annotations

import logging
import math
import threading
import time
from pathlib import Path
from typing import Literal, Optional

import msgspec

from protocol.conventions import LOCKSTEP_EPOCH_NS, ClockMode
from protocol.messages import SimClock
from services.robot.rs485_bus import BusConfig, RS485Bus
from services.runtime.service import Service
from services.robot.hardware import DEFAULT_TIMING, HardwareError, JointReading
from services.robot.node import RobotNode, RobotNodeConfig
from services.model.arm import load_arm
from services.robot_gateway.kinova_sdk import ArmStartError, KinovaSdk, SdkArm, SdkError, SdkEthernetConfig, open_arm
from services.robot_gateway.kinova_usb import (COMMAND_LAYER, HIGH_LEVEL_CHECK_DEG, KinovaUsbBus,
                                               high_level_disagreement, locate_comm_layer, open_kinova_usb)
from services.robot_gateway.link import ActuatorLink, LinkError, LinkHardware
from services.robot_gateway.sdk_driver import SdkConnection, SdkDriver

#: ``bus.interface`` for a real arm's actuator bus through Kinova's USB comm layer (services.robot_gateway.kinova_usb)
KINOVA_USB = "kinova_usb"


#: stamps below this are simulated time (lockstep starts at 1 s); wall-clock stamps are about 1.7e18 ns
SIMULATED_TIME_LIMIT_NS = 10**17


class GatewayConfig(RobotNodeConfig):
    backend: Literal["rs485", "kinova_sdk"] = "rs485"
    bus: BusConfig = msgspec.field(default_factory=BusConfig)
    #: the actuators' bus addresses, joint by joint; null: the arm description's
    addresses: Optional[list[int]] = None
    #: realtime: an actuator that has not replied after this long is a bus error (lockstep: lockstep.link_timeout_s)
    link_timeout_s: float = 0.01
    #: at start, keep asking the actuators for their positions this long (an arm, or robot_sim, powering up)
    connect_timeout_s: float = 30.0
    #: Kinova's SDK: its directory or its command-layer file (null: $MFVS_KINOVA_SDK)
    sdk_library: Optional[str] = None
    #: the serial number of the arm to drive (null: the only one connected)
    sdk_serial: Optional[str] = None
    sdk_transport: Literal["usb", "ethernet"] = "usb"
    #: bus.interface kinova_usb: before activation, read the joint angles through Kinova's high-level API (its
    #: command layer, beside the comm layer) and refuse to start when the first RS-485 positions differ from them
    #: by more than this (deg): a position read from the wrong field or the wrong actuator is never acted on.
    #: null: no check (an emulated arm behind a comm layer with no command layer)
    high_level_check_deg: Optional[float] = HIGH_LEVEL_CHECK_DEG
    sdk_ethernet: SdkEthernetConfig = msgspec.field(default_factory=SdkEthernetConfig)

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.backend == "kinova_sdk" and ClockMode(self.clock) is not ClockMode.REALTIME:
            raise ValueError("the kinova_sdk backend runs in realtime only (a real arm has no simulated clock)")
        if ClockMode(self.clock) is ClockMode.LOCKSTEP and self.bus.timing != DEFAULT_TIMING:
            raise ValueError(f"bus.period_ms {self.bus.period_ms:g}: in lockstep each exchange is one of the emulated "
                             f"actuators' {DEFAULT_TIMING.period_ms:g} ms cycles; a longer period is realtime's")
        if self.high_level_check_deg is not None and not (math.isfinite(self.high_level_check_deg)
                                                          and self.high_level_check_deg > 0):
            raise ValueError("high_level_check_deg must be a positive number of degrees, or null (no check)")
        arm = load_arm(self.arm)
        if self.addresses is not None and (len(self.addresses) != arm.n_joints
                                           or len(set(self.addresses)) != arm.n_joints):
            raise ValueError(f"addresses must be {arm.n_joints} distinct bus addresses (the {arm.name}'s joints)")

    def bus_addresses(self) -> list[int]:
        """The actuators' addresses: the config's, else the arm description's."""
        return list(load_arm(self.arm).bus_addresses) if self.addresses is None else list(self.addresses)


class RobotGatewayService(RobotNode):
    """The robot node on actuators behind an RS-485 bus."""

    name = "robot_gateway"

    def __init__(self, config: GatewayConfig | None = None, bus=None, **kw) -> None:
        """``bus``: the actuators' bus already open (the process's entry opens Kinova's comm layer first, so that
        an arm that cannot be reached is said before anything starts); None: opened at start."""
        config = config or GatewayConfig()
        if config.backend != "rs485":
            raise ValueError("RobotGatewayService is the rs485 backend; use robot_gateway_service() for any")
        super().__init__(config, **kw)
        self.config: GatewayConfig = config
        self.bus: Optional[RS485Bus | KinovaUsbBus] = bus
        #: lockstep: the simulator's ticks heard so far → the stamp of the frame taken at each (0: none)
        self._ticks: dict[int, int] = {}
        self._latest_tick = 0
        self._ticks_cond = threading.Condition()

    def open_hardware(self):
        cfg = self.config
        if self.bus is None:
            self.bus = open_bus(cfg, self.counters, self.log)
        elif self.bus.counters is not self.counters:  # opened by the process's entry: its counts become ours
            for name, count in self.bus.counters.snapshot().items():
                self.counters.inc(name, count)
            self.bus.counters = self.counters
        timeout = cfg.lockstep.link_timeout_s if self.lockstep else cfg.link_timeout_s
        # realtime: pipelined, so that the round trip does not stretch the 2 ms cycle; lockstep: in step, so that
        # the arm behind the bus computes exactly what the simulated arm in robot_sim's process does
        try:
            hardware = LinkHardware(ActuatorLink(self.bus, cfg.bus_addresses(), timeout, self.counters), self.arm,
                                    pipelined=not self.lockstep, counted_from_ns=self._counted_timeline(),
                                    timing=cfg.bus.timing)
            reading = self._connect(hardware)
            if self.lockstep and reading.stamp_ns >= SIMULATED_TIME_LIMIT_NS:
                # in lockstep the gateway exchanges as fast as the arm answers: only an arm on a simulated clock
                # (robot_sim's actuators in lockstep) waits for each exchange; a real one would be driven too fast
                raise ValueError("lockstep needs robot_sim's emulated actuators in lockstep on the bus; this bus "
                                 "answers in wall time (a real arm, or actuators in realtime)")
            return hardware, reading
        except BaseException:
            self.bus.close()  # a start that fails leaves no socket behind
            self.bus = None
            raise

    def _counted_timeline(self) -> Optional[int]:
        """In lockstep on a bus that carries no stamps (Kinova's USB comm layer), where the arm's timeline starts
        (:func:`open_bus` has checked that the arm is robot_sim's emulation, which steps once per exchange)."""
        if not self.lockstep or self.bus.arm_timeline:
            return None
        return LOCKSTEP_EPOCH_NS

    def arm_summary(self) -> str:
        """The arm, its actuators, and how the bus is reached: the interface, its cycle, and on Kinova's comm layer
        how long its calls take (what `mfvs status` shows of a real arm's bus)."""
        addresses = self.config.bus_addresses()
        summary = (f"arm {self.arm.name}: {len(addresses)} actuators on the bus "
                   f"({', '.join(f'0x{a:02X}' for a in addresses)}) over {self.config.bus.interface}, a "
                   f"{self.bus_timing.period_ms:g} ms cycle")
        call_times = getattr(self.bus, "call_times", {})
        figures = [f"{name} {stats['p50_ms']:.2f}/{stats['max_ms']:.2f}"
                   for name, stats in ((n, d.stats()) for n, d in call_times.items() if n != "activate") if stats["n"]]
        return summary + (f" (calls p50/max ms: {', '.join(figures)})" if figures else "")

    def _connect(self, hardware: LinkHardware) -> JointReading:
        """The actuators' first answer, waiting up to ``connect_timeout_s`` for them; the start fails after."""
        deadline = time.monotonic() + self.config.connect_timeout_s
        while True:
            try:
                return hardware.read()
            except HardwareError as exc:
                if time.monotonic() > deadline or self.stop_requested:
                    raise LinkError(str(exc)) from exc
                self.log.warning("waiting for the actuators: %s", exc)
                time.sleep(0.5)

    # ------------------------------------------------------------------ lockstep: the simulator's frames
    def on_sim_clock(self, tick: SimClock) -> None:
        with self._ticks_cond:
            self._ticks[tick.sim_time_ns] = tick.frame_stamp_ns
            self._latest_tick = max(self._latest_tick, tick.sim_time_ns)
            for old in [t for t in self._ticks if t < self._latest_tick - 1_000_000_000]:
                del self._ticks[old]
            self._ticks_cond.notify_all()

    def frame_at_tick(self, tick_ns: int) -> Optional[int]:
        """In lockstep, whether the simulator took a frame at this tick: its clock message says so (it may reach
        us after the bus replies of the same tick, so wait for it)."""
        if not self.lockstep:
            return None
        with self._ticks_cond:
            heard = self._ticks_cond.wait_for(lambda: self._latest_tick >= tick_ns or self.stop_requested,
                                              timeout=self.config.lockstep.cycle_timeout_s)
            if not heard:
                self.counters.inc("lockstep.timeouts.clock")
            return self._ticks.get(tick_ns) or None


def connect_sdk_arm(config: GatewayConfig, sdk: Optional[KinovaSdk] = None,
                    log: Optional[logging.Logger] = None) -> SdkConnection:
    """Kinova's SDK found (unless given) and the arm opened and read once (:class:`ArmStartError` with one line
    otherwise, the API closed again)."""
    sdk = sdk or KinovaSdk.find(config.sdk_library, config.sdk_transport)
    ethernet = config.sdk_ethernet if config.sdk_transport == "ethernet" else None
    description = load_arm(config.arm)
    session = open_arm(sdk, serial=config.sdk_serial, arm_name=description.name, n_joints=description.n_joints,
                       ethernet=ethernet, log=log)
    try:
        arm = SdkArm(sdk, config.dsp, description)
        try:
            reading = arm.read()
        except SdkError as exc:
            raise ArmStartError(f"the arm does not report its state: {exc}") from None
    except BaseException:
        session.close()
        raise
    return SdkConnection(sdk, session, arm, reading)


class SdkGatewayService(RobotNode):
    """The robot node on an arm behind Kinova's SDK (:class:`~services.robot_gateway.sdk_driver.SdkDriver`): every
    DSP cycle (10 ms) it reads the arm, publishes its state and forwards the latest robot command to the arm's own
    DSP. It opens the arm in :meth:`start` before it joins the network, unless it is given one already open
    (``connection``: the process's entry opens it first)."""

    name = "robot_gateway"

    def __init__(self, config: GatewayConfig | None = None, connection: Optional[SdkConnection] = None,
                 **kw) -> None:
        config = config or GatewayConfig(backend="kinova_sdk")
        super().__init__(config, **kw)
        self.config: GatewayConfig = config
        self.connection = connection
        #: the library, found and loaded now so that a missing one fails before anything starts
        self.sdk = connection.sdk if connection else KinovaSdk.find(config.sdk_library, config.sdk_transport)

    def start(self) -> "SdkGatewayService":
        """Open the arm, then start the service (the router comes second: a gateway that cannot reach its arm
        says so, whatever the network)."""
        if self.state != "created":
            return super().start()  # refuses, saying why
        if self.connection is None:
            self.connection = connect_sdk_arm(self.config, self.sdk, self.log)
        try:
            return super().start()
        except BaseException:
            self.connection.close()
            raise

    def open_driver(self) -> SdkDriver:
        return SdkDriver(self.connection, self.loop)

    def arm_summary(self) -> str:
        return f"arm {self.arm.name}: {self.arm.n_joints} joints behind Kinova's SDK"

    def torque_setup_summary(self) -> str:
        return ""  # the arm holds its own: the SDK passes Table 5.1's calls to it and cannot read them back


def open_bus(config: GatewayConfig, counters=None, log: Optional[logging.Logger] = None):
    """The actuators' bus the config names: through Kinova's USB comm layer (``kinova_usb``: a real arm, or
    robot_sim's emulated base), else a python-can interface (the emulation's CAN stand-in)."""
    if config.bus.interface != KINOVA_USB:
        return RS485Bus(config.bus, counters)
    arm = load_arm(config.arm)
    comm_layer = locate_comm_layer(config.sdk_library)
    # lockstep exchanges as fast as the arm answers: only robot_sim's emulated base steps once per exchange
    bus = open_kinova_usb(comm_layer, arm.name, arm.n_joints, counters, log or logging.getLogger("mfvs.robot_gateway"),
                          emulated_only=ClockMode(config.clock) is ClockMode.LOCKSTEP,
                          command_layer=high_level_api(config, comm_layer))
    try:
        check_first_positions(bus, config)
    except BaseException:
        bus.close()
        raise
    return bus


def check_first_positions(bus: KinovaUsbBus, config: GatewayConfig) -> None:
    """The first RS-485 positions (0x01 → 0x02) against the angles Kinova's high-level API read just before
    activation (where it did): beyond ``high_level_check_deg`` on any joint, :class:`ArmStartError` naming them. The
    arm is asked until it answers, for ``connect_timeout_s`` at most."""
    if bus.high_level_deg is None:
        return
    link = ActuatorLink(bus, config.bus_addresses(), config.link_timeout_s, bus.counters)
    deadline = time.monotonic() + config.connect_timeout_s
    while True:
        try:
            measured = link.positions_deg()
            break
        except LinkError as exc:
            if time.monotonic() > deadline:
                raise ArmStartError(f"the actuators do not answer on RS-485: {exc}") from None
            time.sleep(0.1)
    off = high_level_disagreement(measured, bus.high_level_deg, config.high_level_check_deg)
    if off:
        raise ArmStartError(f"the first RS-485 positions disagree with GetAngularPosition read before activation "
                            f"({off}; tolerance {config.high_level_check_deg}°): refusing to drive the arm")


def high_level_api(config: GatewayConfig, comm_layer: Path) -> Optional[Path]:
    """Kinova's command layer beside the comm layer, for the check of the first RS-485 positions (None: the check
    is off); missing while the check is on: :class:`ArmStartError` saying so."""
    if config.high_level_check_deg is None:
        return None
    command_layer = comm_layer.parent / COMMAND_LAYER
    if not command_layer.is_file():
        raise ArmStartError(f"no {command_layer.name} beside {comm_layer}: the first RS-485 positions are checked "
                            "against Kinova's high-level API before the arm is driven (high_level_check_deg: null "
                            "turns the check off, for an emulated arm only)")
    return command_layer


def robot_gateway_service(config: GatewayConfig | None = None, **kw) -> Service:
    """robot_gateway with its configured backend."""
    config = config or GatewayConfig()
    return (SdkGatewayService if config.backend == "kinova_sdk" else RobotGatewayService)(config, **kw)


robot_gateway_service.name = "robot_gateway"
