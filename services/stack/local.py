"""Start a whole mfvs stack on this host, as deployed: a zenoh router on a free loopback port and every service a
process of its own, a client of the router (:class:`LocalStack`, which ``mfvs servo``, the benchmarks and the
tests use; ``mfvs up`` starts the same commands from a profile). Also the rigs of the robot's side alone:
:class:`RobotProcesses` (the gateway profile's hub, emulated actuators and gateway) and :func:`simulated_link`.
"""
from __future__ import annotations

import contextlib
import itertools
import json
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
import weakref
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional

import msgspec
import yaml
from zenoh import SampleKind, Session

from protocol.conventions import ClockMode
from protocol.keys import PIPELINE_START_ORDER, Keys, last_chunk
from services.model.arm import ArmDescription, load_arm
from services.paths import REPO
from services.robot.rs485_bus import BusConfig, RS485Bus
from services.runtime.transport import ZenohConfig, open_session
from services.controller.service import ControllerConfig
from services.runtime.pacing import SWITCH_INTERVAL_S
from services.robot_gateway.link import ActuatorLink
from services.robot_gateway.kinova_usb import has_command_layer
from services.robot_gateway.service import GatewayConfig
from services.robot_sim.arm_on_bus import ArmOnBus, ArmOnBusConfig
from services.robot_sim.service import RobotSimConfig
from services.robot_sim.usb_base import stand_in_libusb
from services.stack.launcher import ProfileService, gateway_robot_services, service_command, spawn, usb_robot_services
from services.robot_sim.sim import Simulation
from services.safety.service import SafetyConfig
from services.stack.warm_start import spawn_warm
from services.vision.service import VisionConfig

_rig_channels = itertools.count()


class StackLogs:
    """The directory of a stack's logs and configs: removed when the stack stops (or, never started, when it is
    collected), kept once :meth:`keep` was called (a start that failed names it in its error). Not
    :class:`tempfile.TemporaryDirectory`, which removes its directory when the object is collected, whatever its
    owner meant: the logs a failed start named were gone by the time anyone looked."""

    def __init__(self, prefix: str) -> None:
        self.path = Path(tempfile.mkdtemp(prefix=prefix))
        self._removal = weakref.finalize(self, shutil.rmtree, self.path, ignore_errors=True)

    def keep(self) -> None:
        self._removal.detach()

    def close(self) -> None:
        """Remove the directory, unless it is kept."""
        self._removal()


#: s: how long the host's link waits for the arm's replies in lockstep, where the arm's cycle comes when its thread
#: is next scheduled and a late reply changes nothing (a starved host's pause, not the bus's 50 ms)
LOCKSTEP_LINK_TIMEOUT_S = 2.0


@contextlib.contextmanager
def simulated_link(bus: BusConfig | None = None, timeout_s: float | None = None, settle_s: float = 0.05,
                   lockstep: bool = False, arm: ArmDescription | None = None):
    """A simulated arm's actuators answering on a bus (robot_sim's ArmOnBus, in a thread) and the host's link to
    them, as ``(arm, link)``: the gateway's view of the arm without zenoh, for tests and benchmarks. By default the
    bus is a fresh in-process channel (``mfvs_local``). ``lockstep``: the arm runs one cycle per command batch
    from the host, so that what the host does is exactly repeatable (two realtime loops in one interpreter share
    its lock, which no deployment does: realtime behaviour is measured with the arm in its own process). ``arm``: the
    arm simulated (default: the default arm). ``timeout_s``: the link's wait for replies (default: the bus's 50 ms
    in realtime, :data:`LOCKSTEP_LINK_TIMEOUT_S` in lockstep)."""
    if timeout_s is None:
        timeout_s = LOCKSTEP_LINK_TIMEOUT_S if lockstep else 0.05
    arm = arm or load_arm()
    bus = bus or BusConfig(interface="mfvs_local", channel=f"simulated-link-{os.getpid()}-{next(_rig_channels)}")
    # the arm's loop and the host's in one process: the GIL must change hands well within a bus cycle
    sys.setswitchinterval(min(sys.getswitchinterval(), SWITCH_INTERVAL_S))
    runner = ArmOnBus(Simulation(render=False, arm=arm), RS485Bus(bus), ArmOnBusConfig(lockstep=lockstep)).start()
    try:
        host = RS485Bus(bus)
        try:
            time.sleep(settle_s)
            yield runner, ActuatorLink(host, arm.bus_addresses, timeout_s=timeout_s)
        finally:
            host.close()
    finally:
        runner.stop()


