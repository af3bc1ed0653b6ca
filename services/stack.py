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

import msgspec
import yaml

from protocol.conventions import ClockMode
from protocol.keys import Keys
from services.common.rs485_bus import BusConfig, RS485Bus
from services.common.transport import Router, open_session
from services.controller.service import ControllerConfig, ControllerService
from services.robot_gateway.link import ActuatorLink
from services.robot_gateway.service import GatewayConfig
from services.robot_sim.bus_runner import BusRunner
from services.robot_sim.service import RobotSimConfig, RobotSimService
from services.robot_sim.sim import Simulation
from services.safety.service import SafetyConfig, SafetyService
from services.vision.service import VisionConfig, VisionService

REPO = Path(__file__).resolve().parents[1]
_rig_channels = itertools.count()


@contextlib.contextmanager
def simulated_link(bus: BusConfig | None = None, timeout_s: float = 0.05, settle_s: float = 0.05):
    """A simulated arm's actuators answering on a bus (robot_sim's BusRunner, in a thread) and the host's link to
    them, as ``(runner, link)``: the gateway's view of the arm without zenoh, for tests and benchmarks. By
    default the bus is a fresh python-can virtual channel of this process."""
    bus = bus or BusConfig(channel=f"simulated-link-{os.getpid()}-{next(_rig_channels)}")
    runner = BusRunner(Simulation(render=False), bus).start()
    try:
        host = RS485Bus(bus)
        try:
            time.sleep(settle_s)
            yield runner, ActuatorLink(host, timeout_s=timeout_s)
        finally:
            host.close()
    finally:
        runner.stop()


@dataclass
class StackConfig:
    clock: ClockMode = ClockMode.LOCKSTEP
    #: sim: robot_sim with its emulated DSP; gateway: robot_sim's actuators on an RS-485 bus (the CAN hub) driven
    #: by robot_gateway, as processes — realtime only
    profile: str = "sim"
    robot: RobotSimConfig = field(default_factory=RobotSimConfig)
    vision: VisionConfig = field(default_factory=VisionConfig)
    controller: ControllerConfig = field(default_factory=ControllerConfig)
    safety: SafetyConfig = field(default_factory=SafetyConfig)


class LocalStack:
    """Router + safety + vision + controller + robot_sim (+ robot_gateway with the gateway profile). Use as a
    context manager."""

    def __init__(self, config: StackConfig) -> None:
        self.config = config
        self.router = Router(port=0)
        self.services: list = []
        self.processes: list[subprocess.Popen] = []
        self._files = tempfile.TemporaryDirectory(prefix="mfvs-stack-")
        self._keep_files = False  # kept when the robot processes failed to start: their logs say why

    def __enter__(self) -> "LocalStack":
        self.router.start()
        client = self.router.client_config()
        cfg = self.config
        if cfg.profile not in ("sim", "gateway"):
            raise ValueError(f"unknown profile {cfg.profile!r}: sim or gateway")
        gateway = cfg.profile == "gateway"
        if gateway:
            cfg.clock = ClockMode.REALTIME
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
            time.sleep(0.3)  # let the declarations reach the router before the robot starts the clock
            if gateway:
                self._start_robot_processes()
            else:
                self.robot = RobotSimService(cfg.robot).start()
                self.services.append(self.robot)
        except BaseException:
            self.__exit__(None, None, None)
            raise
        return self

    def _start_robot_processes(self) -> None:
        cfg = self.config
        bus = BusConfig(interface="mfvs_hub", channel=self._start_hub())
        robot = msgspec.structs.replace(cfg.robot, mode="actuator_bus", bus=bus)
        gateway = GatewayConfig(zenoh=cfg.robot.zenoh, robot_id=cfg.robot.robot_id, bus=bus, dsp=cfg.robot.dsp,
                                log_level=cfg.robot.log_level)
        self._spawn(["-m", "services.robot_sim", "--config", self._write("robot_sim", robot)], "robot_sim")
        self._spawn(["-m", "services.robot_gateway", "--config", self._write("robot_gateway", gateway)],
                    "robot_gateway")
        keys = Keys(cfg.robot.robot_id)
        session = open_session(self.router.client_config())
        try:
            deadline = time.monotonic() + 60.0
            while not list(session.liveliness().get(keys.liveliness("robot_gateway"), timeout=1.0)):
                dead = [p.args for p in self.processes if p.poll() is not None]
                if dead or time.monotonic() > deadline:
                    self._keep_files = True
                    raise RuntimeError(f"the gateway profile's robot did not come up (exited: {dead}; logs in "
                                       f"{self._files.name})")
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
        path = Path(self._files.name) / f"{name}.yaml"
        path.write_text(yaml.safe_dump(msgspec.to_builtins(config), sort_keys=False))
        return str(path)

    def _spawn(self, args: list[str], name: str) -> None:
        log = open(Path(self._files.name) / f"{name}.log", "ab")
        self.processes.append(subprocess.Popen([sys.executable, *args], cwd=REPO, stdout=log,
                                               stderr=subprocess.STDOUT))
        log.close()

    def robot_alive(self) -> bool:
        """The robot still runs (in this process: its loop; with the gateway profile: its processes)."""
        if self.processes:
            return all(p.poll() is None for p in self.processes)
        return not self.robot.finished.is_set() and self.robot.state == "running"

    @property
    def endpoint(self) -> str:
        return self.router.endpoint

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
        for service in reversed(self.services):
            try:
                service.stop()
            except Exception:
                pass
        self.services.clear()
        self.router.close()
        if not self._keep_files:
            self._files.cleanup()
