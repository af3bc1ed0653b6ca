"""Hand-eye: the solver on exact synthetic motions (and against OpenCV's where the installed OpenCV has it), then a
recording made by moving the simulated arm, solved to within 2 mm and 0.5° of the simulator's mounting."""
import cv2
import numpy as np
import pytest

from services.calibration.hand_eye import HandEyeFailed, calibrate_hand_eye, park_martin, solve_hand_eye
from services.calibration.simulate import CAMERA, mounting_error, record_hand_eye
from services.model import frames
from services.model.board import BoardConfig


def synthetic(n=10, seed=1, noise=0.0):
    rng = np.random.default_rng(seed)
    X = frames.pose_from_xyz_rpy_deg((0.06, -0.01, -0.02), (3.0, -4.0, 88.0))
    T_base_target = frames.pose_from_xyz_rpy_deg((0.1, -0.5, 0.3), (170.0, 5.0, 20.0))
    T_base_ee, T_camera_target = [], []
    for _ in range(n):
        T = frames.pose_from_xyz_rpy_deg(rng.uniform(-0.3, 0.3, 3) + (0.0, -0.3, 0.5), rng.uniform(-40, 40, 3))
        T_base_ee.append(T)
        seen = np.linalg.inv(T @ X) @ T_base_target
        seen[:3, 3] += rng.normal(0.0, noise, 3)
        T_camera_target.append(seen)
    return X, T_base_ee, T_camera_target


def test_park_martin_recovers_an_exact_mounting():
    X, A, B = synthetic()
    mm, deg = mounting_error(park_martin(A, B), X)
    assert mm < 1e-6 and deg < 1e-6
    solved, solver = solve_hand_eye(A, B)  # OpenCV's where it has one, else this one
    assert max(mounting_error(solved, X)) < 1e-3 and "park" in solver


@pytest.mark.skipif(not hasattr(cv2, "calibrateHandEye"), reason="this OpenCV's Python package lacks "
                    "calibrateHandEye (opencv/opencv#29565)")
def test_park_martin_agrees_with_opencvs():
    X, A, B = synthetic(noise=0.0005)
    R, t = cv2.calibrateHandEye([T[:3, :3] for T in A], [T[:3, 3] for T in A], [T[:3, :3] for T in B],
                                [T[:3, 3] for T in B], method=cv2.CALIB_HAND_EYE_PARK)
    mm, deg = mounting_error(park_martin(A, B), frames.homogeneous(R, t.reshape(3)))
    assert mm < 0.01 and deg < 0.01


def test_the_simulated_arms_mounting_is_recovered(tmp_path):
    truth = record_hand_eye(tmp_path, BoardConfig(), poses=12, seed=2)
    result = calibrate_hand_eye(tmp_path, BoardConfig(), CAMERA.matrix(), np.zeros(5))
    mm, deg = mounting_error(result.T_ee_camera, truth.T_ee_camera)
    assert mm < 2.0 and deg < 0.5, (mm, deg)
    assert result.board_spread_mm < 2.0 and result.reprojection_rms_px < 0.3 and result.poses_used == 12
    # the same recording with the arm's angles off by a degree at the shoulder: the spread says so
    text = (tmp_path / "arm_poses.yaml").read_text()
    poses = __import__("yaml").safe_load(text)
    for i, pose in enumerate(poses["poses"]):
        pose["joints_deg"][1] += 1.5 * (-1) ** i
    (tmp_path / "arm_poses.yaml").write_text(__import__("yaml").safe_dump(poses))
    worse = calibrate_hand_eye(tmp_path, BoardConfig(), CAMERA.matrix(), np.zeros(5))
    assert worse.board_spread_mm > 3 * result.board_spread_mm
    assert worse.reprojection_rms_px > 5 * result.reprojection_rms_px


def test_a_recording_without_enough_poses_is_refused(tmp_path):
    (tmp_path / "arm_poses.yaml").write_text("poses: [{image: a.png, joints_deg: [270, 170, 0, 80, 0, 220, 0]}]\n")
    with pytest.raises(HandEyeFailed, match="at 0 of 1"):
        calibrate_hand_eye(tmp_path, BoardConfig(), CAMERA.matrix(), np.zeros(5))
    (tmp_path / "arm_poses.yaml").write_text("poses: [{image: a.png, joints_deg: [1, 2]}]\n")
    with pytest.raises(HandEyeFailed, match="joints_deg has 2 angles; the j2s7s300 has 7 joints"):
        calibrate_hand_eye(tmp_path, BoardConfig(), CAMERA.matrix(), np.zeros(5))
