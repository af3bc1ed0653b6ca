"""Kinova API calls on their way from the ``robot/api/*`` queryable to the robot's worker, and their answers.

A zenoh callback must not wait: while it runs, its session delivers nothing else (robot commands, other queries).
So the queryable only hands the call over (:meth:`ApiCallQueue.submit`) and returns; the robot's worker, the one
thread that talks to the arm (the DSP worker in realtime, the loop in lockstep), runs each call between its cycles
and answers it (:meth:`take`, :meth:`finish`). A call still waiting at its deadline is answered as timed out
without being run (:meth:`expire`, from a thread of the node's own, so that it is answered even while the worker is
held up, as a slow SDK call can hold it for seconds); one that is running when its deadline passes is answered
when it ends. Every call is answered exactly once. No zenoh here: answering is a function the caller gives.
"""
from __future__ import annotations

import collections
import threading
import time
from dataclasses import dataclass, field
from typing import Callable, Optional

from protocol import kinova

Answer = Callable[[kinova.ApiReply], None]


@dataclass
class ApiCall:
    function: str
    argument: object
    answer: Answer
    deadline: float
    #: queued → running → answered (or queued → answered: timed out, or the node stopped)
    state: str = field(default="queued")


class ApiCallQueue:
    def __init__(self, timeout_s: float, capacity: int = 64, on_timeout: Callable[[ApiCall], None] = lambda c: None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.timeout_s = timeout_s
        self.capacity = capacity
        self._on_timeout = on_timeout
        self._clock = clock
        self._queue: collections.deque[ApiCall] = collections.deque()
        self._lock = threading.Lock()
        self._changed = threading.Condition(self._lock)
        self._closed = ""

    def submit(self, function: str, argument, answer: Answer) -> str:
        """Queue a call; '' when queued, else why not (full, or the node stopped), the caller answering."""
        with self._lock:
            if self._closed:
                return self._closed
            if len(self._queue) >= self.capacity:
                return f"{len(self._queue)} Kinova API calls are waiting already"
            self._queue.append(ApiCall(function, argument, answer, self._clock() + self.timeout_s))
            self._changed.notify_all()
        return ""

    def take(self) -> Optional[ApiCall]:
        """The next call to run (now running), or None; calls past their deadline are answered on the way."""
        while True:
            with self._lock:
                if not self._queue:
                    return None
                call = self._queue.popleft()
                expired = self._clock() >= call.deadline
                call.state = "answered" if expired else "running"
            if not expired:
                return call
            self._timed_out(call)

    def finish(self, call: ApiCall, reply: kinova.ApiReply) -> None:
        """Answer a call the worker ran."""
        call.state = "answered"
        call.answer(reply)

    def expire(self) -> int:
        """Answer every waiting call past its deadline as timed out; how many."""
        now = self._clock()
        with self._lock:
            due = [call for call in self._queue if now >= call.deadline]
            for call in due:
                self._queue.remove(call)
                call.state = "answered"
        for call in due:
            self._timed_out(call)
        return len(due)

    def wait_for_deadline(self, longest_s: float) -> None:
        """Sleep until the earliest waiting call's deadline (or a new call, or ``longest_s``), for the thread that
        calls :meth:`expire`."""
        with self._lock:
            deadline = min((call.deadline for call in self._queue), default=self._clock() + longest_s)
            self._changed.wait(max(0.0, min(deadline - self._clock(), longest_s)))

    def close(self, reason: str) -> None:
        """Answer every waiting call with ``reason`` (the node is stopping) and refuse further ones."""
        with self._lock:
            self._closed = reason
            waiting, self._queue = list(self._queue), collections.deque()
            for call in waiting:
                call.state = "answered"
            self._changed.notify_all()
        for call in waiting:
            call.answer(kinova.ApiReply(code=int(kinova.ErrorCode.UNKNOWN_ERROR), message=f"not run: {reason}"))

    def _timed_out(self, call: ApiCall) -> None:
        self._on_timeout(call)
        call.answer(kinova.ApiReply(code=int(kinova.ErrorCode.ERROR_COMM_TIMEOUT),
                                    message=f"{call.function} not run: the robot did not take it within "
                                            f"{self.timeout_s:g} s"))
