"""A camera's intrinsics and lens distortion from images of a ChArUco board: OpenCV's CharucoDetector finds the
board's inner corners in each image, ``cv2.calibrateCamera`` fits the pinhole and OpenCV's distortion (k1 k2 p1 p2;
k3 held at zero) to all of them (zero skew: the camera info carries none).

What a lab needs to know of the result is printed beside it: the RMS reprojection error, each image's own, which
images were left out and why (too few corners: a blurred or cut-off board), and how far apart the views were (a
calibration from near-identical views fits its noise).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from services.camera.calibration import Intrinsics
from services.camera.sources import IMAGE_SUFFIXES
from services.model.board import BoardConfig, BoardDetector

#: fewer views than this cannot separate focal length from distance and distortion
MIN_VIEWS = 6
#: a view with fewer corners than this is left out
MIN_CORNERS = 8


class CalibrationFailed(RuntimeError):
    """The images cannot give a calibration: the reason, and what to do."""


@dataclass
class IntrinsicsResult:
    intrinsics: Intrinsics
    rms_px: float
    #: image name → RMS reprojection error of its corners (px)
    per_view_px: dict[str, float]
    #: image name → why it was left out
    skipped: dict[str, str] = field(default_factory=dict)
    #: the largest angle between two views' board normals (deg): small means the views were too alike
    view_spread_deg: float = 0.0

    def summary(self) -> dict:
        K = self.intrinsics
        return {"fx": K.fx, "fy": K.fy, "cx": K.cx, "cy": K.cy, "distortion": K.distortion.tolist(),
                "width": K.width, "height": K.height, "rms_px": self.rms_px, "views": len(self.per_view_px),
                "worst_view_px": max(self.per_view_px.values()), "view_spread_deg": self.view_spread_deg,
                "skipped": self.skipped}


def read_images(directory: Path) -> dict[str, np.ndarray]:
    """The grey images of a folder (``IMAGE_SUFFIXES``), by name."""
    images = {}
    for path in sorted(p for p in Path(directory).iterdir() if p.suffix.lower() in IMAGE_SUFFIXES):
        gray = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        if gray is not None:
            images[path.name] = gray
    return images


def calibrate_intrinsics(images: dict[str, np.ndarray], board: BoardConfig) -> IntrinsicsResult:
    """Calibrate from ``images`` (name → grey pixels, all of one size) of ``board``."""
    if not images:
        raise CalibrationFailed("no images")
    sizes = {gray.shape[::-1] for gray in images.values()}
    if len(sizes) != 1:
        raise CalibrationFailed(f"the images have different sizes {sorted(sizes)}: one camera mode at a time")
    width, height = sizes.pop()
    detector = BoardDetector(board)
    names, object_points, image_points, skipped = [], [], [], {}
    for name, gray in images.items():
        view = detector.find(gray, MIN_CORNERS)
        if view is None:
            skipped[name] = f"fewer than {MIN_CORNERS} board corners found"
            continue
        names.append(name)
        object_points.append(view.object_points.astype(np.float32))
        image_points.append(view.image_points.astype(np.float32))
    if len(names) < MIN_VIEWS:
        raise CalibrationFailed(f"the board was found in {len(names)} of {len(images)} images; at least {MIN_VIEWS} "
                                "needed, seen from different angles and filling different parts of the image")
    # OpenCV's pinhole calibration keeps the skew at zero. k1 k2 p1 p2 are fitted and k3 is held at zero, as OpenCV's
    # documentation advises for all but wide lenses: with views that do not reach the image's corners, k3 fits the
    # noise (6.4 on a distortion-free simulated lens) and bends the corners it never saw
    rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(object_points, image_points, (width, height), None, None,
                                                     flags=cv2.CALIB_FIX_K3)
    per_view = {}
    for name, obj, img, rvec, tvec in zip(names, object_points, image_points, rvecs, tvecs):
        projected, _ = cv2.projectPoints(obj, rvec, tvec, K, dist)
        per_view[name] = float(np.sqrt(np.mean(np.sum((projected.reshape(-1, 2) - img) ** 2, axis=1))))
    normals = [cv2.Rodrigues(r)[0][:, 2] for r in rvecs]
    spread = max(np.degrees(np.arccos(np.clip(a @ b, -1.0, 1.0))) for a in normals for b in normals)
    intrinsics = Intrinsics(width, height, K, dist.reshape(-1)[:5], rms_px=float(rms))
    return IntrinsicsResult(intrinsics, float(rms), per_view, skipped, float(spread))
