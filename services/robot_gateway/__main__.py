"""``python -m services.robot_gateway [--config FILE] [--connect ENDPOINT]``"""
import sys

from services.runtime.service import service_main
from services.robot_gateway.service import GatewayConfig, robot_gateway_service

if __name__ == "__main__":
    sys.exit(service_main(robot_gateway_service, GatewayConfig, description="the robot API backed by a real arm"))
