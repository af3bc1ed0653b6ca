"""Arm kinematics through Pinocchio: an immutable model shared by all, a mutable workspace per user."""
from __future__ import annotations

from typing import Optional

import numpy as np
import pinocchio as pin

from services.model.arm import ArmDescription


class ArmKinematics:
    """End-effector pose and base Jacobian of an arm at a configuration (model angles, rad).

    Not thread-safe: each thread or loop owns its own instance (the Pinocchio model itself is shared).
    """

    def __init__(self, arm: ArmDescription) -> None:
        self.arm = arm
        pinocchio_arm = self.arm.load_pinocchio()
        self.model = pinocchio_arm.model
        self.ee_frame_id = pinocchio_arm.ee_frame_id
        self.data = self.model.createData()
        #: the length that puts translation and rotation in one unit (:func:`normalized_jacobian`): the arm's reach
        self.characteristic_length_m = self.arm.reach

    def pose(self, q) -> tuple[np.ndarray, np.ndarray]:
        """(R_be, p) of the end effector in the base frame."""
        pin.framesForwardKinematics(self.model, self.data, np.asarray(q, dtype=float))
        M = self.data.oMf[self.ee_frame_id]
        return M.rotation.copy(), M.translation.copy()

    def jacobian_base(self, q) -> np.ndarray:
        """6×n [v; ω] of the end-effector origin, both in base coordinates."""
        pin.computeJointJacobians(self.model, self.data, np.asarray(q, dtype=float))
        pin.updateFramePlacements(self.model, self.data)
        return pin.getFrameJacobian(self.model, self.data, self.ee_frame_id, pin.LOCAL_WORLD_ALIGNED).copy()

    def ee_velocity(self, q, dq) -> np.ndarray:
        """The end effector's linear velocity in the base frame (m/s): the first three rows of J(q)·dq."""
        return (self.jacobian_base(q) @ np.asarray(dq, dtype=float))[:3]

    def ee_speed(self, q, dq) -> float:
        """The end effector's linear speed (m/s), as a robot state's joints say."""
        return float(np.linalg.norm(self.ee_velocity(q, dq)))

    def pose_and_jacobian(self, q) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(R_be, p, J_base) in one pass."""
        q = np.asarray(q, dtype=float)
        pin.computeJointJacobians(self.model, self.data, q)
        pin.updateFramePlacements(self.model, self.data)
        M = self.data.oMf[self.ee_frame_id]
        J = pin.getFrameJacobian(self.model, self.data, self.ee_frame_id, pin.LOCAL_WORLD_ALIGNED)
        return M.rotation.copy(), M.translation.copy(), J.copy()

    def link_poses(self, q) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """(R, p) in the base frame of every link of the description (base_link, link_0 … link_n, end_effector),
        for drawing the arm."""
        pin.framesForwardKinematics(self.model, self.data, np.asarray(q, dtype=float))
        return {frame.name: (self.data.oMf[i].rotation.copy(), self.data.oMf[i].translation.copy())
                for i, frame in enumerate(self.model.frames) if frame.type == pin.FrameType.BODY}

    def gravity(self, q) -> np.ndarray:
        """Joint torques that hold the arm still against gravity (N·m)."""
        return pin.computeGeneralizedGravity(self.model, self.data, np.asarray(q, dtype=float)).copy()


def manipulability(J: np.ndarray) -> float:
    """Yoshikawa's manipulability w = √det(J Jᵀ), the product of J's singular values (Nelson 1995 eq. 6; 0 at a
    singularity)."""
    return float(np.prod(np.linalg.svd(J, compute_uv=False)))



def normalized_jacobian(J: np.ndarray, length_m: float) -> np.ndarray:
    """J with its linear rows divided by a characteristic length of the arm: every row then maps joint rates (rad/s)
    to rad/s (a rotation, or a translation as the turn of the arm's length it amounts to), so its singular values
    compare translation with rotation in one unit, and an arm scaled in size has the same ones at the same angles."""
    Jn = np.array(J, dtype=float, copy=True)
    Jn[:3] /= length_m
    return Jn


def singularity_measure(J: np.ndarray, length_m: float) -> float:
    """How far the arm is from a singularity, without units: the smallest singular value of
    :func:`normalized_jacobian` (0 at a singularity; the j2s7s300 at its home pose: 0.13). With every joint at
    1 rad/s the end effector can move at least this fast in any direction, in rad/s or arm lengths per second."""
    return float(np.linalg.svd(normalized_jacobian(J, length_m), compute_uv=False)[-1])


def inverse_kinematics(kin: ArmKinematics, q0, target_R: np.ndarray, target_p: np.ndarray, tool: np.ndarray = None,
                       tolerance_m: float = 1e-6, tolerance_rad: float = 1e-6, damping: float = 1e-6,
                       max_iterations: int = 500) -> tuple[np.ndarray, bool]:
    """Joint angles that put the frame ``tool`` (its pose in the end effector's frame, 4×4; default the end effector)
    at (``target_R``, ``target_p``) in the base frame, from ``q0``: damped Gauss-Newton on the pose's error in the
    tool's own frame (Pinocchio's closed-loop inverse kinematics, its log₆ error and the frame's local Jacobian,
    Jlog₆ applied), the joints kept within their limits; (q, whether it arrived within the tolerances). A redundant
    arm ends near ``q0``: each step is the least-norm one. Where full steps do not arrive (a step near a singular
    configuration can throw the joints far: the j2n6s300's side grasp from its home spun a continuous joint past
    -4000°), it starts again from ``q0`` with each step at most :data:`IK_RETRY_STEP_RAD` long; what arrives with full
    steps is found as before."""
    tool = np.eye(4) if tool is None else np.asarray(tool, dtype=float)
    q, ok = _gauss_newton(kin, q0, target_R, target_p, tool, tolerance_m, tolerance_rad, damping, max_iterations)
    if ok:
        return q, ok
    return _gauss_newton(kin, q0, target_R, target_p, tool, tolerance_m, tolerance_rad, damping,
                         4 * max_iterations, max_step=IK_RETRY_STEP_RAD)


#: the longest joint step of the inverse kinematics' second try (rad): our choice, small beside a joint's range and
#: large enough to cross it in a few dozen steps
IK_RETRY_STEP_RAD = 0.1


def _gauss_newton(kin: ArmKinematics, q0, target_R, target_p, tool: np.ndarray, tolerance_m: float,
                  tolerance_rad: float, damping: float, max_iterations: int,
                  max_step: Optional[float] = None) -> tuple[np.ndarray, bool]:
    goal = pin.SE3(np.asarray(target_R, dtype=float), np.asarray(target_p, dtype=float))
    ee_in_tool = pin.SE3(tool[:3, :3], tool[:3, 3]).inverse()
    lower, upper = kin.arm.model_limits()
    q = np.array(q0, dtype=float)
    for _ in range(max_iterations):
        pin.computeJointJacobians(kin.model, kin.data, q)
        pin.updateFramePlacements(kin.model, kin.data)
        ee = kin.data.oMf[kin.ee_frame_id]
        tool_now = ee * pin.SE3(tool[:3, :3], tool[:3, 3])
        error = pin.log6(tool_now.inverse() * goal).vector
        if np.linalg.norm(error[:3]) <= tolerance_m and np.linalg.norm(error[3:]) <= tolerance_rad:
            return q, True
        J_ee = pin.getFrameJacobian(kin.model, kin.data, kin.ee_frame_id, pin.LOCAL)
        J = pin.Jlog6(tool_now.inverse() * goal) @ ee_in_tool.action @ J_ee
        step = J.T @ np.linalg.solve(J @ J.T + damping * np.eye(6), error)
        if max_step is not None:
            longest = float(np.max(np.abs(step)))
            if longest > max_step:
                step = step * (max_step / longest)
        q = np.clip(q + step, np.where(np.isfinite(lower), lower, -np.inf), np.where(np.isfinite(upper), upper, np.inf))
    return q, False
