"""The robot's 500 Hz low-level torque loop (``robot/lowlevel/command`` in, ``robot/lowlevel/state`` out), measured
as a torque client sees it.

A realtime robot runs as deployed, each part a process of its own (:class:`services.stack.RobotProcesses`: robot_sim
alone, or the gateway profile's CAN hub, emulated actuators and robot_gateway), on the arm ``--arm`` names. A client
in this process sends TorqueCommands at 500 Hz (its sending thread at realtime priority where the OS grants it, as
safety's resend loop runs): the joints go to torque mode and the arm holds under the robot's gravity compensation
and the client's light hold about where it found the arm (:data:`HOLD_RPS`). After a warm-up, over ``--seconds``:

* the low-level states heard: their rate; the period between two of them as heard, and its jitter (|period − 2 ms|,
  p50/p99/max: the cycle-to-cycle jitter a client sees); cycles the arm ran without an exchange (gaps in the
  states' own stamps, which are on the arm's timeline); states lost on the way (gaps in their sequence numbers);
  the share of them in torque mode; how far the holding arm drifted;
* the robot's own account (its health): the bus loop's rate, and its wake-up lag and work per cycle over its last
  2500 cycles (5 s: a shorter window shows some of the warm-up too), and its counters over the window: late cycles, missed cycles (the loop did not run them), cycles the arm ran without the loop's
  exchange, failed exchanges, ``lowlevel.watchdog`` (cycles whose newest torque command was older than the
  watchdog, 5 ms: the arm held on its gravity alone), torque safety stops and refused torque commands;
* with the gateway profile, the emulated actuators' own 500 Hz cycle (rate, jitter p99);
* the client: its commands, their rate, the slots it woke too late for (skipped, not sent late in a burst) and its
  send jitter, and ``command_to_state_ms``: from a command's send to the
  arrival of the first state the robot measured at or after it (its stamp). A low-level state does not say which
  torque command it applied (a RobotState does: ``applied_command``), so this is the round trip when the command
  reached the robot before that cycle's step, and a lower bound when it came later.

``python -m bench.lowlevel [--json] [--arm NAME] [--profile sim|gateway] [--seconds S]`` or ``mfvs bench lowlevel``.
"""
from __future__ import annotations

import argparse
import json
import threading
import time

import numpy as np

from bench.latency import stats
from bench.stack import detail_fields, measured_arm, unknown_arm
from protocol import messages as m
from protocol.keys import Keys
from services.cli.options import add_arm_option
from services.model.dynamics import DynamicsModel
from services.model.arm import DEFAULT_ARM, ArmDescription, load_arm
from services.robot.hardware import CYCLE_NS, CYCLE_S
from services.runtime.pacing import normal_priority, request_realtime
from services.robot_sim.service import RobotSimConfig
from services.runtime.service import query_health
from services.runtime.transport import GuardedPublisher, open_session
from services.stack.local import RobotProcesses, RouterProcess

#: which service runs the robot's loop, by profile
ROBOTS = {"sim": "robot_sim", "gateway": "robot_gateway"}
#: the robot's counters reported over the window (their growth)
COUNTERS = ("cycles.late", "cycles.missed", "cycles.arm_missed", "bus.failed_exchanges", "lowlevel.watchdog",
            "lowlevel.safety_stops", "rejected.lowlevel_command")
#: and why torque commands were refused (services.robot.node_inputs: stale, replayed, after a safety stop, ...)
REFUSALS = "refused.lowlevel_"
#: the sending thread's SCHED_FIFO priority: safety's (and bench/command_source.py's), below the robot's loops
CLIENT_PRIORITY = 30
#: before the window: torque mode engaged, the routes warm
WARM_UP_S = 1.0
#: the client's hold about the angles it found (on top of the robot's gravity compensation): critically damped at
#: this natural frequency (rad/s) for each joint's inertia. Behind the gateway the robot's compensation is the
#: description's ĝ(q) (the actuators add none over RS-485), which misses the emulated hand's extra weight: without
#: the hold, zero extra torque lets the arm sag tens of degrees over a run
HOLD_RPS = 20.0