class RouterProcess:
    """A zenoh router as its own process (``mfvs router --port 0``), as deployed (at realtime priority where the OS
    grants it): a context manager with the endpoint and ``client_config()`` of
    :class:`services.runtime.transport.Router`.

    ``warm_log``: forked from the warm server (:mod:`services.stack.warm_start`, a lockstep stack's), its output in that
    file, where the endpoint it prints is read: an interpreter less to start for every run (~0.07 s of CPU)."""

    def __init__(self, realtime_priority: int = 30, warm_log: Optional[Path] = None, timeout_s: float = 30.0) -> None:
        self.realtime_priority = realtime_priority
        self.warm_log = warm_log
        self.timeout_s = timeout_s
        self.process = None
        self.endpoint = ""

    def __enter__(self) -> "RouterProcess":
        command = [sys.executable, "-m", "services.cli", "router", "--port", "0", "--realtime-priority",
                   str(self.realtime_priority)]
        if self.warm_log is not None:
            self.process = spawn_warm(command, self.warm_log, REPO)
            line = _endpoint_line(self.warm_log, self.process, self.timeout_s)
        else:
            self.process = subprocess.Popen(command, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                                            text=True)
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
            process, self.process = self.process, None
            stop_processes([process], timeout_s=ROUTER_STOP_TIMEOUT_S)


#: how often a warm router's log is read for its endpoint
ENDPOINT_POLL_S = 0.002


def _endpoint_line(log: Path, process, timeout_s: float) -> str:
    """The line in which the router ``process`` prints its endpoint (JSON) to ``log``, whatever it logs before it;
    what the log holds when it exits first or ``timeout_s`` passes."""
    deadline = time.monotonic() + timeout_s
    text = ""
    while time.monotonic() < deadline:
        exited = process.poll() is not None
        text = log.read_text() if log.exists() else ""
        for line in text.splitlines(keepends=True):
            if line.startswith('{"router"') and line.endswith("\n"):
                return line
        if exited:
            break
        time.sleep(ENDPOINT_POLL_S)
    return text


class ConsoleProcess:
    """``mfvs console`` as its own process, as deployed, on a free port of the loopback (``--port 0``) for the robot
    of the router at ``endpoint``, with extra command-line options: a context manager with its :attr:`url` (what it
    printed once it listened). It reads no run directory (its own, empty, stands in for the user's)."""

    def __init__(self, endpoint: str, *options: str, robot_id: str = "jaco") -> None:
        self.args = [sys.executable, "-m", "services.cli", "console", "--port", "0", "--connect", endpoint,
                     "--robot-id", robot_id, *options]
        self.process: Optional[subprocess.Popen] = None
        self.url = ""
        self.ready: dict = {}
        self._files = tempfile.TemporaryDirectory(prefix="mfvs-console-")
        self.log = Path(self._files.name) / "console.log"

    def __enter__(self) -> "ConsoleProcess":
        env = dict(os.environ, MFVS_RUN_DIR=self._files.name)
        with self.log.open("ab") as log:
            self.process = subprocess.Popen(self.args, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=log,
                                            text=True)
        line = self.process.stdout.readline()
        try:
            self.ready = json.loads(line)
            self.url = self.ready["console"]
        except (ValueError, KeyError):
            said = self.log.read_text()
            self.__exit__(None, None, None)
            raise RuntimeError(f"the console did not start (it said {line!r}; its log: {said[-2000:]})") from None
        return self

    def __exit__(self, *exc) -> None:
        if self.process is not None:
            stop_processes([self.process])
            self.process = None
        self._files.cleanup()


def write_config(directory: Path, name: str, config) -> str:
    """``config`` as ``directory/name.yaml`` (what a service's ``--config`` reads); its path."""
    path = directory / f"{name}.yaml"
    path.write_text(yaml.safe_dump(msgspec.to_builtins(config), sort_keys=False))
    return str(path)


