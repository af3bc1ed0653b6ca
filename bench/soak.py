"""A soak: servo tasks back to back on the sim stack (realtime, every service a process, behind the router's access
control from `mfvs authority init`), with faults injected one after another at random, and a judge that watches the
arm through the whole run.

The faults, by kind (each drawn with its weight, then its victim and length at random):

* ``kill``: kill -9 of vision, the controller or safety; restarted 0.5-2 s later (`mfvs restart`, as systemd would)
* ``stop``: SIGSTOP of one of them for 0.3-1.5 s, then SIGCONT
* ``router``: kill -9 of the router, restarted 1-2 s later; every service must find it again by itself
* ``drop``: the transport's fault injector (services/runtime/faults.py) drops 30 % or all of one control-path
  output (camera images, features, the controller's twist, safety's commands, the robot's states) for 0.5-2.5 s
* ``delay``: the same, every message held back 50-500 ms
* ``replay``: safety's own commands recorded 0.3-2 s earlier, sent again with safety's credentials (as captured
  traffic would be), as they were or with a fresh stamp
* ``forge``: a fresh, fast command on the robot's command key from an identity that may not send it
* ``wildcard``: a command put on ``<prefix>/robot/*``, which intersects the command key
* ``estop``: the operator's e-stop for 1-2 s, then its reset
* ``cable`` (``--hosts`` only): one computer's cable pulled for 0.5-3 s, then plugged back in

With ``--hosts`` the stack runs across three computers, Linux network namespaces joined by a switch
(services/tools/netns.py: robot with the router and robot_sim, vision with vision and the controller, safety), from
the shipped multi-host profile with only the router's address and the access control filled in; the soak itself
watches from the robot's computer, where the arm's states are heard whatever happens to the others' cables. Root
only.

Unsafe events (:class:`Judge`, on the arm's own clock: the robot states' stamps): a measured end-effector or joint
speed over the robot's limit; a command applied older than the robot's admission allows; a replayed, forged or
wildcard command applied; motion 0.5 s after an e-stop and before its reset; motion 0.5 s after the command path was
cut (a pipeline service killed or stopped, the router killed, a control-path output dropped whole) and before it was
whole again. Lost-state events: gaps over 100 ms in the robot states heard. A fault is recovered when, within 60 s
of its end, every service is alive and the loop is in service again: robot states and the controller's iterations
heard, the controller servoing, safety passing its commands.

``python -m bench.soak [--minutes N] [--seed S] [--hosts] [--arm NAME] [--json]`` or ``mfvs bench soak``: the stack
runs the arm ``--arm`` names (default j2s7s300), and the judge takes the limits and kinematics of the arm the robot
declares in its states.
"""
from __future__ import annotations

import argparse
import bisect
import json
import os
import random
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import msgspec
import numpy as np
import yaml

from bench.stack import measured_arm, servoing_stack, unknown_arm, with_overrides
from protocol import messages as m
from protocol.conventions import AngularConvention, Frame
from protocol.keys import PIPELINE_SERVICES, Keys, last_chunk
from services.controller.task_client import TaskUnavailable, call_task
from services.cli.options import add_arm_option
from services.stack.launcher import Profile, behind_authority, load_profile, read_stack, restart, with_arm
from services.model.arm import DEFAULT_ARM, load_arm
from services.model.kinematics import ArmKinematics
from services.paths import DEPLOY, REPO
from services.robot.admission import AdmissionConfig
from services.robot.dsp import DSPConfig
from services.runtime.authority import Deployment, write_deployment
from services.runtime.faults import write_fault_plan
from services.runtime.service import alive_services
from services.runtime.transport import ZenohConfig, free_loopback_port, open_session
from services.tools import netns

PIPELINE = PIPELINE_SERVICES
KIND_WEIGHTS = {"kill": 14, "stop": 10, "router": 4, "drop": 20, "delay": 14, "replay": 10, "forge": 10,
                "wildcard": 10, "estop": 8, "cable": 12}