def hold_gains(arm: ArmDescription) -> tuple[np.ndarray, np.ndarray]:
    """The hold's stiffness (N·m/rad) and damping (N·m·s/rad) per joint, from the model's inertia at home."""
    inertia = np.diag(DynamicsModel(arm).mass(arm.home))
    return inertia * HOLD_RPS**2, 2.0 * inertia * HOLD_RPS


class TorqueSender:
    """The hold's torques (:data:`HOLD_RPS`, from the newest state ``latest()`` gives) at 500 Hz, from a thread of
    its own, until stopped; the send times
    (``time.time_ns()``). A slot the thread woke too late for (more than a cycle) is skipped, as the robot's loop
    skips one for a remote arm (the figures count them): a torque for a past cycle is worth nothing, and a burst of
    them would only queue behind each other."""

    def __init__(self, session, keys: Keys, arm: ArmDescription, latest) -> None:
        self.publisher = GuardedPublisher.declare(session, keys.lowlevel_command)
        self.latest = latest
        self.stiffness, self.damping = hold_gains(arm)
        self._hold_q: np.ndarray | None = None
        self.sent_ns: list[int] = []
        # the robot refuses a sequence number not above the sender's last: start above any earlier run's
        self._seq = time.time_ns() // 1000
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="bench-lowlevel-client", daemon=True)

    def start(self) -> "TorqueSender":
        self._thread.start()
        return self

    def _run(self) -> None:
        request_realtime(CLIENT_PRIORITY, "bench lowlevel's client")
        try:
            start = time.monotonic()
            k = 0
            while not self._stop.is_set():
                time.sleep(max(0.0, start + k * CYCLE_S - time.monotonic()))
                k = max(k, int((time.monotonic() - start) / CYCLE_S))  # woke a cycle or more late: this slot
                self._seq += 1
                now = time.time_ns()
                self.publisher.put(m.encode(m.TorqueCommand(header=m.Header(seq=self._seq, stamp_ns=now),
                                                            torques=self._hold_torques().tolist())))
                self.sent_ns.append(now)
                k += 1
        finally:
            normal_priority()

    def _hold_torques(self) -> np.ndarray:
        state = self.latest()
        q, dq = np.asarray(state.q), np.asarray(state.dq)
        if self._hold_q is None:
            self._hold_q = q
        return self.stiffness * (self._hold_q - q) - self.damping * dq

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5.0)
        self.publisher.undeclare()


def _p50_p99(value: str | None) -> dict:
    """A health detail's ``p50/p99`` pair (ms)."""
    try:
        p50, p99 = (float(v) for v in (value or "").split("/"))
    except ValueError:
        return {"p50": None, "p99": None}
    return {"p50": p50, "p99": p99}


