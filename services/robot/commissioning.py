"""The commissioning check as the robot node runs it, between the thread that takes the request (zenoh's) and the one
that runs the DSP: no zenoh here; the rules of the check itself are services.robot.arm_check's.

:meth:`Commissioning.request` takes a request (``…/robot/check/arm``) or says why not: unconfirmed (the check moves
the arm), low-level torque control owning the arm, a check already running. A request taken gives a future of the
verdict, and starts at the DSP's next tick (:meth:`Commissioning.command`), which erases the DSP's trajectories. While
the check runs the DSP takes the check's own joint velocities, tick by tick, and holds the commands that come
(counted: ``arm_check.commands_held``); an emergency stop among them ends the check and goes to the DSP. At its end
the samples are judged (:func:`~services.robot.arm_check.analyse`) and the verdict is kept (``arm_check.record``)
and said in every state (:attr:`Commissioning.state`); a check that could not judge (aborted, no samples) leaves the
verdict the arm had.
"""
from __future__ import annotations

import logging
import threading
import time
from concurrent.futures import Future
from typing import Callable, Optional

import msgspec

from protocol.messages import ArmCheckReply, ArmCheckRequest, ArmCheckState, CommandMode, Header, RobotCommand
from services.model.arm import ArmDescription
from services.robot import arm_check
from services.robot.command_inbox import Received
from services.robot.dsp import KinovaDSP
from services.robot.hardware import JointReading
from services.runtime.metrics import Counters


class Commissioning:
    def __init__(self, config: arm_check.ArmCheckConfig, arm: ArmDescription, counters: Counters,
                 log: logging.Logger, header: Callable[..., Header]) -> None:
        """``header(stream, stamp_ns=...)``: a header for the check's own commands (the node's, with its sequence)."""
        self.config = config
        self.arm = arm
        self.counters = counters
        self.log = log
        self._header = header
        #: the verdict on this arm (said in every state), and why
        self.state, self.detail = arm_check.load_verdict(config, arm)
        #: guards the request between the thread that takes it and the DSP's
        self._lock = threading.Lock()
        self._requested: Optional[tuple[ArmCheckRequest, Future]] = None
        self._running: Optional[tuple[arm_check.ArmCheckRun, Future]] = None
        self._verdict_before = (self.state, self.detail)

    def request(self, request: ArmCheckRequest, torque_mode: bool) -> tuple[Optional[Future], str]:
        """A check asked for (``torque_mode``: low-level torque control owns the arm now): its future verdict, or
        why it is refused."""
        if not request.confirm:
            return None, (f"the check moves joints {request.joints} by {request.step_deg}° each, at "
                          f"{request.speed_dps}°/s, and back: confirm that the arm is clear to (mfvs check arm --yes)")
        if torque_mode:
            return None, "low-level torque control owns the arm"
        future: Future = Future()
        with self._lock:
            if self._requested is not None or self._running is not None:
                return None, "a check is already running"
            self._requested = (request, future)
        return future, ""

    def command(self, tick_ns: int, taken: Optional[Received], reading: JointReading,
                dsp: KinovaDSP) -> Optional[Received]:
        """At a DSP tick, on its reading: start a requested check (erasing ``dsp``'s trajectories), or step the one
        running. The command the DSP takes: the check's own while it runs (``taken`` held, an emergency stop ending
        the check), else ``taken``."""
        if self._requested is not None and self._running is None:
            with self._lock:
                (request, future), self._requested = self._requested, None
            plan = arm_check.ArmCheckPlan(joints=tuple(request.joints), step_deg=request.step_deg,
                                          speed_dps=request.speed_dps)
            try:
                run = arm_check.ArmCheckRun(plan, self.arm, reading.q, tick_ns * 1e-9)
            except ValueError as exc:
                future.set_result(ArmCheckReply(ok=False, state=self.state, message=str(exc)))
                return taken
            dsp.erase_all_trajectories()
            with self._lock:
                self._running = (run, future)
            self._verdict_before = (self.state, self.detail)
            self.state = ArmCheckState.RUNNING
        if self._running is None:
            return taken
        run, future = self._running
        if taken is not None and taken[0].mode is CommandMode.EMERGENCY_STOP:
            run.abort("an emergency stop ended the check")
        elif taken is not None:
            self.counters.inc("arm_check.commands_held")
        velocity = run.step(tick_ns * 1e-9, reading.q, reading.dq, reading.arm_pose)
        if velocity is None:
            self._finish(run, future)
            return taken
        header = self._header("arm_check", stamp_ns=tick_ns)
        return RobotCommand(header=header, mode=CommandMode.JOINT_VELOCITY, joint_velocities=velocity.tolist(),
                            reason="commissioning check"), tick_ns

    def abort(self, reason: str) -> None:
        """End the check running, if any, at the next tick (the arm cannot be driven: a failing bus)."""
        if self._running is not None:
            self._running[0].abort(reason)

    def stop(self) -> None:
        """The node stops: a check requested or running is answered, unfinished."""
        for pending in (self._requested, self._running):
            if pending is not None and not pending[1].done():
                pending[1].set_result(ArmCheckReply(ok=False, state=self.state,
                                                    message="the robot stopped before the check ended"))

    def _finish(self, run: arm_check.ArmCheckRun, future: Future) -> None:
        reply = arm_check.analyse(run.samples, self.arm.dh_forward_kinematics, failure=run.failure)
        with self._lock:
            self._running = None
        if not reply.ok:  # the check could not judge: the arm's verdict is what it was before
            self.state, self.detail = self._verdict_before
            reply = msgspec.structs.replace(reply, state=self.state)
        else:
            self.state, self.detail = reply.state, reply.message
            arm_check.save_verdict(self.config, self.arm, reply, time.strftime("%Y-%m-%dT%H:%M:%S%z"))
        self.counters.inc(f"arm_check.{reply.state.value}")
        (self.log.info if reply.passed else self.log.warning)("commissioning check: %s: %s", reply.state.value,
                                                             reply.message)
        future.set_result(reply)
