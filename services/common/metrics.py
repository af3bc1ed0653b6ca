"""Counters and rate meters a service exposes in its health messages."""
from __future__ import annotations

import collections
import threading
import time


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
