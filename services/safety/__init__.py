"""safety: the only path to the robot. Checks every desired command; forwards, clamps or stops."""