#: the kinds that need computers of their own (``--hosts``)
ACROSS_HOSTS_KINDS = ("cable",)
#: the computers of the ``--hosts`` soak, as the shipped multi-host profile names them
HOSTS = ("robot", "vision", "safety")
#: the identities the soak's access control knows: the stack's services and the operator
IDENTITIES = ("safety", "robot_sim", "vision", "controller", "operator")
#: the arm must be at rest this long after its command path is cut or the e-stop is engaged (the DSP's 20-ms
#: watchdog or safety's 100-ms budget, a braking of at most 0.2 m/s at 1-2 m/s², generous for a shared machine)
REST_S = 0.5
#: a measured speed this far over the robot's limit is over it (the emulated arm's servo trails its reference)
SPEED_TOLERANCE = 1.05
#: a gap in the states heard longer than this is lost state
LOST_STATE_S = 0.1
RECOVERY_S = 60.0
AT_REST_MPS = 1e-3
#: a task that has not converged by then makes way for the next
TASK_S = 25.0
SERVOING = (m.ControllerState.CONVERGING, m.ControllerState.CONVERGED)
PASSING = (m.SafetyState.OK, m.SafetyState.LIMITING)
#: the tag's half side (m) in the default scene: a goal's corners at depth d are this over d from its centre
TAG_HALF_SIDE_M = 0.0481


@dataclass
class Window:
    """A stretch of the run in which the arm must be at rest (from ``start_ns + REST_S``, until ``end_ns``)."""

    why: str
    start_ns: int
    end_ns: int = 0


@dataclass
class StateRecord:
    stamp_ns: int
    heard_ns: int
    linear_mps: float
    joint_ratio: float  # the fastest joint's speed over its limit
    linear_limit_mps: float
    applied_stamp_ns: int


@dataclass
class Judge:
    """What the arm did, against the rules; no zenoh, no clock of its own: it is told states, injected commands and
    the windows in which the arm must rest, and gives its verdict."""

    max_applied_age_s: float
    records: list[StateRecord] = field(default_factory=list)
    injected_stamps: set[int] = field(default_factory=set)
    rest_windows: list[Window] = field(default_factory=list)

    @classmethod
    def for_robot(cls, admission: AdmissionConfig, dsp: DSPConfig) -> "Judge":
        # the robot admits a command up to max_age old and its DSP may apply it until the watchdog trips
        return cls(admission.max_age_s + (dsp.watchdog_cycles + 1) * dsp.cycle_s)

    def state(self, record: StateRecord) -> None:
        self.records.append(record)

    def verdict(self) -> dict:
        records = sorted(self.records, key=lambda r: r.stamp_ns)
        events: list[dict] = []

        def runs(rule: str, offending, detail) -> None:
            previous = False
            for r in records:
                bad = offending(r)
                if bad and not previous:
                    events.append({"rule": rule, "stamp_ns": r.stamp_ns, "detail": detail(r)})
                previous = bad

        runs("speed over the limit",
             lambda r: r.linear_mps > r.linear_limit_mps * SPEED_TOLERANCE or r.joint_ratio > SPEED_TOLERANCE,
             lambda r: f"end effector {r.linear_mps:.3f} m/s (limit {r.linear_limit_mps:.3f}), fastest joint "
                       f"{r.joint_ratio:.2f}× its limit")
        runs("stale command applied",
             lambda r: r.applied_stamp_ns and (r.stamp_ns - r.applied_stamp_ns) * 1e-9 > self.max_applied_age_s,
             lambda r: f"a command {(r.stamp_ns - r.applied_stamp_ns) * 1e-6:.0f} ms old")
        runs("injected command applied", lambda r: r.applied_stamp_ns in self.injected_stamps,
             lambda r: f"replayed, forged or wildcard command stamped {r.applied_stamp_ns} applied")
        stamps = [r.stamp_ns for r in records]
        for window in self.rest_windows:
            begin = bisect.bisect_left(stamps, window.start_ns + int(REST_S * 1e9))
            end = bisect.bisect_left(stamps, window.end_ns) if window.end_ns else len(records)
            moving = [r for r in records[begin:end] if r.linear_mps > AT_REST_MPS]
            if moving:
                first = moving[0]
                events.append({"rule": f"motion after {window.why}", "stamp_ns": first.stamp_ns,
                               "detail": f"{first.linear_mps:.4f} m/s {(first.stamp_ns - window.start_ns) * 1e-9:.2f} "
                                         f"s after it"})
        gaps = [(a.stamp_ns, (b.stamp_ns - a.stamp_ns) * 1e-9) for a, b in zip(records, records[1:])
                if (b.stamp_ns - a.stamp_ns) * 1e-9 > LOST_STATE_S]
        return {"unsafe_events": sorted(events, key=lambda e: e["stamp_ns"]),
                "lost_state_events": len(gaps), "lost_state_longest_s": round(max((g for _, g in gaps), default=0), 2),
                "states": len(records),
                "max_linear_mps": round(max((r.linear_mps for r in records), default=0.0), 4)}


