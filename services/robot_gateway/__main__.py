"""``python -m services.robot_gateway [--config FILE] [--connect ENDPOINT]``"""
import sys

from services.common.service import service_main
from services.robot_gateway.service import GatewayConfig, RobotGatewayService

if __name__ == "__main__":
    sys.exit(service_main(RobotGatewayService, GatewayConfig, description="the robot API backed by an RS-485 arm"))
