"""Work done once a tick on a thread of its own, so that the thread that hands it over never waits for it: the robot
node's DSP cycle beside its bus loop (services.robot.dsp_worker), as a robot's servo loop never waits for its planner.

:meth:`AsyncCycle.submit` hands over one tick's work and returns at once, with a
:class:`~concurrent.futures.Future` of its result (``future.result(timeout)`` waits for it, with a deadline). The
thread does the newest work handed over: a tick handed over while the last one has not been taken yet replaces it,
and the one replaced is skipped (its future cancelled) and counted as an overrun: the thread is behind, and only
the newest tick's work is worth doing. A tick handed over while the thread runs the last one waits for it.
:meth:`stop` cancels what waits, lets what runs finish, and ends the thread.
"""
from __future__ import annotations

import threading
from concurrent.futures import Future
from typing import Callable, Optional

from services.runtime.threads import start_thread


class AsyncCycle:
    def __init__(self, name: str, on_overrun: Callable[[], None] = lambda: None) -> None:
        """``name``: the thread's (for Python and the kernel: services.runtime.threads); ``on_overrun``: called, on
        the thread that submits, for each tick skipped."""
        self.name = name
        #: ticks skipped: replaced by a newer one before the thread took them
        self.overruns = 0
        self._on_overrun = on_overrun
        self._cond = threading.Condition()
        self._waiting: Optional[tuple[Callable[[], object], Future]] = None
        self._stopped = False
        self._thread = start_thread(self._run, name)

    def submit(self, work: Callable[[], object]) -> Future:
        """Hand over this tick's work; its future (cancelled if a newer tick replaces it, or the cycle stops)."""
        future: Future = Future()
        with self._cond:
            if self._stopped:
                future.cancel()
                return future
            replaced, self._waiting = self._waiting, (work, future)
            if replaced is not None:
                replaced[1].cancel()
                self.overruns += 1
            self._cond.notify()
        if replaced is not None:
            self._on_overrun()
        return future

    def stop(self, timeout_s: float = 5.0) -> None:
        """Cancel the work waiting, and wait up to ``timeout_s`` for the work running to end (then the thread)."""
        with self._cond:
            self._stopped = True
            waiting, self._waiting = self._waiting, None
            self._cond.notify_all()
        if waiting is not None:
            waiting[1].cancel()
        if self._thread is not threading.current_thread():
            self._thread.join(timeout_s)

    def _run(self) -> None:
        while True:
            with self._cond:
                while self._waiting is None and not self._stopped:
                    self._cond.wait()
                if self._stopped:
                    return
                (work, future), self._waiting = self._waiting, None
            if not future.set_running_or_notify_cancel():
                continue
            try:
                result = work()
            except Exception as exc:  # the work's to report; the cycle goes on with the next tick
                future.set_exception(exc)
            else:
                future.set_result(result)