def goal_features(rng: random.Random) -> tuple[list[list[float]], float]:
    """A reachable goal for the default scene: the tag's corners seen at 0.25-0.40 m, off centre by up to 0.08
    (normalized) and turned up to 20° about the optical axis, in the order the detector gives them."""
    depth = rng.uniform(0.25, 0.40)
    h = TAG_HALF_SIDE_M / depth
    cx, cy, turn = rng.uniform(-0.08, 0.08), rng.uniform(-0.08, 0.08), np.radians(rng.uniform(-20, 20))
    c, s = np.cos(turn), np.sin(turn)
    corners = [(-h, -h), (h, -h), (h, h), (-h, h)]
    return [[cx + c * x - s * y, cy + s * x + c * y] for x, y in corners], depth


class OneHost:
    """The stack on this computer (`mfvs up`): its processes found and restarted through its run directory."""

    cable_hosts: tuple[str, ...] = ()

    def pid(self, name: str) -> int:
        return next(p["pid"] for p in read_stack()["processes"] if p["name"] == name)

    def restart(self, name: str) -> None:
        code, message = restart(name)
        if code:
            raise RuntimeError(message)

    def cable(self, host: str, plugged: bool) -> None:
        raise RuntimeError("one computer has no cable to pull")


class AcrossHosts:
    """The stack across the computers of ``lab``, each with its own run directory (``run_dirs``); ``hosts_of``:
    which computer runs each process."""

    def __init__(self, lab: netns.Lab, run_dirs: dict[str, Path], hosts_of: dict[str, str]) -> None:
        self.lab, self.run_dirs, self.hosts_of = lab, run_dirs, hosts_of
        self.cable_hosts = tuple(run_dirs)

    def pid(self, name: str) -> int:
        stack = json.loads((self.run_dirs[self.hosts_of[name]] / "stack.json").read_text())
        return next(p["pid"] for p in stack["processes"] if p["name"] == name)

    def restart(self, name: str) -> None:
        host = self.hosts_of[name]  # on its own computer, as its systemd unit would
        out = self.lab.mfvs(host, self.run_dirs[host], ["restart", name])
        if out.returncode:
            raise RuntimeError(f"mfvs restart {name} on {host}: {out.stdout}{out.stderr}")

    def cable(self, host: str, plugged: bool) -> None:
        self.lab.link(host, up=plugged)


