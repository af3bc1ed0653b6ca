"""The torque controller as a process: a zenoh client of the robot's low-level API (``robot/lowlevel/state`` in,
``robot/lowlevel/command`` out) as a real client would be, running one of the JACO thesis's controllers
(:mod:`services.controller.torque_controllers`) for one run (:mod:`services.torque_controller.core`), then exiting.

It takes the robot's arm from its states (the same description, by name and fingerprint; one it was not started
for is refused), reads X0 from the arm's own Cartesian report (``GetCartesianPosition``, as the thesis read X0 from
its arm), makes the torque-mode setup of the thesis's Table 5.1 through the arm's Kinova API
(:func:`services.robot.torque_setup.table_5_1`: safety factor 1, vibration controller 1, damping 0, gravity OPTIMAL
with every optimal-Z parameter 0 so the arm adds no gravity, actuator gain 0) before its first torque, and answers
each low-level state with a :class:`~protocol.messages.TorqueCommand` (its own sequence numbers and stamps, the
controller's whole torque, its ĝ(q) included: ``gravity_compensation: false``, which says so; with the arm's
gravity off the robot adds none either way). The subscriber keeps
only the newest state; a worker thread answers it, so a late host skips states (counted) instead of answering old
ones. At the end it asks the robot for its own counters (``lowlevel.watchdog``, late and missed cycles) and writes
the run's log.
"""
from __future__ import annotations

import enum
import itertools
import threading
import time
from pathlib import Path
from typing import Optional

import msgspec
import numpy as np

from protocol import kinova
from protocol.messages import LowLevelState, ProtocolError, RobotState, TorqueCommand, decode, encode
from services.controller.torque_controllers import (CONTROLLERS, TASK_CONTROLLERS, ControllerOptions,
                                                    make_controller)
from services.model.arm import ArmError, check_arm_name, declared_arm
from protocol.keys import ROBOT_SERVICES
from services.robot.torque_setup import table_5_1
from services.runtime.service import Service, ServiceConfig, query_health
from services.runtime.threads import start_thread
from services.torque_controller.core import TorqueRun
from services.runtime.ports import Port, Ports

#: the robot's counters are read this long before the run ends, while commands still flow: after its last command
#: the robot counts a watchdog cycle every 2 ms until it releases torque control (250 ms), which is the end of the
#: run, not a missed cycle
COUNTERS_BEFORE_END_S = 0.1
#: the robot's counters a run reports (their growth during the run)
ROBOT_COUNTERS = ("lowlevel.watchdog", "lowlevel.safety_stops", "refused.lowlevel_after_safety_stop",
                  "torque.limited_ms", "cycles.late", "cycles.missed", "cycles.arm_missed", "dsp.overruns",
                  "rejected.lowlevel_command", "refused.lowlevel_sequence", "refused.lowlevel_stale",
                  "refused.joint_count")
#: the thesis's calibration, which the runs leave out (the log says so)
CALIBRATION_NOT_APPLIED = {
    "SetTorqueZero": "the controllers read no torque sensor (their laws use q and q̇ only), and the thesis zeroed "
                     "the sensors at [*, 180, 180, 0, 0, 180]° where gravity loads no joint, a pose away from the "
                     "runs' start; over RS-485 the call does not exist",
    "SetJointZero": "the emulated position sensors never slip (the thesis re-zeroed after sudden stops); the "
                    "emulated arm refuses it",
}


