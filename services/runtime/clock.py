"""Clocks: wall time for ``realtime``, the simulator's published time for ``lockstep``.

A service takes its stamps from exactly one clock; it never mixes simulated and wall time in one computation.
Stamps are integer nanoseconds. Wall time is ``time.time_ns`` (comparable across processes and, with NTP,
across hosts); durations inside a process use ``time.monotonic`` and never appear on the wire.
"""
from __future__ import annotations

import threading
import time

from protocol.conventions import ClockMode


class WallClock:
    mode = ClockMode.REALTIME

    def now_ns(self) -> int:
        return time.time_ns()

    def now_s(self) -> float:
        return self.now_ns() * 1e-9


class SimulatedClock:
    """Simulated time, advanced by its owner (the simulator) or by the clock messages it publishes.

    Time never runs backwards: an older value is refused with ``ValueError`` so a reordered clock message cannot
    rewind a service.
    """

    mode = ClockMode.LOCKSTEP

    def __init__(self, start_ns: int = 0) -> None:
        self._now = int(start_ns)
        self._cond = threading.Condition()

    def now_ns(self) -> int:
        with self._cond:
            return self._now

    def now_s(self) -> float:
        return self.now_ns() * 1e-9

    def advance_to(self, t_ns: int) -> None:
        """Move to ``t_ns`` unless already there or later (concurrent callers cannot rewind each other)."""
        with self._cond:
            if int(t_ns) > self._now:
                self._now = int(t_ns)
                self._cond.notify_all()

    def set_ns(self, t_ns: int) -> None:
        t_ns = int(t_ns)
        with self._cond:
            if t_ns < self._now:
                raise ValueError(f"simulated time cannot run backwards ({t_ns} < {self._now})")
            self._now = t_ns
            self._cond.notify_all()

    def advance_ns(self, dt_ns: int) -> int:
        if dt_ns < 0:
            raise ValueError("cannot advance by a negative duration")
        with self._cond:
            self._now += int(dt_ns)
            self._cond.notify_all()
            return self._now

    def wait_until_ns(self, t_ns: int, timeout_s: float | None = None) -> bool:
        """Block until simulated time reaches ``t_ns``; False if ``timeout_s`` (wall) passed first."""
        with self._cond:
            return self._cond.wait_for(lambda: self._now >= t_ns, timeout=timeout_s)


class PeriodicSchedule:
    """Wakes a loop on an absolute schedule of fixed period (wall, monotonic), so periods do not drift. After a
    stall longer than ``max_lag_periods`` it skips ahead instead of running the missed slots back to back (None:
    never skip). ``wait()`` returns the slot index it woke for and whether it had to skip."""

    def __init__(self, period_s: float, max_lag_periods: float | None = 5.0) -> None:
        self.period_s = period_s
        self.max_lag_periods = max_lag_periods
        self.start = time.monotonic()
        self._next = 0

    def elapsed_s(self) -> float:
        return time.monotonic() - self.start

    def wait(self) -> tuple[int, bool]:
        delay = self.start + self._next * self.period_s - time.monotonic()
        skipped = False
        if delay > 0:
            time.sleep(delay)
        elif self.max_lag_periods is not None and delay < -self.max_lag_periods * self.period_s:
            self._next = int(self.elapsed_s() / self.period_s)
            skipped = True
        slot = self._next
        self._next += 1
        return slot, skipped


def make_clock(mode: ClockMode | str) -> WallClock | SimulatedClock:
    mode = ClockMode(mode)
    return WallClock() if mode is ClockMode.REALTIME else SimulatedClock()
