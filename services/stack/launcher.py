"""``mfvs up``, ``mfvs down`` and ``mfvs status``: run a stack as background processes and look at it.

A stack is a zenoh router plus services, each its own process (``python -m services.<name>``) with its config
file, logging to the run directory (``$MFVS_RUN_DIR``, default ``~/.local/state/mfvs``), which also holds
``stack.json`` (the router's endpoint, every process id and log). The stack comes up idle: the arm moves only
once a task is started (``mfvs task start``, :func:`stack_task`). Profiles:

- ``sim``: robot_sim (its emulated DSP and API), vision, controller, safety with their shipped configs;
- ``gateway``: the same, except that robot_sim runs only the actuators (``mode: actuator_bus``) on an RS-485 bus
  carried by the loopback CAN hub (``mfvs bus-hub``), and robot_gateway offers the robot's zenoh API on top of
  that bus, as it would for a real arm (in lockstep the actuators wait for each of the gateway's exchanges);
- a YAML file::

    router: {port: 7447, config: null}          # config: a zenoh router config (access control, TLS)
    bus_hub: {port: 7448}                       # optional: run the loopback CAN hub (python-can mfvs_hub)
    services:
      - {name: safety, config: services/safety/safety.yaml}
      - {name: robot_sim, config: my_robot.yaml, zenoh_config: secrets/clients/robot_sim.json5,
         set: [mode=actuator_bus]}              # set: config overrides, as `--set KEY=VALUE`
"""
from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Optional

import msgspec

from protocol import messages as m
from protocol.keys import ARM_SERVICES, PIPELINE_START_ORDER, Keys
from services.paths import REPO
from services.runtime.config import ConfigError, ConfigStruct, config_mapping, load_config
from services.runtime.service import EXIT_FILE_ENV, alive_services, query_health, service_condition
from services.runtime.transport import ZenohConfig, file_access_control, file_endpoints, open_session

SERVICES = (*PIPELINE_START_ORDER, "robot_sim")
#: optional beside the pipeline: a real camera, the ROS 2 bridge (`mfvs up --ros2`)
KNOWN_SERVICES = (*SERVICES, "robot_gateway", "camera", "ros2_bridge")
BUS_HUB_PORT = 7448


class ProfileService(ConfigStruct):
    name: str
    #: the computer it runs on, in a profile that spans several (`mfvs up --host NAME` starts that host's part)
    host: Optional[str] = None
    config: Optional[str] = None
    zenoh_config: Optional[str] = None
    #: config overrides, each ``dotted.key=value`` (the service's ``--set``)
    set: list[str] = msgspec.field(default_factory=list)
    #: environment variables it runs with besides the launcher's (e.g. a libusb's directory on LD_LIBRARY_PATH)
    env: dict[str, str] = msgspec.field(default_factory=dict)


class ProfileRouter(ConfigStruct):
    port: int = 7447
    config: Optional[str] = None
    #: the computer it runs on, in a profile that spans several
    host: Optional[str] = None
    #: where the services (on every host) reach it, and where it listens (unless its config says)
    address: str = "127.0.0.1"


class ProfileBusHub(ConfigStruct):
    port: int = BUS_HUB_PORT
    host: str = "127.0.0.1"


class Profile(ConfigStruct):
    router: ProfileRouter = msgspec.field(default_factory=ProfileRouter)
    bus_hub: Optional[ProfileBusHub] = None
    services: list[ProfileService] = msgspec.field(default_factory=list)
    robot_id: str = "jaco"

    def __post_init__(self) -> None:
        unknown = [s.name for s in self.services if s.name not in KNOWN_SERVICES]
        if unknown:
            raise ValueError(f"unknown services {unknown}; known: {', '.join(KNOWN_SERVICES)}")
        placed = [s.host is not None for s in self.services] + [self.router.host is not None]
        if any(placed) and not all(placed):
            raise ValueError("a profile that names hosts names one for the router and for every service")
        if self.hosts and self.bus_hub is not None:
            raise ValueError("the CAN hub is a one-host loopback bus: not in a profile across hosts")

    @property
    def hosts(self) -> list[str]:
        """The computers it spans, the router's first ([] for a one-host profile)."""
        named = [self.router.host] + [s.host for s in self.services]
        return list(dict.fromkeys(h for h in named if h is not None))

    def endpoint(self) -> str:
        """Where every service reaches the router."""
        return f"tcp/{self.router.address}:{self.router.port}"

    def part(self, host: Optional[str]) -> tuple[bool, list[ProfileService]]:
        """(whether this host runs the router, the services it runs); ValueError when ``host`` does not fit the
        profile (a profile across hosts needs one of its hosts; a one-host profile, none)."""
        if not self.hosts:
            if host is not None:
                raise ValueError("this profile runs on one computer: no --host (it names no hosts)")
            return True, list(self.services)
        if host not in self.hosts:
            raise ValueError(f"this profile spans {', '.join(self.hosts)}: say which this computer is (--host)"
                             if host is None else f"no host {host!r} in this profile ({', '.join(self.hosts)})")
        return self.router.host == host, [s for s in self.services if s.host == host]


