"""The robot node's command window (``command_window_s``): the DSP's plan must be ready before the next bus exchange.
How the DSP waits in it: tests/services/robot/test_command_inbox.py."""
import pytest

from services.robot.node import MAX_COMMAND_WINDOW_S, RobotNodeConfig


def test_the_window_must_leave_the_plan_time_before_the_next_exchange():
    with pytest.raises(ValueError, match="command_window_s"):
        RobotNodeConfig(command_window_s=MAX_COMMAND_WINDOW_S * 2)
    with pytest.raises(ValueError, match="command_window_s"):
        RobotNodeConfig(command_window_s=-0.001)
