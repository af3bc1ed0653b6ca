"""A lockstep stack composed in one process (services/stack/composed.py): its session reaches nothing outside the
process, it refuses what it cannot run, and its services' logs are theirs. That a composed run logs exactly what the
same run as processes logs: tests/services/servo/test_run.py."""
import logging
import os
import shutil
import subprocess
import sys
import threading
import time

import pytest

from protocol.conventions import ClockMode
from protocol.keys import Keys
from services.stack.composed import CallbackExecutor, ComposedStack, SharedSession, composable, open_local_session
from services.runtime.service import Service, query_health
from services.servo.scenario import load_scenario, stack_config
from services.vision.service import VisionService
from tests.helpers import REPO

EASY = REPO / "examples" / "scenarios" / "easy.yaml"


def _network_socket_inodes() -> set[str]:
    """The inodes of every TCP socket listening on this host and of every UDP socket (scouting is UDP multicast),
    IPv4 and IPv6."""
    inodes = set()
    for table, listening_only in (("/proc/net/tcp", True), ("/proc/net/tcp6", True), ("/proc/net/udp", False),
                                  ("/proc/net/udp6", False)):
        with open(table) as f:
            for line in list(f)[1:]:
                fields = line.split()
                if not listening_only or fields[3] == "0A":  # TCP_LISTEN
                    inodes.add(fields[9])
    return inodes


def _my_socket_inodes() -> set[str]:
    inodes = set()
    for fd in os.listdir("/proc/self/fd"):
        try:
            target = os.readlink(f"/proc/self/fd/{fd}")
        except OSError:
            continue
        if target.startswith("socket:["):
            inodes.add(target[len("socket:["):-1])
    return inodes


def test_the_local_session_listens_on_no_port_scouts_nobody_and_delivers_within_itself():
    before = _my_socket_inodes() & _network_socket_inodes()
    session = open_local_session()
    try:
        time.sleep(0.3)  # a scout's socket opens on zenoh's threads, after the session is open
        assert _my_socket_inodes() & _network_socket_inodes() == before
        got = threading.Event()
        subscriber = session.declare_subscriber("mfvs/test/composed", lambda sample: got.set())
        session.put("mfvs/test/composed", b"x")
        assert got.wait(5.0)
        subscriber.undeclare()
    finally:
        session.close()


def test_only_the_sim_profile_in_lockstep_is_composed():
    config = stack_config(load_scenario(EASY))
    assert config.clock is ClockMode.LOCKSTEP and composable(config)
    config.profile = "gateway"
    assert not composable(config)
    with pytest.raises(ValueError, match="gateway profile"):
        ComposedStack(config)
    config.profile, config.clock = "sim", ClockMode.REALTIME
    with pytest.raises(ValueError, match="realtime"):
        ComposedStack(config)


def test_a_composed_stack_answers_health_logs_each_service_to_its_file_and_keeps_them_when_its_start_fails():
    """The services come up on the stack's session (their health answers there), each logging into ``<name>.log``
    rather than this process's handlers; a start that fails stops what started, leaves this process's logging as it
    was, and keeps the logs."""
    config = stack_config(load_scenario(EASY))
    seen: dict = {}
    root_records: list[logging.LogRecord] = []

    class Collect(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            root_records.append(record)

    collect = Collect(level=logging.DEBUG)
    logging.getLogger().addHandler(collect)

    def before_robot(stack: ComposedStack) -> None:
        session = stack.open_session()
        session.close()  # a client's close: the stack's session stays open
        seen["health"] = query_health(session, Keys(config.robot.robot_id))
        seen["logs"] = stack.logs
        raise RuntimeError("the observer failed")

    try:
        with pytest.raises(RuntimeError, match="the observer failed"):
            with ComposedStack(config, before_robot=before_robot):
                pass
    finally:
        logging.getLogger().removeHandler(collect)
    assert set(seen["health"]) == {"safety", "vision", "controller"}
    logs = seen["logs"]
    assert logs.is_dir(), "the logs of a stack that failed to start are kept"
    assert "safety started" in (logs / "safety.log").read_text()
    assert "vision started" in (logs / "vision.log").read_text()
    assert not [r for r in root_records if r.name.startswith(("mfvs.safety", "mfvs.vision", "mfvs.controller"))]
    assert logging.getLogger("mfvs.safety").propagate and not logging.getLogger("mfvs.safety").handlers
    alive = [t.name for t in threading.enumerate() if t.name.startswith(("safety", "vision", "controller"))]
    assert not alive, f"threads of the stopped services: {alive}"
    shutil.rmtree(logs)


def test_a_process_running_one_composed_run_after_another_does_not_keep_what_each_run_freed():
    """Every composed run starts threads of its own, and glibc keeps what a thread frees in that thread's arena:
    without giving it back after each run, a process grew by ~20 MB a run (to ~500 MB after 16 runs); with it, by
    ~1 MB. Six short runs in a fresh process: the last holds at most 50 MB more than the first."""
    script = f"""
import sys
sys.path.insert(0, {str(REPO)!r})
from bench.cpu import rss_mb
import os
from services.servo.run import run
from services.servo.scenario import load_scenario
scenario = load_scenario({str(EASY)!r})
scenario.convergence.max_iterations = 10
for _ in range(6):
    assert run(scenario, plots=False).stack == "composed"
    print(rss_mb(os.getpid()), flush=True)
"""
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300, cwd=REPO)
    assert done.returncode == 0, done.stderr[-2000:]
    resident = [float(line) for line in done.stdout.split()]
    assert len(resident) == 6
    assert resident[-1] - resident[0] < 50.0, resident


