"""How near a singularity the arm is, and how much a commanded motion may keep of its speed there (pure).

MoveIt Servo's rule (moveit_servo's ``velocityScalingFactorForSingularity``): the Jacobian's condition number
κ = σ_max/σ_min; a motion toward the nearest singularity keeps ``1 − (κ − slow_from)/(stop_at − slow_from)`` of its
speed between the two bounds and none beyond ``stop_at``; a motion away is not slowed, so the person can always drive
out.

What differs from MoveIt Servo, and why. *Toward*: MoveIt Servo takes the left singular vector of σ_min, resolves its
sign by a small step ahead along it (the step that makes κ grow points toward), and calls a motion toward when its
dot product with that vector is positive. A motion at an angle to that vector can still raise κ: a wrist jog on the
j2n6s300 that the dot product called *away* drove κ from 32 to 144 (tests/services/model/test_singularity.py).
Here the motion itself is looked a small step ahead (:func:`raises_condition`): toward when κ grows along it. *κ*:
taken of :func:`~services.model.kinematics.normalized_jacobian` (the
linear rows over the arm's reach), not of J in m and rad, so that translation and rotation compare in one unit and
the bounds mean the same on arms of other sizes; it is the matrix whose smallest singular value is the emulated DSP's
singularity measure (services/robot/dsp.py), so both judge one thing (κ ≈ 2/measure on both JACO-2s: σ_max stays
within 1.7-2.0). The bounds are ours, not MoveIt's 17 and 30 (its defaults), checked on both arms: the j2n6s300
stands at κ 17.8 at its home pose and 16-22 across its ordinary workspace, so 17 would slow the 6-DoF arm wherever it
works, and seed 000's Part B (a large rotation about the optical axis) takes the servo through κ 48 on the j2s7s300
and 49 on the j2n6s300 (the identity bench's logs), which the arm makes as commanded: slowed there, Part B took 273
iterations instead of 115. So safety slows a motion toward a singularity only from κ 50 (measure ≈ 0.04), above what
the seed's experiments reach, and stops it at 80 (measure ≈ 0.025): near the workspace's edge κ grows steeply, and
from a stop at 90 the arm's braking (its acceleration limits) could not keep a reach at 0.1 m/s out of the
singularity (the j2n6s300 went through to κ 10⁴); from 80 it stops at 80, and from the jog's top speed (0.2 m/s) at
83, both before the emulated DSP's damped least squares (measure 0.02, κ ≈ 95), where the arm would no longer move
as commanded.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from services.model.kinematics import ArmKinematics, normalized_jacobian
from services.runtime.config import ConfigStruct


class SingularityBounds(ConfigStruct):
    #: a motion toward a singularity is slowed from this condition number of the normalized Jacobian ...
    slow_from: float = 50.0
    #: ... linearly to a stop here (the module's docstring says why these)
    stop_at: float = 80.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.slow_from) and math.isfinite(self.stop_at) and 1.0 <= self.slow_from < self.stop_at):
            raise ValueError("singularity bounds need 1 <= slow_from < stop_at")


@dataclass
class SingularityScale:
    """What a motion may keep of its speed (1: all of it), the condition number there, and whether the motion
    goes toward the nearest singularity."""

    factor: float
    condition: float
    toward: bool


#: the look-ahead: the joints moved along the command's resolved joint motion until the one that moves most has turned
#: this far (rad): small enough that κ changes smoothly over it even next to a singularity, where a step of fixed
#: task-space length (MoveIt Servo's: the vector over 100) turns the joints far enough to jump past it
LOOK_AHEAD_RAD = 1e-3


def condition_number(J_normalized: np.ndarray) -> float:
    """κ = σ_max/σ_min (infinite at a singularity)."""
    s = np.linalg.svd(J_normalized, compute_uv=False)
    return math.inf if s[-1] <= 0.0 else float(s[0] / s[-1])


def raises_condition(kin: ArmKinematics, q, J_normalized: np.ndarray, motion: np.ndarray, condition: float) -> bool:
    """Whether a small step of ``motion`` (normalized task units: linear over the reach, then angular) from ``q``,
    resolved by the pseudo-inverse as the arm resolves it, makes κ grow."""
    dq = np.linalg.pinv(J_normalized) @ motion
    largest = float(np.max(np.abs(dq)))
    if largest == 0.0:
        return False
    step = dq * (LOOK_AHEAD_RAD / largest)
    ahead = condition_number(normalized_jacobian(kin.jacobian_base(np.asarray(q, dtype=float) + step),
                                                 kin.characteristic_length_m))
    return ahead > condition


def singularity_scale(kin: ArmKinematics, q, J_base: np.ndarray, twist_base: np.ndarray,
                      bounds: SingularityBounds) -> SingularityScale:
    """How much of ``twist_base`` (v, ω in the base frame) the arm at ``q`` (its base Jacobian ``J_base``) may keep."""
    length = kin.characteristic_length_m
    Jn = normalized_jacobian(J_base, length)
    condition = condition_number(Jn)
    if condition < bounds.slow_from:  # far from any: the look-ahead is not needed
        return SingularityScale(1.0, condition, False)
    motion = np.asarray(twist_base, dtype=float).copy()
    motion[:3] /= length  # in the normalized Jacobian's task units
    if not raises_condition(kin, q, Jn, motion, condition):
        return SingularityScale(1.0, condition, False)
    if condition >= bounds.stop_at:
        return SingularityScale(0.0, condition, True)
    factor = 1.0 - (condition - bounds.slow_from) / (bounds.stop_at - bounds.slow_from)
    return SingularityScale(factor, condition, True)