def _shipped(name: str, overrides: list[str] | None = None) -> ProfileService:
    return ProfileService(name=name, config=str(REPO / "services" / name / f"{name}.yaml"), set=overrides or [])


def sim_profile(port: int) -> Profile:
    return Profile(router=ProfileRouter(port=port), services=[_shipped(name) for name in SERVICES])


def gateway_profile(port: int, bus_port: int = BUS_HUB_PORT) -> Profile:
    """robot_sim's actuators on the hub's bus, robot_gateway in front of them; everything else as in ``sim``.
    Only the robot's side changes: vision, controller and safety run with exactly their ``sim`` configs."""
    pipeline = [_shipped(name) for name in SERVICES if name != "robot_sim"]
    return Profile(router=ProfileRouter(port=port), bus_hub=ProfileBusHub(port=bus_port),
                   services=[*pipeline, *gateway_robot_services(f"127.0.0.1:{bus_port}")])


def gateway_robot_services(bus_channel: str, robot_sim_config: Optional[str] = None,
                           robot_gateway_config: Optional[str] = None) -> list[ProfileService]:
    """The gateway profile's robot side, defined once for `mfvs up --profile gateway`, `mfvs servo --profile
    gateway`, the benchmarks and the tests (:class:`services.stack.RobotProcesses`): robot_sim's emulated
    actuators on the CAN hub's bus at ``bus_channel``, robot_gateway in front of them (configs: the shipped ones
    unless given)."""
    bus = ["bus.interface=mfvs_hub", f"bus.channel={bus_channel}"]
    # the arm behind this bus is robot_sim's emulation of the description itself: its check is waived (and an
    # RS-485 bus carries no Cartesian report the check could compare with)
    return [ProfileService(name="robot_sim", config=robot_sim_config or _shipped("robot_sim").config,
                           set=["mode=actuator_bus", *bus]),
            ProfileService(name="robot_gateway", config=robot_gateway_config or _shipped("robot_gateway").config,
                           set=[*bus, "arm_check.waived=true"])]


def usb_robot_services(socket_path: str, libusb_dir: Path, robot_sim_config: Optional[str] = None,
                       robot_gateway_config: Optional[str] = None, high_level_check: bool = True
                       ) -> list[ProfileService]:
    """The gateway profile's robot side with the actuator bus reached as a real arm's is, through Kinova's USB comm
    layer: robot_sim's actuators behind an emulated base on USB (its socket at ``socket_path``), robot_gateway on
    ``kinova_usb`` with Kinova's comm layer (``sdk_library``, else ``$MFVS_KINOVA_SDK``) loaded over the stand-in
    libusb in ``libusb_dir`` (services.robot_sim.usb_base). robot_sim first: the gateway's first call asks the base
    who it is. ``high_level_check``: the gateway checks the first RS-485 positions against Kinova's high-level API
    (the emulated base answers it); off for a comm layer without Kinova's command layer beside it (the tests'
    stand-in)."""
    from services.robot_sim.usb_base import host_environment

    return [ProfileService(name="robot_sim", config=robot_sim_config or _shipped("robot_sim").config,
                           set=["mode=actuator_bus", "bus.interface=kinova_usb_base", f"bus.channel={socket_path}"]),
            ProfileService(name="robot_gateway", config=robot_gateway_config or _shipped("robot_gateway").config,
                           set=["bus.interface=kinova_usb", "arm_check.waived=true",
                                *([] if high_level_check else ["high_level_check_deg=null"])],
                           env=host_environment(socket_path, libusb_dir))]


def service_command(service: ProfileService, endpoint: Optional[str] = None, robot_id: Optional[str] = None,
                    clock: Optional[str] = None) -> list[str]:
    """The command line that runs one service of a profile (what is not given comes from its config file)."""
    args = [sys.executable, "-m", f"services.{service.name}"]
    if endpoint:
        args += ["--connect", endpoint]
    if robot_id:
        args += ["--robot-id", robot_id]
    if service.config:
        args += ["--config", service.config]
    if clock:
        args += ["--clock", clock]
    if service.zenoh_config:
        args += ["--zenoh-config", service.zenoh_config]
    for assignment in service.set:
        args += ["--set", assignment]
    return args


