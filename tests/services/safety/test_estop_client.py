"""The e-stop client `mfvs estop` and the console share, against the safety service on a real router."""
import time

from protocol import messages as m
from protocol.conventions import ClockMode
from services.safety.estop_client import EStopClient
from services.runtime.transport import open_session
from services.safety.service import SafetyConfig, SafetyService
from tests.stack import KEYS, Recorder, wait_for


def test_engage_and_release_are_confirmed_by_safetys_status(router):
    safety = SafetyService(SafetyConfig(clock=ClockMode.REALTIME, zenoh=router.client_config())).start()
    session = open_session(router.client_config())
    requests = Recorder(session, KEYS.estop, m.EStop)
    try:
        with EStopClient(session, KEYS) as client:
            engaged = client.send(reset=False, operator="alice", reason="test", timeout_s=10)
            assert engaged is not None and engaged.state is m.SafetyState.ESTOP
            assert safety.core.estop_latched and safety.core.estop_reason == "alice: test"
            released = client.send(reset=True, operator="alice", timeout_s=10)
            assert released is not None and released.state is not m.SafetyState.ESTOP
            assert not safety.core.estop_latched
        assert wait_for(lambda: len(requests) >= 2)
        assert [r.reset for r in requests.snapshot()][:1] == [False] and requests.last().reset
    finally:
        requests.close()
        session.close()
        safety.stop()


def test_without_safety_nothing_confirms_and_the_request_is_sent_again(router):
    session = open_session(router.client_config())
    requests = Recorder(session, KEYS.estop, m.EStop)
    try:
        with EStopClient(session, KEYS) as client:
            time.sleep(0.2)
            started = time.monotonic()
            assert client.send(reset=False, operator="alice", timeout_s=0.5) is None
            assert 0.5 <= time.monotonic() - started < 2.0
        assert wait_for(lambda: len(requests) >= 3)  # one every 0.1 s until the time ran out
    finally:
        requests.close()
        session.close()
