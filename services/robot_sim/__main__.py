"""``python -m services.robot_sim [--config FILE] [--clock realtime|lockstep] [--connect ENDPOINT]``"""
import sys

from services.runtime.service import service_main
from services.robot_sim.service import RobotSimConfig, robot_sim_service

if __name__ == "__main__":
    sys.exit(service_main(robot_sim_service, RobotSimConfig,
                          description="the simulated JACO-2: the robot node on it (api) or its actuators on a bus"))
