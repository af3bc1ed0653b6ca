"""Start a whole mfvs stack: a zenoh router on a free loopback port and the services, each a separate zenoh
client of the router (they talk only over zenoh, exactly as when deployed as processes).

With the ``sim`` profile every service runs in this process. With ``gateway`` the robot's side runs as its own
processes, as deployed: the CAN hub, robot_sim's actuators and robot_gateway, each with two 500 Hz loops that
would otherwise compete with vision and rendering for one interpreter.
"""
from __future__ import annotations

import contextlib
import itertools
import json
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional

import msgspec
import yaml

from protocol.conventions import ClockMode
from protocol.keys import Keys
from services.robot.rs485_bus import BusConfig, RS485Bus
from services.runtime.transport import Router, ZenohConfig, open_session
from services.controller.service import ControllerConfig, ControllerService
from services.robot.pacing import SWITCH_INTERVAL_S
from services.robot_gateway.link import ActuatorLink
from services.robot_gateway.service import GatewayConfig
from services.robot_sim.arm_on_bus import ArmOnBus, ArmOnBusConfig
from services.robot_sim.service import RobotSimConfig, robot_sim_service
from services.launcher import gateway_robot_services, service_command, spawn
from services.robot_sim.sim import Simulation
from services.safety.service import SafetyConfig, SafetyService
from services.vision.service import VisionConfig, VisionService

REPO = Path(__file__).resolve().parents[1]
_rig_channels = itertools.count()


@contextlib.contextmanager
def simulated_link(bus: BusConfig | None = None, timeout_s: float = 0.05, settle_s: float = 0.05,
                   lockstep: bool = False):
    """A simulated arm's actuators answering on a bus (robot_sim's ArmOnBus, in a thread) and the host's link to
    them, as ``(arm, link)``: the gateway's view of the arm without zenoh, for tests and benchmarks. By default the
    bus is a fresh in-process channel (``mfvs_local``). ``lockstep``: the arm runs one cycle per command batch
    from the host, so that what the host does is exactly repeatable (two realtime loops in one interpreter share
    its lock, which no deployment does: realtime behaviour is measured with the arm in its own process)."""
    bus = bus or BusConfig(interface="mfvs_local", channel=f"simulated-link-{os.getpid()}-{next(_rig_channels)}")
    # the arm's loop and the host's in one process: the GIL must change hands well within a bus cycle
    sys.setswitchinterval(min(sys.getswitchinterval(), SWITCH_INTERVAL_S))
    runner = ArmOnBus(Simulation(render=False), RS485Bus(bus), ArmOnBusConfig(lockstep=lockstep)).start()
    try:
        host = RS485Bus(bus)
        try:
            time.sleep(settle_s)
            yield runner, ActuatorLink(host, timeout_s=timeout_s)
        finally:
            host.close()
    finally:
        runner.stop()


