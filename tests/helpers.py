"""Shared test helpers: random configurations and reference kinematics through Pinocchio."""
import numpy as np
import pinocchio as pin

from services.common import jaco2


def random_q(rng, margin_deg: float = 2.0) -> np.ndarray:
    """Model angles: limited joints uniformly inside their limits, continuous joints over ±2 turns."""
    lower, upper = jaco2.model_limits()
    q = rng.uniform(-4 * np.pi, 4 * np.pi, jaco2.N_JOINTS)
    limited = np.isfinite(lower)
    m = np.radians(margin_deg)
    q[limited] = rng.uniform(lower[limited] + m, upper[limited] - m)
    return q


class PinArm:
    """Forward kinematics and Jacobians of the end effector through Pinocchio."""

    def __init__(self):
        arm = jaco2.load_pinocchio()
        self.model, self.fid = arm.model, arm.ee_frame_id
        self.data = self.model.createData()

    def pose(self, q) -> tuple[np.ndarray, np.ndarray]:
        pin.framesForwardKinematics(self.model, self.data, np.asarray(q, float))
        M = self.data.oMf[self.fid]
        return M.rotation.copy(), M.translation.copy()

    def jacobian_base(self, q) -> np.ndarray:
        """[v; ω] of the end-effector origin, both in base coordinates."""
        pin.computeJointJacobians(self.model, self.data, np.asarray(q, float))
        pin.updateFramePlacements(self.model, self.data)
        return pin.getFrameJacobian(self.model, self.data, self.fid, pin.LOCAL_WORLD_ALIGNED).copy()