def analyse(heard: list[tuple[int, m.LowLevelState]], sent_ns: list[int], window: tuple[int, int]) -> dict:
    """The states heard and the commands sent within ``window`` (``time.time_ns()`` at its start and end), each
    state with the time it was heard; ``heard`` in full, since a command near the window's end is answered after it."""
    begin, end = window
    states = [(t, s) for t, s in heard if begin <= t < end]
    if len(states) < 2:
        raise RuntimeError(f"{len(states)} low-level states heard in the window: is the robot's loop running?")
    times = np.array([t for t, _ in states], dtype=np.int64)
    stamps = np.array([s.header.stamp_ns for _, s in states], dtype=np.int64)
    seqs = np.array([s.header.seq for _, s in states], dtype=np.int64)
    period_ms = np.diff(times) / 1e6
    steps = np.rint(np.diff(stamps) / CYCLE_NS).astype(np.int64)
    q = np.array([s.q for _, s in states])
    window_s = (end - begin) / 1e9
    commands = np.array([t for t in sent_ns if begin <= t < end], dtype=np.int64)
    # each command against the first state measured at or after its send (over every state heard, in stamp order)
    all_stamps = np.array([s.header.stamp_ns for _, s in heard], dtype=np.int64)
    all_times = np.array([t for t, _ in heard], dtype=np.int64)
    order = np.argsort(all_stamps, kind="stable")
    index = np.searchsorted(all_stamps[order], commands)
    answered = index < len(order)
    round_trip_ms = (all_times[order][index[answered]] - commands[answered]) / 1e6
    return {
        "states": {"n": len(states), "rate_hz": round(len(states) / window_s, 1),
                   "period_ms": stats(list(period_ms)),
                   "jitter_ms": stats(list(np.abs(period_ms - CYCLE_S * 1e3))),
                   "arm_cycles_without_exchange": int(np.clip(steps - 1, 0, None).sum()),
                   "lost": int(np.clip(np.diff(seqs) - 1, 0, None).sum()),
                   "torque_mode_share": round(sum(s.mode is m.ActuatorMode.TORQUE for _, s in states) / len(states),
                                              4),
                   "drift_deg_max": round(float(np.degrees(np.abs(q - q[0]).max())), 4)},
        "client": {"commands": len(commands), "slots_skipped": max(0, round(window_s / CYCLE_S) - len(commands)),
                   "rate_hz": round(len(commands) / window_s, 1),
                   "send_jitter_ms": stats(list(np.abs(np.diff(commands) / 1e6 - CYCLE_S * 1e3))),
                   "command_to_state_ms": stats(list(round_trip_ms))},
    }


def robot_figures(before: m.ServiceHealth, after: m.ServiceHealth) -> dict:
    """The robot's own account over the window: its loop's rates and times (at the window's end) and the growth
    of its counters."""
    detail = detail_fields(after.detail)
    return {"bus_rate_hz": round(after.rates_hz.get("bus_cycle", 0.0), 1),
            "lowlevel_state_hz": round(after.rates_hz.get("pub.lowlevel_state", 0.0), 1),
            "wake_lag_ms": _p50_p99(detail.get("wake_lag_ms")), "work_ms": _p50_p99(detail.get("work_ms")),
            "exchange_ms": _p50_p99(detail.get("exchange_ms")),
            "counters": {name: after.errors.get(name, 0) - before.errors.get(name, 0)
                         for name in (*COUNTERS, *sorted(k for k in after.errors if k.startswith(REFUSALS)))}}


def _healths(session, keys: Keys, names: tuple[str, ...]) -> dict[str, m.ServiceHealth]:
    found = query_health(session, keys)
    missing = [name for name in names if name not in found]
    if missing:
        raise RuntimeError(f"{', '.join(missing)} did not answer its health query")
    return found


def run(seconds: float = 10.0, profile: str = "sim", arm: str = DEFAULT_ARM) -> dict:
    """The low-level loop of a realtime robot on ``arm`` (``profile``: sim or gateway) over ``seconds``."""
    if profile not in ROBOTS:
        raise ValueError(f"unknown profile {profile!r}: sim or gateway")
    robot = ROBOTS[profile]
    names = (robot, "robot_sim") if profile == "gateway" else (robot,)
    keys = Keys()
    description = load_arm(arm)
    n_joints = description.n_joints
    with RouterProcess() as router, RobotProcesses(router.client_config(), RobotSimConfig(arm=arm), profile=profile):
        session = open_session(router.client_config())
        heard: list[tuple[int, m.LowLevelState]] = []
        declared: set[str] = set()
        session.declare_subscriber(keys.lowlevel_state, lambda s: heard.append(
            (time.time_ns(), m.decode(s.payload.to_bytes(), m.LowLevelState))))
        session.declare_subscriber(keys.robot_state, lambda s: declared.add(
            m.decode(s.payload.to_bytes(), m.RobotState).arm))
        try:
            deadline = time.monotonic() + 30.0
            while len(heard) < 50 or not declared:
                if time.monotonic() > deadline:
                    raise RuntimeError(f"the robot published {len(heard)} low-level states in 30 s")
                time.sleep(0.05)
            sender = TorqueSender(session, keys, description, lambda: heard[-1][1]).start()
            try:
                time.sleep(WARM_UP_S)
                before = _healths(session, keys, names)
                begin = time.time_ns()
                time.sleep(seconds)
                end = time.time_ns()
                after = _healths(session, keys, names)
                time.sleep(0.1)  # the window's last commands answered
            finally:
                sender.stop()
            snapshot, sent = list(heard), list(sender.sent_ns)
        finally:
            session.close()
    result = {"arm": measured_arm(arm, declared), "joints": n_joints, "profile": profile, "robot": robot,
              "seconds": round((end - begin) / 1e9, 3), **analyse(snapshot, sent, (begin, end)),
              "loop": robot_figures(before[robot], after[robot]), "actuators": None}
    if profile == "gateway":
        actuators = detail_fields(after["robot_sim"].detail)
        result["actuators"] = {"cycle_rate_hz": float(actuators.get("bus_cycle_rate_hz", "nan")),
                               "cycle_jitter_ms_p99": float(actuators.get("jitter_ms_p99", "nan"))}
    return result


