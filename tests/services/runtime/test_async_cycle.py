"""services/runtime/async_cycle.py: a tick's work on a thread of its own; the one who hands it over never waits, a tick
not taken before the next comes is skipped and counted, and stopping ends the thread."""
import threading
from concurrent.futures import CancelledError

import pytest

from services.runtime.async_cycle import AsyncCycle


def held(release: threading.Event, started: threading.Event, value):
    def work():
        started.set()
        assert release.wait(10.0)
        return value
    return work


def test_the_work_runs_on_the_cycle_s_thread_and_its_result_can_be_waited_for_with_a_deadline():
    cycle = AsyncCycle("test-cycle")
    try:
        future = cycle.submit(lambda: threading.current_thread().name)
        assert future.result(timeout=5.0) == "test-cycle"
        release, started = threading.Event(), threading.Event()
        slow = cycle.submit(held(release, started, 2))
        with pytest.raises(TimeoutError):
            slow.result(timeout=0.05)  # the deadline passes: the caller goes on, the work too
        release.set()
        assert slow.result(timeout=5.0) == 2 and cycle.overruns == 0
    finally:
        cycle.stop()


def test_a_tick_not_taken_before_the_next_comes_is_skipped_and_counted():
    counted = []
    cycle = AsyncCycle("test-cycle", on_overrun=lambda: counted.append(threading.current_thread().name))
    release, started = threading.Event(), threading.Event()
    try:
        running = cycle.submit(held(release, started, "first"))
        assert started.wait(5.0)
        waiting = cycle.submit(lambda: "second")  # the thread is busy: this one waits for it, no overrun yet
        assert cycle.overruns == 0 and not counted
        newest = cycle.submit(lambda: "third")  # the second was never taken: skipped for the newest
        assert cycle.overruns == 1 and counted == [threading.current_thread().name]  # said to the one submitting
        release.set()
        assert running.result(timeout=5.0) == "first" and newest.result(timeout=5.0) == "third"
        with pytest.raises(CancelledError):
            waiting.result(timeout=5.0)
    finally:
        release.set()
        cycle.stop()


def test_a_failing_work_fails_its_own_future_and_the_cycle_goes_on():
    cycle = AsyncCycle("test-cycle")
    try:
        failed = cycle.submit(lambda: 1 / 0)
        with pytest.raises(ZeroDivisionError):
            failed.result(timeout=5.0)
        assert cycle.submit(lambda: "next").result(timeout=5.0) == "next"
    finally:
        cycle.stop()


def test_stop_cancels_what_waits_lets_what_runs_finish_and_ends_the_thread():
    cycle = AsyncCycle("test-cycle-stop")
    release, started = threading.Event(), threading.Event()
    running = cycle.submit(held(release, started, "ran"))
    assert started.wait(5.0)
    waiting = cycle.submit(lambda: "never")
    threading.Timer(0.1, release.set).start()
    cycle.stop(timeout_s=5.0)
    assert running.result(timeout=0) == "ran" and waiting.cancelled()
    assert "test-cycle-stop" not in [t.name for t in threading.enumerate()]
    assert cycle.submit(lambda: "after").cancelled()  # nothing is taken once stopped
