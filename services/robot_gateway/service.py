"""The robot_gateway service: the robot's zenoh API (state, commands, the Kinova API queryables) backed by an arm
on an RS-485 actuator bus (python-can). It runs the emulated DSP itself at 100 Hz on top of a 500 Hz link to the
actuators, so every other service sees the same robot as with robot_sim.

Backends: ``rs485`` (the actuator bus, any python-can interface); ``kinova_sdk`` drives the arm through Kinova's
USB command layer loaded with ctypes where it is installed (services.robot_gateway.kinova_sdk: the arm's own DSP
interprets the commands; no low-level torque API); without the library it fails with a clear message.

Bus failures (timeouts, NACKs, missing replies, garbled frames) are counted; the arm is held at its last
measured angles, and after ``max_bus_errors`` consecutive failures the gateway reports itself unhealthy and
refuses motion until the bus answers again.
"""
from __future__ import annotations

import threading
import time
from typing import Literal, Optional

import msgspec
import numpy as np

from protocol import kinova
from protocol import rs485 as r
from protocol.conventions import ClockMode
from services.common import frames, jaco2
from services.common.clock import PeriodicSchedule
from services.common.dsp import DSPConfig, KinovaDSP
from services.common.kinematics import ArmKinematics
from services.common.lowlevel import LowLevelConfig
from services.common.metrics import LoopTimer
from services.common.robot_frontend import RobotFrontEnd
from services.common.rs485_bus import BusConfig, RS485Bus
from services.common.service import Service, ServiceConfig
from services.robot_gateway.actuators import LinkActuators
from services.robot_gateway.kinova_sdk import KINOVA_SDK_LIBRARY, KinovaSdk, SdkArm, SdkError
from services.robot_gateway.link import ActuatorLink, LinkError


class GatewayConfig(ServiceConfig):
    backend: Literal["rs485", "kinova_sdk"] = "rs485"
    bus: BusConfig = msgspec.field(default_factory=BusConfig)
    addresses: list[int] = msgspec.field(default_factory=lambda: list(r.ACTUATOR_ADDRESSES))
    link_timeout_s: float = 0.01
    #: at start, keep asking the actuators for their positions this long (an arm, or robot_sim, powering up)
    connect_timeout_s: float = 30.0
    max_bus_errors: int = 5
    dsp: DSPConfig = msgspec.field(default_factory=DSPConfig)
    sdk_library: str = KINOVA_SDK_LIBRARY
    #: the low-level torque API's watchdog and release (services.common.lowlevel)
    lowlevel: LowLevelConfig = msgspec.field(default_factory=LowLevelConfig)


class _NoTorque:
    """The kinova_sdk backend's joints as low-level control sees them: never in torque mode."""

    torque_mode = False

    def enter_torque_mode(self) -> None:
        raise RuntimeError("no low-level torque API through the Kinova SDK")

    def leave_torque_mode(self) -> None:
        pass

    def set_torques(self, torques) -> None:
        pass


class _LinkView:
    """The RobotView of the arm behind the link (for the Kinova API and the state)."""

    def __init__(self, actuators: LinkActuators) -> None:
        self.actuators = actuators
        self.kin = ArmKinematics()

    @property
    def q(self) -> np.ndarray:
        return self.actuators.read().q

    @property
    def dq(self) -> np.ndarray:
        return self.actuators.read().dq

    @property
    def tau(self) -> np.ndarray:
        return self.actuators.read().tau

    @property
    def q_ref(self) -> np.ndarray:
        return self.actuators.q_ref.copy()

    def ee_pose(self) -> np.ndarray:
        return frames.homogeneous(*self.kin.pose(self.q))


