"""services/stack.py's rigs: the robot's side as processes carries one arm."""
import pytest

from services.robot_gateway.service import GatewayConfig
from services.robot_sim.service import RobotSimConfig
from services.runtime.transport import ZenohConfig
from services.stack import RobotProcesses


def test_the_gateway_runs_the_robot_s_arm_and_a_gateway_for_another_is_refused():
    six = RobotProcesses(ZenohConfig(), RobotSimConfig(arm="j2n6s300"))
    assert (six.robot.arm, six.gateway.arm) == ("j2n6s300", "j2n6s300")
    with pytest.raises(ValueError, match=r"mixes arms \(robot_sim j2n6s300, robot_gateway j2s7s300\)"):
        RobotProcesses(ZenohConfig(), RobotSimConfig(arm="j2n6s300"), GatewayConfig())
    # robot_sim alone has no gateway to disagree with
    assert RobotProcesses(ZenohConfig(), RobotSimConfig(arm="j2n6s300"), GatewayConfig(), profile="sim").robot.arm \
        == "j2n6s300"
