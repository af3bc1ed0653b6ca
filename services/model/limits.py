"""Which speed and acceleration limits apply: the robot declares the ones it applies in every state
(``RobotState.limits``, set by its DSP's configuration or the arm's own); the controller saturates its output to
them and safety checks against them, or against stricter ones where a site configuration says so. Nobody else
repeats the numbers. A robot that declares none is taken at the arm description's maxima (:mod:`jaco2`).
"""
from __future__ import annotations

import math
from typing import Optional

import numpy as np

from protocol.messages import MotionLimits, RobotState
from services.model import jaco2


def arm_limits(linear_speed_mps: float = jaco2.MAX_LINEAR_SPEED_MPS,
               angular_speed_rps: float = jaco2.MAX_ANGULAR_SPEED_RPS, joint_speed_scale: float = 1.0,
               linear_accel_mps2: float = jaco2.LINEAR_ACCEL_MPS2, angular_accel_rps2: float = jaco2.ANGULAR_ACCEL_RPS2,
               joint_accel_dps2: float = jaco2.JOINT_ACCEL_DPS2) -> MotionLimits:
    """The limits of a JACO-2 set to these values (its DSP's configuration); by default the most it allows
    (Kinova's client configuration ranges, the actuators' rated speeds)."""
    return MotionLimits(linear_speed_mps=linear_speed_mps, angular_speed_rps=angular_speed_rps,
                        joint_speed_rps=(jaco2.MAX_SPEED * joint_speed_scale).tolist(),
                        linear_accel_mps2=linear_accel_mps2, angular_accel_rps2=angular_accel_rps2,
                        joint_accel_rps2=math.radians(joint_accel_dps2))


_ARM_LIMITS = arm_limits()


def declared(state: Optional[RobotState]) -> MotionLimits:
    """The limits the robot declares in ``state``, else the arm description's."""
    if state is not None and state.limits is not None:
        return state.limits
    return _ARM_LIMITS


def stricter(limits: MotionLimits, linear_speed_mps: Optional[float] = None,
             angular_speed_rps: Optional[float] = None, joint_speed_scale: float = 1.0,
             linear_accel_mps2: Optional[float] = None, angular_accel_rps2: Optional[float] = None,
             joint_accel_rps2: Optional[float] = None) -> MotionLimits:
    """``limits`` where each given value is lower (a site's own limits never loosen the robot's)."""
    def low(value: float, own: Optional[float]) -> float:
        return value if own is None else min(value, own)

    return MotionLimits(
        linear_speed_mps=low(limits.linear_speed_mps, linear_speed_mps),
        angular_speed_rps=low(limits.angular_speed_rps, angular_speed_rps),
        joint_speed_rps=(np.asarray(limits.joint_speed_rps) * min(1.0, joint_speed_scale)).tolist(),
        linear_accel_mps2=low(limits.linear_accel_mps2, linear_accel_mps2),
        angular_accel_rps2=low(limits.angular_accel_rps2, angular_accel_rps2),
        joint_accel_rps2=low(limits.joint_accel_rps2, joint_accel_rps2),
    )
