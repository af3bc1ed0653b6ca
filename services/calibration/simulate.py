"""Calibration recordings made in the simulator, for a dry run and for the tests: the simulated camera photographs a
ChArUco board the way a lab would (the board moved in front of the camera for the intrinsics; the arm moved
through wrist poses in front of a fixed board for hand-eye) and the recording is written exactly as one taken on the
real arm, so the same solver reads it. The truth it is checked against is the simulator's camera: its intrinsics
and its mounting on the end effector.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import yaml

from services.model import frames
from services.model.arm import ArmDescription, load_arm
from services.model.board import BoardConfig, BoardDetector
from services.robot_sim.scene import CameraConfig, PoseConfig, SceneConfig, TargetConfig
from services.robot_sim.sim import Simulation
from services.calibration.hand_eye import MIN_CORNERS, POSES_FILE

#: the default simulated camera for calibration: not the scene's default, so that a solver that returned the
#: defaults could not pass
CAMERA = CameraConfig(fx=602.0, fy=598.0, cx=324.5, cy=236.0,
                      camera_in_ee=PoseConfig(xyz=(0.062, 0.004, -0.018), rpy_deg=(1.5, -2.0, 91.0)))


@dataclass
class Truth:
    camera: CameraConfig

    @property
    def T_ee_camera(self) -> np.ndarray:
        return self.camera.camera_in_ee.matrix()


def _facing(distance: float, x: float, y: float, tilt_x: float, tilt_y: float, roll: float) -> PoseConfig:
    """A target pose in the camera frame: ``distance`` ahead, off the axis by x, y, its face toward the camera."""
    return PoseConfig(xyz=(x, y, distance), rpy_deg=(180.0 + tilt_x, tilt_y, roll))


def record_intrinsics(directory: Path, board: BoardConfig, camera: CameraConfig = CAMERA, views: int = 16,
                      seed: int = 0, arm: ArmDescription | None = None) -> Truth:
    """``views`` images of the board at 0.35-0.6 m, tilted up to 35°, written to ``directory``; the board's centre
    reaches 70 % of the way to the image's edges, so that the views cover its corners, where the lens bends most
    (a board cut by the edge is still found: ChArUco corners are identified one by one)."""
    rng = np.random.default_rng(seed)
    directory.mkdir(parents=True, exist_ok=True)
    sim = Simulation(SceneConfig(floor=False, camera=camera, target=TargetConfig(board=board)),
                     arm=arm or load_arm())
    try:
        T_base_camera = sim.camera_pose()
        for i in range(views):
            distance = rng.uniform(0.35, 0.6)
            half_width, half_height = distance * camera.width / 2 / camera.fx, distance * camera.height / 2 / camera.fy
            pose = _facing(distance, 0.7 * rng.uniform(-1, 1) * half_width, 0.7 * rng.uniform(-1, 1) * half_height,
                           rng.uniform(-35, 35), rng.uniform(-35, 35), rng.uniform(-30, 30))
            T_camera_board_centre = pose.matrix()
            # the target's frame is the board's centre: shift so that the board's centre is where asked
            sim.set_target_pose(T_base_camera @ T_camera_board_centre)
            gray = cv2.cvtColor(sim.render(), cv2.COLOR_RGB2GRAY)
            cv2.imwrite(str(directory / f"view_{i:03d}.png"), gray)
    finally:
        sim.close()
    return Truth(camera)


def record_hand_eye(directory: Path, board: BoardConfig, camera: CameraConfig = CAMERA, poses: int = 15,
                    seed: int = 0, max_tries: int = 400, arm: ArmDescription | None = None) -> Truth:
    """The arm (default: the default arm) at ``poses`` wrist poses around its home, the board fixed 0.45 m in front
    of the camera's initial view; each image with the board's corners in view is kept with its joint angles, and
    the recording says which arm it was made on."""
    arm = arm or load_arm()
    rng = np.random.default_rng(seed)
    directory.mkdir(parents=True, exist_ok=True)
    scene = SceneConfig(floor=False, camera=camera,
                        target=TargetConfig(board=board, pose_in_camera=_facing(0.45, 0.0, 0.0, 0.0, 0.0, 0.0)))
    detector = BoardDetector(board)
    q0 = np.array(scene.start_deg(arm))
    # the wrist does most of the turning; the shoulder and elbow move the camera about (a last joint beyond the
    # wrist's three turns the camera about its axis: left alone)
    span = np.array([6.0, 5.0, 5.0, 25.0, 25.0, 30.0, 0.0][:arm.n_joints])
    lower, upper = (np.degrees(v) for v in arm.model_limits())
    sim = Simulation(scene, arm=arm)
    kept = []
    try:
        for _ in range(max_tries):
            if len(kept) == poses:
                break
            q = q0 + rng.uniform(-1.0, 1.0, arm.n_joints) * span
            model = np.degrees(arm.physical_deg_to_model(q))
            if np.any(model < lower + 2.0) or np.any(model > upper - 2.0):
                continue
            sim.reset(q.tolist())
            gray = cv2.cvtColor(sim.render(), cv2.COLOR_RGB2GRAY)
            view = detector.find(gray, MIN_CORNERS)
            if view is None or len(view) < 0.6 * (board.squares_x - 1) * (board.squares_y - 1):
                continue  # the board mostly out of view: a lab would not keep this pose either
            name = f"pose_{len(kept):03d}.png"
            cv2.imwrite(str(directory / name), gray)
            kept.append({"image": name, "joints_deg": [round(float(v), 6) for v in q]})
    finally:
        sim.close()
    if len(kept) < poses:
        raise RuntimeError(f"only {len(kept)} of {poses} wrist poses kept the board in view")
    (directory / POSES_FILE).write_text(
        "# the arm, and its physical joint angles (deg, as GetAngularPosition) when each image was taken\n"
        + yaml.safe_dump({"arm": arm.name, "poses": kept}, sort_keys=False))
    return Truth(camera)


def mounting_error(found: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """Translation (mm) and rotation (deg) between two mountings."""
    delta = np.linalg.inv(truth) @ found
    return float(np.linalg.norm(delta[:3, 3]) * 1e3), float(np.degrees(np.linalg.norm(
        frames.rotation_log(delta[:3, :3]))))
