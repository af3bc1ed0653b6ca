"""Camera calibration files: a camera's intrinsics and distortion, and where it sits on the end effector.

Intrinsics are read from either of the two formats labs have:

* OpenCV's ``FileStorage`` YAML or XML (``%YAML:1.0`` with ``!!opencv-matrix`` entries), as OpenCV's calibration
  sample and ``mfvs calibrate intrinsics`` write it: ``image_width``, ``image_height``, ``camera_matrix``,
  ``distortion_coefficients`` (also under the names ``cameraMatrix``/``K`` and ``distCoeffs``/``D``);
* ROS's ``camera_info`` YAML (``camera_calibration``'s output): ``image_width``, ``image_height``,
  ``camera_matrix.data``, ``distortion_model``, ``distortion_coefficients.data``.

Only OpenCV's standard model (plumb_bob / rational_polynomial: 4, 5, 8, 12 or 14 coefficients) is taken: it is what
``cv2.undistortPoints`` in vision inverts. A fisheye (equidistant) calibration is refused with that reason rather
than read as something it is not.

The camera's mounting (camera frame in the end-effector frame) is a small YAML file, ``camera_in_ee: {xyz, rpy_deg}``
(metres, XYZ Euler degrees as every mfvs pose in a file), as ``mfvs calibrate hand-eye`` writes it.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np
import yaml

from services.runtime.config import ConfigError, config_from_mapping, read_yaml
from services.model.frames import PoseConfig

#: the coefficient counts of OpenCV's standard distortion model (k1 k2 p1 p2 [k3 [k4 k5 k6 [s1..s4 [τx τy]]]])
DISTORTION_LENGTHS = (4, 5, 8, 12, 14)
_ROS_MODELS = {"plumb_bob", "rational_polynomial", ""}
_MATRIX_NAMES = ("camera_matrix", "cameraMatrix", "K")
_DISTORTION_NAMES = ("distortion_coefficients", "distCoeffs", "dist_coeffs", "D")


class CalibrationError(ConfigError):
    """A calibration file that cannot be used: the file and the reason."""

    def __init__(self, path: str | os.PathLike, reason: str) -> None:
        super().__init__(str(path), reason)


@dataclass(frozen=True)
class Intrinsics:
    """A calibrated pinhole camera with OpenCV's distortion model, for images of ``width`` × ``height``."""

    width: int
    height: int
    camera_matrix: np.ndarray
    distortion: np.ndarray
    #: RMS reprojection error of the calibration (px), when the file says
    rms_px: Optional[float] = None

    def __post_init__(self) -> None:
        K = np.asarray(self.camera_matrix, dtype=float)
        d = np.asarray(self.distortion, dtype=float).reshape(-1)
        if K.shape != (3, 3) or not np.all(np.isfinite(K)):
            raise ValueError("the camera matrix must be a finite 3x3 matrix")
        if K[0, 0] <= 0 or K[1, 1] <= 0 or K[2, 2] != 1.0 or K[1, 0] or K[2, 0] or K[2, 1]:
            raise ValueError(f"not a camera matrix [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0: {K.tolist()}")
        if abs(K[0, 1]) > 1e-9 * K[0, 0]:
            raise ValueError(f"the camera matrix has a skew of {K[0, 1]:g}; the camera info carries none (calibrate "
                             "with OpenCV's default, zero skew)")
        if d.size not in DISTORTION_LENGTHS or not np.all(np.isfinite(d)):
            raise ValueError(f"{d.size} distortion coefficients; OpenCV's model has {DISTORTION_LENGTHS}, all finite")
        if not (8 <= self.width <= 8192 and 8 <= self.height <= 8192):
            raise ValueError(f"image size {self.width}x{self.height} is not within 8..8192 pixels")
        object.__setattr__(self, "camera_matrix", K)
        object.__setattr__(self, "distortion", d)

    @property
    def fx(self) -> float:
        return float(self.camera_matrix[0, 0])

    @property
    def fy(self) -> float:
        return float(self.camera_matrix[1, 1])

    @property
    def cx(self) -> float:
        return float(self.camera_matrix[0, 2])

    @property
    def cy(self) -> float:
        return float(self.camera_matrix[1, 2])


def read_intrinsics(path: str | os.PathLike) -> Intrinsics:
    """A camera's intrinsics from an OpenCV or ROS calibration file (see the module's text); a
    :class:`CalibrationError` names the file and what is wrong with it."""
    path = Path(path)
    try:
        text = path.read_text(errors="replace")
    except OSError as exc:
        raise CalibrationError(path, f"cannot read ({exc.strerror or exc})") from None
    try:
        if text.lstrip().startswith("%YAML:") or "!!opencv-matrix" in text or path.suffix.lower() == ".xml":
            return _read_opencv(path)
        return _read_ros(path, text)
    except CalibrationError:
        raise
    except (ValueError, TypeError, KeyError) as exc:
        raise CalibrationError(path, str(exc)) from None


