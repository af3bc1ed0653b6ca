"""The simulated camera's imperfections: what a real camera does to the renderer's perfect image.

In order, as light meets a sensor:

1. **motion blur** over the exposure: the image integrates the scene while the camera (and the target) move. The
   renderer draws the scene at the end of the exposure; :func:`motion_blur` averages ``samples`` copies of it, each
   warped by the homography that carries the target's plane from its place at the end to its place at that instant
   (linearly between its place at the exposure's start and end). Exact for the target's plane, which is what vision
   measures; the background gets the same smear, an approximation (it lies at other depths);
2. **light**: a gain (dimmer light is a gain below 1) and the sensor's noise, Gaussian in grey levels, clipped to
   0..255;
3. **compression**: JPEG at a quality, as a USB webcam's MJPEG stream arrives.

The noise is drawn from a generator seeded by the scene's seed and the frame's stamp, so a lockstep run stays a
function of its scenario: the same frame gets the same noise. No zenoh, no threads, no MuJoCo beyond the corner
projection.
"""
from __future__ import annotations

from typing import Optional

import cv2
import mujoco
import numpy as np

from services.runtime.config import ConfigStruct


class ImagingConfig(ConfigStruct):
    """A camera as imperfect as a real one. The defaults are a common USB webcam's indoors (a 640×480 MJPEG stream,
    10 ms exposure, a little read noise)."""

    #: Gaussian read noise (grey levels, σ)
    noise_sigma: float = 2.0
    #: how long the shutter is open before the frame's stamp (s); the camera's motion over it blurs the image
    exposure_s: float = 0.01
    #: instants the blur is averaged over (more: smoother for long blurs, slower)
    blur_samples: int = 8
    #: the light: 1 as rendered, below 1 dimmer (the image scaled before the noise)
    gain: float = 1.0
    #: JPEG quality the frames go through (null: raw frames, as a machine-vision camera's)
    jpeg_quality: Optional[int] = 85
    #: the noise's seed (with each frame's stamp)
    seed: int = 0

    def __post_init__(self) -> None:
        if not 0.0 <= self.noise_sigma <= 64.0:
            raise ValueError("noise_sigma must be within 0..64 grey levels")
        if not 0.0 <= self.exposure_s <= 0.1:
            raise ValueError("exposure_s must be within 0..0.1 s")
        if not 1 <= self.blur_samples <= 64:
            raise ValueError("blur_samples must be within 1..64")
        if not 0.05 <= self.gain <= 4.0:
            raise ValueError("gain must be within 0.05..4")
        if self.jpeg_quality is not None and not 1 <= self.jpeg_quality <= 100:
            raise ValueError("jpeg_quality must be within 1..100 (or null)")


#: the target's printed geom: a tag's (or board's), or a markerless object's (services/robot_sim/scene.py)
TARGET_GEOMS = ("tag", "target")


def target_corners_px(model: mujoco.MjModel, data: mujoco.MjData, camera_id: int, camera_matrix: np.ndarray,
                      geom: str | None = None) -> np.ndarray:
    """Where the target's printed face's four corners are in the image (px, 4×2), for the state in ``data``
    (after mj_kinematics): a tag's (or a plane's) face; a cup's, the box around its wall across its axis (the blur
    of its image's motion is then that of a plane through its axis: a cup 8 cm across, seen from 0.3 m)."""
    g = model.geom(geom) if geom is not None else next(
        model.geom(name) for name in TARGET_GEOMS if mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, name) >= 0)
    if model.geom_type[g.id] == mujoco.mjtGeom.mjGEOM_BOX:
        half_x, half_y = model.geom_size[g.id][:2]
        centre = np.zeros(3)
    else:  # its bounding box in its frame: MuJoCo's own (geom_aabb: centre, half sizes)
        centre, (half_x, half_y, _) = model.geom_aabb[g.id][:3], model.geom_aabb[g.id][3:]
    local = centre + np.array([[-half_x, -half_y, 0.0], [half_x, -half_y, 0.0], [half_x, half_y, 0.0],
                               [-half_x, half_y, 0.0]])
    world = data.geom_xpos[g.id] + local @ data.geom_xmat[g.id].reshape(3, 3).T
    R_wc = data.cam_xmat[camera_id].reshape(3, 3)  # MuJoCo's camera looks along its −z, y up
    in_camera = (world - data.cam_xpos[camera_id]) @ R_wc
    optical = in_camera * np.array([1.0, -1.0, -1.0])  # OpenCV's: z ahead, y down
    projected = optical @ camera_matrix.T
    return projected[:, :2] / projected[:, 2:3]


def motion_blur(image: np.ndarray, corners_end: np.ndarray, corners_start: np.ndarray, samples: int) -> np.ndarray:
    """``image`` (the scene at the exposure's end) averaged over the exposure: ``samples`` instants, the target's
    corners moving linearly from ``corners_start`` to ``corners_end``."""
    if samples <= 1 or np.abs(corners_end - corners_start).max() < 0.05:
        return image
    height, width = image.shape[:2]
    total = np.zeros(image.shape, np.float32)
    for k in range(samples):
        s = (k + 0.5) / samples  # the middle of each slice of the exposure, from its start (0) to its end (1)
        corners = corners_start + s * (corners_end - corners_start)
        H = cv2.getPerspectiveTransform(corners_end.astype(np.float32), corners.astype(np.float32))
        total += cv2.warpPerspective(image, H, (width, height), flags=cv2.INTER_LINEAR,
                                     borderMode=cv2.BORDER_REPLICATE)
    return np.clip(total / samples + 0.5, 0, 255).astype(np.uint8)


def expose(image: np.ndarray, config: ImagingConfig, stamp_ns: int) -> np.ndarray:
    """Light and compression: gain, read noise (seeded by the frame's stamp), JPEG."""
    out = image
    if config.gain != 1.0 or config.noise_sigma > 0.0:
        rng = np.random.default_rng([config.seed, stamp_ns & 0xFFFFFFFFFFFF])
        values = image.astype(np.float32) * config.gain
        if config.noise_sigma > 0.0:
            values += rng.normal(0.0, config.noise_sigma, image.shape).astype(np.float32)
        out = np.clip(values + 0.5, 0, 255).astype(np.uint8)
    if config.jpeg_quality is not None:
        ok, encoded = cv2.imencode(".jpg", out, [cv2.IMWRITE_JPEG_QUALITY, int(config.jpeg_quality)])
        if ok:
            out = cv2.imdecode(encoded, cv2.IMREAD_UNCHANGED).reshape(out.shape)
    return out