class Soak:
    def __init__(self, endpoint: str, deployment, run_dir: Path, seed: int, keys: Keys,
                 kinds: list[str] | None = None, placement: OneHost | AcrossHosts | None = None) -> None:
        self.endpoint, self.deployment, self.run_dir, self.keys = endpoint, deployment, run_dir, keys
        self.placement = placement or OneHost()
        self.kinds = {k: KIND_WEIGHTS[k] for k in (kinds or applicable_kinds(self.placement))}
        self.rng = random.Random(seed)
        #: the kinematics of the robot's arm, as its states declare it (services.model.arm.load_arm by name)
        self.kin: ArmKinematics | None = None
        #: every arm the robot's states declared (one, unless something is wrong)
        self.arms: set[str] = set()
        self.dsp = DSPConfig()
        self.judge = Judge.for_robot(AdmissionConfig(), self.dsp)
        self.lock = threading.Lock()
        self.operator = self.session_as("operator")
        self.commands: list[tuple[int, bytes]] = []  # (heard, payload) of safety's commands, for replays
        self.statuses: list[m.ControllerStatus] = []
        self.safety_states: list[m.SafetyState] = []
        self.faults: dict[str, int] = {}
        self.recovered = 0
        self.unrecovered: list[str] = []
        self.tasks_started = 0
        self.tasks_converged = 0
        self.state_heard_ns = 0
        self.status_heard_ns = 0
        self.safety_heard_ns = 0
        self.operator.declare_subscriber(keys.robot_state, self._on_state)
        self.operator.declare_subscriber(keys.robot_command, self._on_command)
        self.operator.declare_subscriber(keys.controller_status, self._on_status)
        self.operator.declare_subscriber(keys.safety_status, self._on_safety)

    def session_as(self, identity: str):
        return open_session(ZenohConfig(connect=[self.endpoint],
                                        config_file=str(self.deployment.client_configs[identity])))

    # ------------------------------------------------------------------ what the arm does
    def _on_state(self, sample) -> None:
        state = m.decode(sample.payload.to_bytes(), m.RobotState)
        if self.kin is None or self.kin.arm.name != state.arm:
            self.kin = ArmKinematics(load_arm(state.arm))
            self.arms.add(state.arm)
        linear = self.kin.ee_speed(state.q, state.dq)
        limits = state.limits
        joint_ratio = float(np.max(np.abs(state.dq) / np.asarray(limits.joint_speed_rps))) if limits else 0.0
        applied = state.applied_command
        record = StateRecord(state.header.stamp_ns, time.time_ns(), linear, joint_ratio,
                             limits.linear_speed_mps if limits else self.kin.arm.max_linear_speed_mps,
                             applied.stamp_ns if applied else 0)
        with self.lock:
            self.judge.state(record)
            self.state_heard_ns = record.heard_ns

    def _on_status(self, sample) -> None:
        self.statuses.append(m.decode(sample.payload.to_bytes(), m.ControllerStatus))
        del self.statuses[:-100]
        self.status_heard_ns = time.time_ns()

    def _on_safety(self, sample) -> None:
        self.safety_states.append(m.decode(sample.payload.to_bytes(), m.SafetyStatus).state)
        del self.safety_states[:-100]
        self.safety_heard_ns = time.time_ns()

    def in_service(self) -> bool:
        """The loop runs again: robot states and the controller's iterations heard just now, the controller
        servoing (converging or converged), safety passing commands (not refusing, no e-stop)."""
        now = time.time_ns()
        return (now - self.state_heard_ns < 0.3e9 and now - self.status_heard_ns < 0.5e9
                and now - self.safety_heard_ns < 0.5e9
                and bool(self.statuses) and self.statuses[-1].status in SERVOING
                and bool(self.safety_states) and self.safety_states[-1] in PASSING)

    def _on_command(self, sample) -> None:
        with self.lock:
            self.commands.append((time.time_ns(), sample.payload.to_bytes()))
            del self.commands[:-300]  # the last 3 s

    # ------------------------------------------------------------------ tasks
    def task_state(self) -> m.TaskState | None:
        try:
            return call_task(self.operator, self.keys, m.GET_TASK, timeout_s=2.0).state
        except TaskUnavailable:
            return None

    def next_task(self) -> None:
        """Stop what runs, give vision a new goal, start a task toward it."""
        features, depth = goal_features(self.rng)
        try:
            call_task(self.operator, self.keys, m.STOP_TASK, m.TaskRequest(operator="soak", reason="next task"), 2.0)
        except TaskUnavailable:
            return
        goal = m.VisionGoal(header=m.Header(stamp_ns=time.time_ns()), features=features, depth_m=depth)
        for _ in self.operator.get(self.keys.vision_api("set_goal"), payload=m.encode(goal), timeout=2.0):
            pass
        self.statuses.clear()
        try:
            if call_task(self.operator, self.keys, m.START_TASK,
                         m.TaskRequest(operator="soak", reason="soak task"), 2.0).ok:
                self.tasks_started += 1
        except TaskUnavailable:
            pass

    def converged(self) -> bool:
        return any(s.status is m.ControllerState.CONVERGED for s in self.statuses[-5:])

    def tend_tasks(self, task_started: float) -> float:
        """Keep a task running: the next one once this one converged or ran TASK_S, or when the controller came
        back idle (a restarted controller); returns when the current task started."""
        now = time.monotonic()
        converged = self.converged()
        if converged:
            self.tasks_converged += 1
        if converged or now - task_started > TASK_S or self.task_state() is m.TaskState.IDLE:
            self.next_task()
            return time.monotonic()
        return task_started

    # ------------------------------------------------------------------ faults
    def inject(self) -> str:
        kind = self.rng.choices(list(self.kinds), weights=list(self.kinds.values()))[0]
        detail = getattr(self, f"_fault_{kind}")()
        name = f"{kind}:{detail}" if detail else kind
        self.faults[kind] = self.faults.get(kind, 0) + 1
        return name

    def _rest_window(self, why: str) -> Window:
        window = Window(why, time.time_ns())
        with self.lock:
            self.judge.rest_windows.append(window)
        return window

    def _fault_kill(self) -> str:
        victim = self.rng.choice(PIPELINE)
        window = self._rest_window(f"{victim} killed")
        os.kill(self.placement.pid(victim), signal.SIGKILL)
        time.sleep(self.rng.uniform(0.5, 2.0))
        window.end_ns = time.time_ns()
        self.placement.restart(victim)
        return victim

    def _fault_stop(self) -> str:
        victim = self.rng.choice(PIPELINE)
        pid = self.placement.pid(victim)
        window = self._rest_window(f"{victim} stopped")
        os.kill(pid, signal.SIGSTOP)
        time.sleep(self.rng.uniform(0.3, 1.5))
        window.end_ns = time.time_ns()
        os.kill(pid, signal.SIGCONT)
        return victim

    def _fault_router(self) -> str:
        window = self._rest_window("the router killed")
        os.kill(self.placement.pid("router"), signal.SIGKILL)
        time.sleep(self.rng.uniform(1.0, 2.0))
        window.end_ns = time.time_ns()
        self.placement.restart("router")
        return ""

    def _fault_cable(self) -> str:
        host = self.rng.choice(self.placement.cable_hosts)
        window = self._rest_window(f"{host}'s cable pulled")
        self.placement.cable(host, plugged=False)
        time.sleep(self.rng.uniform(0.5, 3.0))
        window.end_ns = time.time_ns()
        self.placement.cable(host, plugged=True)
        return host

    def _outputs(self) -> list[tuple[str, str]]:
        """(publishing service, key) of the control path's outputs."""
        k = self.keys
        return [("robot_sim", k.camera_image), ("vision", k.features), ("controller", k.desired_twist),
                ("safety", k.robot_command), ("robot_sim", k.robot_state)]

    def _link_fault(self, fault: dict, cut: bool) -> str:
        service, key = self.rng.choice(self._outputs())
        plan = self.run_dir / "faults" / f"{service}.yaml"
        window = self._rest_window(f"{last_chunk(key)} dropped") if cut else None
        write_fault_plan(plan, [{"key": key, **fault}], seed=self.rng.randrange(1 << 30))
        time.sleep(self.rng.uniform(0.5, 2.5))
        if window is not None:
            window.end_ns = time.time_ns()
        plan.unlink()
        return key.split("/", 2)[-1]

    def _fault_drop(self) -> str:
        share = self.rng.choice([0.3, 1.0])
        return f"{share:g} {self._link_fault({'drop': share}, cut=share == 1.0)}"

    def _fault_delay(self) -> str:
        delay = round(self.rng.uniform(50, 500))
        return f"{delay} ms {self._link_fault({'delay_ms': float(delay)}, cut=False)}"

    def _send_as(self, identity: str, key: str, payloads: list[bytes]) -> None:
        session = self.session_as(identity)
        try:
            publisher = session.declare_publisher(key)
            time.sleep(0.2)  # the declaration reaches the router
            for payload in payloads:
                publisher.put(payload)
                time.sleep(0.01)
        finally:
            session.close()

    def _fault_replay(self) -> str:
        age = self.rng.uniform(0.3, 2.0)
        with self.lock:
            old = [p for heard, p in self.commands if heard < time.time_ns() - age * 1e9][-20:]
        if not old:
            return "nothing recorded yet"
        restamp = self.rng.random() < 0.5
        if restamp:  # a captured command made fresh: only its sequence number gives it away
            commands = [m.decode(p, m.RobotCommand) for p in old]
            now = time.time_ns()
            for i, command in enumerate(commands):
                command.header.stamp_ns = now + i
            with self.lock:
                self.judge.injected_stamps.update(c.header.stamp_ns for c in commands)
            old = [m.encode(c) for c in commands]
        self._send_as("safety", self.keys.robot_command, old)
        return "restamped" if restamp else "as captured"

    def _fast_command(self, seq: int) -> m.RobotCommand:
        stamp = time.time_ns()
        with self.lock:
            self.judge.injected_stamps.add(stamp)
        twist = m.Twist(header=m.Header(seq=seq, stamp_ns=stamp), frame=Frame.MIXED,
                        angular=AngularConvention.SEED000, linear=(0.5, 0.0, 0.0), rotational=(0.0, 0.0, 0.0))
        return m.RobotCommand(header=m.Header(seq=seq, stamp_ns=stamp, trace=[m.Hop(service="safety",
                              recv_ns=stamp, pub_ns=stamp)]), mode=m.CommandMode.CARTESIAN_VELOCITY, twist=twist)

    def _fault_forge(self) -> str:
        identity = self.rng.choice(["vision", "controller", "operator"])
        self._send_as(identity, self.keys.robot_command,
                      [m.encode(self._fast_command(10**9 + i)) for i in range(20)])
        return identity

    def _fault_wildcard(self) -> str:
        identity = self.rng.choice(["safety", "controller"])
        self._send_as(identity, f"{self.keys.prefix}/robot/*",
                      [m.encode(self._fast_command(2 * 10**9 + i)) for i in range(20)])
        return identity

    def _estop(self, reset: bool) -> bool:
        session = self.session_as("operator")
        try:
            publisher = session.declare_publisher(self.keys.estop)
            message = m.EStop(header=m.Header(stamp_ns=time.time_ns()), reset=reset, operator="soak")
            deadline = time.monotonic() + 10.0
            while time.monotonic() < deadline:
                publisher.put(m.encode(message))  # until safety says so, as `mfvs estop` does
                time.sleep(0.1)
                if self.safety_states and (self.safety_states[-1] is m.SafetyState.ESTOP) != reset:
                    return True
            return False
        finally:
            session.close()

    def _fault_estop(self) -> str:
        window = self._rest_window("the e-stop")
        confirmed = self._estop(reset=False)
        time.sleep(self.rng.uniform(1.0, 2.0))
        window.end_ns = time.time_ns()
        if not self._estop(reset=True):
            raise RuntimeError("the e-stop could not be reset")
        return "confirmed" if confirmed else "not confirmed"

    # ------------------------------------------------------------------ recovery
    def recover(self, names: set[str]) -> float | None:
        """Seconds until every service is alive and the loop is in service again (:meth:`in_service`), None when
        that does not happen within RECOVERY_S."""
        start = time.monotonic()
        task_started = start
        while time.monotonic() - start < RECOVERY_S:
            try:
                alive = names <= set(alive_services(self.operator, self.keys, 1.0))
            except Exception:
                alive = False
            if alive:
                task_started = self.tend_tasks(task_started)
                if self.in_service():
                    return time.monotonic() - start
            time.sleep(0.2)
        return None

    def close(self) -> None:
        self.operator.close()