def print_result(r: dict) -> None:
    s, loop, client, c = r["states"], r["loop"], r["client"], r["loop"]["counters"]
    print(f"low-level torque loop: the {r['arm']} ({r['joints']} joints), {r['profile']} profile ({r['robot']}), "
          f"{r['seconds']:g} s, a light hold at 500 Hz")
    j = s["jitter_ms"]
    print(f"  states heard {s['rate_hz']}/s (the robot publishes {loop['lowlevel_state_hz']}/s, its bus loop "
          f"{loop['bus_rate_hz']}/s); jitter |period − 2 ms| p50 {j['p50']} ms, p99 {j['p99']} ms, max {j['max']} ms; "
          f"{s['lost']} lost; {s['torque_mode_share']:.1%} in torque mode; drift {s['drift_deg_max']}°")
    print(f"  robot: wake-up lag p50/p99 {loop['wake_lag_ms']['p50']}/{loop['wake_lag_ms']['p99']} ms, work "
          f"{loop['work_ms']['p50']}/{loop['work_ms']['p99']} ms; late {c['cycles.late']}, missed "
          f"{c['cycles.missed']}, the arm without an exchange {c['cycles.arm_missed']} (in the stamps "
          f"{s['arm_cycles_without_exchange']}), failed exchanges {c['bus.failed_exchanges']}, watchdog "
          f"{c['lowlevel.watchdog']}, safety stops {c['lowlevel.safety_stops']}, refused "
          f"{c['rejected.lowlevel_command']}" + "".join(f", {k.removeprefix(REFUSALS)} {v}" for k, v in c.items()
                                                        if k.startswith(REFUSALS) and v))
    if r["actuators"]:
        a = r["actuators"]
        print(f"  actuators (robot_sim): cycle {a['cycle_rate_hz']} Hz, jitter p99 {a['cycle_jitter_ms_p99']} ms")
    t, sj = client["command_to_state_ms"], client["send_jitter_ms"]
    print(f"  client: {client['commands']} commands at {client['rate_hz']}/s ({client['slots_skipped']} slots it woke "
          f"too late for), send jitter p50 {sj['p50']} ms, p99 {sj['p99']} ms; command → first state after it p50 {t['p50']} ms, p99 {t['p99']} ms, max {t['max']} ms")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="mfvs bench lowlevel", description=__doc__.split("\n\n")[0])
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--seconds", type=float, default=10.0, help="measurement window (s; default 10)")
    parser.add_argument("--profile", choices=sorted(ROBOTS), default="sim",
                        help="sim: robot_sim's own loop (default); gateway: robot_gateway over the RS-485 bus hub")
    add_arm_option(parser)
    args = parser.parse_args(argv)
    if unknown_arm(parser, args):
        return 2
    if not args.seconds > 0:
        parser.error("--seconds must be positive")
    result = run(args.seconds, args.profile, args.arm)
    if args.json:
        print(json.dumps(result))
    else:
        print_result(result)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
