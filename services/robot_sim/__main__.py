"""``python -m services.robot_sim [--config FILE] [--clock realtime|lockstep] [--connect ENDPOINT]``"""
import sys

from services.common.service import service_main
from services.robot_sim.service import RobotSimConfig, RobotSimService

if __name__ == "__main__":
    sys.exit(service_main(RobotSimService, RobotSimConfig, description="MuJoCo JACO-2 behind the emulated Kinova API"))
