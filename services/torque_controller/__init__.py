"""A client of the robot's 500 Hz low-level torque API running one of the JACO thesis's controllers (``python -m
services.torque_controller``): :mod:`.core` the run without zenoh, :mod:`.service` the process."""
