"""A rig for the markerless front end without services (its tests and `mfvs bench vision`): MuJoCo renders the
eye-in-hand camera with the arm placed where a test wants the camera (inverse kinematics), and a taught goal is
made from two views as vision makes it."""
from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")

import cv2
import numpy as np

from protocol import messages as m
from services.model import frames
from services.model.arm import load_arm
from services.model.frames import PoseConfig
from services.model.kinematics import ArmKinematics, inverse_kinematics
from services.robot_sim.scene import SceneConfig, TargetConfig, camera_info
from services.robot_sim.sim import Simulation
from services.vision.front_end import Camera
from services.vision.taught import TaughtGoal, decode_goal, encode_goal
from services.vision.teach import TeachConfig, TeachSession

#: Table 2's goal: the camera squarely in front of the target at 0.2888 m
GOAL_IN_CAMERA = PoseConfig(xyz=(0.0, 0.0, 0.2888), rpy_deg=(180.0, 0.0, 0.0))


class Rig:
    """The arm at its home with the target ``target`` (a TargetConfig) at the goal in front of its camera."""

    def __init__(self, target: TargetConfig, arm: str = "j2s7s300", objects=(), light=None) -> None:
        self.arm = load_arm(arm)
        self.kin = ArmKinematics(self.arm)
        kw = {"light": light} if light is not None else {}
        self.scene = SceneConfig(target=target, objects=list(objects), **kw)
        self.sim = Simulation(self.scene, arm=self.arm)
        self.camera_in_ee = self.scene.camera.camera_in_ee.matrix()
        self.info = camera_info(self.scene.camera, m.Header())
        self.camera = Camera.from_info(self.info)
        self.home = self.arm.home.copy()

    def close(self) -> None:
        self.sim.close()

    def camera_pose(self, q) -> np.ndarray:
        return frames.homogeneous(*self.kin.pose(q)) @ self.camera_in_ee

    def moved(self, q, d_camera=(0.0, 0.0, 0.0), turn: np.ndarray | None = None) -> np.ndarray:
        """Joint angles that move the camera by ``d_camera`` (its own frame) and turn it by ``turn`` from ``q``."""
        T = self.camera_pose(q)
        goal = T.copy()
        goal[:3, 3] += T[:3, :3] @ np.asarray(d_camera, dtype=float)
        if turn is not None:
            goal[:3, :3] = T[:3, :3] @ turn
        q_new, ok = inverse_kinematics(self.kin, q, goal[:3, :3], goal[:3, 3], tool=self.camera_in_ee)
        assert ok, "the camera pose is out of the arm's reach"
        return q_new

    def gray(self, q) -> np.ndarray:
        self.sim.reset(self.arm.model_to_physical_deg(q))
        return cv2.cvtColor(self.sim.render(), cv2.COLOR_RGB2GRAY)

    def state(self, q, dq=None) -> m.RobotState:
        R, p = self.kin.pose(q)
        return m.RobotState(arm=self.arm.name, arm_digest=self.arm.digest, header=m.Header(stamp_ns=1), q=list(q),
                            dq=list(np.zeros(len(q)) if dq is None else dq), tau=[0.0] * len(q),
                            pose=m.KinovaPose(**frames.kinova_pose(R, p)), control_mode=m.ControlMode.IDLE)

    def teach(self, region=None, detector: str = "sift", probe=(0.03, 0.0, 0.0), config: TeachConfig | None = None,
              equalization: str | None = None) -> TaughtGoal:
        """The goal taught at home, as vision teaches it (a first view, the probe's second view, triangulation)."""
        session = TeachSession(config or TeachConfig())
        session.begin(self.gray(self.home), self.info, self.state(self.home), self.kin,
                      None if region is None else np.asarray(region, dtype=float), detector, "test", equalization)
        q2 = self.moved(self.home, probe)
        session.second_view(self.gray(q2), self.state(q2), self.kin)
        return decode_goal(encode_goal(session.finish("test", 0)))

    def true_projection(self, taught: TaughtGoal, ids, q) -> tuple[np.ndarray, np.ndarray]:
        """Where the taught 3D points of ``ids`` are (pixels, depths) from configuration ``q``, by the truth: the
        camera's motion from the teach's home (the taught points themselves are the teach's measurement)."""
        T = np.linalg.inv(self.camera_pose(q)) @ self.camera_pose(self.home)
        P = taught.points_camera[np.asarray(ids)] @ T[:3, :3].T + T[:3, 3]
        K = self.camera.K
        return np.column_stack([K[0, 0] * P[:, 0] / P[:, 2] + K[0, 2], K[1, 1] * P[:, 1] / P[:, 2] + K[1, 2]]), P[:, 2]

    def target_region(self, margin_px: float = 0.0) -> list:
        """The target's outline at the goal, as a person would draw it around the object (a box, px)."""
        from services.robot_sim.scene import target_outline

        T = GOAL_IN_CAMERA.matrix()
        P = target_outline(self.scene.target) @ T[:3, :3].T + T[:3, 3]
        K = self.camera.K
        px = np.column_stack([K[0, 0] * P[:, 0] / P[:, 2] + K[0, 2], K[1, 1] * P[:, 1] / P[:, 2] + K[1, 2]])
        (x0, y0), (x1, y1) = px.min(axis=0) - margin_px, px.max(axis=0) + margin_px
        return [(x0, y0), (x1, y0), (x1, y1), (x0, y1)]


def goal_target(kind: str, **kw) -> TargetConfig:
    return TargetConfig(kind=kind, pose_in_camera=GOAL_IN_CAMERA, **kw)
