"""The e-stop sent from a realtime process of its own (services/safety/estop_sender.py), against the safety service
on a real router: confirmed as EStopClient's, every thread of the sender at SCHED_FIFO, an engage never behind a
release, and the e-stop still sent when the sender is gone."""
import os
import signal
import threading
import time

import pytest

from protocol import messages as m
from protocol.conventions import ClockMode
from services.runtime.metrics import Counters
from services.runtime.transport import open_session
from services.safety.estop_sender import ESTOP_REALTIME_PRIORITY, EStopSender
from services.safety.service import SafetyConfig, SafetyService
from tests.stack import KEYS, Recorder, wait_for

SCHED_FIFO = 1


def scheduling(pid: int) -> dict[str, tuple[int, int]]:
    """Each thread of a process: (policy, realtime priority), from /proc (stat fields 40 and 41)."""
    found = {}
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            with open(f"/proc/{pid}/task/{tid}/stat") as f:
                stat = f.read()
            with open(f"/proc/{pid}/task/{tid}/comm") as f:
                name = f.read().strip()
        except FileNotFoundError:  # a thread that ended meanwhile
            continue
        fields = stat[stat.rindex(")") + 2:].split()  # after the command's name, which may hold spaces
        found[f"{name}/{tid}"] = (int(fields[38]), int(fields[37]))
    return found


@pytest.fixture
def session_and_safety(router):
    safety = SafetyService(SafetyConfig(clock=ClockMode.REALTIME, zenoh=router.client_config())).start()
    session = open_session(router.client_config())
    try:
        yield session, safety
    finally:
        session.close()
        safety.stop()


def test_engage_and_release_go_out_from_the_realtime_sender_and_are_confirmed(router, session_and_safety):
    session, safety = session_and_safety
    counters = Counters()
    requests = Recorder(session, KEYS.estop, m.EStop)
    try:
        with EStopSender(session, KEYS, router.client_config(), count=counters.inc) as sender:
            assert sender.wait_ready(30)
            threads = scheduling(sender._child.pid)
            assert threads and all(policy == (SCHED_FIFO, ESTOP_REALTIME_PRIORITY) for policy in threads.values()), \
                threads
            engaged = sender.send(reset=False, operator="alice", reason="test", timeout_s=10)
            assert engaged is not None and engaged.state is m.SafetyState.ESTOP
            assert safety.core.estop_latched and safety.core.estop_reason == "alice: test"
            released = sender.send(reset=True, operator="alice", timeout_s=10)
            assert released is not None and released.state is not m.SafetyState.ESTOP
            assert counters.get("estop.sent_by_child") == 2 and counters.get("estop.fallback") == 0
            assert sender.health() == (True, "e-stop sender ready")
        assert wait_for(lambda: len(requests) >= 2)
        assert [r.reset for r in requests.snapshot()][:1] == [False] and requests.last().reset
    finally:
        requests.close()


def test_an_engage_goes_out_while_a_release_waits_for_its_confirmation(router):
    """No safety: a release waits its whole timeout for a confirmation that never comes; an engage asked meanwhile
    is on the wire before that wait ends."""
    session = open_session(router.client_config())
    requests = Recorder(session, KEYS.estop, m.EStop)
    try:
        with EStopSender(session, KEYS, router.client_config()) as sender:
            assert sender.wait_ready(30)
            release = threading.Thread(target=sender.send, args=(True, "alice", "", 5.0))
            release.start()
            assert wait_for(lambda: any(r.reset for r in requests.snapshot()), timeout=5)
            assert sender.send(reset=False, operator="bob", timeout_s=0.3) is None
            engages = [r for r in requests.snapshot() if not r.reset]
            assert engages and release.is_alive(), "the engage waited behind the release"
            assert engages[0].operator == "bob"
            release.join()
    finally:
        requests.close()
        session.close()


def test_with_the_sender_gone_the_e_stop_goes_out_from_the_service_and_its_health_says_so(router,
                                                                                        session_and_safety):
    session, safety = session_and_safety
    counters = Counters()
    with EStopSender(session, KEYS, router.client_config(), count=counters.inc) as sender:
        assert sender.wait_ready(30)
        os.kill(sender._child.pid, signal.SIGKILL)
        assert wait_for(lambda: not sender.health()[0], timeout=10)
        assert "exited" in sender.health()[1]
        engaged = sender.send(reset=False, operator="alice", reason="sender gone", timeout_s=10)
        assert engaged is not None and engaged.state is m.SafetyState.ESTOP
        assert safety.core.estop_reason == "alice: sender gone"
        assert counters.get("estop.fallback") == 1 and counters.get("estop.child_exits") == 1


def test_before_the_sender_is_up_the_e_stop_goes_out_from_the_service(router, session_and_safety):
    session, safety = session_and_safety
    counters = Counters()
    with EStopSender(session, KEYS, router.client_config(), count=counters.inc) as sender:
        started = time.monotonic()
        assert not sender.ready  # a fresh interpreter takes far longer than this to import zenoh and declare
        engaged = sender.send(reset=False, operator="alice", timeout_s=10)
        assert engaged is not None and engaged.state is m.SafetyState.ESTOP, time.monotonic() - started
        assert counters.get("estop.fallback") == 1


def test_a_hung_sender_is_ended_and_the_e_stop_goes_out_from_the_service(router, session_and_safety):
    """Alive but silent (SIGSTOP): the engage goes out from the service once the child has not put it on the wire
    within its budget, without waiting for the request's timeout; past that timeout the child is ended, and the
    next e-stop does not wait for it again."""
    session, safety = session_and_safety
    counters = Counters()
    with EStopSender(session, KEYS, router.client_config(), count=counters.inc) as sender:
        assert sender.wait_ready(30)
        os.kill(sender._child.pid, signal.SIGSTOP)
        engaged = sender.send(reset=False, operator="alice", reason="hung sender", timeout_s=8)
        assert engaged is not None and engaged.state is m.SafetyState.ESTOP
        assert sender._child.poll() is None, "the engage waited for the hung child to be ended"
        assert counters.get("estop.fallback") == 1 and counters.get("estop.child_late") == 1
        assert wait_for(lambda: not sender.health()[0], timeout=20)
        started = time.monotonic()
        assert sender.send(reset=True, operator="alice", timeout_s=10) is not None
        assert counters.get("estop.fallback") == 2 and time.monotonic() - started < 5


def test_a_malformed_request_is_refused_by_the_sender_which_goes_on(router, session_and_safety):
    session, safety = session_and_safety
    counters = Counters()
    with EStopSender(session, KEYS, router.client_config(), count=counters.inc) as sender:
        assert sender.wait_ready(30)
        sender._child.stdin.write(b"not json\n{\"id\": 1, \"reset\": \"maybe\"}\n")
        engaged = sender.send(reset=False, operator="alice", timeout_s=10)
        assert engaged is not None and engaged.state is m.SafetyState.ESTOP
        assert counters.get("estop.sent_by_child") == 1 and sender.health() == (True, "e-stop sender ready")
