"""A kinematic closed loop for control laws, a test rig: ideal joint-velocity tracking and exact projection of the
tag corners, no rendering, no services. The real loop is ``mfvs servo``."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from services.model import tag as tags
from services.model.kinematics import ArmKinematics
from services.controller.law import Law, LawOutput, ServoInput
from services.model.arm import load_arm

ARM = load_arm("j2s7s300")


@dataclass
class KinematicStep:
    q: np.ndarray
    points: np.ndarray
    depths: np.ndarray
    error_norm: float
    output: LawOutput


@dataclass
class KinematicLoop:
    law: Law
    #: the tag's pose in the base frame (4×4) at t = 0, and its constant velocity (m/s, base frame)
    tag_in_base: np.ndarray
    camera_in_ee: np.ndarray
    q0: np.ndarray
    goal_points: np.ndarray
    goal_depths: np.ndarray
    size_m: float = 0.0962
    period_s: float = 1.0 / 30.0
    tag_velocity: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self) -> None:
        self.kin = ArmKinematics(ARM)
        self.q = np.asarray(self.q0, dtype=float).copy()
        #: the joints' velocity now: the last command, tracked ideally
        self.dq = np.zeros_like(self.q)
        self.t = 1.0

    def observe(self) -> tuple[np.ndarray, np.ndarray]:
        R, p = self.kin.pose(self.q)
        T_be = np.eye(4)
        T_be[:3, :3], T_be[:3, 3] = R, p
        T_bt = self.tag_in_base.copy()
        T_bt[:3, 3] = T_bt[:3, 3] + self.tag_velocity * (self.t - 1.0)
        T_ct = np.linalg.inv(T_be @ self.camera_in_ee) @ T_bt
        corners = (T_ct[:3, :3] @ tags.corners_in_tag(self.size_m).T).T + T_ct[:3, 3]
        return corners[:, :2] / corners[:, 2:3], corners[:, 2]

    def step(self) -> KinematicStep:
        points, depths = self.observe()
        inp = ServoInput(t_s=self.t, points=points, depths=depths, goal_points=self.goal_points,
                         goal_depths=self.goal_depths, q=self.q.copy(), camera_in_ee=self.camera_in_ee,
                         dq=self.dq.copy())
        output = self.law.step(inp)
        dq = output.joint_velocities
        if dq is None:
            raise TypeError("the kinematic loop runs joint-velocity laws")
        self.q = self.q + dq * self.period_s
        self.dq = np.asarray(dq, dtype=float).copy()
        self.t += self.period_s
        return KinematicStep(self.q.copy(), points, depths, float(np.linalg.norm(inp.error)), output)

    def run(self, steps: int, stop_below: float = 0.0) -> list[KinematicStep]:
        out = []
        for _ in range(steps):
            out.append(self.step())
            if out[-1].error_norm < stop_below:
                break
        return out


def within_limits(q) -> bool:
    lower, upper = ARM.model_limits()
    return bool(np.all(q >= lower) and np.all(q <= upper))
