"""What every robot service offers on zenoh, whatever drives the arm (robot_sim's physics or robot_gateway's
RS-485 bus): robot commands in, the Kinova API as queryables, robot state out. A mixin for a
:class:`~services.common.service.Service` whose loop thread owns the DSP.

The loop calls :meth:`take_command` (or waits on ``command_cond``), then :meth:`apply_command`, runs the DSP
cycle, and :meth:`publish_state`. API calls arrive on zenoh threads and run in the loop thread through
:meth:`run_api_calls`, so the DSP is never touched concurrently. With :meth:`declare_lowlevel`, the low-level
torque API too: the loop calls :meth:`lowlevel_cycle` and :meth:`publish_lowlevel` every actuator cycle (2 ms).
"""
from __future__ import annotations

import queue
import threading
import time
from concurrent.futures import Future
from typing import Optional

import numpy as np
import zenoh

from protocol import kinova
from protocol.messages import (
    ActuatorMode,
    Header,
    KinovaPose,
    LowLevelState,
    ProtocolError,
    RobotCommand,
    RobotState,
    TorqueCommand,
    decode,
    encode,
)
from services.common import frames
from services.common.dsp import CommandRefused, KinovaDSP
from services.common.kinova_api import KinovaApi, RobotView
from services.common.lowlevel import LowLevelConfig, LowLevelControl, Outcome, TorqueJoints

#: Kinova API functions that move the arm: refused while low-level torque control owns it (they would be queued
#: in the DSP and run, unexpectedly, once torque control ends)
MOTION_FUNCTIONS = frozenset({"SendBasicTrajectory", "MoveHome"})