def soak_profile(port: int, deployment, faults_dir: Path, arm: str = DEFAULT_ARM):
    """The sim profile on ``arm`` behind the authority router, each service reading its fault plan from
    ``faults_dir``."""
    profile = behind_authority(with_arm(load_profile("sim", port), arm), deployment)
    for service in profile.services:
        service.set.append(f"faults_file={faults_dir / f'{service.name}.yaml'}")
    return profile


def applicable_kinds(placement) -> list[str]:
    """Every fault kind the placement can inject (a cable needs computers of its own)."""
    return [k for k in KIND_WEIGHTS if placement.cable_hosts or k not in ACROSS_HOSTS_KINDS]


def check_kinds(kinds: list[str] | None, hosts: bool) -> None:
    unknown = sorted(set(kinds or []) - set(KIND_WEIGHTS))
    if unknown:
        raise ValueError(f"unknown fault kinds {unknown}: {', '.join(KIND_WEIGHTS)}")
    if not hosts and set(kinds or []) & set(ACROSS_HOSTS_KINDS):
        raise ValueError(f"{', '.join(ACROSS_HOSTS_KINDS)} faults need computers of their own: --hosts")


def campaign(soak: Soak, names: set[str], minutes: float, progress=None) -> dict:
    """Faults one after another for ``minutes``, each followed by its recovery and a quiet spell with tasks
    tended; the result (what ``mfvs bench soak --json`` prints)."""
    try:
        start = time.monotonic()
        deadline = start + minutes * 60.0
        soak.next_task()
        recoveries: list[float] = []
        log: list[dict] = []
        next_report = start + 60.0
        while time.monotonic() < deadline:
            fault = soak.inject()
            took = soak.recover(names)
            log.append({"at_s": round(time.monotonic() - start, 1), "fault": fault,
                        "recovery_s": None if took is None else round(took, 2),
                        "controller": soak.statuses[-1].status.value if soak.statuses else None,
                        "safety": soak.safety_states[-1].value if soak.safety_states else None})
            if took is None:
                soak.unrecovered.append(fault)
            else:
                soak.recovered += 1
                recoveries.append(took)
            quiet_until = time.monotonic() + soak.rng.uniform(0.5, 1.5)
            task_started = time.monotonic()
            while time.monotonic() < min(quiet_until, deadline):
                task_started = soak.tend_tasks(task_started)
                time.sleep(0.2)
            if progress is not None and time.monotonic() >= next_report:
                next_report += 60.0
                with soak.lock:
                    unsafe = len(soak.judge.verdict()["unsafe_events"])
                progress(f"{(time.monotonic() - start) / 60:.0f} min: {sum(soak.faults.values())} faults, "
                         f"{soak.tasks_started} tasks, {unsafe} unsafe events")
        time.sleep(1.0)  # the last states
        with soak.lock:
            verdict = soak.judge.verdict()
    finally:
        soak.close()
    return {
        "tasks": {"started": soak.tasks_started, "converged": soak.tasks_converged},
        "faults": dict(sorted(soak.faults.items())), "faults_total": sum(soak.faults.values()),
        "recoveries": soak.recovered, "unrecovered": soak.unrecovered,
        "recovery_s": {"p50": round(float(np.percentile(recoveries, 50)), 2) if recoveries else None,
                       "max": round(max(recoveries), 2) if recoveries else None},
        "unsafe_events": len(verdict["unsafe_events"]), "unsafe": verdict["unsafe_events"][:20],
        "lost_state_events": verdict["lost_state_events"], "lost_state_longest_s": verdict["lost_state_longest_s"],
        "states": verdict["states"], "max_linear_mps": verdict["max_linear_mps"], "log": log,
        "declared_arms": sorted(soak.arms),
    }


