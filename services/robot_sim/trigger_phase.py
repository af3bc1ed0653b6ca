"""Where in the DSP's 10 ms cycle to trigger the camera, chosen from the paths the commands took.

A command derived from a frame is applied at the first DSP tick after it reaches the robot. With the camera fired
``offset`` ms after a tick, the first tick after the capture is ``10 − offset`` ms later: a pipeline that makes it
is applied then, one that does not waits a whole cycle more. So the time from capture to applied is not the
pipeline's time but a step function of it, and which offset is best depends on how fast this host renders, detects
and hands the command on (measured here from 7.5 ms to 10 ms on the same code, a day apart). A fixed offset that
suits one day puts the next day's frames just past the tick: a whole cycle lost on most of them.

:class:`TriggerPhase` does what a commissioning engineer does with a hardware-triggered camera: it measures each
command's path (capture → arrival at the robot node), predicts for every offset when those commands would have been
applied (:func:`applied_after_ms`), and moves the trigger to the offset where the typical command (the median) is
applied soonest (:func:`best_offset`), with hysteresis so that measurement noise does not move it back and forth.
The median, not the mean: the mean trades the typical frame's 2 ms for a late minority's whole cycle, and on this
host it moved the camera onto the DSP's tick, where the commands' tail then waited a cycle more (p99 20.3-21.2 ms
against 18.9 ms, with the median 2 ms worse). Pure: no clock of its own, no I/O, no
locks; robot_sim feeds it and reads it.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np

#: a command must reach the robot node this much before the moment its DSP takes commands to count as in time
GUARD_MS = 0.3
#: move only for a predicted gain of at least this much (ms, median capture → applied)
HYSTERESIS_MS = 1.0
#: paths outside this are not a pipeline's (clocks apart, a frame from before a restart): not counted
PLAUSIBLE_PATH_MS = (0.0, 1000.0)
#: after a move, the commands of this many frames are not counted (taken at the old phase, still in the pipeline)
IN_FLIGHT_FRAMES = 3
#: how long what was measured at an offset vetoes a move back to it (the path can depend on the phase itself: on
#: a shared 2-core host the render lands on different work; the model cannot see that, experience can)
MEMORY_NS = 10_000_000_000
#: the model must predict the current offset's measured median within this (ms) before it may move the camera
CONSISTENCY_MS = 1.0
#: the first frames after start are not counted (vision's first full-frame detections, caches still cold)
WARMUP_FRAMES = 30


def tick_lag_ms(applied_ms: np.ndarray, offset_ms: float, cycle_ms: float = 10.0) -> float:
    """How long after the DSP tick's nominal time its robot node takes the commands it applies (its loop's wake-up,
    the exchange, a bus reading's own delay through robot_gateway), in [0, cycle): the circular mean, over commands
    applied ``applied_ms`` after their frame's capture with the camera fired ``offset_ms`` after a tick, of how far
    past a tick each was applied (circular: a lag near a whole cycle is the same phase as one near 0)."""
    phase = 2.0 * np.pi * (np.asarray(applied_ms, dtype=float) - (cycle_ms - offset_ms)) / cycle_ms
    mean = np.arctan2(np.mean(np.sin(phase)), np.mean(np.cos(phase)))
    return float(np.mod(mean * cycle_ms / (2.0 * np.pi), cycle_ms))


def applied_after_ms(path_ms: np.ndarray, offset_ms: float, lag_ms: float, cycle_ms: float = 10.0,
                     guard_ms: float = GUARD_MS) -> np.ndarray:
    """Capture → the DSP cycle that takes each command, for commands that reach the robot ``path_ms`` after their
    frame's capture, with the camera fired ``offset_ms`` after a tick and the robot node taking commands ``lag_ms``
    after each tick: the first such moment at least ``guard_ms`` after the arrival."""
    first_take = cycle_ms - offset_ms + lag_ms
    late_by = np.maximum(0.0, np.asarray(path_ms, dtype=float) + guard_ms - first_take)
    return first_take + cycle_ms * np.ceil(late_by / cycle_ms)


def best_offset(path_ms: np.ndarray, lag_ms: float, offsets_ms: Sequence[int], current_ms: int,
                cycle_ms: float = 10.0, hysteresis_ms: float = HYSTERESIS_MS,
                measured_ms: Optional[dict[int, float]] = None) -> tuple[int, float, float]:
    """The offset with the lowest median predicted capture → applied time, the mean breaking ties (``current_ms``
    unless another beats it by ``hysteresis_ms``), with that median and the current offset's. ``measured_ms``:
    the median measured at some offsets (the current one included); an offset measured no better than the current
    one is not a candidate, whatever the prediction says."""
    predicted = {offset: applied_after_ms(path_ms, offset, lag_ms, cycle_ms) for offset in offsets_ms}
    medians = {offset: float(np.median(p)) for offset, p in predicted.items()}
    measured = measured_ms or {}
    now = measured.get(current_ms)
    candidates = [offset for offset in offsets_ms if offset == current_ms or now is None or offset not in measured
                  or measured[offset] < now - hysteresis_ms]
    best = min(candidates, key=lambda offset: (medians[offset], float(np.mean(predicted[offset]))))
    if medians[current_ms] - medians[best] < hysteresis_ms:
        best = current_ms
    return best, medians[best], medians[current_ms]


@dataclass(frozen=True)
class PhaseChange:
    """The trigger moved: from, to (ms after the tick), the predicted median capture → applied at each, the robot
    node's measured lag after its tick, and how many commands the decision rests on."""
    from_ms: int
    to_ms: int
    predicted_from_ms: float
    predicted_to_ms: float
    lag_ms: float
    samples: int