#: lockstep: how long the robot waits, before its first cycle, to see the safety the stack started before it (it
#: is alive: this is the time its liveliness takes to reach the robot's new session; seconds only on a stalled host)
ANSWERERS_SEEN_TIMEOUT_S = 10.0
#: how often a stack coming up looks whether one of its processes exited (which declares no liveliness to wait for)
PROCESS_EXIT_POLL_S = 0.05


def wait_alive(zenoh: ZenohConfig, robot_id: str, names, processes, timeout_s: float, logs: Path) -> None:
    """Until every one of ``names`` has declared its liveliness (services declare it after their subscriptions);
    raises if one of ``processes`` exits first or ``timeout_s`` passes. Told by a liveliness subscriber (the tokens
    already declared, then each new one) rather than by asking the router every 0.1 s: a stack is up when its last
    service is (asked, each start of a stack waited ~0.1 s twice for nothing)."""
    keys = Keys(robot_id)
    wanted = set(names)
    alive: set[str] = set()
    changed = threading.Condition()

    def on_token(sample) -> None:
        name = last_chunk(sample.key_expr)
        with changed:
            if sample.kind == SampleKind.PUT:
                alive.add(name)
            else:
                alive.discard(name)
            changed.notify_all()

    session = open_session(zenoh)
    try:
        tokens = session.liveliness().declare_subscriber(keys.liveliness_all, on_token, history=True)
        try:
            deadline = time.monotonic() + timeout_s
            with changed:
                while not wanted <= alive:
                    dead = [p.args for p in processes if p.poll() is not None]
                    if dead or time.monotonic() > deadline:
                        raise RuntimeError(f"the stack did not come up: {', '.join(sorted(wanted - alive))} not "
                                           f"alive (exited: {dead}; logs in {logs})")
                    changed.wait(PROCESS_EXIT_POLL_S)  # a process that exits declares nothing: polled
        finally:
            tokens.undeclare()
    finally:
        session.close()


#: how long a stack's process has to stop once told (SIGTERM) before it is killed; a router, which stops a session
#: and nothing else, less
STOP_TIMEOUT_S = 20.0
ROUTER_STOP_TIMEOUT_S = 10.0


def stop_processes(processes, together: bool = False, timeout_s: float = STOP_TIMEOUT_S) -> None:
    """Terminate each of ``processes`` in order, waiting for it (killed after ``timeout_s``); ``together``: terminate
    them all first, then wait for each (they stop side by side)."""
    processes = list(processes)
    if together:
        for process in processes:
            process.terminate()
    for process in processes:
        if not together:
            process.terminate()
        try:
            process.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
        if process.stdout is not None:
            process.stdout.close()