def run(minutes: float = 10.0, seed: int = 1, overrides: list[str] | None = None, kinds: list[str] | None = None,
        progress=None, arm: str = DEFAULT_ARM) -> dict:
    """The soak on this computer."""
    check_kinds(kinds, hosts=False)
    with tempfile.TemporaryDirectory(prefix="mfvs-soak-") as directory:
        run_dir = Path(directory)
        (run_dir / "faults").mkdir()
        port = free_loopback_port()
        deployment = write_deployment(run_dir / "authority", port=port,
                                      services=IDENTITIES)
        profile = with_overrides(soak_profile(port, deployment, run_dir / "faults", arm), overrides or [])
        names = {s.name for s in profile.services}
        with servoing_stack(profile, "bench soak") as endpoint:
            soak = Soak(endpoint, deployment, run_dir, seed, Keys(profile.robot_id), kinds)
            result = campaign(soak, names, minutes, progress)
    return {"minutes": minutes, "seed": seed, "hosts": False, "arm": measured_arm(arm, result["declared_arms"]),
            **result}


def hosts_profile(path: Path, lab: netns.Lab, deployment, faults_dir: Path, overrides: list[str],
                  arm: str = DEFAULT_ARM) -> dict:
    """The shipped multi-host profile as a lab fills it in (the robot computer's address, access control), on
    ``arm``, each service reading its fault plan from ``faults_dir``, written to ``path``; which computer runs each
    process."""
    profile = yaml.safe_load((DEPLOY / "profiles" / "multi-host.yaml").read_text())
    profile["router"].update(address=lab.address("robot"), config=str(deployment.router_config))
    for service in profile["services"]:
        service["zenoh_config"] = str(deployment.client_configs[service["name"]])
        service["set"] = [f"faults_file={faults_dir / (service['name'] + '.yaml')}"] + [
            o.partition(":")[2] for o in overrides if o.partition(":")[0] == service["name"]]
    unknown = {o.partition(":")[0] for o in overrides} - {s["name"] for s in profile["services"]}
    if unknown:
        raise ValueError(f"--set: no service called {', '.join(sorted(unknown))} in the multi-host profile")
    filled = with_arm(msgspec.convert(profile, Profile), arm)
    path.write_text(yaml.safe_dump(msgspec.to_builtins(filled)))
    return {"router": filled.router.host, **{s.name: s.host for s in filled.services}}


