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
the seed's fixed starts reach (its random starts go further, into the hundreds; the visual servo's twists are left to
the robot's DSP: services/safety/sources.py NearSingularity), and stops it at 80 (measure ≈ 0.025): near the
workspace's edge κ grows steeply, and from a stop at 90 the arm's braking (its acceleration limits) could not keep a
reach at 0.1 m/s out of the singularity (the j2n6s300 went through to κ 10⁴); from 80 it stops at 80, and from the
jog's top speed (0.2 m/s) at 83, both before the emulated DSP's damped least squares (measure 0.02, κ ≈ 95), where
the arm would no longer move as commanded.

*Braking*, which MoveIt Servo leaves to the robot. Those figures are for an arm that follows the commands exactly.
The arm follows a cycle late and brakes at its acceleration limits, and near the workspace's edge a millimetre
raises κ by tens: through the emulated DSP in realtime the ramp alone let the arms come to rest at κ 109-125. So a
twist toward a singularity also keeps no more than the arm can still stop from before ``stop_at``
(:func:`angle_to_bound` on κ's 1/distance shape, :func:`braking_scale` with the arm's decelerations and a lag):
in realtime, the arms then stop at κ 80-85 (tests/services/jog/test_jog_stack.py).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import numpy as np

from services.model.kinematics import ArmKinematics, normalized_jacobian
from services.runtime.config import ConfigStruct


class SingularityBounds(ConfigStruct):
    #: a motion toward a singularity is slowed from this condition number of the normalized Jacobian ...
    slow_from: float = 50.0
    #: ... linearly to a stop here (the module's docstring says why these)
    stop_at: float = 80.0
    #: s: how long a command toward it goes on at the speed it had before the arm starts braking (:class:`Braking`):
    #: ours, the state a command is judged by is up to one robot period old (10 ms at the arm's 100 Hz), the command
    #: reaches the arm's next cycle (up to another) and the DSP's ramp starts there (one more)
    braking_lag_s: float = 0.03

    def __post_init__(self) -> None:
        if not (math.isfinite(self.slow_from) and math.isfinite(self.stop_at) and 1.0 <= self.slow_from < self.stop_at):
            raise ValueError("singularity bounds need 1 <= slow_from < stop_at")
        if not (math.isfinite(self.braking_lag_s) and 0.0 <= self.braking_lag_s <= 1.0):
            raise ValueError("singularity braking_lag_s: seconds within [0, 1]")


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


def condition_gradient(kin: ArmKinematics, q, J_normalized: np.ndarray, motion: np.ndarray,
                       condition: float) -> float:
    """How fast κ grows along ``motion`` (normalized task units: linear over the reach, then angular) from ``q``,
    resolved by the pseudo-inverse as the arm resolves it: per radian of the joint that turns most, over the
    look-ahead step (0 for no motion; negative: κ falls)."""
    return _gradient_along(kin, q, np.linalg.pinv(J_normalized) @ motion, condition)


def _gradient_along(kin: ArmKinematics, q, dq: np.ndarray, condition: float) -> float:
    """:func:`condition_gradient` along the joint motion ``dq`` the task motion resolves to."""
    largest = float(np.max(np.abs(dq)))
    if largest == 0.0:
        return 0.0
    step = dq * (LOOK_AHEAD_RAD / largest)
    ahead = condition_number(normalized_jacobian(kin.jacobian_base(np.asarray(q, dtype=float) + step),
                                                 kin.characteristic_length_m))
    return (ahead - condition) / LOOK_AHEAD_RAD


def raises_condition(kin: ArmKinematics, q, J_normalized: np.ndarray, motion: np.ndarray, condition: float) -> bool:
    """Whether a small step of ``motion`` from ``q`` makes κ grow (:func:`condition_gradient`)."""
    return condition_gradient(kin, q, J_normalized, motion, condition) > 0.0


def angle_to_bound(condition: float, gradient: float, bound: float) -> float:
    """How far (rad, of the joint that turns most) the arm may go on before κ reaches ``bound``, κ taken to grow as
    one over the distance d to the singularity ahead, κ = c/d: at a simple singularity σ_min falls linearly with the
    joints' distance to it while σ_max stays (within 1.7-2.0 on the JACO-2s), so this is κ's own shape there. From
    κ and its gradient g = c/d², c = κ²/g and what is left to the bound is c(1/κ − 1/bound) = (κ/g)(1 − κ/bound):
    less than a straight line through the gradient would leave (which overestimates it by bound/κ), so a stop
    planned on it comes before the bound, not after."""
    if condition >= bound:
        return 0.0
    if gradient <= 0.0:
        return math.inf
    return (condition / gradient) * (1.0 - condition / bound)


