"""The camera service's rules, without zenoh, threads or clocks: a captured frame becomes an Image message of the
configured encoding only when it has the calibrated size, and the calibration becomes the CameraInfo message vision
and the controller read (intrinsics, distortion, the camera's mounting on the end effector)."""
from __future__ import annotations

import cv2
import numpy as np

from protocol.messages import CameraInfo, Header, Image, ImageEncoding, Pose
from services.camera.calibration import Intrinsics
from services.model import frames

_CONVERSIONS = {
    # (channels in, encoding out): the OpenCV conversion (None: the pixels as they are)
    (1, ImageEncoding.MONO8): None,
    (3, ImageEncoding.MONO8): cv2.COLOR_BGR2GRAY,
    (1, ImageEncoding.RGB8): cv2.COLOR_GRAY2RGB,
    (3, ImageEncoding.RGB8): cv2.COLOR_BGR2RGB,
    (1, ImageEncoding.BGR8): cv2.COLOR_GRAY2BGR,
    (3, ImageEncoding.BGR8): None,
}


def pixels_for(pixels: np.ndarray, encoding: ImageEncoding, intrinsics: Intrinsics) -> np.ndarray:
    """The frame's pixels in ``encoding`` (OpenCV gives grey or BGR). Raises ValueError for a frame of another size
    than the calibration's (its intrinsics would be wrong for it) or of a kind no encoding holds."""
    if pixels.dtype != np.uint8 or pixels.ndim not in (2, 3) or (pixels.ndim == 3 and pixels.shape[2] not in (1, 3)):
        raise ValueError(f"a frame of {pixels.dtype} {pixels.shape} is not an 8-bit grey or colour image")
    height, width = pixels.shape[:2]
    if (width, height) != (intrinsics.width, intrinsics.height):
        raise ValueError(f"the frame is {width}x{height}, the calibration is for {intrinsics.width}x"
                         f"{intrinsics.height}")
    channels = 1 if pixels.ndim == 2 else pixels.shape[2]
    if pixels.ndim == 3 and channels == 1:
        pixels = pixels[:, :, 0]
    code = _CONVERSIONS[(channels, encoding)]
    return np.ascontiguousarray(pixels if code is None else cv2.cvtColor(pixels, code))


def image_message(pixels: np.ndarray, encoding: ImageEncoding, header: Header) -> Image:
    height, width = pixels.shape[:2]
    return Image(header=header, width=width, height=height, encoding=encoding, data=pixels.tobytes())


def camera_info(intrinsics: Intrinsics, T_ee_camera: np.ndarray, header: Header) -> CameraInfo:
    """The CameraInfo message of a calibrated camera mounted at ``T_ee_camera`` (4×4, camera frame in the end
    effector's)."""
    return CameraInfo(
        header=header, width=intrinsics.width, height=intrinsics.height, fx=intrinsics.fx, fy=intrinsics.fy,
        cx=intrinsics.cx, cy=intrinsics.cy, distortion=[float(v) for v in intrinsics.distortion],
        camera_in_ee=Pose(xyz=tuple(float(v) for v in T_ee_camera[:3, 3]),
                          quat_wxyz=tuple(float(v) for v in frames.matrix_to_quat_wxyz(T_ee_camera[:3, :3]))))
