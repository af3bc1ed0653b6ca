"""Shared test helpers: random configurations and reference kinematics through Pinocchio."""
import numpy as np

from services.common import jaco2
from services.common.kinematics import ArmKinematics


def random_q(rng, margin_deg: float = 2.0) -> np.ndarray:
    """Model angles: limited joints uniformly inside their limits, continuous joints over ±2 turns."""
    lower, upper = jaco2.model_limits()
    q = rng.uniform(-4 * np.pi, 4 * np.pi, jaco2.N_JOINTS)
    limited = np.isfinite(lower)
    m = np.radians(margin_deg)
    q[limited] = rng.uniform(lower[limited] + m, upper[limited] - m)
    return q


class PinArm(ArmKinematics):
    """Reference kinematics for tests: the product's Pinocchio wrapper (checked against MuJoCo and the DH table
    in test_jaco2_model)."""
