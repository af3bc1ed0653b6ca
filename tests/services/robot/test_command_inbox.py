"""services/robot/command_inbox.py, no zenoh: commands are admitted and the latest held for the DSP; in its command
window (``command_window_s``, realtime) the DSP waits a little for a command from a newer frame than the last it
took, never for a resend, never past its deadline, never for a stop; in lockstep a command answers a tick stamped at
or after it, and the frame taken at it."""
import threading
import time

from protocol import messages as m
from protocol.conventions import AngularConvention
from services.robot.admission import AdmissionConfig
from services.robot.command_inbox import CommandInbox, fresh


def command(source_ns: int, mode=m.CommandMode.CARTESIAN_VELOCITY, seq=0, stamp_ns=None) -> m.RobotCommand:
    header = m.Header(seq=seq, stamp_ns=time.time_ns() if stamp_ns is None else stamp_ns, source_stamp_ns=source_ns)
    return m.RobotCommand(header=header, mode=mode,
                          twist=m.Twist(header=header, frame=m.Frame.MIXED, angular=AngularConvention.EULER_XYZ_RATES,
                                        linear=(0.01, 0.0, 0.0), rotational=(0.0, 0.0, 0.0)))


class Arrivals:
    """Commands as the zenoh callback offers them, each numbered after the last (admission wants a sequence)."""

    def __init__(self, inbox: CommandInbox) -> None:
        self.inbox, self.seq = inbox, 0

    def __call__(self, source_ns: int, mode=m.CommandMode.CARTESIAN_VELOCITY) -> m.RobotCommand:
        self.seq += 1
        cmd = command(source_ns, mode, seq=self.seq)
        assert self.inbox.offer(cmd, time.time_ns()) is None
        return cmd


def test_fresh_is_a_newer_frame_s_command_or_one_from_no_frame_or_a_stop():
    assert fresh(command(200), 100) and not fresh(command(100), 100) and not fresh(command(50), 100)
    assert fresh(command(0), 100)  # an operator's or an API's
    assert fresh(command(50, m.CommandMode.STOP), 100) and fresh(command(50, m.CommandMode.EMERGENCY_STOP), 100)


def test_the_dsp_waits_in_its_window_for_a_newer_frame_s_command_and_takes_it_when_it_comes():
    inbox = CommandInbox(AdmissionConfig())
    arrive = Arrivals(inbox)
    arrive(100)
    assert inbox.take()[0].header.source_stamp_ns == 100  # the frame's command, taken
    arrive(100)  # safety's resend of it
    later = threading.Timer(0.05, arrive, (200,))
    later.start()
    start = time.monotonic()
    taken = inbox.take(wait_until=start + 10.0)  # a window far longer than the real one: no race
    assert taken[0].header.source_stamp_ns == 200 and time.monotonic() - start < 5.0  # when it came, not at the end
    # nothing newer comes: the resend waiting is taken at the deadline
    arrive(200)
    start = time.monotonic()
    taken = inbox.take(wait_until=start + 0.05)
    assert taken[0].header.source_stamp_ns == 200 and time.monotonic() - start >= 0.05
    # nothing at all: None at the deadline; a fresh one waiting: at once
    assert inbox.take(wait_until=time.monotonic() + 0.01) is None
    arrive(300)
    start = time.monotonic()
    assert inbox.take(wait_until=start + 10.0)[0].header.source_stamp_ns == 300
    assert time.monotonic() - start < 5.0


def test_a_stop_is_never_waited_past_nor_a_node_that_is_done():
    inbox = CommandInbox(AdmissionConfig())
    arrive = Arrivals(inbox)
    arrive(100)
    inbox.take()
    arrive(100, m.CommandMode.EMERGENCY_STOP)
    start = time.monotonic()
    assert inbox.take(wait_until=start + 10.0)[0].mode is m.CommandMode.EMERGENCY_STOP
    assert time.monotonic() - start < 5.0
    start = time.monotonic()
    assert inbox.take(wait_until=start + 10.0, done=lambda: True) is None and time.monotonic() - start < 5.0


def test_only_admitted_commands_wait_and_the_newest_replaces_one_not_taken():
    inbox = CommandInbox(AdmissionConfig())
    now = time.time_ns()
    assert inbox.offer(command(0, seq=5, stamp_ns=now), now) is None
    assert inbox.offer(command(0, seq=5, stamp_ns=now), now).kind == "sequence"  # a repeat
    assert inbox.offer(command(0, seq=9, stamp_ns=now - 10**9), now).kind == "stale"
    assert inbox.offer(command(0, seq=6, stamp_ns=now), now) is None
    assert inbox.take()[0].header.seq == 6 and inbox.take() is None
    inbox.new_session("")  # the sender's new session numbers afresh, for robot and torque commands alike
    assert inbox.offer(command(0, seq=1, stamp_ns=now), now) is None
    assert inbox.admit_torque(m.Header(seq=1, stamp_ns=now), now) is None
    assert inbox.admit_torque(m.Header(seq=1, stamp_ns=now), now).kind == "sequence"


def test_a_command_answers_a_tick_stamped_at_or_after_it_and_the_frame_taken_at_it():
    inbox = CommandInbox(AdmissionConfig())
    tick = time.time_ns()
    with inbox.changed:
        assert not inbox.answers(tick, None)  # nothing waiting
    inbox.offer(command(source_ns=tick - 5, seq=1, stamp_ns=tick - 1), tick)
    with inbox.changed:
        assert not inbox.answers(tick, None)  # stamped before the tick: the last tick's answer
    inbox.offer(command(source_ns=tick - 5, seq=2, stamp_ns=tick), tick)
    with inbox.changed:
        assert inbox.answers(tick, None) and not inbox.answers(tick, tick - 2)  # from an older frame than the tick's
    inbox.offer(command(source_ns=tick - 2, seq=3, stamp_ns=tick + 1), tick)
    with inbox.changed:
        assert inbox.answers(tick, tick - 2)