class RouterProcess:
    """A zenoh router as its own process (``mfvs router --port 0``), as deployed (at realtime priority where the OS
    grants it): a context manager with the endpoint and ``client_config()`` of :class:`Router`."""

    def __init__(self, realtime_priority: int = 30) -> None:
        self.realtime_priority = realtime_priority
        self.process: Optional[subprocess.Popen] = None
        self.endpoint = ""

    def __enter__(self) -> "RouterProcess":
        self.process = subprocess.Popen(
            [sys.executable, "-m", "services.cli", "router", "--port", "0", "--realtime-priority",
             str(self.realtime_priority)], cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
        line = self.process.stdout.readline()
        try:
            self.endpoint = json.loads(line)["router"]
        except (ValueError, KeyError):
            self.__exit__(None, None, None)
            raise RuntimeError(f"the router did not start (it said {line!r})") from None
        return self

    def client_config(self, **overrides) -> ZenohConfig:
        return ZenohConfig(mode="client", connect=[self.endpoint], **overrides)

    def __exit__(self, *exc) -> None:
        if self.process is not None:
            self.process.terminate()
            try:
                self.process.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
            self.process.stdout.close()
            self.process = None


class RobotProcesses:
    """The robot's side of the gateway profile as processes, as deployed: the CAN hub, robot_sim's emulated arm
    (``mode: actuator_bus``) and robot_gateway in front of it, clients of the router at ``zenoh``. A context
    manager; the start fails (keeping the logs, whose directory it names) if the gateway does not come up."""

    def __init__(self, zenoh: ZenohConfig, robot: RobotSimConfig | None = None,
                 gateway: GatewayConfig | None = None, clock: ClockMode = ClockMode.REALTIME,
                 timeout_s: float = 60.0) -> None:
        robot = robot or RobotSimConfig()
        self.zenoh, self.clock, self.timeout_s = zenoh, ClockMode(clock), timeout_s
        self.robot = msgspec.structs.replace(robot, zenoh=zenoh, clock=self.clock)
        self.gateway = msgspec.structs.replace(
            gateway or GatewayConfig(robot_id=robot.robot_id, dsp=robot.dsp, lockstep=robot.lockstep,
                                     log_level=robot.log_level), zenoh=zenoh, clock=self.clock)
        self.processes: list[subprocess.Popen] = []
        self._files = tempfile.TemporaryDirectory(prefix="mfvs-robot-")
        self.logs = Path(self._files.name)
        self._keep_files = False

    def __enter__(self) -> "RobotProcesses":
        try:
            # the profile's robot side as `mfvs up --profile gateway` runs it, with these configs
            services = gateway_robot_services(self._start_hub(), self._write("robot_sim", self.robot),
                                              self._write("robot_gateway", self.gateway))
            for service in services:
                self.processes.append(spawn(service_command(service), self.logs / f"{service.name}.log"))
            self._wait_for_gateway()
        except BaseException:
            self.__exit__(None, None, None)
            raise
        return self

    def _wait_for_gateway(self) -> None:
        keys = Keys(self.robot.robot_id)
        session = open_session(self.zenoh)
        try:
            deadline = time.monotonic() + self.timeout_s
            while not list(session.liveliness().get(keys.liveliness("robot_gateway"), timeout=1.0)):
                dead = [p.args for p in self.processes if p.poll() is not None]
                if dead or time.monotonic() > deadline:
                    self._keep_files = True
                    raise RuntimeError(f"the gateway profile's robot did not come up (exited: {dead}; logs in "
                                       f"{self.logs})")
                time.sleep(0.2)
        finally:
            session.close()

    def _start_hub(self) -> str:
        """The CAN hub on a port it picks itself (no window for another program to take it); its channel."""
        hub = subprocess.Popen([sys.executable, "-m", "services.cli", "bus-hub", "--port", "0"], cwd=REPO,
                               stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
        self.processes.append(hub)
        line = hub.stdout.readline()  # the hub's first line says where it listens (EOF if it failed)
        try:
            return json.loads(line)["bus_hub"]
        except (ValueError, KeyError):
            raise RuntimeError(f"the CAN hub did not start (it said {line!r})") from None

    def _write(self, name: str, config) -> str:
        path = self.logs / f"{name}.yaml"
        path.write_text(yaml.safe_dump(msgspec.to_builtins(config), sort_keys=False))
        return str(path)

    def alive(self) -> bool:
        return all(p.poll() is None for p in self.processes)

    def __exit__(self, *exc) -> None:
        for process in reversed(self.processes):  # the gateway, then the actuators, then the hub
            process.terminate()
            try:
                process.wait(timeout=20)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()
            if process.stdout is not None:
                process.stdout.close()
        self.processes.clear()
        if not self._keep_files:
            self._files.cleanup()


@dataclass
class StackConfig:
    clock: ClockMode = ClockMode.LOCKSTEP
    #: sim: robot_sim with its robot node in this process; gateway: robot_sim's actuators on an RS-485 bus (the CAN
    #: hub) driven by robot_gateway, as processes
    profile: str = "sim"
    robot: RobotSimConfig = field(default_factory=RobotSimConfig)
    vision: VisionConfig = field(default_factory=VisionConfig)
    controller: ControllerConfig = field(default_factory=ControllerConfig)
    safety: SafetyConfig = field(default_factory=SafetyConfig)


class LocalStack:
    """Router + safety + vision + controller + robot_sim (+ robot_gateway with the gateway profile). Use as a
    context manager."""

    def __init__(self, config: StackConfig, before_robot: Optional[Callable[["LocalStack"], None]] = None) -> None:
        """``before_robot(stack)`` runs once the router and the pipeline are up and before the robot starts (an
        observer that subscribes there misses none of the robot's messages)."""
        self.config = config
        self._before_robot = before_robot
        self.router = Router(port=0)
        self.services: list = []
        self.robot_processes: Optional[RobotProcesses] = None

    def __enter__(self) -> "LocalStack":
        self.router.start()
        client = self.router.client_config()
        cfg = self.config
        if cfg.profile not in ("sim", "gateway"):
            raise ValueError(f"unknown profile {cfg.profile!r}: sim or gateway")
        gateway = cfg.profile == "gateway"
        for service_cfg in (cfg.safety, cfg.vision, cfg.controller, cfg.robot):
            service_cfg.zenoh = client
            service_cfg.clock = cfg.clock
        try:
            # the pipeline first, so that it is listening when the robot publishes its first frame
            self.safety = SafetyService(cfg.safety).start()
            self.services.append(self.safety)
            self.vision = VisionService(cfg.vision).start()
            self.services.append(self.vision)
            self.controller = ControllerService(cfg.controller).start()
            self.services.append(self.controller)
            if self._before_robot is not None:
                self._before_robot(self)
            time.sleep(0.3)  # let the declarations reach the router before the robot starts the clock
            if gateway:
                self._start_robot_processes()
            else:
                self.robot = robot_sim_service(cfg.robot).start()
                self.services.append(self.robot)
        except BaseException:
            self.__exit__(None, None, None)
            raise
        return self

    def _start_robot_processes(self) -> None:
        cfg = self.config
        self.robot_processes = RobotProcesses(cfg.robot.zenoh, cfg.robot, clock=cfg.clock).__enter__()

    def robot_alive(self) -> bool:
        """The robot still runs (in this process: its loop; with the gateway profile: its processes)."""
        if self.robot_processes is not None:
            return self.robot_processes.alive()
        return not self.robot.finished.is_set() and self.robot.state == "running"

    @property
    def endpoint(self) -> str:
        return self.router.endpoint

    def __exit__(self, *exc) -> None:
        if self.robot_processes is not None:
            self.robot_processes.__exit__(None, None, None)
            self.robot_processes = None
        for service in reversed(self.services):
            try:
                service.stop()
            except Exception:
                pass
        self.services.clear()
        self.router.close()
