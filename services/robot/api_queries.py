"""The Kinova API as the robot node offers it on zenoh (``…/robot/api/<Function>``): each query decoded, or refused
and answered at once; handed to the robot's worker through an :class:`~services.robot.api_calls.ApiCallQueue` (the
callback returns at once: while it runs its session delivers nothing else); run on the worker between DSP cycles
(:meth:`ApiQueries.run_waiting`) and answered; the calls the worker did not take in time answered by a thread of
their own (:meth:`ApiQueries.answer_timeouts`), even while the worker is held up (a slow SDK call).
"""
from __future__ import annotations

from typing import Callable

import zenoh

from protocol import kinova
from protocol.keys import last_chunk
from protocol.messages import ProtocolError, encode, missing_fields
from services.robot.api_calls import ApiCallQueue
from services.robot.core import RobotCore
from services.runtime.logs import RateLimitedLogger
from services.runtime.metrics import Counters
from services.runtime.service import query_argument

#: Kinova API functions that move the arm: refused while low-level torque control owns it (they would be queued
#: in the DSP and run, unexpectedly, once torque control ends)
MOTION_FUNCTIONS = frozenset({"SendBasicTrajectory", "MoveHome"})
#: a Kinova API call not taken by the robot's worker within this long is answered as timed out, without being run
API_TIMEOUT_S = 5.0


class ApiQueries:
    """The node's Kinova API queryable and the calls it hands to the worker. ``refuse(stream, reason)`` counts and
    logs a refused query (the node's :meth:`~services.runtime.service.Service.refuse`); ``wake()`` wakes a DSP
    waiting for a command, so that it runs a new call now; ``stopping()`` ends the timeouts' thread."""

    def __init__(self, name: str, counters: Counters, limited_log: RateLimitedLogger,
                 refuse: Callable[[str, str], None], wake: Callable[[], None], stopping: Callable[[], bool]) -> None:
        self.name = name
        self.counters = counters
        self.limited_log = limited_log
        self._refuse = refuse
        self._wake = wake
        self._stopping = stopping
        #: the calls on their way to the worker, each answered once
        self.calls = ApiCallQueue(API_TIMEOUT_S, on_timeout=lambda call: counters.inc("api.timeouts"))

    def on_query(self, query: zenoh.Query) -> None:
        """A query (zenoh's callback): decoded and handed to the worker, or refused and answered now."""
        function = last_chunk(query.key_expr)
        spec = kinova.API_FUNCTIONS.get(function)
        if spec is None:
            self._refuse("api", f"unknown Kinova API function {function!r}")
            query.reply(query.key_expr, encode(kinova.ApiReply(code=int(kinova.ErrorCode.ERROR_INVALID_PARAM),
                                                               message=f"unknown function {function}")))
            return
        argument_type, _ = spec
        try:
            argument = query_argument(query, function, argument_type)  # no payload for MoveHome & co
            if argument_type is not None and function in kinova.MUTATING_API_FUNCTIONS:
                missing = missing_fields(query.payload.to_bytes(), argument_type)
                if missing:
                    raise ProtocolError(argument_type.__name__, "a request that changes the arm must give every "
                                        f"field; missing: {', '.join(missing[:8])}")
        except ProtocolError as exc:
            self._refuse("api", str(exc))
            query.reply(query.key_expr, encode(kinova.ApiReply(
                code=int(kinova.ErrorCode.ERROR_INVALID_PARAM), message=str(exc)[:256])))
            return
        # handed to the worker, which answers (this callback must not wait: its session delivers nothing meanwhile)
        refusal = self.calls.submit(function, argument, lambda reply: self._answer(query, reply))
        if refusal:
            self._refuse("api", f"{function}: {refusal}")
            self._answer(query, kinova.ApiReply(code=int(kinova.ErrorCode.UNKNOWN_ERROR),
                                                message=f"not run: {refusal}"))
            return
        self._wake()  # a DSP waiting for a command runs the call now

    def _answer(self, query: zenoh.Query, reply: kinova.ApiReply) -> None:
        try:
            query.reply(query.key_expr, encode(reply))
        except Exception:  # the session closed under it (the node stopping)
            self.counters.inc("errors.api_reply")
        finally:
            query.drop()  # the final answer goes out now, not when the query is collected

    def answer_timeouts(self) -> None:
        """Answer the API calls the worker did not take in time, even while it is held up (a slow SDK call): the
        body of a thread of its own, until the node stops."""
        while not self._stopping():
            self.calls.wait_for_deadline(0.5)
            self.calls.expire()

    def run_waiting(self, api, core: RobotCore) -> None:
        """Run and answer the calls waiting, on ``api`` (what drives the arm answers them: ``call(function,
        argument) -> ApiReply``), refusing the motions while ``core`` is in torque mode (on the worker, between DSP
        cycles)."""
        while (call := self.calls.take()) is not None:
            if call.function in MOTION_FUNCTIONS and core.torque_mode:
                self._refuse("api", f"{call.function}: low-level torque control is active")
                reply = kinova.ApiReply(code=int(kinova.ErrorCode.ERROR_INVALID_PARAM),
                                        message="low-level torque control is active")
            else:
                try:
                    reply = api.call(call.function, call.argument)
                except Exception as exc:
                    self.counters.inc("errors.api")
                    self.limited_log.error("api", "%s: %s failed: %s", self.name, call.function, exc)
                    reply = kinova.ApiReply(code=int(kinova.ErrorCode.UNKNOWN_ERROR),
                                            message=f"{call.function} failed: {exc}"[:512])
            self.calls.finish(call, reply)
