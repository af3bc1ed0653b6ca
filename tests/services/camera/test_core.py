"""The camera core: frames become images of the configured encoding only at the calibrated size; the calibration
becomes the camera info vision reads."""
import cv2
import numpy as np
import pytest

from protocol import messages as m
from services.camera import core
from services.camera.calibration import Intrinsics
from services.model import frames

INTRINSICS = Intrinsics(64, 48, np.array([[60.0, 0, 31.5], [0, 61.0, 23.5], [0, 0, 1]]),
                        np.array([-0.1, 0.02, 0.001, -0.002, 0.003]))


def colour_frame():
    rng = np.random.default_rng(3)
    return rng.integers(0, 256, (48, 64, 3), dtype=np.uint8)


@pytest.mark.parametrize("encoding", [m.ImageEncoding.MONO8, m.ImageEncoding.RGB8])
def test_colour_and_grey_frames_become_the_configured_encoding_as_opencv_converts(encoding):
    bgr = colour_frame()
    grey = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)
    for frame in (bgr, grey, grey[:, :, None]):
        pixels = core.pixels_for(frame, encoding, INTRINSICS)
        image = core.image_message(pixels, encoding, m.Header())
        assert (image.width, image.height, image.encoding) == (64, 48, encoding)
    assert np.array_equal(core.pixels_for(bgr, m.ImageEncoding.MONO8, INTRINSICS), grey)
    assert np.array_equal(core.pixels_for(bgr, m.ImageEncoding.RGB8, INTRINSICS), bgr[:, :, ::-1])


@pytest.mark.parametrize("frame, reason", [
    (np.zeros((480, 640), np.uint8), "640x480, the calibration is for 64x48"),
    (np.zeros((48, 64), np.uint16), "8-bit"),
    (np.zeros((48, 64, 4), np.uint8), "8-bit"),
])
def test_a_frame_the_calibration_does_not_describe_is_refused(frame, reason):
    with pytest.raises(ValueError, match=reason):
        core.pixels_for(frame, m.ImageEncoding.MONO8, INTRINSICS)


def test_the_camera_info_carries_the_calibration_and_the_mounting():
    T = frames.pose_from_xyz_rpy_deg((0.06, 0.01, -0.02), (0.0, 3.0, 90.0))
    info = m.decode(m.encode(core.camera_info(INTRINSICS, T, m.Header())), m.CameraInfo)
    assert (info.width, info.height, info.fx, info.fy, info.cx, info.cy) == (64, 48, 60.0, 61.0, 31.5, 23.5)
    assert info.distortion == pytest.approx(list(INTRINSICS.distortion))
    R = frames.quat_wxyz_to_matrix(info.camera_in_ee.quat_wxyz)
    assert np.allclose(R, T[:3, :3]) and np.allclose(info.camera_in_ee.xyz, T[:3, 3])