def run_dir() -> Path:
    path = Path(os.environ.get("MFVS_RUN_DIR", Path.home() / ".local" / "state" / "mfvs"))
    path.mkdir(parents=True, exist_ok=True)
    return path


def _alive(pid: int) -> bool:
    """Whether the process runs: a zombie (dead, not yet reaped by the process that started it, as when `up` ran
    in this one) is not."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    try:
        # the state follows the command name, which is in parentheses and may hold anything
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except (OSError, IndexError):
        return True


def read_stack() -> Optional[dict]:
    path = run_dir() / "stack.json"
    if not path.exists():
        return None
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return None


def service_environment() -> dict:
    """The environment a service runs in: this process's, rendering through EGL unless it says otherwise."""
    env = dict(os.environ)
    env.setdefault("MUJOCO_GL", "egl")
    return env


def spawn(args: list[str], log: Path, exit_file: Optional[Path] = None,
          extra_env: Optional[dict[str, str]] = None) -> subprocess.Popen:
    """A service (or the router, or the hub) as a background process of its own session, logging to ``log``."""
    env = {**service_environment(), **(extra_env or {})}
    if exit_file is not None:
        exit_file.unlink(missing_ok=True)
        env[EXIT_FILE_ENV] = str(exit_file)
    with log.open("ab") as out:  # the child keeps its own descriptor
        return subprocess.Popen(args, cwd=REPO, env=env, stdout=out, stderr=subprocess.STDOUT,
                                start_new_session=True)


def up(profile: Profile, clock: Optional[str], wait_s: float = 60.0, host: Optional[str] = None) -> tuple[int, str]:
    """Start the stack, or on a profile across hosts this host's part of it (``host``); returns (exit code,
    message)."""
    try:
        runs_router, services = profile.part(host)
        arm = profile_arm(profile)
    except ValueError as exc:
        return 2, str(exc)
    current = read_stack()
    if current and any(_alive(p["pid"]) for p in current["processes"]):
        return 1, f"a stack is already up (router {current['endpoint']}); run `mfvs down` first"
    directory = run_dir()
    endpoint = profile.endpoint()
    router_args = [sys.executable, "-m", "services.cli", "router"]
    listen = file_endpoints(profile.router.config, "listen") if profile.router.config else []
    if listen:  # the router's config says where it listens (and whether over TLS)
        scheme = listen[0].split("/", 1)[0]
        # across hosts the services reach it at its address (the file must listen there, or on 0.0.0.0)
        endpoint = f"{scheme}/{profile.router.address}:{profile.router.port}" if profile.hosts else listen[0]
        router_args += ["--config", profile.router.config]
    else:
        router_args += ["--port", str(profile.router.port), "--host", profile.router.address]
        if profile.router.config:
            router_args += ["--config", profile.router.config]
    # behind an authority router, the launcher's own checks (and `status`, `estop`) need an identity: the
    # operator's, from the same directory as the services' client configs
    observer = _observer_config(profile)
    if observer is None and profile.router.config and file_access_control(profile.router.config):
        return 2, f"the router's access control ({profile.router.config}) would refuse the launcher: " \
                  f"{NO_OPERATOR_IDENTITY}"
    processes = []
    children: list[subprocess.Popen] = []
    if runs_router:
        log = directory / "router.log"
        children.append(spawn(router_args, log))
        processes.append({"name": "router", "pid": children[-1].pid, "log": str(log), "args": router_args})
    if profile.bus_hub is not None:
        log = directory / "bus_hub.log"
        hub_args = [sys.executable, "-m", "services.cli", "bus-hub", "--port", str(profile.bus_hub.port),
                    "--host", profile.bus_hub.host]
        children.append(spawn(hub_args, log))
        processes.append({"name": "bus_hub", "pid": children[-1].pid, "log": str(log), "args": hub_args})
    time.sleep(0.5)
    for service in services:
        args = service_command(service, endpoint, profile.robot_id, clock)
        log = directory / f"{service.name}.log"
        exit_file = directory / f"{service.name}.exit"
        children.append(spawn(args, log, exit_file, service.env))
        processes.append({"name": service.name, "pid": children[-1].pid, "log": str(log),
                          "exit_file": str(exit_file), "args": args, "env": service.env})
    stack = {"endpoint": endpoint, "robot_id": profile.robot_id, "processes": processes, "started": time.time(),
             "zenoh_config": observer, "host": host}
    _write_stack(stack)
    # wait until every service of this host announces itself (the router may be another host's, and later)
    names = {s.name for s in services}
    deadline = time.monotonic() + wait_s
    alive: set[str] = set()
    while time.monotonic() < deadline:
        dead = [p for p, child in zip(processes, children, strict=True) if child.poll() is not None]
        if dead:
            down()
            logs = "; ".join(f"{p['name']} exited (log {p['log']})" for p in dead)
            return 1, f"the stack did not come up: {logs}"
        try:
            alive = set(status(endpoint, profile.robot_id, liveliness_only=True, zenoh_config=observer))
        except Exception:
            alive = set()
        if names <= alive:
            where = f"host {host}: " if host else ""
            return 0, (f"{where}stack up: router {endpoint}, services {', '.join(sorted(names))} "
                       f"(logs in {directory})")
        time.sleep(0.5)
    down()
    hint = f" (behind a router with access control, {NO_OPERATOR_IDENTITY})" if observer is None else ""
    return 1, f"services not alive after {wait_s:g} s: {', '.join(sorted(names - alive))}{hint}"