def _read_opencv(path: Path) -> Intrinsics:
    import cv2

    try:
        storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except cv2.error as exc:
        raise CalibrationError(path, f"OpenCV cannot parse it ({exc.err})") from None
    if not storage.isOpened():
        raise CalibrationError(path, "OpenCV cannot open it as a FileStorage file")
    try:
        K = _first_matrix(storage, _MATRIX_NAMES)
        d = _first_matrix(storage, _DISTORTION_NAMES)
        if K is None:
            raise CalibrationError(path, f"no camera matrix (looked for {', '.join(_MATRIX_NAMES)})")
        if d is None:
            raise CalibrationError(path, f"no distortion coefficients (looked for {', '.join(_DISTORTION_NAMES)})")
        width, height = storage.getNode("image_width"), storage.getNode("image_height")
        if width.empty() or height.empty():
            raise CalibrationError(path, "no image_width/image_height: the intrinsics hold for one image size only")
        rms = storage.getNode("avg_reprojection_error")
        return Intrinsics(int(width.real()), int(height.real()), K, d,
                          None if rms.empty() else float(rms.real()))
    finally:
        storage.release()


def _first_matrix(storage, names) -> Optional[np.ndarray]:
    for name in names:
        node = storage.getNode(name)
        if not node.empty():
            matrix = node.mat()
            if matrix is None:
                raise ValueError(f"'{name}' is not an !!opencv-matrix")
            return np.asarray(matrix, dtype=float)
    return None


def _read_ros(path: Path, text: str) -> Intrinsics:
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise CalibrationError(path, f"neither OpenCV FileStorage nor valid YAML ({exc})") from None
    if not isinstance(data, dict) or "camera_matrix" not in data:
        raise CalibrationError(path, "not a calibration file: no camera_matrix (OpenCV FileStorage or ROS camera_info)")
    model = str(data.get("distortion_model", "") or "")
    if model not in _ROS_MODELS:
        raise CalibrationError(path, f"distortion_model {model!r} is not OpenCV's standard model (plumb_bob or "
                                     "rational_polynomial); vision cannot undistort it")
    K = np.asarray(_ros_matrix(data["camera_matrix"], "camera_matrix"), dtype=float).reshape(3, 3)
    d = np.asarray(_ros_matrix(data.get("distortion_coefficients", [0.0] * 5), "distortion_coefficients"),
                   dtype=float)
    for key in ("image_width", "image_height"):
        if not isinstance(data.get(key), int):
            raise CalibrationError(path, f"{key} must be an integer: the intrinsics hold for one image size only")
    return Intrinsics(data["image_width"], data["image_height"], K, d)


def _ros_matrix(node, name: str) -> list:
    values = node.get("data") if isinstance(node, dict) else node
    if not isinstance(values, list) or not all(isinstance(v, (int, float)) for v in values):
        raise ValueError(f"{name} must be a list of numbers (or a mapping with one under 'data')")
    return values


def write_intrinsics(path: str | os.PathLike, intrinsics: Intrinsics, *, comment: str = "") -> None:
    """Write ``intrinsics`` as OpenCV FileStorage YAML (what :func:`read_intrinsics` and OpenCV both read)."""
    import cv2

    storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    try:
        if comment:
            storage.writeComment(comment)
        storage.write("image_width", int(intrinsics.width))
        storage.write("image_height", int(intrinsics.height))
        storage.write("camera_matrix", intrinsics.camera_matrix)
        storage.write("distortion_coefficients", intrinsics.distortion.reshape(1, -1))
        if intrinsics.rms_px is not None:
            storage.write("avg_reprojection_error", float(intrinsics.rms_px))
    finally:
        storage.release()


def read_camera_in_ee(path: str | os.PathLike) -> PoseConfig:
    """The camera's mounting from a hand-eye file (``camera_in_ee: {xyz, rpy_deg}``)."""
    data = read_yaml(path)
    if not isinstance(data, dict) or "camera_in_ee" not in data:
        raise CalibrationError(path, "no camera_in_ee: {xyz, rpy_deg} in it")
    return config_from_mapping(data, PoseConfig, str(path), section="camera_in_ee")


def write_camera_in_ee(path: str | os.PathLike, T_ee_camera: np.ndarray, residuals: dict | None = None,
                       comment: str = "") -> None:
    """Write a hand-eye file: the mounting as ``camera_in_ee: {xyz, rpy_deg}`` (paste-able into any mfvs config) and,
    beside it, what the calibration measured."""
    from services.model import frames

    rpy = np.degrees(frames.matrix_to_euler_xyz(T_ee_camera[:3, :3]))
    document = {"camera_in_ee": {"xyz": [round(float(v), 6) for v in T_ee_camera[:3, 3]],
                                 "rpy_deg": [round(float(v), 4) for v in rpy]}}
    if residuals:
        document["residuals"] = {k: (float(v) if isinstance(v, (int, float)) and math.isfinite(v) else v)
                                 for k, v in residuals.items()}
    header = "".join(f"# {line}\n" for line in comment.splitlines())
    Path(path).write_text(header + yaml.safe_dump(document, sort_keys=False))
