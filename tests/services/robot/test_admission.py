"""The robot applies only fresh commands, in sequence per sender (services.robot.admission), and says why not."""
import time

import msgspec
import numpy as np
import pytest

from protocol import messages as m
from protocol.conventions import AngularConvention, ClockMode, Frame
from services.runtime.transport import open_session
from services.robot.admission import AdmissionConfig, CommandAdmission
from services.robot_sim.service import RobotSimConfig, RobotSimService
from tests.stack import KEYS, Recorder, wait_for

NOW = 10_000_000_000


def header(seq, stamp=NOW, sender=None):
    trace = [m.Hop(service=sender, recv_ns=stamp, pub_ns=stamp)] if sender else []
    return m.Header(seq=seq, stamp_ns=stamp, trace=trace)


def test_fresh_commands_in_sequence_pass():
    admission = CommandAdmission()
    assert [admission.admit(header(s, NOW + s), NOW + s) for s in (1, 2, 5)] == [None, None, None]


@pytest.mark.parametrize("stamp, kind", [(0, "stale"), (NOW - 300_000_000, "stale"), (NOW - 3600 * 10**9, "stale"),
                                         (NOW + 60_000_000, "future"), (NOW + 3600 * 10**9, "future")])
def test_stale_unstamped_and_future_commands_are_refused(stamp, kind):
    rejection = CommandAdmission().admit(header(1, stamp), NOW)
    assert rejection is not None and rejection.kind == kind


def test_within_the_age_and_the_skew_pass():
    config = AdmissionConfig(max_age_s=0.2, max_future_s=0.05)
    assert CommandAdmission(config).admit(header(1, NOW - 190_000_000), NOW) is None
    assert CommandAdmission(config).admit(header(1, NOW + 40_000_000), NOW) is None


def test_a_command_fresh_on_arrival_is_stale_at_a_tick_past_its_age():
    """The robot checks the age again at the tick that would apply the command (services/robot/node.py dsp_tick):
    admitted 190 ms old, it must not be applied 15 ms later."""
    admission = CommandAdmission(AdmissionConfig(max_age_s=0.2))
    command = header(1, NOW - 190_000_000)
    assert admission.admit(command, NOW) is None
    assert admission.stale(command, NOW + 5_000_000) is None
    late = admission.stale(command, NOW + 15_000_000)
    assert late is not None and late.kind == "stale" and "205 ms ago" in late.reason


def test_a_repeat_or_a_replay_is_refused_per_sender_until_its_new_session():
    admission = CommandAdmission()
    assert admission.admit(header(7, sender="safety"), NOW) is None
    for seq in (7, 3):
        rejection = admission.admit(header(seq, sender="safety"), NOW)
        assert rejection.kind == "sequence" and "safety" in rejection.reason
    assert admission.admit(header(1, sender="operator_tool"), NOW) is None  # another sender numbers its own
    admission.new_session("safety")
    assert admission.admit(header(1, sender="safety"), NOW) is None


def command(seq, stamp_ns, linear=(0.05, 0.0, 0.0)):
    h = m.Header(seq=seq, stamp_ns=stamp_ns)
    twist = m.Twist(header=h, frame=Frame.MIXED, angular=AngularConvention.SEED000, linear=linear,
                    rotational=(0.0, 0.0, 0.0))
    return m.encode(m.RobotCommand(header=h, mode=m.CommandMode.CARTESIAN_VELOCITY, twist=twist))


def test_the_robot_refuses_a_replayed_capture_stale_future_and_repeated_commands(router):
    """Probes of the issue: a command stamped an hour ago, one stamped 0, one an hour ahead, a repeated sequence
    number, and a capture of valid commands replayed a second later: none moves the arm; each is counted and the
    state says why."""
    robot = RobotSimService(RobotSimConfig(clock=ClockMode.REALTIME, zenoh=router.client_config())).start()
    client = open_session(router.client_config())
    try:
        states = Recorder(client, KEYS.robot_state, m.RobotState)
        assert wait_for(lambda: len(states) > 5)
        q0 = np.array(states.last().q)
        now = time.time_ns()
        for payload in (command(1, now - 3600 * 10**9), command(2, 0), command(3, now + 3600 * 10**9)):
            client.put(KEYS.robot_command, payload)
        assert wait_for(lambda: robot.counters.get("rejected.command") == 3, timeout=5)
        assert robot.counters.get("refused.stale") == 2 and robot.counters.get("refused.future") == 1
        # a valid burst moves the arm; the same bytes replayed are refused
        capture = [command(100 + k, time.time_ns() + k * 10_000_000) for k in range(30)]
        for k, payload in enumerate(capture):
            time.sleep(max(0.0, (msgspec.msgpack.decode(payload)["header"]["stamp_ns"] - time.time_ns()) * 1e-9))
            client.put(KEYS.robot_command, payload)
        assert wait_for(lambda: np.abs(np.array(states.last().q) - q0).max() > 1e-3, timeout=5)
        client.put(KEYS.robot_command, command(129, time.time_ns(), linear=(0.0, 0.0, 0.0)))  # repeat of the last
        assert wait_for(lambda: robot.counters.get("refused.sequence") == 1, timeout=5)
        time.sleep(0.5)  # the arm stops (the watchdog) and settles
        rest = np.array(states.last().q)
        refused_before = robot.counters.get("rejected.command")
        for payload in capture:  # replayed: fresh enough? no: stale, or out of sequence
            client.put(KEYS.robot_command, payload)
            time.sleep(0.01)
        assert wait_for(lambda: robot.counters.get("rejected.command") == refused_before + len(capture), timeout=5)
        time.sleep(0.2)
        assert np.abs(np.array(states.last().q) - rest).max() < 1e-3
        assert any(f.startswith("refused: ") for s in states.snapshot()[-30:] for f in s.faults)
    finally:
        client.close()
        robot.stop()


def test_low_level_torques_are_admitted_as_robot_commands_are(router):
    """Torques bypass safety: a stale or repeated torque command does not engage low-level control."""
    robot = RobotSimService(RobotSimConfig(clock=ClockMode.REALTIME, zenoh=router.client_config())).start()
    client = open_session(router.client_config())
    try:
        time.sleep(0.3)
        torques = lambda seq, stamp: m.encode(m.TorqueCommand(header=m.Header(seq=seq, stamp_ns=stamp),
                                                              torques=[0.0] * 7))
        client.put(KEYS.lowlevel_command, torques(1, time.time_ns() - 3600 * 10**9))
        client.put(KEYS.lowlevel_command, torques(2, 0))
        assert wait_for(lambda: robot.counters.get("refused.lowlevel_stale") == 2, timeout=5)
        client.put(KEYS.lowlevel_command, torques(5, time.time_ns()))
        client.put(KEYS.lowlevel_command, torques(5, time.time_ns()))
        assert wait_for(lambda: robot.counters.get("refused.lowlevel_sequence") == 1, timeout=5)
    finally:
        client.close()
        robot.stop()