@dataclass(frozen=True)
class Braking:
    """How the arm stops a twist it was given: at its declared decelerations (the emulated DSP's and the real arm's
    acceleration limits, which safety's own acceleration limit also keeps), the hand's and each joint's, whichever
    takes longer (near a singularity a slow hand needs fast joints, and the joints' limit is the one that binds:
    measured on the j2n6s300 reaching out, 0.12 m/s² at the hand against its 0.64), after ``lag_s`` in which it goes
    on at the speed it had (a command's way to the arm and the arm's first cycle)."""

    linear_mps2: float
    angular_rps2: float
    joint_rps2: float
    lag_s: float

    def time_to_stop(self, twist_base: np.ndarray, dq: np.ndarray) -> float:
        """s: how long the arm takes to stop from ``twist_base`` (v, ω) and its joints' ``dq``."""
        return max(float(np.linalg.norm(twist_base[:3])) / self.linear_mps2,
                   float(np.linalg.norm(twist_base[3:])) / self.angular_rps2,
                   float(np.max(np.abs(dq))) / self.joint_rps2)


def braking_scale(joint_speed_rps: float, braking_time_s: float, lag_s: float, angle_left_rad: float) -> float:
    """The largest fraction s of a motion (whose fastest joint turns at ``joint_speed_rps`` and which takes
    ``braking_time_s`` to stop at the arm's decelerations, both at s = 1) from which the arm still stops within
    ``angle_left_rad`` of that joint: it goes on s·ω·lag, then brakes over s·ω·s·T/2 (a constant deceleration from
    s·ω to 0 in s·T), so s is the positive root of (ωT/2)s² + (ω·lag)s − angle_left = 0 (at most 1)."""
    if angle_left_rad <= 0.0:
        return 0.0
    a, b = joint_speed_rps * braking_time_s / 2.0, joint_speed_rps * lag_s
    if a <= 0.0 and b <= 0.0:
        return 1.0
    s = angle_left_rad / b if a <= 0.0 else (-b + math.sqrt(b * b + 4.0 * a * angle_left_rad)) / (2.0 * a)
    return min(1.0, s)


def singularity_scale(kin: ArmKinematics, q, J_base: np.ndarray, twist_base: np.ndarray,
                      bounds: SingularityBounds, braking: Optional[Braking] = None) -> SingularityScale:
    """How much of ``twist_base`` (v, ω in the base frame) the arm at ``q`` (its base Jacobian ``J_base``) may keep:
    MoveIt Servo's ramp between the bounds and, with ``braking``, no more than the arm can still stop from before
    κ reaches ``stop_at`` (:func:`angle_to_bound`, :func:`braking_scale`): near the workspace's edge κ grows so
    steeply that the ramp alone leaves the arm, which follows its commands a cycle late and brakes at its
    decelerations, going on well past the bound."""
    length = kin.characteristic_length_m
    Jn = normalized_jacobian(J_base, length)
    condition = condition_number(Jn)
    if condition < bounds.slow_from:  # far from any: the look-ahead is not needed
        return SingularityScale(1.0, condition, False)
    twist_base = np.asarray(twist_base, dtype=float)
    motion = twist_base.copy()
    motion[:3] /= length  # in the normalized Jacobian's task units
    dq = np.linalg.pinv(Jn) @ motion  # the joints' motion, the same as J_base's pseudo-inverse gives the twist
    gradient = _gradient_along(kin, q, dq, condition)
    if gradient <= 0.0:
        return SingularityScale(1.0, condition, False)
    if condition >= bounds.stop_at:
        return SingularityScale(0.0, condition, True)
    factor = 1.0 - (condition - bounds.slow_from) / (bounds.stop_at - bounds.slow_from)
    if braking is not None:
        factor = min(factor, braking_scale(float(np.max(np.abs(dq))), braking.time_to_stop(twist_base, dq),
                                           braking.lag_s,
                                           angle_to_bound(condition, gradient, bounds.stop_at)))
    return SingularityScale(factor, condition, True)
