"""The camera trigger's phase chosen from measured command paths (services/robot_sim/trigger_phase.py)."""
import numpy as np
import pytest

from services.robot_sim.scene import TRIGGER_OFFSETS_MS
from services.robot_sim.trigger_phase import (GUARD_MS, IN_FLIGHT_FRAMES, WARMUP_FRAMES, TriggerPhase,
                                              applied_after_ms, best_offset, tick_lag_ms)

MS = 1_000_000


def test_a_command_is_applied_at_the_first_take_after_it_arrives():
    # camera 2 ms after the tick, the robot takes commands 0.8 ms after each tick: the takes are 8.8, 18.8, ...
    paths = np.array([1.0, 8.8 - GUARD_MS - 0.01, 8.8 - GUARD_MS + 0.01, 18.0, 30.0])
    assert applied_after_ms(paths, 2, 0.8).tolist() == pytest.approx([8.8, 8.8, 18.8, 18.8, 38.8])


def test_the_lag_after_the_tick_is_read_from_when_commands_were_applied():
    assert tick_lag_ms(np.array([8.8, 18.8, 8.9, 8.7]), 2) == pytest.approx(0.8, abs=0.01)
    # a lag straddling the cycle: 9.9 and 0.1 ms past a tick are 0.1 ms apart, not 9.8 (and their mean is not 5)
    lag = tick_lag_ms(np.array([19.9, 10.1, 19.9, 10.1]), 0)
    assert min(lag, 10.0 - lag) < 0.01


def test_the_best_offset_is_applied_soonest_on_average():
    lag = 0.8
    fast = np.full(50, 7.5)  # in time for 2 ms's first take (8.8), not for 4 ms's (6.8)
    assert best_offset(fast, lag, TRIGGER_OFFSETS_MS, current_ms=2)[0] == 2
    slow = np.full(50, 9.5)  # misses 8.8, makes 0 ms's 10.8
    offset, predicted, was = best_offset(slow, lag, TRIGGER_OFFSETS_MS, current_ms=2)
    assert (offset, predicted, was) == (0, pytest.approx(10.8), pytest.approx(18.8))
    slower = np.full(50, 11.5)  # 8 ms's first take 2.8 + 10 = 12.8 is the next
    assert best_offset(slower, lag, TRIGGER_OFFSETS_MS, current_ms=2)[0] == 8


def test_the_typical_command_decides_not_a_late_minority():
    # 35 % of the commands miss 2 ms's first take: their mean there (12.3) is worse than 0 ms's (10.8), but the
    # typical command is applied at 8.8 ms: the camera stays
    paths = np.array([7.5] * 65 + [9.0] * 35)
    assert best_offset(paths, 0.8, TRIGGER_OFFSETS_MS, current_ms=2)[0] == 2
    # most miss it: then the typical command is applied sooner at 0 ms
    paths = np.array([7.5] * 35 + [9.0] * 65)
    assert best_offset(paths, 0.8, TRIGGER_OFFSETS_MS, current_ms=2)[0] == 0


def test_hysteresis_keeps_the_offset_for_a_small_gain():
    paths = np.full(50, 7.5)  # at 0 ms: 10.8; at 2 ms: 8.8
    assert best_offset(paths, 0.8, TRIGGER_OFFSETS_MS, current_ms=0)[0] == 2
    assert best_offset(paths, 0.8, TRIGGER_OFFSETS_MS, current_ms=0, hysteresis_ms=3.0)[0] == 0


def feed(phase: TriggerPhase, start_ns: int, count: int, path_ms: float, applied_ms: float) -> int:
    """``count`` frames 33 ms apart whose commands took ``path_ms`` to arrive and were applied ``applied_ms``
    after capture; the next frame's capture stamp."""
    capture = start_ns
    for _ in range(count):
        phase.observe(capture, capture + int(path_ms * MS), capture + int(applied_ms * MS))
        capture += 33 * MS
    return capture


