"""robot_gateway: the robot's zenoh API backed by a real arm, over its RS-485 actuator bus (python-can) or the
Kinova SDK. So far: the host side of the RS-485 link (:mod:`services.robot_gateway.link`)."""
