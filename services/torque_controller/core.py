"""One controller's run against the low-level API, without zenoh, locks or a clock of its own: the service hands it
each low-level state it takes (with the wall time) and publishes the torque it returns.

* The run starts at the first state it answers: t = 0 is that state's stamp, and the reference is evaluated at each
  state's own stamp (the arm's time), so a late host or transport costs tracking only through the delay of the
  answer, never through a reference that runs ahead.
* It ends ``duration_s`` later (the reference's motion and a hold), or when the controller gives up (an error
  beyond its abort thresholds): then it answers nothing more, and the robot holds the arm (on its gravity alone
  after the 5 ms watchdog, position mode after 250 ms).
* Timing, from the client's side: states received, answered, *late* (answered more than a bus cycle, 2 ms, after
  the state could first have been answered: its stamp plus the smallest stamp-to-arrival delay of the run, which
  is the robot's own pipeline (about 0.3 ms from robot_sim, a bus cycle more through the gateway, whose reading
  is a cycle old when it is published); such an answer missed the cycle it was for, whether the robot, the
  transport or the client was late, and the client's own share, arrival to answer, is reported beside it), *superseded* (a newer state came before this one was
  taken: never answered), *unseen* (cycles whose state never arrived: gaps in the stamps). The missed low-level
  cycles are the sum of the three.
* A state for an arm of another joint count is refused and counted (``refused.joint_count``); nothing is answered.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np

from protocol.messages import ActuatorMode, LowLevelState
from services.controller.torque_controllers import Start, TorqueController
from services.robot.hardware import CYCLE_NS

#: a step longer than this (a stall) is integrated as this long: an integral does not jump for a host's pause
MAX_STEP_S = 0.02


@dataclass
class ClientTiming:
    """The client's side of the low-level loop (see the module's doc)."""

    received: int = 0
    answered: int = 0
    superseded: int = 0
    unseen: int = 0
    refused: int = 0
    latencies_ms: list = field(default_factory=list)
    responses_ms: list = field(default_factory=list)
    arrival_intervals_ms: list = field(default_factory=list)
    stamp_intervals_ms: list = field(default_factory=list)
    first_stamp_ns: int = 0
    last_stamp_ns: int = 0
    #: the robot's bus cycle, one state each (LowLevelState.cycle_ns: the hardware's)
    cycle_ns: int = CYCLE_NS
    _last_arrival_ns: int = 0

    def received_state(self, stamp_ns: int, arrival_ns: int, cycle_ns: int = CYCLE_NS) -> None:
        """A state arrived (in the subscriber's thread, before it may be superseded)."""
        self.received += 1
        self.cycle_ns = cycle_ns
        if self.last_stamp_ns:
            gap = int(round((stamp_ns - self.last_stamp_ns) / cycle_ns)) - 1
            if gap > 0:
                self.unseen += gap
            self.stamp_intervals_ms.append((stamp_ns - self.last_stamp_ns) / 1e6)
            self.arrival_intervals_ms.append((arrival_ns - self._last_arrival_ns) / 1e6)
        else:
            self.first_stamp_ns = stamp_ns
        self.last_stamp_ns, self._last_arrival_ns = max(stamp_ns, self.last_stamp_ns), arrival_ns

    def answered_state(self, stamp_ns: int, arrival_ns: int, sent_ns: int) -> None:
        """A state answered: its latency (stamp to answer: the robot's, the transport's and the client's share) and
        the client's own response (arrival to answer)."""
        self.answered += 1
        self.latencies_ms.append((sent_ns - stamp_ns) / 1e6)
        self.responses_ms.append((sent_ns - arrival_ns) / 1e6)

    @property
    def late(self) -> int:
        if not self.latencies_ms:
            return 0
        latency, response = np.asarray(self.latencies_ms), np.asarray(self.responses_ms)
        pipeline = float(np.min(latency - response))  # the earliest a state of this robot arrives after its stamp
        return int(np.count_nonzero(latency - pipeline > self.cycle_ns / 1e6))

    @property
    def missed(self) -> int:
        return self.late + self.superseded + self.unseen

    def summary(self) -> dict:
        def percentiles(values) -> dict:
            if not values:
                return {"p50": None, "p99": None, "max": None}
            a = np.asarray(values, dtype=float)
            return {"p50": round(float(np.percentile(a, 50)), 3), "p99": round(float(np.percentile(a, 99)), 3),
                    "max": round(float(a.max()), 3)}

        span_s = (self.last_stamp_ns - self.first_stamp_ns) / 1e9
        jitter = [abs(v - self.cycle_ns / 1e6) for v in self.arrival_intervals_ms]
        arrival = [lat - res for lat, res in zip(self.latencies_ms, self.responses_ms)]
        return {"received": self.received, "answered": self.answered, "late": self.late,
                "superseded": self.superseded, "unseen": self.unseen, "missed": self.missed, "refused": self.refused,
                "cycle_rate_hz": round((self.received - 1) / span_s, 1) if span_s > 0 else None,
                "latency_ms": percentiles(self.latencies_ms), "response_ms": percentiles(self.responses_ms),
                "arrival_delay_ms": percentiles(arrival),
                "arrival_jitter_ms": percentiles(jitter),
                "stamp_interval_ms": percentiles(self.stamp_intervals_ms)}


class TorqueRun:
    """A controller's run: :meth:`answer` each state taken, :meth:`sent` once its torque went out."""

    def __init__(self, controller: TorqueController, duration_s: float) -> None:
        self.controller = controller
        self.arm = controller.arm
        self.duration_s = duration_s
        self.limits = self.arm.max_torque.copy()  # each actuator's peak (its data sheet)
        self.timing = ClientTiming()
        self.start: Optional[Start] = None
        self.start_ns: Optional[int] = None
        self.abort = ""
        self.finished = False
        self._last_ns: Optional[int] = None
        #: the faults the robot reported in the states answered (joint limits, torque...), and in how many states
        self.faults: dict[str, int] = {}
        self._rows: dict[str, list] = {k: [] for k in (
            "t", "stamp_ns", "q", "dq", "tau_measured", "tau_command", "torque_mode", "x", "x_d", "q_d",
            "position_error_m", "orientation_error_deg", "joint_error_deg", "latency_ms", "response_ms")}

    def fits(self, state: LowLevelState) -> bool:
        """Whether a state is for this arm (its joint count); one that is not is refused and counted."""
        if len(state.q) == self.arm.n_joints:
            return True
        self.timing.refused += 1
        return False

    def begin(self, state: LowLevelState, x0_reported=None) -> Start:
        """The run starts at this state (the arm's joints) and, for a task controller, the arm's Cartesian report."""
        self.start = self.controller.begin(np.asarray(state.q, dtype=float), x0_reported)
        self.start_ns = state.header.stamp_ns
        return self.start

    def elapsed_s(self, state: LowLevelState) -> float:
        """The run's time at a state (s from the first answered state's stamp)."""
        return 0.0 if self.start_ns is None else (state.header.stamp_ns - self.start_ns) / 1e9

    def answer(self, state: LowLevelState) -> Optional[np.ndarray]:
        """The torque (model sign, N·m, gravity included where the law has it) for this state; None once the run
        is over (its time is up, or the controller gave up)."""
        if self.finished or self.start is None:
            return None
        stamp = state.header.stamp_ns
        t = (stamp - self.start_ns) / 1e9
        if t > self.duration_s:
            self.finished = True
            return None
        dt = state.cycle_ns / 1e9 if self._last_ns is None else min(max((stamp - self._last_ns) / 1e9, 0.0), MAX_STEP_S)
        self._last_ns = stamp
        for fault in state.faults:
            self.faults[fault] = self.faults.get(fault, 0) + 1
        q, dq = np.asarray(state.q, dtype=float), np.asarray(state.dq, dtype=float)
        step = self.controller.step(t, dt, q, dq)
        if step.abort or not np.all(np.isfinite(step.tau)):
            self.abort = step.abort or "the law's torque is not finite"
            self.finished = True
            return None
        rows = self._rows
        n = self.arm.n_joints
        rows["t"].append(t)
        rows["stamp_ns"].append(stamp)
        rows["q"].append(q)
        rows["dq"].append(dq)
        rows["tau_measured"].append(np.asarray(state.tau, dtype=float))
        rows["tau_command"].append(step.tau)
        rows["torque_mode"].append(state.mode is ActuatorMode.TORQUE)
        rows["x"].append(step.x if step.x is not None else np.full(6, np.nan))
        rows["x_d"].append(step.x_d if step.x_d is not None else np.full(6, np.nan))
        rows["q_d"].append(step.q_d if step.q_d is not None else np.full(n, np.nan))
        rows["position_error_m"].append(step.position_error_m)
        rows["orientation_error_deg"].append(step.orientation_error_deg)
        rows["joint_error_deg"].append(step.joint_error_deg)
        return step.tau

    def sent(self, state: LowLevelState, arrival_ns: int, sent_ns: int) -> None:
        """The answer to the last state :meth:`answer` took went out at ``sent_ns`` (it arrived at ``arrival_ns``)."""
        self.timing.answered_state(state.header.stamp_ns, arrival_ns, sent_ns)
        self._rows["latency_ms"].append((sent_ns - state.header.stamp_ns) / 1e6)
        self._rows["response_ms"].append((sent_ns - arrival_ns) / 1e6)

    def arrays(self) -> dict[str, np.ndarray]:
        n = self.arm.n_joints
        shapes = {"q": n, "dq": n, "tau_measured": n, "tau_command": n, "q_d": n, "x": 6, "x_d": 6}
        out = {}
        for key, values in self._rows.items():
            if values:
                out[key] = np.asarray(values)
            else:
                out[key] = np.zeros((0, shapes[key])) if key in shapes else np.zeros(0)
        return out

    def meta(self, **extra) -> dict:
        start = self.start
        return {"controller": self.controller.name, "arm": self.arm.name, "n_joints": self.arm.n_joints,
                "duration_s": self.duration_s, "reference_s": self.controller.duration_s,
                "options": _builtins(self.controller.options),
                "torque_limits_nm": self.limits.tolist(),
                "q0": None if start is None else start.q0.tolist(),
                "x0": None if start is None or start.x0 is None else start.x0.tolist(),
                "xf": None if start is None or start.xf is None else start.xf.tolist(),
                "target": None if start is None else start.target,
                "abort": self.abort, "faults": dict(self.faults), "timing": self.timing.summary(), **extra}

    def save(self, path: Path, **extra) -> Path:
        """The run's log: its arrays and, as JSON under ``meta``, what it was and how its loop kept time."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(path, meta=np.array(json.dumps(self.meta(**extra))), **self.arrays())
        return path


def load_log(path: Path) -> tuple[dict, dict[str, np.ndarray]]:
    """(meta, arrays) of a run's log written by :meth:`TorqueRun.save`."""
    with np.load(Path(path), allow_pickle=False) as data:
        arrays = {k: data[k] for k in data.files if k != "meta"}
        meta = json.loads(str(data["meta"]))
    return meta, arrays


def _builtins(options) -> dict:
    import msgspec

    return msgspec.to_builtins(options)
