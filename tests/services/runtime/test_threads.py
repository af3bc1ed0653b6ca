"""A service's loop thread: named for the kernel, and a failing loop logged, counted and marked finished."""
import logging
import threading

from services.runtime.metrics import Counters
from services.runtime.threads import run_loop, start_thread


def test_a_failing_loop_is_logged_counted_and_finished(caplog):
    counters, finished = Counters(), threading.Event()

    def body():
        raise RuntimeError("bus gone")

    with caplog.at_level(logging.ERROR):
        run_loop(body, "robot loop", logging.getLogger("test"), counters, finished)
    assert finished.is_set() and counters.snapshot()["errors.loop"] == 1
    assert "robot loop failed" in caplog.text and "bus gone" in caplog.text
    finished.clear()
    run_loop(lambda: None, "robot loop", logging.getLogger("test"), counters, finished)
    assert finished.is_set() and counters.snapshot()["errors.loop"] == 1


def test_a_thread_is_named_for_the_kernel_too():
    seen = {}

    def body():
        with open(f"/proc/self/task/{threading.get_native_id()}/comm") as f:
            seen["comm"] = f.read().strip()

    start_thread(body, "mfvs-test-loop").join(5)
    assert seen["comm"] == "mfvs-test-loop"
