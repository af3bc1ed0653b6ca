"""Intrinsics from rendered ChArUco views: the simulator's camera (not the scene's default one) recovered within
0.5 % in focal length; too few usable views refused with the reason."""
import cv2
import numpy as np
import pytest

from services.calibration.intrinsics import CalibrationFailed, calibrate_intrinsics, read_images
from services.calibration.simulate import CAMERA, record_intrinsics
from services.model.board import BoardConfig


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    directory = tmp_path_factory.mktemp("intrinsics")
    record_intrinsics(directory, BoardConfig(), views=12, seed=3)
    return directory


def test_the_simulators_camera_is_recovered(recording):
    result = calibrate_intrinsics(read_images(recording), BoardConfig())
    K = result.intrinsics
    cx, cy = CAMERA.principal_point
    assert abs(K.fx - CAMERA.fx) / CAMERA.fx < 0.005 and abs(K.fy - CAMERA.fy) / CAMERA.fy < 0.005
    assert abs(K.cx - cx) < 3.0 and abs(K.cy - cy) < 3.0
    # the simulated lens has none: undistorting moves no pixel of the image by a pixel (0.67 at the far corner)
    u, v = np.meshgrid(np.arange(0, 640, 16.0), np.arange(0, 480, 16.0))
    pixels = np.stack([u.ravel(), v.ravel()], axis=1).reshape(-1, 1, 2)
    moved = cv2.undistortPoints(pixels, K.camera_matrix, K.distortion, P=K.camera_matrix).reshape(-1, 2)
    assert np.abs(moved - pixels.reshape(-1, 2)).max() < 1.0
    assert result.rms_px < 0.5 and result.view_spread_deg > 20.0 and not result.skipped


def test_too_few_views_or_mixed_sizes_are_refused(recording):
    images = read_images(recording)
    few = dict(list(images.items())[:4])
    with pytest.raises(CalibrationFailed, match="at least 6"):
        calibrate_intrinsics(few, BoardConfig())
    mixed = dict(few, small=np.zeros((240, 320), np.uint8))
    with pytest.raises(CalibrationFailed, match="different sizes"):
        calibrate_intrinsics(mixed, BoardConfig())
    blank = {f"{i}.png": np.full((480, 640), 128, np.uint8) for i in range(8)}
    with pytest.raises(CalibrationFailed, match="found in 0 of 8"):
        calibrate_intrinsics(blank, BoardConfig())