def client_config(service: ProfileService) -> Optional[str]:
    """The zenoh client config a profile's service runs with: its ``zenoh_config``, else its config's
    ``zenoh.config_file`` (in its config file or set through ``set:``), as the service itself resolves it."""
    if service.zenoh_config:
        return service.zenoh_config
    try:
        zenoh = config_mapping(service.config, service.set, f"{service.name}'s set").get("zenoh") or {}
    except ConfigError:
        return None  # the service itself says what is wrong with its config
    return zenoh.get("config_file") if isinstance(zenoh, dict) else None


def service_setting(service: ProfileService, key: str):
    """A top-level setting of a profile's service as it will run with it (its config file, then ``set:``), or None
    where neither gives one (or its config cannot be read: the service says why when it starts)."""
    try:
        return config_mapping(service.config, service.set, f"{service.name}'s set").get(key)
    except ConfigError:
        return None


def with_arm(profile: Profile, arm: str) -> Profile:
    """The profile with every service that runs on an arm set to ``arm`` (`mfvs up --arm NAME`)."""
    services = [msgspec.structs.replace(s, set=[*s.set, f"arm={arm}"]) if s.name in ARM_SERVICES else s
                for s in profile.services]
    return msgspec.structs.replace(profile, services=services)


def with_bus_period(profile: Profile, period_ms: float) -> Profile:
    """The profile with its actuator bus's host period set (`mfvs up --bus-period MS`): robot_gateway paces its
    exchanges on it, robot_sim's emulated actuators spread their targets over it; ValueError for a period that is
    no bus period (services.robot.hardware.BusTiming) or a profile without robot_gateway (no bus to set)."""
    from services.robot.hardware import BusTiming

    timing = BusTiming.from_period_ms(period_ms)
    if not any(s.name == "robot_gateway" for s in profile.services):
        raise ValueError("--bus-period is the actuator bus's: a profile with robot_gateway (gateway, real-arm)")
    services = [msgspec.structs.replace(s, set=[*s.set, f"bus.period_ms={timing.period_ms:g}"])
                if s.name in ("robot_gateway", "robot_sim") else s for s in profile.services]
    return msgspec.structs.replace(profile, services=services)


def with_ros2(profile: Profile, domain_id: int) -> Profile:
    """The profile with the ROS 2 bridge on ROS domain ``domain_id`` (`mfvs up --ros2`), on the first host of a
    profile across hosts (the router's: it needs no device), unless the profile runs one already."""
    if any(s.name == "ros2_bridge" for s in profile.services):
        return profile
    bridge = msgspec.structs.replace(_shipped("ros2_bridge", [f"domain_id={domain_id}"]),
                                     host=profile.router.host)
    return msgspec.structs.replace(profile, services=[*profile.services, bridge])


