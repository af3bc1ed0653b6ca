"""Footage for the camera service's tests and the real-arm profile's dry run: a real video file (and an image folder)
of the tag as a camera with a lens would see it, with the calibration file that describes that camera and the
tag's true pose in every frame.

The simulator renders an ideal pinhole image larger than the camera's; each frame is then distorted by OpenCV's
model with known coefficients (every output pixel looks up where the ideal camera saw the same ray), so the
distortion is the one ``cv2.undistortPoints`` inverts, and the truth is MuJoCo's poses. Regenerate the shipped
example with ``python -m tests.services.camera.footage examples/camera``.
"""
from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from services.camera.calibration import Intrinsics, write_intrinsics
from services.robot_sim.scene import CameraConfig, PoseConfig, SceneConfig, TargetConfig
from services.robot_sim.sim import Simulation

WIDTH, HEIGHT, FOCAL = 640, 480, 615.0
#: a mild barrel lens, like a webcam's: 3 px at the image's corners
DISTORTION = np.array([-0.12, 0.05, 0.0008, -0.0006, 0.0])
#: the ideal image is rendered this much larger on every side, so that the distorted frame's corners have pixels
MARGIN_PX = 48


@dataclass
class Footage:
    video: Path
    calibration: Path
    images: Path
    #: the tag's pose in the camera (4×4) in each frame
    truths: list[np.ndarray]
    intrinsics: Intrinsics


def camera_matrix() -> np.ndarray:
    return np.array([[FOCAL, 0.0, (WIDTH - 1) / 2.0], [0.0, FOCAL, (HEIGHT - 1) / 2.0], [0.0, 0.0, 1.0]])


def distortion_maps() -> tuple[np.ndarray, np.ndarray]:
    """For every pixel of the distorted frame, where the ideal (larger) render saw the same ray."""
    u, v = np.meshgrid(np.arange(WIDTH, dtype=np.float64), np.arange(HEIGHT, dtype=np.float64))
    pixels = np.stack([u.ravel(), v.ravel()], axis=1).reshape(-1, 1, 2)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-10)
    rays = cv2.undistortPoints(pixels, camera_matrix(), DISTORTION, criteria=criteria).reshape(-1, 2)
    map_x = (FOCAL * rays[:, 0] + (WIDTH - 1) / 2.0 + MARGIN_PX).reshape(HEIGHT, WIDTH).astype(np.float32)
    map_y = (FOCAL * rays[:, 1] + (HEIGHT - 1) / 2.0 + MARGIN_PX).reshape(HEIGHT, WIDTH).astype(np.float32)
    return map_x, map_y


def tag_poses(n: int) -> list[PoseConfig]:
    """The tag sweeping across the view at 0.45-0.6 m, turning: off the centre, where the lens bends most."""
    poses = []
    for i in range(n):
        s = i / max(1, n - 1)
        poses.append(PoseConfig(xyz=(-0.16 + 0.32 * s, 0.09 - 0.14 * s, 0.45 + 0.15 * s),
                                rpy_deg=(180.0 + 20.0 * s, -15.0 + 25.0 * s, 10.0 + 40.0 * s)))
    return poses


def render_frames(n: int) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """``n`` distorted grey frames of the tag and its true pose in the camera in each."""
    ideal = CameraConfig(width=WIDTH + 2 * MARGIN_PX, height=HEIGHT + 2 * MARGIN_PX, fx=FOCAL, fy=FOCAL)
    map_x, map_y = distortion_maps()
    frames, truths = [], []
    for pose in tag_poses(n):
        sim = Simulation(SceneConfig(floor=False, camera=ideal, target=TargetConfig(pose_in_camera=pose)))
        try:
            grey = cv2.cvtColor(sim.render(), cv2.COLOR_RGB2GRAY)
            truths.append(np.linalg.inv(sim.camera_pose()) @ sim.target_pose())
        finally:
            sim.close()
        frames.append(cv2.remap(grey, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT))
    return frames, truths


def write_footage(directory: Path, n: int = 24, fps: float = 30.0, with_images: bool = True) -> Footage:
    """The video (MJPEG in AVI, as a webcam's stream is), the same frames as PNGs (``with_images``), and the
    calibration file."""
    directory.mkdir(parents=True, exist_ok=True)
    frames, truths = render_frames(n)
    video = directory / "tag_sweep.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), fps, (WIDTH, HEIGHT), isColor=True)
    if not writer.isOpened():
        raise RuntimeError("OpenCV cannot write MJPEG video here")
    writer.set(cv2.VIDEOWRITER_PROP_QUALITY, 95)
    images = directory / "frames"
    if with_images:
        images.mkdir(exist_ok=True)
    for i, grey in enumerate(frames):
        writer.write(cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR))
        if with_images:
            cv2.imwrite(str(images / f"frame_{i:04d}.png"), grey)
    writer.release()
    intrinsics = Intrinsics(WIDTH, HEIGHT, camera_matrix(), DISTORTION)
    calibration = directory / "calibration.yaml"
    write_intrinsics(calibration, intrinsics, comment="the lens of tag_sweep.avi (tests/services/camera/footage.py)")
    return Footage(video, calibration, images, truths, intrinsics)


if __name__ == "__main__":
    out = write_footage(Path(sys.argv[1]) if len(sys.argv) > 1 else Path("examples/camera"), n=90,
                        with_images=False)
    print(f"wrote {out.video} and {out.calibration}")