def run_across_hosts(minutes: float = 10.0, seed: int = 1, overrides: list[str] | None = None,
                     kinds: list[str] | None = None, progress=None, arm: str = DEFAULT_ARM) -> dict:
    """The soak with the stack across three computers (network namespaces), watched from the robot's."""
    check_kinds(kinds, hosts=True)
    why = netns.unavailable()
    if why:
        raise RuntimeError(f"--hosts needs network namespaces: {why}")
    with tempfile.TemporaryDirectory(prefix="mfvs-soak-hosts-") as directory, netns.Lab(list(HOSTS)) as lab:
        run_dir = Path(directory)
        (run_dir / "faults").mkdir()
        deployment = write_deployment(run_dir / "authority", host=lab.address("robot"), port=7447,
                                      services=IDENTITIES)
        profile_file = run_dir / "multi-host.yaml"
        hosts_of = hosts_profile(profile_file, lab, deployment, run_dir / "faults", overrides or [], arm)
        run_dirs = {host: run_dir / host for host in HOSTS}  # the router's computer first
        with netns.stack_across(lab, profile_file, run_dirs, deployment.endpoint):
            spec = {"endpoint": deployment.endpoint, "router_config": str(deployment.router_config),
                    "client_configs": {k: str(v) for k, v in deployment.client_configs.items()},
                    "run_dir": str(run_dir), "run_dirs": {h: str(d) for h, d in run_dirs.items()},
                    "hosts_of": hosts_of, "lab": {"hosts": lab.hosts, "net": lab.net, "tag": lab.tag},
                    "seed": seed, "minutes": minutes, "kinds": kinds, "arm": arm}
            (run_dir / "spec.json").write_text(json.dumps(spec))
            # the soak watches from the robot's computer: its states are heard whatever happens to other cables
            inside = subprocess.run(lab.command("robot", [sys.executable, "-m", "bench.soak", "--inside",
                                                          str(run_dir / "spec.json")]),
                                    stdout=subprocess.PIPE, text=True, cwd=REPO,
                                    timeout=minutes * 60 + 600)
            if inside.returncode not in (0, 1) or not inside.stdout.strip():
                raise RuntimeError(f"the soak on the robot's computer failed (exit {inside.returncode})")
            result = json.loads(inside.stdout.strip().splitlines()[-1])
    return result