def profile_arm(profile: Profile) -> str:
    """The one arm a profile runs (its robot's; the default arm where none is set); ValueError naming the services
    when they do not agree (a controller or safety started for another arm than the robot's would do nothing)."""
    from services.model.arm import DEFAULT_ARM, check_arm_name

    arms = {s.name: service_setting(s, "arm") for s in profile.services if s.name in ARM_SERVICES}
    robots = {name: arm or DEFAULT_ARM for name, arm in arms.items() if name in ("robot_sim", "robot_gateway")}
    named = {**robots, **{name: arm for name, arm in arms.items() if arm is not None}}
    if len(set(named.values())) > 1:
        listed = ", ".join(f"{name} {arm}" for name, arm in named.items())
        raise ValueError(f"the profile mixes arms ({listed}): one arm for the whole stack (mfvs up --arm NAME)")
    arm = next(iter(named.values()), DEFAULT_ARM)
    check_arm_name(arm)
    return arm


def _observer_config(profile: Profile) -> Optional[str]:
    """The operator's client config next to the services' (``mfvs authority init`` writes them together), if the
    services run with client configs."""
    for service in profile.services:
        config = client_config(service)
        if config:
            candidate = Path(config).parent / "operator.json5"
            if candidate.is_file():
                return str(candidate)
    return None


#: what to do when the launcher has no identity for a router that checks them
NO_OPERATOR_IDENTITY = ("the launcher (and `mfvs status`, `task`, `estop`) needs the operator's identity: put "
                        "operator.json5 (written by `mfvs authority init`) beside the services' client configs "
                        "(their zenoh_config, or zenoh.config_file in their config or set:)")


def stack_task(function: str, operator: str = "mfvs", reason: str = "", timeout_s: float = 5.0) -> m.TaskStatus:
    """Start, stop or read the running stack's task (``m.START_TASK``, ``m.STOP_TASK``, ``m.GET_TASK``), reached
    through its run directory as `mfvs task` reaches it: the stack comes up idle."""
    from services.controller.task_client import call_task

    stack = read_stack()
    if stack is None:
        raise RuntimeError(f"no stack in {run_dir()} (mfvs up)")
    session = open_session(ZenohConfig(connect=[stack["endpoint"]], config_file=stack.get("zenoh_config")))
    try:
        request = None if function == m.GET_TASK else m.TaskRequest(operator=operator, reason=reason)
        return call_task(session, Keys(stack.get("robot_id") or "jaco"), function, request, timeout_s)
    finally:
        session.close()


def down(timeout_s: float = 15.0) -> tuple[int, str]:
    stack = read_stack()
    if stack is None:
        return 0, "no stack is up"
    # the services first, then what carries their traffic (the CAN hub, the router)
    infrastructure = ("bus_hub", "router")
    ordered = [p for p in stack["processes"] if p["name"] not in infrastructure] + \
              [p for p in stack["processes"] if p["name"] in infrastructure]
    services = sum(p["name"] not in infrastructure for p in ordered)
    for group in (ordered[:services], ordered[services:]):
        _end([p["pid"] for p in group], timeout_s)
    (run_dir() / "stack.json").unlink(missing_ok=True)
    return 0, f"stopped {len(ordered)} processes"


def _end(pids: list[int], timeout_s: float, wake: bool = False) -> None:
    """SIGTERM to each process still running (and SIGCONT with ``wake``, so a stopped one hears it), reaping those
    this process started, then SIGKILL to what still runs after ``timeout_s``."""
    for pid in pids:
        if _alive(pid):
            for sig in (signal.SIGTERM, signal.SIGCONT) if wake else (signal.SIGTERM,):
                with contextlib.suppress(ProcessLookupError):
                    os.kill(pid, sig)
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and any(_alive(pid) for pid in pids):
        time.sleep(0.05)
        for pid in pids:  # reap our children if we started them in this process
            with contextlib.suppress(ChildProcessError):
                os.waitpid(pid, os.WNOHANG)
    for pid in pids:
        if _alive(pid):
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)


def restart(name: str, timeout_s: float = 10.0) -> tuple[int, str]:
    """Restart one process of the running stack (a service, the router, the hub) with the command line it was
    started with, as its systemd unit would: ended first if it still runs (SIGTERM, a stopped one woken to hear it,
    SIGKILL after ``timeout_s``). The run directory remembers how often and when (`mfvs status` shows it)."""
    stack = read_stack()
    if stack is None:
        return 1, f"no stack in {run_dir()} (mfvs up)"
    process = next((p for p in stack["processes"] if p["name"] == name), None)
    if process is None:
        return 2, f"no {name} in this stack ({', '.join(p['name'] for p in stack['processes'])})"
    if "args" not in process:
        return 1, f"{name} was started by an older mfvs: its command line is not known (mfvs down; mfvs up)"
    _end([process["pid"]], timeout_s, wake=True)
    exit_file = Path(process["exit_file"]) if process.get("exit_file") else None
    child = spawn(process["args"], Path(process["log"]), exit_file, process.get("env"))
    process.update(pid=child.pid, restarts=process.get("restarts", 0) + 1, restarted=time.time())
    _write_stack(stack)
    return 0, f"{name} restarted (pid {child.pid})"


