"""The DSP's command window (``command_window_s``, realtime): after its tick it waits a little for a command from a
newer frame than the last it took, never for a resend, never past its deadline, never for a stop."""
import threading
import time

import pytest

from protocol import messages as m
from protocol.conventions import AngularConvention
from services.robot.node import MAX_COMMAND_WINDOW_S, RobotNode, RobotNodeConfig, fresh


def command(source_ns: int, mode=m.CommandMode.CARTESIAN_VELOCITY) -> m.RobotCommand:
    header = m.Header(stamp_ns=time.time_ns(), source_stamp_ns=source_ns)
    return m.RobotCommand(header=header, mode=mode,
                          twist=m.Twist(header=header, frame=m.Frame.MIXED, angular=AngularConvention.EULER_XYZ_RATES,
                                        linear=(0.01, 0.0, 0.0), rotational=(0.0, 0.0, 0.0)))


def test_fresh_is_a_newer_frame_s_command_or_one_from_no_frame_or_a_stop():
    assert fresh(command(200), 100) and not fresh(command(100), 100) and not fresh(command(50), 100)
    assert fresh(command(0), 100)  # an operator's or an API's
    assert fresh(command(50, m.CommandMode.STOP), 100) and fresh(command(50, m.CommandMode.EMERGENCY_STOP), 100)


def arrive(node: RobotNode, cmd: m.RobotCommand) -> None:
    """As _on_command leaves an admitted command for the DSP."""
    with node.command_cond:
        node._command = (cmd, time.time_ns())
        node.command_cond.notify_all()


def test_the_dsp_waits_in_its_window_for_a_newer_frame_s_command_and_takes_it_when_it_comes():
    node = RobotNode(RobotNodeConfig(command_window_s=0.001))
    arrive(node, command(100))
    assert node.take_command()[0].header.source_stamp_ns == 100  # the frame's command, taken
    arrive(node, command(100))  # safety's resend of it
    later = command(200)
    threading.Timer(0.05, arrive, (node, later)).start()
    start = time.monotonic()
    taken = node.take_command(wait_until=start + 10.0)  # a window far longer than the real one: no race
    assert taken[0] is later and time.monotonic() - start < 5.0  # taken when it came, not at the deadline
    # nothing newer comes: the resend waiting is taken at the deadline
    arrive(node, command(200))
    start = time.monotonic()
    taken = node.take_command(wait_until=start + 0.05)
    assert taken[0].header.source_stamp_ns == 200 and time.monotonic() - start >= 0.05
    # nothing at all: None at the deadline; a fresh one waiting: at once
    assert node.take_command(wait_until=time.monotonic() + 0.01) is None
    arrive(node, command(300))
    start = time.monotonic()
    assert node.take_command(wait_until=start + 10.0)[0].header.source_stamp_ns == 300
    assert time.monotonic() - start < 5.0


def test_a_stop_is_never_waited_past():
    node = RobotNode(RobotNodeConfig(command_window_s=0.001))
    arrive(node, command(100))
    node.take_command()
    arrive(node, command(100, m.CommandMode.EMERGENCY_STOP))
    start = time.monotonic()
    assert node.take_command(wait_until=start + 10.0)[0].mode is m.CommandMode.EMERGENCY_STOP
    assert time.monotonic() - start < 5.0


def test_the_window_must_leave_the_plan_time_before_the_next_exchange():
    with pytest.raises(ValueError, match="command_window_s"):
        RobotNodeConfig(command_window_s=MAX_COMMAND_WINDOW_S * 2)
    with pytest.raises(ValueError, match="command_window_s"):
        RobotNodeConfig(command_window_s=-0.001)
