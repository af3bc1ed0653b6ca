"""Calibration files as labs have them: OpenCV FileStorage (YAML and XML, both naming conventions) and ROS
camera_info YAML read to the same intrinsics; what vision could not use is refused with the reason."""
import cv2
import numpy as np
import pytest

from services.camera.calibration import (CalibrationError, Intrinsics, read_camera_in_ee, read_intrinsics,
                                         write_camera_in_ee, write_intrinsics)
from services.model import frames

K = np.array([[612.3, 0.0, 318.4], [0.0, 611.8, 242.1], [0.0, 0.0, 1.0]])
D = np.array([-0.118, 0.052, 0.0007, -0.0005, -0.011])

ROS_FILE = """image_width: 640
image_height: 480
camera_name: usb_cam
camera_matrix:
  rows: 3
  cols: 3
  data: [612.3, 0.0, 318.4, 0.0, 611.8, 242.1, 0.0, 0.0, 1.0]
distortion_model: plumb_bob
distortion_coefficients:
  rows: 1
  cols: 5
  data: [-0.118, 0.052, 0.0007, -0.0005, -0.011]
rectification_matrix:
  rows: 3
  cols: 3
  data: [1, 0, 0, 0, 1, 0, 0, 0, 1]
projection_matrix:
  rows: 3
  cols: 4
  data: [600.1, 0, 318.0, 0, 0, 605.2, 241.0, 0, 0, 0, 1, 0]
"""


def same(intrinsics: Intrinsics) -> bool:
    return (intrinsics.width, intrinsics.height) == (640, 480) and np.allclose(intrinsics.camera_matrix, K) \
        and np.allclose(intrinsics.distortion, D)


def test_what_mfvs_writes_it_reads_back_and_opencv_reads_too(tmp_path):
    path = tmp_path / "calibration.yaml"
    write_intrinsics(path, Intrinsics(640, 480, K, D, rms_px=0.21), comment="test")
    back = read_intrinsics(path)
    assert same(back) and back.rms_px == pytest.approx(0.21)
    storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    assert np.allclose(storage.getNode("camera_matrix").mat(), K)
    storage.release()


def test_opencv_xml_with_opencvs_own_names_is_read(tmp_path):
    path = tmp_path / "camera.xml"
    storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    storage.write("image_width", 640)
    storage.write("image_height", 480)
    storage.write("cameraMatrix", K)
    storage.write("distCoeffs", D.reshape(-1, 1))
    storage.release()
    assert same(read_intrinsics(path))


def test_a_ros_camera_info_file_is_read(tmp_path):
    path = tmp_path / "usb_cam.yaml"
    path.write_text(ROS_FILE)
    assert same(read_intrinsics(path))


@pytest.mark.parametrize("change, reason", [
    (("plumb_bob", "equidistant"), "equidistant"),
    (("image_width: 640\n", ""), "image_width"),
    (("data: [-0.118, 0.052, 0.0007, -0.0005, -0.011]", "data: [-0.118, 0.052, 0.0007]"), "3 distortion"),
    (("data: [612.3, 0.0, 318.4", "data: [612.3, 2.5, 318.4"), "skew"),
    (("data: [612.3, 0.0, 318.4", "data: [-612.3, 0.0, 318.4"), "fx, fy > 0"),
    (("data: [612.3, 0.0, 318.4", "data: [.nan, 0.0, 318.4"), "finite"),
    (("camera_matrix:", "matrix:"), "no camera_matrix"),
])
def test_what_vision_could_not_use_is_refused_with_the_reason(tmp_path, change, reason):
    path = tmp_path / "bad.yaml"
    path.write_text(ROS_FILE.replace(*change))
    with pytest.raises(CalibrationError, match=reason) as caught:
        read_intrinsics(path)
    assert str(path) in str(caught.value)


@pytest.mark.parametrize("text", ["[1, 2, 3]", "a: [", "%YAML:1.0\n---\nimage_width: 640\n", ""])
def test_garbage_is_refused_not_crashed_on(tmp_path, text):
    path = tmp_path / "garbage.yaml"
    path.write_text(text)
    with pytest.raises(CalibrationError):
        read_intrinsics(path)


def test_a_missing_file_is_named(tmp_path):
    with pytest.raises(CalibrationError, match="cannot read"):
        read_intrinsics(tmp_path / "nope.yaml")


def test_the_hand_eye_file_round_trips_to_the_same_mounting(tmp_path):
    T = frames.pose_from_xyz_rpy_deg((0.061, -0.004, -0.023), (1.5, -2.0, 91.0))
    path = tmp_path / "hand_eye.yaml"
    write_camera_in_ee(path, T, {"translation_rms_mm": 0.4, "poses": 12}, comment="test")
    back = read_camera_in_ee(path).matrix()
    assert np.allclose(back[:3, 3], T[:3, 3], atol=1e-6) and np.allclose(back[:3, :3], T[:3, :3], atol=1e-6)
    path.write_text("residuals: {}\n")
    with pytest.raises(CalibrationError, match="camera_in_ee"):
        read_camera_in_ee(path)
