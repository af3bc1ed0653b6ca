"""Counters and rate meters a service exposes in its health messages."""
from __future__ import annotations

import collections
import threading
import time

import numpy as np


class Counters:
    """Named monotonic counters (thread-safe)."""

    def __init__(self) -> None:
        self._values: dict[str, int] = collections.defaultdict(int)
        self._lock = threading.Lock()

    def inc(self, name: str, by: int = 1) -> int:
        with self._lock:
            self._values[name] += by
            return self._values[name]

    def get(self, name: str) -> int:
        with self._lock:
            return self._values.get(name, 0)

    def snapshot(self) -> dict[str, int]:
        with self._lock:
            return dict(self._values)


class RateMeter:
    """Events per second over a sliding window of wall (monotonic) time.

    Until the meter has existed for a full window the rate is taken over its lifetime so far.
    """

    def __init__(self, window_s: float = 2.0, clock=time.monotonic) -> None:
        self.window_s = window_s
        self._clock = clock
        self._created = clock()
        self._stamps: collections.deque[float] = collections.deque()
        self._lock = threading.Lock()

    def tick(self) -> None:
        now = self._clock()
        with self._lock:
            self._stamps.append(now)
            self._trim(now)

    def _trim(self, now: float) -> None:
        cutoff = now - self.window_s
        while self._stamps and self._stamps[0] < cutoff:
            self._stamps.popleft()

    def rate_hz(self) -> float:
        now = self._clock()
        with self._lock:
            self._trim(now)
            elapsed = min(self.window_s, now - self._created)
            return len(self._stamps) / elapsed if elapsed > 1e-3 else 0.0


class Rates:
    """A RateMeter per name."""

    def __init__(self, window_s: float = 2.0, clock=time.monotonic) -> None:
        self._window_s = window_s
        self.window_s = window_s
        self._clock = clock
        self._meters: dict[str, RateMeter] = {}
        self._lock = threading.Lock()

    def tick(self, name: str) -> None:
        with self._lock:
            meter = self._meters.get(name)
            if meter is None:
                meter = self._meters[name] = RateMeter(self._window_s, self._clock)
        meter.tick()

    def snapshot(self) -> dict[str, float]:
        with self._lock:
            meters = dict(self._meters)
        return {name: round(m.rate_hz(), 3) for name, m in meters.items()}


class LoopTimer:
    """Periods of a periodic loop (wall, monotonic): achieved rate and period jitter over the last ``window``."""

    def __init__(self, nominal_s: float, window: int = 2500, clock=time.monotonic) -> None:
        self.nominal_s = nominal_s
        self._clock = clock
        self._last: float | None = None
        self._periods: collections.deque[float] = collections.deque(maxlen=window)
        self._lock = threading.Lock()

    def tick(self) -> None:
        now = self._clock()
        with self._lock:
            if self._last is not None:
                self._periods.append(now - self._last)
            self._last = now

    def stats(self) -> dict[str, float]:
        """rate_hz, and the period error |period − nominal| in ms: p50, p99, max; n periods. (NumPy, not a Python
        sort: this runs in another thread of a process whose realtime loop needs the interpreter lock, and a sort
        holds it throughout.)"""
        with self._lock:
            periods = np.array(self._periods)
        if not len(periods):
            return {"rate_hz": 0.0, "jitter_ms_p50": 0.0, "jitter_ms_p99": 0.0, "jitter_ms_max": 0.0, "n": 0}
        errors = np.abs(periods - self.nominal_s) * 1e3
        p50, p99 = np.percentile(errors, [50, 99], method="nearest")
        return {"rate_hz": len(periods) / float(periods.sum()), "jitter_ms_p50": float(p50),
                "jitter_ms_p99": float(p99), "jitter_ms_max": float(errors.max()), "n": len(periods)}


class DurationStats:
    """Durations of a repeated piece of work (e.g. one cycle of a loop, without its sleep): p50, p99 and max over
    the last ``window`` in ms."""

    def __init__(self, window: int = 2500) -> None:
        self._values: collections.deque[float] = collections.deque(maxlen=window)
        self._lock = threading.Lock()

    def add(self, seconds: float) -> None:
        with self._lock:
            self._values.append(seconds)

    def stats(self) -> dict[str, float]:
        """(NumPy, not a Python sort: see LoopTimer.stats.)"""
        with self._lock:
            values = np.array(self._values) * 1e3
        if not len(values):
            return {"p50_ms": 0.0, "p99_ms": 0.0, "max_ms": 0.0, "n": 0}
        p50, p99 = np.percentile(values, [50, 99], method="nearest")
        return {"p50_ms": float(p50), "p99_ms": float(p99), "max_ms": float(values.max()), "n": len(values)}