class TriggerPhase:
    """The camera's trigger offset: fixed (``auto`` false), or moved now and then to the best for the commands
    measured since the last move (at least ``min_samples`` of them, at most every ``period_ns``; the last
    ``window``; not the first ``warmup_frames`` after start), and only while the model predicts what is measured
    at the current offset."""

    def __init__(self, offset_ms: int, offsets_ms: Sequence[int], auto: bool, cycle_ms: float = 10.0,
                 window: int = 120, min_samples: int = 60, period_ns: int = 1_000_000_000,
                 warmup_frames: int = WARMUP_FRAMES) -> None:
        if offset_ms not in offsets_ms:
            raise ValueError(f"trigger offset {offset_ms} ms is not one of {tuple(offsets_ms)}")
        self.offset_ms, self.offsets_ms, self.auto, self.cycle_ms = offset_ms, tuple(offsets_ms), auto, cycle_ms
        self.min_samples, self.period_ns = min_samples, period_ns
        self._paths: deque[tuple[float, float]] = deque(maxlen=window)
        self._last_capture_ns = 0
        self._skip = warmup_frames
        self._next_decision_ns = 0
        #: how many times the trigger moved, and how many decisions were not taken because the model did not
        #: predict what was measured at the current offset
        self.moves = self.inconsistent = 0
        #: offset → (median capture → applied measured while it was in force, when)
        self._measured: dict[int, tuple[float, int]] = {}

    @property
    def offset_ns(self) -> int:
        return self.offset_ms * 1_000_000

    def observe(self, capture_ns: int, arrival_ns: int, applied_ns: int) -> bool:
        """A command derived from the frame captured at ``capture_ns`` reached the robot node at ``arrival_ns``
        and was applied at ``applied_ns`` (the first such command per frame counts; later ones, implausible paths
        and the frames in flight across a move do not). Whether it was counted."""
        if capture_ns <= self._last_capture_ns:
            return False
        self._last_capture_ns = capture_ns
        path_ms, applied_ms = (arrival_ns - capture_ns) / 1e6, (applied_ns - capture_ns) / 1e6
        if not PLAUSIBLE_PATH_MS[0] < path_ms <= applied_ms < PLAUSIBLE_PATH_MS[1]:
            return False
        if self._skip > 0:
            self._skip -= 1
            return False
        self._paths.append((path_ms, applied_ms))
        return True

    def update(self, now_ns: int) -> Optional[PhaseChange]:
        """Decide, when it is time: the change made, or None. The commands measured at the old offset are dropped
        with a move (a phase can change the path itself: a render over the DSP's tick in the same process)."""
        if not self.auto or len(self._paths) < self.min_samples or now_ns < self._next_decision_ns:
            return None
        self._next_decision_ns = now_ns + self.period_ns
        measured = np.array(self._paths, dtype=float)
        paths, applied = measured[:, 0], measured[:, 1]
        lag = tick_lag_ms(applied, self.offset_ms, self.cycle_ms)
        self._measured[self.offset_ms] = (float(np.median(applied)), now_ns)
        recent = {offset: median for offset, (median, when) in self._measured.items() if now_ns - when < MEMORY_NS}
        best, predicted_best, predicted_now = best_offset(paths, lag, self.offsets_ms, self.offset_ms, self.cycle_ms,
                                                          measured_ms=recent)
        if best == self.offset_ms:
            return None
        if abs(predicted_now - self._measured[self.offset_ms][0]) > CONSISTENCY_MS:
            self.inconsistent += 1
            return None
        change = PhaseChange(self.offset_ms, best, predicted_now, predicted_best, lag, len(paths))
        self.offset_ms = best
        self.moves += 1
        self._paths.clear()
        self._skip = IN_FLIGHT_FRAMES
        return change