class TorqueControllerConfig(ServiceConfig):
    #: the arm the controller is for (its description); null: the robot's, whichever it declares
    arm: Optional[str] = None
    #: one of services.controller.torque_controllers.CONTROLLERS
    controller: str = ""
    options: ControllerOptions = msgspec.field(default_factory=ControllerOptions)
    #: make the thesis's Table 5.1 torque-mode setup through the Kinova API before the first torque (false: the
    #: arm's setup as it is, its defaults unless someone changed them)
    table_5_1: bool = True
    #: how long the run lasts (s); null: the controller's reference and ``hold_s`` after it
    duration_s: Optional[float] = None
    hold_s: float = 4.0
    #: where the run's log goes (.npz); null: nowhere
    log: Optional[str] = None
    #: SCHED_FIFO priority where the OS grants it: between the router's (30) and the robot's loop (40)
    realtime_priority: int = 35
    #: how long to wait for the robot (its arm and its first low-level state), and for a state during the run
    robot_timeout_s: float = 15.0
    stall_s: float = 1.0

    def __post_init__(self) -> None:
        if self.controller not in CONTROLLERS:
            raise ValueError(f"unknown controller {self.controller!r}; known: {', '.join(CONTROLLERS)}")
        if self.arm is not None:
            try:
                check_arm_name(self.arm)
            except ArmError as exc:
                raise ValueError(str(exc)) from None
        if self.duration_s is not None and not self.duration_s > 0:
            raise ValueError("duration_s must be positive")
        if not (self.hold_s >= 0 and self.robot_timeout_s > 0 and self.stall_s > 0):
            raise ValueError("hold_s must be >= 0, robot_timeout_s and stall_s positive")
        if not 0 <= self.realtime_priority <= 99:
            raise ValueError("realtime_priority must be within 0..99 (SCHED_FIFO)")