def run_inside(spec_file: str, progress=None) -> dict:
    """The campaign of a ``--hosts`` soak, on the robot's computer (``run_across_hosts`` starts it there)."""
    spec = json.loads(Path(spec_file).read_text())
    lab = netns.Lab(**spec["lab"])  # the lab exists: only its cables are used
    deployment = Deployment(Path(spec["router_config"]), {k: Path(v) for k, v in spec["client_configs"].items()},
                            spec["endpoint"], tls=False)
    placement = AcrossHosts(lab, {h: Path(d) for h, d in spec["run_dirs"].items()}, spec["hosts_of"])
    soak = Soak(spec["endpoint"], deployment, Path(spec["run_dir"]), spec["seed"], Keys(), spec["kinds"], placement)
    names = {name for name in spec["hosts_of"] if name != "router"}
    result = campaign(soak, names, spec["minutes"], progress)
    return {"minutes": spec["minutes"], "seed": spec["seed"], "hosts": True,
            "arm": measured_arm(spec["arm"], result["declared_arms"]), **result}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="mfvs bench soak", description=__doc__.split("\n\n")[0])
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--minutes", type=float, default=10.0, help="how long to run (default 10)")
    parser.add_argument("--seed", type=int, default=1, help="the faults' random draws")
    parser.add_argument("--set", action="append", default=[], metavar="SERVICE:KEY=VALUE",
                        help="a service's config override (repeatable), e.g. robot_sim:admission.max_age_s=10 to "
                        "see that the soak catches a robot that admits stale commands")
    parser.add_argument("--kinds", default=None,
                        help=f"the fault kinds to draw from, comma-separated (default all that apply: "
                        f"{','.join(KIND_WEIGHTS)}; {','.join(ACROSS_HOSTS_KINDS)} with --hosts only)")
    parser.add_argument("--hosts", action="store_true",
                        help="the stack across three computers (network namespaces, root only), cables pulled too")
    parser.add_argument("--inside", metavar="SPEC", help=argparse.SUPPRESS)  # run_across_hosts' own campaign
    add_arm_option(parser)
    args = parser.parse_args(argv)
    if unknown_arm(parser, args):
        return 2
    progress = lambda line: print(line, file=sys.stderr, flush=True)  # noqa: E731
    if args.inside:
        result = run_inside(args.inside, progress)
        print(json.dumps(result))
        return 0 if result["unsafe_events"] == 0 else 1
    kinds = [k.strip() for k in args.kinds.split(",") if k.strip()] if args.kinds is not None else None
    try:
        if kinds is not None and not kinds:
            raise ValueError("--kinds: name at least one")
        check_kinds(kinds, args.hosts)
    except ValueError as exc:
        parser.error(str(exc))
    result = (run_across_hosts if args.hosts else run)(args.minutes, args.seed, args.set, kinds, progress, args.arm)
    if args.json:
        print(json.dumps(result))
        return 0 if result["unsafe_events"] == 0 else 1
    where = "across three computers" if result["hosts"] else "on one computer"
    print(f"{result['minutes']:g} min {where} on the {result['arm']}, seed {result['seed']}: {result['tasks']['started']} tasks "
          f"({result['tasks']['converged']} converged), {result['faults_total']} faults "
          f"({', '.join(f'{k} {v}' for k, v in result['faults'].items())})")
    print(f"recovered {result['recoveries']} (p50 {result['recovery_s']['p50']} s, max {result['recovery_s']['max']} s)"
          f", not recovered {len(result['unrecovered'])} {result['unrecovered'][:5]}")
    print(f"unsafe events {result['unsafe_events']}; lost-state events {result['lost_state_events']} (longest "
          f"{result['lost_state_longest_s']} s); {result['states']} states, fastest {result['max_linear_mps']} m/s")
    for event in result["unsafe"]:
        print(f"  UNSAFE {event['rule']}: {event['detail']}")
    return 0 if result["unsafe_events"] == 0 else 1


if __name__ == "__main__":
    raise SystemExit(main())