def _threads_of(*services: str) -> list[str]:
    return [t.name for t in threading.enumerate() if t.name.startswith(services)]


def _logging_restored() -> bool:
    return all(logging.getLogger(name).propagate and not logging.getLogger(name).handlers
               for name in ("mfvs.safety", "mfvs.vision", "mfvs.controller", "mfvs.robot_sim", "mujoco"))


def test_a_service_whose_start_fails_halfway_is_stopped_with_the_rest(monkeypatch):
    """vision's start fails after its on_start began its worker thread: in a process of its own the thread ended with
    the process; composed, the stack stops it, and the services started before it."""
    real = Service.queryable

    def failing(service, key, handler):
        if key.endswith("/health/vision"):
            raise RuntimeError("declaration refused")
        return real(service, key, handler)

    monkeypatch.setattr(Service, "queryable", failing)
    stack = ComposedStack(stack_config(load_scenario(EASY)))
    with pytest.raises(RuntimeError, match="declaration refused"):
        stack.__enter__()
    assert not _threads_of("safety", "vision", "controller", "robot_sim")
    assert stack.session is None and _logging_restored()
    shutil.rmtree(stack.logs)


def test_a_stop_that_fails_leaves_the_rest_stopped_and_this_process_as_it_was(monkeypatch):
    def failing_stop(service):
        raise RuntimeError("vision would not stop")

    monkeypatch.setattr(VisionService, "on_stop", failing_stop)
    stack = ComposedStack(stack_config(load_scenario(EASY))).__enter__()
    assert _threads_of("safety") and _threads_of("robot_sim")
    with pytest.raises(RuntimeError, match="vision would not stop"):
        stack.__exit__(None, None, None)
    assert not _threads_of("safety", "controller", "robot_sim")
    assert stack.session is None and _logging_restored() and not stack.logs.exists()


@pytest.fixture
def executed_session():
    session = open_local_session()
    executor = CallbackExecutor()
    try:
        yield SharedSession(session, executor), executor
    finally:
        executor.close()
        session.close()


def _wait_for(condition, timeout_s: float = 5.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.005)
    return True


def test_every_subscriber_callback_runs_on_the_executor_in_arrival_order(executed_session):
    """Two subscribers' samples, published alternately from this thread, and one published from within a callback:
    every callback on the executor's one thread (never the publisher's), in the order the samples were put; the
    nested put waits its turn instead of running inside the callback that made it."""
    session, _ = executed_session
    seen, all_put = [], threading.Event()

    def on_b(sample):
        seen.append((threading.current_thread().name, "b", sample.payload.to_bytes()))
        all_put.wait(5.0)  # the first one holds the executor until every sample of this thread is queued

    def on_a(sample):
        seen.append((threading.current_thread().name, "a", sample.payload.to_bytes()))
        if sample.payload.to_bytes() == b"3":
            session.put("mfvs/test/b", b"from a")
            seen.append((threading.current_thread().name, "a", b"after its put"))

    subscribers = [session.declare_subscriber("mfvs/test/a", on_a), session.declare_subscriber("mfvs/test/b", on_b)]
    for i in range(10):
        session.put("mfvs/test/a" if i % 2 else "mfvs/test/b", str(i).encode())
    all_put.set()
    assert _wait_for(lambda: len(seen) == 12)
    assert {thread for thread, _, _ in seen} == {"composed-callbacks"}
    assert [(key, payload) for _, key, payload in seen] == [
        ("b", b"0"), ("a", b"1"), ("b", b"2"), ("a", b"3"), ("a", b"after its put"), ("b", b"4"), ("a", b"5"),
        ("b", b"6"), ("a", b"7"), ("b", b"8"), ("a", b"9"), ("b", b"from a")]
    for subscriber in subscribers:
        subscriber.undeclare()


def test_the_executor_goes_on_past_a_failing_callback_and_drops_an_undeclared_subscriber_samples(executed_session):
    session, executor = executed_session
    release, seen = threading.Event(), []

    def blocking_then_failing(sample):
        release.wait(5.0)
        raise RuntimeError("a runner's callback failed")

    first = session.declare_subscriber("mfvs/test/first", blocking_then_failing)
    second = session.declare_subscriber("mfvs/test/second", lambda sample: seen.append(sample.payload.to_bytes()))
    session.put("mfvs/test/first", b"x")  # holds the executor until released
    session.put("mfvs/test/second", b"queued, then undeclared")
    second.undeclare()
    third = session.declare_subscriber("mfvs/test/second",
                                       lambda sample: seen.append(b"third " + sample.payload.to_bytes()))
    session.put("mfvs/test/second", b"after")
    release.set()
    assert _wait_for(lambda: seen == [b"third after"])
    assert executor.failures == 1
    first.undeclare()
    third.undeclare()


def test_a_closed_executor_drops_what_is_queued_and_its_thread_ends():
    executor, ran, release = CallbackExecutor(), [], threading.Event()
    executor.submit(lambda _: release.wait(5.0), None)
    executor.submit(ran.append, "dropped")
    closing = threading.Thread(target=executor.close)
    closing.start()
    assert _wait_for(lambda: executor._closed)  # closed while the first still runs: the second was queued
    release.set()
    closing.join(10.0)
    assert not closing.is_alive() and not executor._thread.is_alive()
    executor.submit(ran.append, "after close")
    time.sleep(0.05)
    assert ran == []
