"""Which speed and acceleration limits apply: the robot declares the ones it applies in every state
(``RobotState.limits``, set by its DSP's configuration or the arm's own); the controller saturates its output to
them and safety checks against them, or against stricter ones where a site configuration says so. Nobody else
repeats the numbers. A robot that declares none is taken at its arm description's maxima (:mod:`services.model.arm`).
"""
from __future__ import annotations

import math
from typing import Optional

import numpy as np

from protocol.messages import MotionLimits, RobotState
from services.model.arm import ArmDescription


def arm_limits(arm: ArmDescription, linear_speed_mps: Optional[float] = None,
               angular_speed_rps: Optional[float] = None, joint_speed_scale: float = 1.0,
               linear_accel_mps2: Optional[float] = None, angular_accel_rps2: Optional[float] = None,
               joint_accel_dps2: Optional[float] = None) -> MotionLimits:
    """The limits of ``arm`` set to these values (its DSP's configuration); what is not given, the most it allows
    (Kinova's client configuration ranges, the actuators' rated speeds, the acceleration limits)."""
    def given(value: Optional[float], default: float) -> float:
        return default if value is None else value

    return MotionLimits(linear_speed_mps=given(linear_speed_mps, arm.max_linear_speed_mps),
                        angular_speed_rps=given(angular_speed_rps, arm.max_angular_speed_rps),
                        joint_speed_rps=(arm.max_speed * joint_speed_scale).tolist(),
                        linear_accel_mps2=given(linear_accel_mps2, arm.linear_accel_mps2),
                        angular_accel_rps2=given(angular_accel_rps2, arm.angular_accel_rps2),
                        joint_accel_rps2=math.radians(given(joint_accel_dps2, arm.joint_accel_dps2)))


def declared(state: Optional[RobotState], arm: ArmDescription) -> MotionLimits:
    """The limits the robot declares in ``state``, else ``arm``'s."""
    if state is not None and state.limits is not None:
        return state.limits
    return arm_limits(arm)


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
