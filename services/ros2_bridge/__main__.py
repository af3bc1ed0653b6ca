"""``python -m services.ros2_bridge [--config FILE] [--connect ENDPOINT] [--set domain_id=3]``"""
import sys

from services.ros2_bridge.service import Ros2BridgeConfig, Ros2BridgeService
from services.runtime.service import service_main

if __name__ == "__main__":
    sys.exit(service_main(Ros2BridgeService, Ros2BridgeConfig,
                          description="the stack as a ROS 2 node on rmw_zenoh's wire"))