class TorqueControllerService(Service):
    name = "torque_controller"
    PORTS = Ports(consumes=(Port("robot_state", RobotState), Port("lowlevel_state", LowLevelState)),
                  produces=(Port("lowlevel_command", TorqueCommand),))
    follows_sim_clock = False

    def __init__(self, config: TorqueControllerConfig, **kw) -> None:
        super().__init__(config, **kw)
        self.config: TorqueControllerConfig = config
        self.run_: Optional[TorqueRun] = None
        #: why the run failed before or while it ran ('' when it completed)
        self.failure = ""
        self.finished = threading.Event()
        self._cond = threading.Condition()
        #: the newest state not yet taken, and when it arrived (wall ns)
        self._pending: Optional[tuple[LowLevelState, int]] = None
        self._robot_state: Optional[RobotState] = None
        self._worker: Optional[threading.Thread] = None
        self._robot_before: dict = {}
        self._robot_after: Optional[dict] = None
        self._counters_thread: Optional[threading.Thread] = None
        #: the torque-mode setup this run made (the Kinova API's answer to each call), for the log
        self.torque_setup: dict = {}

    # ------------------------------------------------------------------ lifecycle
    def on_start(self) -> None:
        keys = self.keys
        # the robot refuses a sequence number not above this sender's last; it starts our numbering afresh when it
        # sees our new session, but commands may reach it first: start above any earlier run's numbers
        self._seq["lowlevel_command"] = itertools.count(time.time_ns() // 1000)
        self.command_pub = self.publisher(keys.lowlevel_command, "lowlevel_command")
        self.subscribe(keys.robot_state, RobotState, self._on_robot_state, "robot_state")
        self.subscribe(keys.lowlevel_state, LowLevelState, self._on_state, "lowlevel_state")
        self._worker = start_thread(self._work, f"{self.name}-worker")

    def on_stop(self) -> None:
        with self._cond:
            self._cond.notify_all()
        if self._worker is not None and self._worker is not threading.current_thread():
            self._worker.join(timeout=5.0)

    def run(self) -> int:
        super().run()
        return 0 if self.finished.is_set() and not self.failure else 1

    def check_health(self) -> tuple[bool, str]:
        run = self.run_
        if run is None:
            return not self.failure, self.failure or "waiting for the robot"
        timing = run.timing.summary()
        return not self.failure, (f"{self.config.controller} on the {run.arm.name}: answered {timing['answered']}, "
                                  f"missed {timing['missed']} (late {timing['late']}, superseded "
                                  f"{timing['superseded']}, unseen {timing['unseen']})" +
                                  (f"; {self.failure}" if self.failure else ""))

    # ------------------------------------------------------------------ inputs (zenoh threads)
    def _on_robot_state(self, state: RobotState, _recv_ns: int) -> None:
        with self._cond:
            self._robot_state = state
            self._cond.notify_all()

    def _on_state(self, state: LowLevelState, _recv_ns: int) -> None:
        arrival_ns = time.time_ns()
        run = self.run_
        if run is not None and not run.fits(state):
            self.counters.inc("refused.joint_count")
            self.refuse("lowlevel_state", f"{len(state.q)} joints for the {run.arm.name}'s {run.arm.n_joints}")
            return
        with self._cond:
            if run is not None and run.start is not None and not run.finished:
                run.timing.received_state(state.header.stamp_ns, arrival_ns, state.cycle_ns)
                if self._pending is not None:
                    run.timing.superseded += 1  # never answered: a newer state came first
            self._pending = (state, arrival_ns)
            self._cond.notify_all()

    # ------------------------------------------------------------------ the run (worker thread)
    def _wait(self, what: str, ready, timeout_s: float):
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while not self.stop_requested:
                value = ready()
                if value is not None:
                    return value
                left = deadline - time.monotonic()
                if left <= 0:
                    raise TimeoutError(f"no {what} within {timeout_s:g} s")
                self._cond.wait(min(left, 0.2))
        raise InterruptedError("stopped")

    def _work(self) -> None:
        try:
            self._prepare_and_run()
        except InterruptedError:
            self.failure = self.failure or "stopped before the run ended"
        except Exception as exc:  # the run cannot go on: say why, write what there is
            self.failure = str(exc) or type(exc).__name__
            self.log.error("%s: %s", self.name, self.failure)
            self.log.debug("run failure", exc_info=True)
        finally:
            self._finish()

    def _prepare_and_run(self) -> None:
        cfg = self.config
        robot = self._wait("robot state", lambda: self._robot_state, cfg.robot_timeout_s)
        arm, why = declared_arm(robot.arm, robot.arm_digest, len(robot.q), cfg.arm, None)
        if arm is None:
            self.counters.inc("refused.wrong_arm")
            raise RuntimeError(why)
        controller = make_controller(cfg.controller, arm, cfg.options)
        duration = cfg.duration_s if cfg.duration_s is not None else controller.duration_s + cfg.hold_s
        run = TorqueRun(controller, duration)
        with self._cond:
            self._pending = None
        self.run_ = run
        self._wait("low-level state", lambda: self._pending, cfg.robot_timeout_s)
        x0 = self._cartesian_position() if cfg.controller in TASK_CONTROLLERS else None
        if cfg.table_5_1:
            self._apply_table_5_1()
        self._robot_before = self._robot_counters()
        first, arrival = self._wait("low-level state", self._take_pending, cfg.robot_timeout_s)
        with self._cond:
            start = run.begin(first, x0)
            run.timing.received_state(first.header.stamp_ns, arrival, first.cycle_ns)
        self.log.info("%s on the %s: %s for %.1f s%s", self.name, arm.name, cfg.controller, duration,
                      "" if start.xf is None else f", X0 {np.round(start.x0, 4).tolist()} → Xf "
                                                 f"{np.round(start.xf, 4).tolist()} ({start.target})")
        state = first
        while True:
            tau = run.answer(state)
            if tau is None:
                break
            self.command_pub.put(TorqueCommand(header=self.header("lowlevel_command", source=state.header),
                                               torques=tau.tolist(), gravity_compensation=False))
            run.sent(state, arrival, time.time_ns())
            if self._counters_thread is None and run.elapsed_s(state) >= duration - COUNTERS_BEFORE_END_S:
                self._counters_thread = start_thread(self._read_robot_after, f"{self.name}-counters")
            state, arrival = self._wait("low-level state", self._take_pending, cfg.stall_s)
        if run.abort:
            self.failure = f"gave up: {run.abort}"
        self.finished.set()

    def _take_pending(self) -> Optional[tuple[LowLevelState, int]]:
        pending, self._pending = self._pending, None
        return pending

    def _call_api(self, function: str, argument=None):
        """One Kinova API function on the robot (``robot/api/<function>``); its reply, or why there is none."""
        reply_type = kinova.API_FUNCTIONS[function][1]
        payload = None if argument is None else encode(argument)
        for reply in self.session.get(self.keys.robot_api(function), payload=payload, timeout=5.0):
            if reply.ok is None:
                continue
            try:
                answer = decode(reply.ok.payload.to_bytes(), reply_type)
            except ProtocolError as exc:
                raise RuntimeError(f"{function}: {exc}") from None
            if answer.code != kinova.ErrorCode.NO_ERROR_KINOVA:
                raise RuntimeError(f"{function} refused (code {answer.code}): {answer.message}")
            return answer
        raise RuntimeError(f"the robot did not answer {function}")

    def _cartesian_position(self) -> np.ndarray:
        """X0 as the arm reports it (GetCartesianPosition: position and XYZ Euler angles)."""
        c = self._call_api("GetCartesianPosition").result.Coordinates
        return np.array([c.X, c.Y, c.Z, c.ThetaX, c.ThetaY, c.ThetaZ])

    def _apply_table_5_1(self) -> None:
        """The thesis's torque-mode setup, call by call in its order; a refused call ends the run before any torque
        (a controller written for the arm without gravity compensation must not run on one with it)."""
        applied = []
        self.torque_setup = {"table": "JACO thesis Table 5.1", "applied": applied,
                             "not_applied": dict(CALIBRATION_NOT_APPLIED)}
        for function, argument in table_5_1():
            self._call_api(function, argument)
            applied.append({"function": function, "argument": _summary(argument)})
        self.log.info("%s: Table 5.1 applied: %s", self.name,
                      ", ".join(f"{a['function']}({a['argument']})" for a in applied))

    def _robot_counters(self) -> dict:
        """The robot's own counters and loop rate, from its health (the gateway's where there is one: robot_sim
        then only emulates the actuators behind it)."""
        found = query_health(self.session, self.keys, timeout_s=2.0)
        for name in sorted(ROBOT_SERVICES, key=lambda n: n != "robot_gateway"):
            if name in found:
                health = found[name]
                return {"service": name, "errors": dict(health.errors), "rates_hz": dict(health.rates_hz),
                        "detail": health.detail}
        return {}

    def _read_robot_after(self) -> None:
        try:
            self._robot_after = self._robot_counters()
        except Exception:  # the robot may be gone: the run's own log still goes out
            self.log.debug("robot counters", exc_info=True)

    def _finish(self) -> None:
        run = self.run_
        if run is not None and self.session is not None:
            robot = {}
            if self._counters_thread is not None:
                self._counters_thread.join(timeout=5.0)
            elif run.start is not None:  # the run ended early: the counters now
                self._read_robot_after()
            after, before = self._robot_after, self._robot_before
            if after:
                robot = {"service": after["service"], "detail": after["detail"],
                         "bus_cycle_hz": after["rates_hz"].get("bus_cycle"),
                         "counters": {k: after["errors"].get(k, 0) - before.get("errors", {}).get(k, 0)
                                      for k in ROBOT_COUNTERS}}
            if self.config.log:
                run.save(Path(self.config.log), failure=self.failure, robot=robot, torque_setup=self.torque_setup,
                         refused_states=self.counters.get("refused.joint_count"))
            timing = run.timing.summary()
            self.log.info("%s: %s; answered %d states, missed %d (late %d, superseded %d, unseen %d); robot %s",
                          self.name, self.failure or "completed", timing["answered"], timing["missed"],
                          timing["late"], timing["superseded"], timing["unseen"], robot.get("counters"))
        self.request_stop()


def _summary(argument: msgspec.Struct) -> str:
    """A Kinova API argument in a line: an enum by its name, an array of one repeated value as ``n × v``."""
    parts = []
    for key in argument.__struct_fields__:
        value = getattr(argument, key)
        if isinstance(value, enum.Enum):
            value = value.name
        elif isinstance(value, list) and value and all(v == value[0] for v in value):
            value = f"{len(value)} × {value[0]:g}"
        parts.append(f"{key}={value}")
    return ", ".join(parts)
