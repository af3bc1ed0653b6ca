"""mfvs echo, hz and keys against a real zenoh router, and the summaries and statistics behind them."""
import io
import json
import threading
import time

import numpy as np
import pytest

from protocol import messages as m
from protocol.keys import Keys
from protocol.topics import UnknownTopic
from services.observe import introspect
from services.runtime.transport import open_session
from services.model.arm import load_arm
from tests.helpers import ARM_DECLARED

ARM = load_arm("j2s7s300")

KEYS = Keys()


def robot_state(seq: int) -> m.RobotState:
    return m.RobotState(**ARM_DECLARED, header=m.Header(seq=seq, stamp_ns=1_000_000_000 + seq * 10_000_000), q=list(ARM.home),
                        dq=[0.0] * 7, tau=[0.0] * 7,
                        pose=m.KinovaPose(X=0.2, Y=-0.3, Z=0.4, ThetaX=0, ThetaY=0, ThetaZ=0),
                        control_mode=m.ControlMode.CARTESIAN_VELOCITY)


class Publishing:
    """Robot states at ``rate_hz`` on the robot's key from a thread of this process, and some garbage on demand."""

    def __init__(self, session, rate_hz: float = 100.0) -> None:
        self.publisher = session.declare_publisher(KEYS.robot_state)
        self.period, self.stop = 1.0 / rate_hz, threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        start, k = time.monotonic(), 0
        while not self.stop.is_set():
            self.publisher.put(m.encode(robot_state(k)))
            k += 1
            self.stop.wait(max(0.0, start + k * self.period - time.monotonic()))

    def __enter__(self):
        self.thread.start()
        return self

    def __exit__(self, *exc):
        self.stop.set()
        self.thread.join()
        self.publisher.undeclare()


def test_a_summary_is_one_short_line_and_json_is_whole_and_strict():
    line = introspect.summary(robot_state(3))
    assert "\n" not in line and line.startswith("stamp=1.030") and "control_mode=\"cartesian_velocity\"" in line
    image = m.Image(header=m.Header(), width=640, height=480, encoding=m.ImageEncoding.MONO8, data=bytes(640 * 480))
    assert "data_bytes=307200" in introspect.summary(image) and len(introspect.summary(image)) < 200
    data = json.loads(introspect.as_json(image))
    assert data["data"] == {"bytes": 307200} and data["width"] == 640


def test_rate_statistics_over_a_window():
    stats = introspect.RateStats(window=50)
    rng = np.random.default_rng(1)
    t = 0.0
    for _ in range(200):
        t += 0.01 + rng.uniform(-0.001, 0.001)
        stats.add(t)
    report = stats.report()
    assert report["count"] == 200 and report["window"] == 50
    assert report["rate_hz"] == pytest.approx(100.0, rel=0.02)
    assert 0.3 < report["jitter_ms"] < 0.7 and report["min_ms"] >= 9.0 and report["max_ms"] <= 11.0
    assert introspect.RateStats().report() is None


def test_echo_prints_each_message_and_says_which_payload_did_not_decode(router):
    session = open_session(router.client_config())
    out, err = io.StringIO(), io.StringIO()
    try:
        garbage, echoed = session.declare_publisher(KEYS.robot_state), threading.Event()

        def spoil():  # among the states, until the echo is done (once, at a fixed time, raced the 30th state)
            while not echoed.wait(0.05):
                garbage.put(b"\x93not a state")

        threading.Thread(target=spoil, daemon=True).start()
        with Publishing(session):
            code = introspect.echo(session, KEYS, "robot/state", count=30, seconds=10.0, out=out, err=err)
        echoed.set()
        lines = out.getvalue().splitlines()
        assert code == 1 and len(lines) == 30 and all(line.startswith("stamp=") for line in lines)
        assert "mfvs/jaco/robot/state: undecodable RobotState payload" in err.getvalue()
        out = io.StringIO()
        with Publishing(session):
            assert introspect.echo(session, KEYS, "robot/*", as_json_lines=True, count=2, seconds=10.0,
                                   out=out) == 0
        first = json.loads(out.getvalue().splitlines()[0])
        assert first["key"] == KEYS.robot_state and first["message"]["q"] == pytest.approx(list(ARM.home))
    finally:
        session.close()


def test_hz_reports_the_rate_and_keys_lists_what_is_published(router):
    session = open_session(router.client_config())
    out = io.StringIO()
    try:
        with Publishing(session, rate_hz=100.0):
            time.sleep(0.2)
            reports = introspect.hz(session, KEYS, "robot/state", seconds=2.2, out=out)
            rows = introspect.discover(session, KEYS, seconds=1.0)
        report = reports[KEYS.robot_state]
        # generous: the publisher shares two cores with everything else
        assert 60 < report["rate_hz"] < 140 and report["count"] > 100
        assert "Hz" in out.getvalue().splitlines()[-1]
        row = next(r for r in rows if r["key"] == KEYS.robot_state)
        assert row["type"] == "RobotState" and row["messages"] > 50 and row["undecodable"] == 0
        assert "RobotState" in introspect.keys_table(rows, [], 1.0)
    finally:
        session.close()


def test_a_bad_key_is_refused_before_anything_is_subscribed(router):
    session = open_session(router.client_config())
    try:
        with pytest.raises(UnknownTopic, match="did you mean mfvs/jaco/robot/state"):
            introspect.echo(session, KEYS, "robot/stat", count=1)
        with pytest.raises(UnknownTopic, match="is no topic"):
            introspect.hz(session, KEYS, "robot/api/GetAngularPosition", seconds=0.1)
    finally:
        session.close()
