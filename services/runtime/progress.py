"""A progress line for long commands on a terminal: the task, its iteration, the error norm and an estimate of the
time left, rewritten in place on stderr. Nothing when stderr is not a terminal (piped, a log file, CI) or when the
command prints JSON, so that what a program reads is unchanged.
"""
from __future__ import annotations

import math
import sys
import time
from typing import Optional, Sequence

#: iterations the decay rate is estimated over
DECAY_WINDOW = 20


def iterations_left(errors: Sequence[float], threshold: float, iteration: int, max_iterations: int) -> Optional[int]:
    """Iterations until ``errors`` (the error per iteration, newest last) falls below ``threshold``, from its
    recent exponential decay rate (what the laws' error does); the iterations up to ``max_iterations`` when it does
    not decay; None before there is a rate to go by."""
    recent = [e for e in errors[-DECAY_WINDOW:] if e > 0 and math.isfinite(e)]
    if len(recent) < 5:
        return None
    if recent[-1] <= threshold:
        return 0
    rate = (math.log(recent[0]) - math.log(recent[-1])) / (len(recent) - 1)
    ceiling = max(0, max_iterations - iteration)
    if rate <= 1e-6:
        return ceiling
    return min(ceiling, math.ceil(math.log(recent[-1] / threshold) / rate))


def shows(enabled: bool = True, stream=None) -> bool:
    """Whether a progress line on ``stream`` (default: stderr) would be seen: ``enabled`` and a terminal."""
    stream = stream if stream is not None else sys.stderr
    return enabled and hasattr(stream, "isatty") and stream.isatty()


class ProgressLine:
    """``update(iteration, error_rms)`` rewrites one line (the per-point RMS error, against the convergence
    threshold); ``done()`` ends it. Silent unless ``stream`` is a terminal and ``enabled``."""

    def __init__(self, task: str, threshold: float, max_iterations: int, enabled: bool = True, stream=None) -> None:
        self.stream = stream if stream is not None else sys.stderr
        self.enabled = shows(enabled, self.stream)
        self.task, self.threshold, self.max_iterations = task, threshold, max_iterations
        self.errors: list[float] = []
        self.start = time.monotonic()
        self._shown = False

    def update(self, iteration: int, error_rms: float) -> None:
        self.errors.append(error_rms)
        if not self.enabled:
            return
        elapsed = time.monotonic() - self.start
        left = iterations_left(self.errors, self.threshold, iteration, self.max_iterations)
        eta = ""
        if left is not None and iteration > 0:
            eta = f"  ETA {left * elapsed / iteration:4.0f} s"
        line = f"{self.task}: iteration {iteration:5d}  e_rms {error_rms:.2e}{eta}"
        self.stream.write("\r" + line.ljust(78)[:120])
        self.stream.flush()
        self._shown = True

    def done(self) -> None:
        if self._shown:
            self.stream.write("\r" + " " * 78 + "\r")
            self.stream.flush()
            self._shown = False