def _write_stack(stack: dict) -> None:
    path = run_dir() / "stack.json"
    tmp = path.with_name("stack.json.tmp")
    tmp.write_text(json.dumps(stack, indent=2))
    tmp.replace(path)


def status(endpoint: str, robot_id: str = "jaco", liveliness_only: bool = False, zenoh_config: str | None = None):
    """Service name → health (ServiceHealth or None when only liveliness is known)."""
    keys = Keys(robot_id)
    session = open_session(ZenohConfig(connect=[endpoint], config_file=zenoh_config))
    try:
        alive = alive_services(session, keys, timeout_s=2.0)
        result: dict = {name: None for name in alive}
        if not liveliness_only:
            result.update(query_health(session, keys))
        return result
    finally:
        session.close()


def status_json(endpoint: str, robot_id: str, zenoh_config: str | None = None) -> dict:
    stack = read_stack() or {"processes": []}
    pids = {p["name"]: p["pid"] for p in stack["processes"]}
    restarts = {p["name"]: {"restarts": p.get("restarts", 0),
                            "restarted_ago_s": round(time.time() - p["restarted"], 1) if p.get("restarted") else None}
                for p in stack["processes"]}
    no_restarts = {"restarts": 0, "restarted_ago_s": None}
    router: dict = {"endpoint": endpoint, "pid": pids.get("router"), "reachable": False,
                    **restarts.get("router", no_restarts)}
    services = []
    try:
        found = status(endpoint, robot_id, zenoh_config=zenoh_config)
        router["reachable"] = True
    except Exception as exc:
        router["error"] = str(exc)
        found = {}
    for name, health in sorted(found.items()):
        condition = service_condition(health)
        services.append({
            "name": name, "pid": health.pid if health else pids.get(name),
            "healthy": condition == "healthy", "condition": condition,
            "state": health.state if health else "unknown",
            "rates_hz": dict(health.rates_hz) if health else {}, "errors": dict(health.errors) if health else {},
            "degraded": list(health.degraded) if health else [], "detail": health.detail if health else "",
            **restarts.get(name, no_restarts),
        })
    # what the run directory started and the bus does not know: dead (with its exit code when it left one), or
    # running but silent
    for process in stack["processes"]:
        name = process["name"]
        if name in found or name in ("router", "bus_hub"):
            continue
        alive = _alive(process["pid"])
        exit_code = _exit_code(process.get("exit_file"))
        services.append({
            "name": name, "pid": process["pid"], "healthy": False,
            "condition": "not responding" if alive else "dead", "state": "running" if alive else "exited",
            "exit_code": None if alive else exit_code, "rates_hz": {}, "errors": {}, "degraded": [],
            "detail": "" if alive else ("killed (no exit code)" if exit_code is None else f"exit code {exit_code}")
                      + f"; log {process.get('log', '')}",
            **restarts.get(name, no_restarts),
        })
    return {"router": router, "services": services}


def _exit_code(path: Optional[str]) -> Optional[int]:
    try:
        return int(Path(path).read_text().strip()) if path else None
    except (OSError, ValueError):
        return None


def behind_authority(profile: Profile, deployment) -> Profile:
    """``profile`` with its router on ``deployment``'s config (`mfvs authority init`: access control, TLS where it
    has certificates) and each service on its own identity's client config there."""
    from services.runtime.authority import TOOLS

    profile.router.config = str(deployment.router_config)
    for service in profile.services:
        # a tool (the ROS 2 bridge) runs as the identity it acts for
        identity = next((who for who, tools in TOOLS.items() if service.name in tools), service.name)
        service.zenoh_config = str(deployment.client_configs[identity])
    return profile


def load_profile(name_or_path: str, port: int, bus_port: int = BUS_HUB_PORT) -> Profile:
    if name_or_path == "sim":
        return sim_profile(port)
    if name_or_path == "gateway":
        return gateway_profile(port, bus_port)
    shipped = REPO / "deploy" / "profiles" / f"{name_or_path}.yaml"
    if "/" not in name_or_path and not name_or_path.endswith(".yaml") and shipped.is_file():
        return load_config(shipped, Profile)
    return load_config(name_or_path, Profile)
