"""What comes in to the robot node on zenoh, on zenoh's callback threads (the first row of the node's thread table):
robot commands from safety, low-level torque commands, who is alive, and the commissioning check's requests. Each
is checked (the arm's joint count, the commands' admission, low-level control's state) and refused with a reason,
or handed over: to the inbox and the lockstep gate for the DSP, to low-level control for the loop, to the
commissioning coordinator for the DSP's next tick. Nothing of the loop's is touched here, and no callback waits: a
check's reply goes when the check is over, from its future. The Kinova API's queries are
:mod:`services.robot.api_queries`'.
"""
from __future__ import annotations

import logging
import time
from concurrent.futures import Future
from typing import Callable, Optional

import zenoh

from protocol.keys import last_chunk
from protocol.messages import ArmCheckReply, ArmCheckRequest, ProtocolError, RobotCommand, TorqueCommand, encode
from services.model.arm import ArmDescription
from services.robot.admission import Rejection
from services.robot.command_inbox import CommandInbox
from services.robot.commissioning import Commissioning
from services.robot.core import RobotCore
from services.robot.lockstep_gate import LockstepGate
from services.robot.lowlevel import LowLevelControl
from services.runtime.metrics import Counters
from services.runtime.service import query_argument


class NodeInputs:
    """The node's zenoh callbacks, on the arm that is open: ``core`` (its torque mode refuses a check), low-level
    control where the driver offers it (else ``lowlevel_unavailable`` says why torque commands are refused).
    ``refuse(stream, reason)`` counts and logs a refused input (the node's
    :meth:`~services.runtime.service.Service.refuse`); ``refuse_command(rejection)`` does so for a robot command
    and names it in the states."""

    def __init__(self, arm: ArmDescription, inbox: CommandInbox, gate: LockstepGate, commissioning: Commissioning,
                 core: RobotCore, lowlevel: Optional[LowLevelControl], lowlevel_unavailable: str,
                 counters: Counters, log: logging.Logger, refuse: Callable[[str, str], None],
                 refuse_command: Callable[[Rejection], None]) -> None:
        self.arm = arm
        self.inbox = inbox
        self.gate = gate
        self.commissioning = commissioning
        self.core = core
        self.lowlevel = lowlevel
        self.lowlevel_unavailable = lowlevel_unavailable
        self.counters = counters
        self.log = log
        self._refuse = refuse
        self._refuse_command = refuse_command

    def _wrong_joint_count(self, kind: str, values: Optional[list]) -> bool:
        """A joint vector for another arm than this one: refused and counted (``refused.joint_count``)."""
        if values is None or len(values) == self.arm.n_joints:
            return False
        self.counters.inc("refused.joint_count")
        self._refuse(kind, f"{len(values)} joint values for the {self.arm.name}'s {self.arm.n_joints} joints")
        return True

    def on_command(self, command: RobotCommand, recv_ns: int) -> None:
        if self._wrong_joint_count("command", command.joint_velocities):
            return
        rejection = self.inbox.offer(command, recv_ns)
        if rejection is not None:
            self._refuse_command(rejection)

    def on_liveliness(self, sample: zenoh.Sample) -> None:
        name, alive = last_chunk(sample.key_expr), sample.kind == zenoh.SampleKind.PUT
        if alive:
            self.inbox.new_session(name)  # a new session of a sender numbers its commands afresh
        self.gate.liveliness(name, alive)

    def on_torque(self, command: TorqueCommand, recv_ns: int) -> None:
        if self._wrong_joint_count("lowlevel_command", command.torques):
            return
        if self.lowlevel_unavailable:
            self._refuse("lowlevel_command", self.lowlevel_unavailable)
            return
        rejection = self.inbox.admit_torque(command.header, recv_ns)
        if rejection is not None:  # torques bypass safety: the same freshness and sequence as robot commands
            self.counters.inc(f"refused.lowlevel_{rejection.kind}")
            self._refuse("lowlevel_command", rejection.reason)
            return
        refusal = self.lowlevel.receive(command, time.monotonic())
        if refusal:
            self.counters.inc("refused.lowlevel_after_safety_stop")
            self._refuse("lowlevel_command", refusal)

    def on_arm_check(self, query: zenoh.Query) -> None:
        """Run the commissioning check (the reply comes when it is over: a minute or two)."""
        try:
            request = query_argument(query, "arm_check", ArmCheckRequest)
        except ProtocolError as exc:
            self._refuse("arm_check", str(exc))
            query.reply(query.key_expr, encode(ArmCheckReply(ok=False, state=self.commissioning.state,
                                                             message=str(exc)[:512])))
            return
        future, reason = self.commissioning.request(request, self.core.torque_mode)
        if reason:
            self._refuse("arm_check", reason)
            query.reply(query.key_expr, encode(ArmCheckReply(ok=False, state=self.commissioning.state,
                                                             message=reason)))
            return
        self.log.info("commissioning check requested by %s: joints %s, %.1f° at %.1f°/s", request.operator or "?",
                      request.joints, request.step_deg, request.speed_dps)
        # the reply goes when the check is over: this callback returns now, so that zenoh goes on delivering the
        # session's other messages meanwhile (an emergency stop among them); the query is kept until then
        future.add_done_callback(lambda done: self._reply_arm_check(query, done))

    def _reply_arm_check(self, query: zenoh.Query, done: Future) -> None:
        try:
            reply = done.result()
        except Exception as exc:
            reply = ArmCheckReply(ok=False, state=self.commissioning.state,
                                  message=f"the check did not finish: {exc}")
        try:
            query.reply(query.key_expr, encode(reply))
        finally:
            query.drop()  # the final answer: the caller's get ends here
