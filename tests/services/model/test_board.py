"""The ChArUco board as the simulator carries it: OpenCV finds its corners in the rendered image, and the board's
pose from them is the target's pose times board_in_target (the board's frame is OpenCV's)."""
import cv2
import numpy as np
import pytest

from services.calibration.hand_eye import board_pose
from services.model.board import BoardConfig, BoardDetector, board_in_target
from services.robot_sim.scene import PoseConfig, SceneConfig, TargetConfig
from services.robot_sim.sim import Simulation


@pytest.mark.parametrize("tilt", [0.0, 30.0])
def test_the_rendered_board_is_found_where_the_simulator_put_it(tilt):
    board = BoardConfig()
    cfg = SceneConfig(floor=False, target=TargetConfig(board=board, pose_in_camera=PoseConfig(
        xyz=(0.02, -0.01, 0.42), rpy_deg=(180.0 + tilt, 10.0, 25.0))))
    sim = Simulation(cfg)
    try:
        gray = cv2.cvtColor(sim.render(), cv2.COLOR_RGB2GRAY)
        T_camera_target = np.linalg.inv(sim.camera_pose()) @ sim.target_pose()
    finally:
        sim.close()
    view = BoardDetector(board).find(gray)
    assert view is not None and len(view) == (board.squares_x - 1) * (board.squares_y - 1)
    T = board_pose(view, cfg.camera.matrix(), np.zeros(5))
    expected = T_camera_target @ board_in_target(board)
    assert np.linalg.norm(T[:3, 3] - expected[:3, 3]) < 0.002
    assert np.degrees(np.arccos(np.clip((np.trace(T[:3, :3].T @ expected[:3, :3]) - 1) / 2, -1, 1))) < 0.5


@pytest.mark.parametrize("bad", [dict(squares_x=2), dict(marker_m=0.05), dict(dictionary="DICT_NOPE")])
def test_a_board_that_cannot_be_printed_is_refused(bad):
    with pytest.raises(ValueError):
        BoardConfig(**bad)