def test_auto_moves_after_enough_commands_and_measures_again():
    phase = TriggerPhase(2, TRIGGER_OFFSETS_MS, auto=True, min_samples=30, period_ns=1_000_000_000,
                         warmup_frames=0)
    capture = feed(phase, 1_000 * MS, 29, path_ms=9.5, applied_ms=18.8)
    assert phase.update(now_ns=5_000 * MS) is None  # 29 < 30
    capture = feed(phase, capture, 1, path_ms=9.5, applied_ms=18.8)
    change = phase.update(now_ns=5_000 * MS)
    assert (change.from_ms, change.to_ms, phase.offset_ms, phase.offset_ns, phase.moves) == (2, 0, 0, 0, 1)
    assert change.lag_ms == pytest.approx(0.8, abs=0.01) and change.samples == 30
    # the frames in flight across the move are not counted; then 30 new ones are needed, and a period must pass
    capture = feed(phase, capture, IN_FLIGHT_FRAMES + 29, path_ms=9.5, applied_ms=10.8)
    assert phase.update(now_ns=7_000 * MS) is None
    capture = feed(phase, capture, 1, path_ms=9.5, applied_ms=10.8)
    assert phase.update(now_ns=5_500 * MS) is None  # within the period after the last decision
    assert phase.update(now_ns=7_000 * MS) is None  # measured at 0 ms, 0 ms is still the best
    assert phase.offset_ms == 0


def test_a_fixed_offset_never_moves():
    phase = TriggerPhase(4, TRIGGER_OFFSETS_MS, auto=False)
    feed(phase, 1_000 * MS, 100, path_ms=9.5, applied_ms=16.8)
    assert phase.update(now_ns=10**12) is None and phase.offset_ms == 4


def test_each_frame_counts_once_and_implausible_paths_not_at_all():
    phase = TriggerPhase(2, TRIGGER_OFFSETS_MS, auto=True, warmup_frames=0)
    assert phase.observe(1_000 * MS, 1_006 * MS, 1_008 * MS)
    assert not phase.observe(1_000 * MS, 1_007 * MS, 1_018 * MS)  # a later command from the same frame
    assert not phase.observe(999 * MS, 1_006 * MS, 1_008 * MS)  # an older frame
    assert not phase.observe(2_000 * MS, 1_999 * MS, 2_008 * MS)  # arrived before its capture: clocks apart
    assert not phase.observe(3_000 * MS, 3_009 * MS, 3_008 * MS)  # applied before it arrived
    assert not phase.observe(4_000 * MS, 5_500 * MS, 5_501 * MS)  # 1.5 s: no pipeline's path


def test_an_offset_outside_the_bus_cycles_is_refused():
    with pytest.raises(ValueError, match="not one of"):
        TriggerPhase(3, TRIGGER_OFFSETS_MS, auto=False)


def test_an_offset_measured_worse_is_not_tried_again_soon():
    # the model says 0 ms (10.8) beats 2 ms (18.8); measured at 0 ms, the path grew and every command waited a
    # cycle more (20.8): back to 2, and the same prediction does not move it to 0 again while that is remembered
    phase = TriggerPhase(2, (0, 2), auto=True, min_samples=30, period_ns=1_000_000_000,
                         warmup_frames=0)
    capture = feed(phase, 1_000 * MS, 30, path_ms=9.5, applied_ms=18.8)
    assert phase.update(now_ns=2_000 * MS).to_ms == 0
    capture = feed(phase, capture, IN_FLIGHT_FRAMES + 30, path_ms=10.6, applied_ms=20.8)
    assert phase.update(now_ns=4_000 * MS).to_ms == 2
    capture = feed(phase, capture, IN_FLIGHT_FRAMES + 30, path_ms=9.5, applied_ms=18.8)
    assert phase.update(now_ns=6_000 * MS) is None and phase.offset_ms == 2
    # forgotten after a while: the prediction is tried again
    capture = feed(phase, capture, 30, path_ms=9.5, applied_ms=18.8)
    assert phase.update(now_ns=40_000 * MS).to_ms == 0


def test_the_first_frames_after_start_are_not_counted():
    phase = TriggerPhase(2, TRIGGER_OFFSETS_MS, auto=True, min_samples=30)
    capture = feed(phase, 1_000 * MS, WARMUP_FRAMES + 29, path_ms=9.5, applied_ms=18.8)
    assert phase.update(now_ns=5_000 * MS) is None
    feed(phase, capture, 1, path_ms=9.5, applied_ms=18.8)
    assert phase.update(now_ns=5_000 * MS).to_ms == 0


def test_no_move_while_the_model_does_not_predict_what_is_measured():
    # this robot takes a command 0.1 ms after it arrives, within the guard: the model says the commands miss the
    # take at 9.6 ms (19.6) while they are applied there; it does not move the camera on such a model
    phase = TriggerPhase(2, TRIGGER_OFFSETS_MS, auto=True, min_samples=30, warmup_frames=0)
    feed(phase, 1_000 * MS, 30, path_ms=9.5, applied_ms=9.6)
    assert phase.update(now_ns=5_000 * MS) is None
    assert (phase.offset_ms, phase.inconsistent) == (2, 1)
