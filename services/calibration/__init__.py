"""Calibration: a camera's intrinsics from a ChArUco board, and its mounting on the end effector (hand-eye)."""