class RobotProcesses:
    """The robot's side of a profile as processes, as deployed, clients of the router at ``zenoh``: for the
    gateway profile the CAN hub, robot_sim's emulated arm (``mode: actuator_bus``) and robot_gateway in front of
    it; for the sim profile robot_sim alone. A context manager; the start fails (keeping the logs, whose directory
    it names) if the robot does not come up. The gateway runs the robot's arm (``robot.arm``) unless ``gateway``
    is given, which must then name the same arm (a ValueError otherwise, as for a profile that mixes arms)."""

    def __init__(self, zenoh: ZenohConfig, robot: RobotSimConfig | None = None,
                 gateway: GatewayConfig | None = None, clock: ClockMode = ClockMode.REALTIME,
                 timeout_s: float = 60.0, profile: str = "gateway", bus: str = "hub") -> None:
        """``bus`` (gateway profile): ``hub``, the emulation's CAN hub; ``kinova_usb``, robot_sim's emulated base
        reached through Kinova's own USB comm layer (Kinova's SDK from ``$MFVS_KINOVA_SDK`` unless the gateway's
        config names it), as a real arm's bus is."""
        if profile not in ("gateway", "sim"):
            raise ValueError(f"unknown robot profile {profile!r} (gateway or sim)")
        if bus not in ROBOT_BUSES:
            raise ValueError(f"unknown robot bus {bus!r} ({' or '.join(ROBOT_BUSES)})")
        self.bus = bus
        robot = robot or RobotSimConfig()
        self.profile = profile
        self.zenoh, self.clock, self.timeout_s = zenoh, ClockMode(clock), timeout_s
        self.robot = msgspec.structs.replace(robot, zenoh=zenoh, clock=self.clock)
        self.gateway = msgspec.structs.replace(
            gateway or GatewayConfig(arm=robot.arm, robot_id=robot.robot_id, dsp=robot.dsp, lockstep=robot.lockstep,
                                     log_level=robot.log_level), zenoh=zenoh, clock=self.clock)
        if profile == "gateway" and self.gateway.arm != self.robot.arm:
            raise ValueError(f"the robot's side mixes arms (robot_sim {self.robot.arm}, robot_gateway "
                             f"{self.gateway.arm}): one arm for the whole stack")
        self.processes: list[subprocess.Popen] = []
        self._logs = StackLogs("mfvs-robot-")
        self.logs = self._logs.path

    def __enter__(self) -> "RobotProcesses":
        try:
            # the profile's robot side as `mfvs up --profile gateway` (or sim) runs it, with these configs
            robot_sim_config = write_config(self.logs, "robot_sim", self.robot)
            gateway_config = write_config(self.logs, "robot_gateway", self.gateway)
            if self.profile == "sim":
                services = [ProfileService(name="robot_sim", config=robot_sim_config)]
            elif self.bus == "kinova_usb":
                socket_path = str(self.logs / "usb.sock")
                services = usb_robot_services(socket_path, stand_in_libusb(), robot_sim_config, gateway_config,
                                              high_level_check=has_command_layer(self.gateway.sdk_library))
            else:
                services = gateway_robot_services(self._start_hub(), robot_sim_config, gateway_config)
            for service in services:
                if service.name == "robot_gateway" and self.bus == "kinova_usb":
                    self._wait_for_base(Path(socket_path))
                self.processes.append(spawn(service_command(service), self.logs / f"{service.name}.log",
                                            extra_env=service.env))
            wait_alive(self.zenoh, self.robot.robot_id, (services[-1].name,), self.processes, self.timeout_s,
                       self.logs)
        except BaseException:
            self._logs.keep()
            self.__exit__(None, None, None)
            raise
        return self

    def _wait_for_base(self, socket_path: Path) -> None:
        """robot_sim's emulated base listening (its socket made), or the start fails naming robot_sim's log."""
        deadline = time.monotonic() + self.timeout_s
        while not socket_path.exists():
            if time.monotonic() > deadline or not self.alive():
                raise RuntimeError(f"robot_sim's emulated base did not come up (log {self.logs / 'robot_sim.log'})")
            time.sleep(0.05)

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

    def alive(self) -> bool:
        return all(p.poll() is None for p in self.processes)

    def __exit__(self, *exc) -> None:
        stop_processes(reversed(self.processes))  # the gateway, then the actuators, then the hub
        self.processes.clear()
        self._logs.close()


@dataclass
class StackConfig:
    clock: ClockMode = ClockMode.LOCKSTEP
    #: sim: robot_sim drives its simulated arm itself; gateway: robot_sim's actuators on an RS-485 bus (the CAN
    #: hub) driven by robot_gateway
    profile: str = "sim"
    #: gateway profile: how robot_gateway reaches the actuators (ROBOT_BUSES: the CAN hub, or Kinova's USB comm layer)
    robot_bus: str = "hub"
    robot: RobotSimConfig = field(default_factory=RobotSimConfig)
    vision: VisionConfig = field(default_factory=VisionConfig)
    controller: ControllerConfig = field(default_factory=ControllerConfig)
    safety: SafetyConfig = field(default_factory=SafetyConfig)

    def services(self) -> dict:
        """Each service's config, by the service's name."""
        return {"safety": self.safety, "vision": self.vision, "controller": self.controller, "robot_sim": self.robot}


#: how the gateway profile's robot side reaches the emulated arm's actuators (RobotProcesses)
ROBOT_BUSES = ("hub", "kinova_usb")

#: the pipeline's services, started (and alive) before the robot, so that they hear its first frame
PIPELINE = PIPELINE_START_ORDER


def lockstep_robot(robot: RobotSimConfig) -> None:
    """The robot of a local lockstep stack: safety is up before the robot starts, so its first tick waits for it."""
    robot.lockstep = msgspec.structs.replace(robot.lockstep, await_answerers_s=ANSWERERS_SEEN_TIMEOUT_S)


