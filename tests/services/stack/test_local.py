"""services/stack/local.py's rigs: the robot's side as processes carries one arm; a stack is up when its services'
liveliness says so; a lockstep stack's router is forked warm."""
import gc
import json
import shutil
import subprocess
import sys
import threading
import time

import pytest

from protocol.keys import Keys
from services.robot_gateway.service import GatewayConfig
from services.robot_sim.service import RobotSimConfig
from services.runtime.transport import ZenohConfig, open_session
from services.stack.local import RobotProcesses, StackLogs, _endpoint_line, wait_alive


def test_the_gateway_runs_the_robot_s_arm_and_a_gateway_for_another_is_refused():
    six = RobotProcesses(ZenohConfig(), RobotSimConfig(arm="j2n6s300"))
    assert (six.robot.arm, six.gateway.arm) == ("j2n6s300", "j2n6s300")
    with pytest.raises(ValueError, match=r"mixes arms \(robot_sim j2n6s300, robot_gateway j2s7s300\)"):
        RobotProcesses(ZenohConfig(), RobotSimConfig(arm="j2n6s300"), GatewayConfig())
    # robot_sim alone has no gateway to disagree with
    assert RobotProcesses(ZenohConfig(), RobotSimConfig(arm="j2n6s300"), GatewayConfig(), profile="sim").robot.arm \
        == "j2n6s300"


def test_a_stack_s_logs_go_when_it_stops_and_stay_when_kept_even_once_the_stack_is_gone():
    stopped, kept, dropped = StackLogs("mfvs-test-"), StackLogs("mfvs-test-"), StackLogs("mfvs-test-")
    paths = [stopped.path, kept.path, dropped.path]
    assert all(path.is_dir() for path in paths)
    stopped.close()
    kept.keep()
    kept.close()  # a failed start keeps them, whatever stops after
    del stopped, kept, dropped  # never started, never stopped: collected
    gc.collect()
    try:
        assert [path.is_dir() for path in paths] == [False, True, False]
    finally:
        shutil.rmtree(paths[1], ignore_errors=True)


def _token(router, robot_id: str, name: str):
    session = open_session(router.client_config())
    return session, session.liveliness().declare_token(Keys(robot_id).liveliness(name))


def test_a_stack_is_up_as_soon_as_its_services_declare_their_liveliness(router, tmp_path):
    sleeper = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    sessions = [_token(router, "arm1", "safety")]
    try:
        declared_at = []

        def declare_later() -> None:
            time.sleep(0.3)
            declared_at.append(time.monotonic())  # before the token: the wait may see it before this thread runs on
            sessions.append(_token(router, "arm1", "vision"))

        start = time.monotonic()
        threading.Thread(target=declare_later).start()
        wait_alive(router.client_config(), "arm1", ["safety", "vision"], [sleeper], 10.0, tmp_path)
        alive_at = time.monotonic()
        # not before the second token was declared (the first was declared before the wait began: the subscriber's
        # history), and not long after
        assert declared_at and start + 0.3 <= declared_at[0] <= alive_at < start + 5.0
        # a token of another robot's is not this robot's service
        with pytest.raises(RuntimeError, match=r"controller not alive \(exited: \[\]"):
            other = _token(router, "arm2", "controller")
            sessions.append(other)
            wait_alive(router.client_config(), "arm1", ["controller"], [sleeper], 0.5, tmp_path)
    finally:
        sleeper.kill()
        sleeper.wait()
        for session, token in sessions:
            token.undeclare()
            session.close()


def test_a_stack_whose_process_exits_before_its_liveliness_fails_at_once_naming_it(router, tmp_path):
    quitter = subprocess.Popen([sys.executable, "-c", "pass"])
    quitter.wait()
    start = time.monotonic()
    with pytest.raises(RuntimeError, match=rf"safety not alive \(exited: .*-c.*pass.*logs in {tmp_path}"):
        wait_alive(router.client_config(), "arm1", ["safety"], [quitter], 30.0, tmp_path)
    assert time.monotonic() - start < 10.0  # not the 30 s timeout


def test_a_warm_router_s_endpoint_is_read_from_its_log_whatever_it_logged_before(tmp_path):
    log = tmp_path / "router.log"
    writer = subprocess.Popen([sys.executable, "-c", (
        "import sys, time\n"
        "f = open(sys.argv[1], 'a')\n"
        "f.write('2026-11-26 WARN zenoh: something first\\n'); f.flush(); time.sleep(0.2)\n"
        "f.write('{\"router\": \"tcp/127.0.0.1:1234\", '); f.flush(); time.sleep(0.2)\n"  # half a line: not yet
        "f.write('\"zid\": \"ab\"}\\n'); f.flush(); time.sleep(30)\n"), str(log)])
    try:
        line = _endpoint_line(log, writer, 10.0)
        assert json.loads(line) == {"router": "tcp/127.0.0.1:1234", "zid": "ab"}
    finally:
        writer.kill()
        writer.wait()
    quitter = subprocess.Popen([sys.executable, "-c", "import sys; open(sys.argv[1], 'w').write('bad config\\n')",
                                str(tmp_path / "quit.log")])
    quitter.wait()
    start = time.monotonic()
    assert _endpoint_line(tmp_path / "quit.log", quitter, 30.0) == "bad config\n"  # what it said, at once
    assert time.monotonic() - start < 10.0


def test_a_lockstep_stack_s_router_is_forked_warm_and_serves(tmp_path):
    from services.stack.local import RouterProcess
    from services.stack.warm_start import WarmProcess

    with RouterProcess(realtime_priority=0, warm_log=tmp_path / "router.log") as router:
        assert isinstance(router.process, WarmProcess)
        session = open_session(router.client_config())
        try:
            got = []
            subscriber = session.declare_subscriber("check/**", lambda sample: got.append(sample.payload.to_bytes()))
            deadline = time.monotonic() + 10.0
            while not got and time.monotonic() < deadline:
                session.put("check/a", b"through the router")
                time.sleep(0.05)
            subscriber.undeclare()
        finally:
            session.close()
        assert got and got[0] == b"through the router"
        process = router.process
    assert process.poll() is not None  # stopped with the context