class RobotFrontEnd:
    """Mixin: requires ``self.keys``, ``self.clock``, ``self.name``, ``self.counters``, ``self.refuse``,
    ``self.header``, ``self.publisher``, ``self.subscribe``, ``self.queryable`` (a Service)."""

    def init_frontend(self, robot: RobotView, dsp: KinovaDSP, api=None) -> None:
        """``api``: what answers ``robot/api/*`` (anything with ``call(function, argument) -> ApiReply``); by
        default the emulated Kinova API on ``robot`` and ``dsp``."""
        self.robot_view = robot
        self.dsp = dsp
        self.api = api if api is not None else KinovaApi(robot, dsp)
        self._command: Optional[tuple[RobotCommand, int]] = None
        self.command_cond = threading.Condition()
        self._api_calls: queue.Queue = queue.Queue()
        self._last_refusal = ""
        self._refusal_cycles = 0
        self.lowlevel: Optional[LowLevelControl] = None
        self._lowlevel_unavailable = ""

    def declare_frontend(self) -> None:
        keys = self.keys
        self.state_pub = self.publisher(keys.robot_state, "state")
        self.subscribe(keys.robot_command, RobotCommand, self._on_command, "command")
        self.queryable(keys.robot_api_all, self._on_api)

    def declare_lowlevel(self, joints: TorqueJoints, config: LowLevelConfig, gravity,
                         unavailable: str = "") -> None:
        """The low-level torque API on ``joints``; ``unavailable``: why torque commands are refused (e.g. a
        lockstep simulation), with the state still published."""
        keys = self.keys
        self.lowlevel = LowLevelControl(config, joints, gravity)
        self._lowlevel_unavailable = unavailable
        self.lowlevel_pub = self.publisher(keys.lowlevel_state, "lowlevel_state")
        self.subscribe(keys.lowlevel_command, TorqueCommand, self._on_torque, "lowlevel_command")

    # ------------------------------------------------------------------ zenoh threads
    def _on_torque(self, command: TorqueCommand, _recv_ns: int) -> None:
        if self._lowlevel_unavailable:
            self.refuse("lowlevel_command", self._lowlevel_unavailable)
            return
        self.lowlevel.receive(command, time.monotonic())

    def _on_command(self, command: RobotCommand, recv_ns: int) -> None:
        with self.command_cond:
            self._command = (command, recv_ns)
            self.command_cond.notify_all()

    def _on_api(self, query: zenoh.Query) -> None:
        function = str(query.key_expr).rsplit("/", 1)[-1]
        spec = kinova.API_FUNCTIONS.get(function)
        if spec is None:
            self.refuse("api", f"unknown Kinova API function {function!r}")
            reply = kinova.ApiReply(code=int(kinova.ErrorCode.ERROR_INVALID_PARAM),
                                    message=f"unknown function {function}")
            query.reply(query.key_expr, encode(reply))
            return
        argument_type, _ = spec
        argument = None
        if argument_type is not None:
            payload = query.payload.to_bytes() if query.payload is not None else b""
            try:
                argument = decode(payload, argument_type)
            except ProtocolError as exc:
                self.refuse("api", str(exc))
                query.reply(query.key_expr, encode(kinova.ApiReply(
                    code=int(kinova.ErrorCode.ERROR_INVALID_PARAM), message=str(exc))))
                return
        future: Future = Future()
        self._api_calls.put((function, argument, future))
        with self.command_cond:
            self.command_cond.notify_all()
        try:
            reply = future.result(timeout=5.0)
        except Exception as exc:  # the loop died or timed out: the caller gets Kinova's unknown error
            reply = kinova.ApiReply(code=int(kinova.ErrorCode.UNKNOWN_ERROR), message=f"not executed: {exc}")
        query.reply(query.key_expr, encode(reply))

    # ------------------------------------------------------------------ the loop thread
    def run_api_calls(self) -> None:
        while True:
            try:
                function, argument, future = self._api_calls.get_nowait()
            except queue.Empty:
                return
            if function in MOTION_FUNCTIONS and self.lowlevel is not None and self.lowlevel.active:
                self.refuse("api", f"{function}: low-level torque control is active")
                future.set_result(kinova.ApiReply(code=int(kinova.ErrorCode.ERROR_INVALID_PARAM),
                                                  message="low-level torque control is active"))
                continue
            try:
                future.set_result(self.api.call(function, argument))
            except Exception as exc:
                self.counters.inc("errors.api")
                future.set_exception(exc)

    def take_command(self) -> Optional[tuple[RobotCommand, int]]:
        with self.command_cond:
            taken, self._command = self._command, None
        return taken

    def peek_command(self) -> Optional[tuple[RobotCommand, int]]:
        return self._command

    def apply_command(self, taken: Optional[tuple[RobotCommand, int]]) -> Optional[Header]:
        """Hand a received command to the DSP; the header (trace + this robot's hop) when it was accepted."""
        self.run_api_calls()
        if taken is None:
            return None
        command, recv_ns = taken
        if self.lowlevel is not None and self.lowlevel.active:
            self.refuse("command", "low-level torque control is active")
            return None
        try:
            self.dsp.submit(command)
        except CommandRefused as exc:
            self.refuse("command", str(exc))
            self.counters.inc("refused.convention")
            self._last_refusal, self._refusal_cycles = str(exc), 100
            return None
        return command.header.with_hop(self.name, recv_ns, self.clock.now_ns())

    def publish_state(self, applied: Optional[Header], extra_faults: tuple = ()) -> None:
        robot, dsp = self.robot_view, self.dsp
        T = robot.ee_pose()
        euler = frames.matrix_to_euler_xyz(T[:3, :3])
        status = dsp.status
        faults = list(status.active_limits) + list(extra_faults)
        if self._refusal_cycles > 0:
            faults.append(f"refused: {self._last_refusal}"[:120])
            self._refusal_cycles -= 1
        q, dq, tau = (np.asarray(v, dtype=float) for v in (robot.q, robot.dq, robot.tau))
        self.state_pub.put(RobotState(
            header=self.header("state"), q=q.tolist(), dq=dq.tolist(), tau=tau.tolist(),
            pose=KinovaPose(X=T[0, 3], Y=T[1, 3], Z=T[2, 3], ThetaX=euler[0], ThetaY=euler[1], ThetaZ=euler[2]),
            control_mode=status.mode, fifo_count=dsp.fifo_count, faults=faults[:32],
            watchdog_tripped=status.watchdog_tripped, angular_convention=dsp.config.angular_convention,
            applied_command=applied,
        ))

    def lowlevel_cycle(self, q: np.ndarray) -> None:
        """One low-level cycle: engage, apply, hold or release torque control (see services.common.lowlevel)."""
        outcome, detail = self.lowlevel.step(time.monotonic(), q)
        if outcome is Outcome.ENGAGED:
            self.dsp.erase_all_trajectories()
            self.log.info("low-level torque control engaged")
        elif outcome is Outcome.RELEASED:
            self.log.info("low-level torque control released %s", detail)
        elif outcome is Outcome.WATCHDOG:
            self.counters.inc("lowlevel.watchdog")
        elif outcome is Outcome.REFUSED:
            self.refuse("lowlevel_command", detail)

    def publish_lowlevel(self, q, dq, tau, current_a, temperature_c, faults=()) -> None:
        self.lowlevel_pub.put(LowLevelState(
            header=self.header("lowlevel_state"),
            mode=ActuatorMode.TORQUE if self.lowlevel.active else ActuatorMode.POSITION,
            q=list(map(float, q)), dq=list(map(float, dq)), tau=list(map(float, tau)),
            current_a=list(map(float, current_a)), temperature_c=list(map(float, temperature_c)),
            faults=list(faults)[:32]))