class LocalStack:
    """The whole stack on this host as ``mfvs up`` runs it: a router, then safety, vision and the controller, then
    the robot (robot_sim; with the gateway profile the CAN hub, robot_sim's emulated actuators and robot_gateway),
    every one a process of its own with this config. Use as a context manager; the logs are kept (and named) when
    the start fails.

    Processes, not threads: in one interpreter the services shared one interpreter lock, and in realtime the
    robot's 500 Hz loop, the detector and the law took turns on it (table2.yaml, which converges in 129 iterations
    in lockstep, took 237 and 451 in realtime, the arm standing still for seconds under a saturated command)."""

    def __init__(self, config: StackConfig, before_robot: Optional[Callable[["LocalStack"], None]] = None,
                 timeout_s: float = 60.0) -> None:
        """``before_robot(stack)`` runs once the router and the pipeline are up and before the robot starts (an
        observer that subscribes there misses none of the robot's messages)."""
        self.config = config
        self._before_robot = before_robot
        self.timeout_s = timeout_s
        self.processes: dict[str, subprocess.Popen] = {}
        self.robot_processes: Optional[RobotProcesses] = None
        self._logs = StackLogs("mfvs-stack-")
        self.logs = self._logs.path
        # lockstep: at normal priority (as its services, see services.runtime.service.service_main), and warm
        lockstep = config.clock is ClockMode.LOCKSTEP
        self.router = RouterProcess(realtime_priority=0 if lockstep else 30,
                                    warm_log=self.logs / "router.log" if lockstep else None)

    def __enter__(self) -> "LocalStack":
        cfg = self.config
        if cfg.profile not in ("sim", "gateway"):
            raise ValueError(f"unknown profile {cfg.profile!r}: sim or gateway")
        self.router.__enter__()
        try:
            client = self.router.client_config()
            for service_cfg in cfg.services().values():
                service_cfg.zenoh = client
                service_cfg.clock = cfg.clock
            if cfg.clock is ClockMode.LOCKSTEP:
                lockstep_robot(cfg.robot)
            for name in PIPELINE:
                self._spawn(name, cfg.services()[name])
            self._wait_alive(PIPELINE)
            if self._before_robot is not None:
                self._before_robot(self)
            if cfg.profile == "gateway":
                self.robot_processes = RobotProcesses(client, cfg.robot, clock=cfg.clock, timeout_s=self.timeout_s,
                                                      bus=cfg.robot_bus).__enter__()
            else:
                self._spawn("robot_sim", cfg.robot)
                self._wait_alive(("robot_sim",))
        except BaseException:
            self._logs.keep()
            self.__exit__(None, None, None)
            raise
        return self

    def _spawn(self, name: str, config) -> None:
        command = service_command(ProfileService(name=name, config=write_config(self.logs, name, config)))
        if self.config.clock is ClockMode.LOCKSTEP:  # imports shared (services.stack.warm_start): nothing it computes
            self.processes[name] = spawn_warm(command, self.logs / f"{name}.log", REPO)
        else:
            self.processes[name] = spawn(command, self.logs / f"{name}.log")

    def _wait_alive(self, names) -> None:
        wait_alive(self.router.client_config(), self.config.robot.robot_id, names, self.processes.values(),
                   self.timeout_s, self.logs)

    def robot_alive(self) -> bool:
        """The robot's processes still run."""
        if self.robot_processes is not None:
            return self.robot_processes.alive()
        robot = self.processes.get("robot_sim")
        return robot is not None and robot.poll() is None

    @property
    def endpoint(self) -> str:
        return self.router.endpoint

    def open_session(self) -> Session:
        """A session of a client of the stack (its router's)."""
        return open_session(self.router.client_config())

    def __exit__(self, *exc) -> None:
        if self.robot_processes is not None:
            self.robot_processes.__exit__(None, None, None)
            self.robot_processes = None
        # the robot first: it stops the arm while safety listens; then the pipeline, side by side
        stop_processes([self.processes.pop("robot_sim")] if "robot_sim" in self.processes else [])
        stop_processes([self.processes.pop(name) for name in reversed(PIPELINE) if name in self.processes],
                       together=True)
        self.router.__exit__(None, None, None)
        self._logs.close()