class RobotGatewayService(RobotFrontEnd, Service):
    name = "robot_gateway"
    follows_sim_clock = False

    def __init__(self, config: GatewayConfig | None = None, **kw) -> None:
        config = config or GatewayConfig()
        if ClockMode(config.clock) is not ClockMode.REALTIME:
            raise ValueError("robot_gateway runs in realtime only (a real arm has no simulated clock)")
        super().__init__(config, **kw)
        self.config: GatewayConfig = config
        #: the kinova_sdk backend's library, loaded now so that a missing one fails before anything starts
        self.sdk: Optional[KinovaSdk] = KinovaSdk(config.sdk_library) if config.backend == "kinova_sdk" else None
        self.bus: Optional[RS485Bus] = None
        self.loop_timer = LoopTimer(r.CYCLE_S)
        self._thread: Optional[threading.Thread] = None
        self._consecutive_errors = 0

    def on_start(self) -> None:
        if self.sdk is not None:
            self._start_sdk()
            return
        cfg = self.config
        self.bus = RS485Bus(cfg.bus, self.counters)
        link = ActuatorLink(self.bus, cfg.addresses, cfg.link_timeout_s, self.counters)
        try:
            self.actuators = self._connect(link)
        except BaseException:
            self.bus.close()  # a start that fails leaves no socket behind
            self.bus = None
            raise
        view = _LinkView(self.actuators)
        self.init_frontend(view, KinovaDSP(cfg.dsp))
        self.declare_frontend()
        self.declare_lowlevel(self.actuators, cfg.lowlevel, view.kin.gravity)
        self._thread = threading.Thread(target=self._run, name="robot_gateway-loop", daemon=True)
        self._thread.start()

    def _start_sdk(self) -> None:
        cfg = self.config
        code = self.sdk.action("InitAPI")
        if code != kinova.ErrorCode.NO_ERROR_KINOVA:
            raise SdkError("InitAPI", code)
        self.arm = SdkArm(self.sdk, cfg.dsp)
        try:
            self.arm.read()
        except BaseException:
            self.sdk.action("CloseAPI")
            raise
        self.init_frontend(self.arm, self.arm, api=self.sdk)
        self.declare_frontend()
        self.declare_lowlevel(_NoTorque(), cfg.lowlevel, gravity=None,
                              unavailable="the kinova_sdk backend has no low-level torque API (the USB layer "
                                          "offers none); use the rs485 backend")
        self._thread = threading.Thread(target=self._run_sdk, name="robot_gateway-sdk", daemon=True)
        self._thread.start()

    def _run_sdk(self) -> None:
        """The DSP cycle (100 Hz): forward the latest robot command, read the arm, publish its state."""
        schedule = PeriodicSchedule(self.config.dsp.cycle_s)
        self.loop_timer = LoopTimer(self.config.dsp.cycle_s)
        faults: tuple = ()
        while not self.stop_requested:
            if schedule.wait()[1]:
                self.counters.inc("overruns")
            self.loop_timer.tick()
            self.rates.tick("cycle")
            applied = self.apply_command(self.take_command())
            try:
                self.arm.cycle()
                self.arm.read()
                self._consecutive_errors, faults = 0, ()
            except Exception as exc:  # an SDK error code, or values the arm should never report (NaN)
                self._consecutive_errors += 1
                self.counters.inc("sdk.errors")
                self.limited_log.error("sdk", "%s", exc)
                faults = (f"sdk: {exc}",)
            self.publish_state(applied, faults)

    def _connect(self, link: ActuatorLink) -> LinkActuators:
        """The actuators' first answer, waiting up to ``connect_timeout_s`` for them; the start fails after."""
        deadline = time.monotonic() + self.config.connect_timeout_s
        while True:
            try:
                return LinkActuators(link)
            except LinkError as exc:
                if time.monotonic() > deadline or self.stop_requested:
                    raise
                self.log.warning("waiting for the actuators: %s", exc)
                time.sleep(0.5)

    def on_stop(self) -> None:
        if self._thread is not None:
            self._thread.join(timeout=5.0)
        if self.sdk is not None:
            self.sdk.action("CloseAPI")
        if self.bus is not None:
            self.bus.close()

    def check_health(self) -> tuple[bool, str]:
        alive = self._thread is not None and self._thread.is_alive()
        if not alive:
            return False, "gateway loop stopped"
        if self._consecutive_errors >= self.config.max_bus_errors:
            return False, "SDK calls failing" if self.sdk is not None else f"bus failing: {self.actuators.faults[:1]}"
        stats = self.loop_timer.stats()
        return True, f"bus_rate_hz={stats['rate_hz']:.1f} jitter_ms_p99={stats['jitter_ms_p99']:.2f}"

    def _publish_lowlevel(self) -> None:
        reading = self.actuators.reading
        if reading is None:
            return
        state = self.actuators.read()
        self.publish_lowlevel(state.q, state.dq, state.tau, jaco2.SIGN * reading.current_a, reading.temperature_c,
                              self.actuators.faults)

    def _run(self) -> None:
        schedule = PeriodicSchedule(r.CYCLE_S)
        cycles_per_dsp = max(1, round(self.dsp.config.cycle_s / r.CYCLE_S))
        while not self.stop_requested:
            k, skipped = schedule.wait()
            if skipped:
                self.counters.inc("overruns")
            self.loop_timer.tick()
            self.lowlevel_cycle(self.actuators.read().q)
            ok = self.actuators.cycle(self.clock.now_ns())
            self._consecutive_errors = 0 if ok else self._consecutive_errors + 1
            self._publish_lowlevel()
            if k % cycles_per_dsp == 0:
                self.rates.tick("cycle")
                taken = self.take_command()
                if self._consecutive_errors >= self.config.max_bus_errors:
                    taken = None  # no motion on a failing bus
                    self.dsp.erase_all_trajectories()
                applied = self.apply_command(taken)
                dq_ref = self.dsp.cycle(self.actuators.read())
                if not self.actuators.torque_mode:
                    self.actuators.write(dq_ref)
                self.publish_state(applied, tuple(self.actuators.faults))
