"""The robot node: one loop (the 500 Hz actuator cycle and the 100 Hz DSP cycle) over one hardware interface,
shared by robot_sim (MuJoCo) and robot_gateway (an arm on an RS-485 bus)."""
