"""Command checks of the safety service, as a plain class: given a desired twist or joint velocity and the
robot's latest state, decide what the robot may do (forward, clamp, or refuse with a reason).

All quantities are SI; joint angles are model angles. Twists are mixed-frame in the robot's convention.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal, Optional

import msgspec
import numpy as np

from protocol.conventions import IMAGE_AGE_BUDGET_S, AngularConvention, Frame
from protocol.messages import MotionLimits
from services.model import frames, saturation
from services.model.limits import stricter
from services.runtime.config import ConfigStruct
from services.model.kinematics import ArmKinematics
from services.model.singularity import Braking, SingularityBounds, singularity_scale
from services.model.zones import Zone, ZoneFilterConfig, default_base_zone, filter_velocity


class SafetyLimits(ConfigStruct):
    #: the convention the robot reads (checked against what the robot reports in its state)
    robot_convention: AngularConvention = AngularConvention.SEED000
    #: a desired command older than this (its stamp to now) is stale
    command_budget_s: float = 0.1
    #: a command derived from an image older than this (capture to now) is stale
    image_budget_s: float = IMAGE_AGE_BUDGET_S
    #: the robot state used for the joint and zone checks must be this fresh
    state_budget_s: float = 0.1
    #: an input stamped further ahead of safety's clock than this is refused (clock skew between hosts, no more)
    future_skew_s: float = 0.05
    #: a device-derived command (a joystick's) whose device was last heard longer ago than this is stale: the device
    #: froze or went (our choice: 2.5 command budgets, so that one late device report does not stop the arm, and a
    #: device gone is noticed within a quarter second)
    device_budget_s: float = 0.25
    #: the speed and acceleration limits are the robot's own, as it declares them in its state
    #: (``RobotState.limits``); a value set here is a stricter site limit (it never loosens the robot's)
    max_linear_speed_mps: Optional[float] = None
    max_angular_speed_rps: Optional[float] = None
    max_linear_accel_mps2: Optional[float] = None
    max_angular_accel_rps2: Optional[float] = None
    #: fraction of the robot's joint speeds a command may ask for
    joint_speed_scale: float = 1.0
    max_joint_accel_dps2: Optional[float] = None
    #: what to do with a command over a speed limit: scale it down to the limit, or refuse it (stop)
    over_limit: Literal["clamp", "refuse"] = "clamp"
    #: joint limits are predicted this far ahead, and kept this far inside
    joint_horizon_s: float = 0.1
    joint_limit_margin_deg: float = 3.0
    #: measured motion: the end effector's speeds (from the robot state's q and dq) and each joint's may exceed
    #: their limits (the speed limits above; the joints' rated speeds, which the robot's DSP enforces) by this
    #: fraction for less than ``measured_overspeed_s``; beyond that, a latched protective stop
    measured_speed_margin: float = 0.1
    measured_overspeed_s: float = 0.01
    #: workspace zones the end effector must not enter (base frame)
    zones: list[Zone] = msgspec.field(default_factory=lambda: [default_base_zone()])
    zone_filter: ZoneFilterConfig = msgspec.field(default_factory=lambda: ZoneFilterConfig(margin_m=0.02))
    #: a twist toward a singularity slowed from, and stopped at, these condition numbers (a source's declared
    #: ``singularity: stop``, services/safety/sources.py; a joint velocity command has no inverse to blow up near
    #: one, and is not slowed, as in MoveIt Servo)
    singularity: SingularityBounds = msgspec.field(default_factory=SingularityBounds)

    def __post_init__(self) -> None:
        for name in ("command_budget_s", "image_budget_s", "state_budget_s", "future_skew_s", "device_budget_s",
                     "joint_horizon_s",
                     "measured_overspeed_s", *SITE_LIMITS):
            value = getattr(self, name)
            if value is not None and not (value > 0 and math.isfinite(value)):
                raise ValueError(f"{name} must be positive")
        if not 0 < self.joint_speed_scale <= 1:
            raise ValueError("joint_speed_scale must be within (0, 1]")
        if not 0 <= self.measured_speed_margin <= 1:
            raise ValueError("measured_speed_margin must be within [0, 1]")


#: the limits a site may set stricter than the robot's
SITE_LIMITS = ("max_linear_speed_mps", "max_angular_speed_rps", "max_linear_accel_mps2", "max_angular_accel_rps2",
               "max_joint_accel_dps2")


def effective_limits(site: SafetyLimits, robot: MotionLimits) -> MotionLimits:
    """The robot's declared limits, or the site's where they are stricter."""
    return stricter(robot, site.max_linear_speed_mps, site.max_angular_speed_rps, site.joint_speed_scale,
                    site.max_linear_accel_mps2, site.max_angular_accel_rps2,
                    None if site.max_joint_accel_dps2 is None else math.radians(site.max_joint_accel_dps2))


@dataclass
class Decision:
    """What the robot may do: a twist (mixed, robot convention) or joint velocities, or nothing (refusal)."""

    twist: Optional[np.ndarray] = None
    joint_velocities: Optional[np.ndarray] = None
    refusal: Optional[str] = None
    #: limits that changed the command (clamps) or refused it
    limits: list[str] = field(default_factory=list)

    @property
    def refused(self) -> bool:
        return self.refusal is not None


def _over_speed(ratio: saturation.TwistRatio, robot: MotionLimits) -> tuple[list[str], str]:
    """The names of a twist's parts over their speed limits, and why (a clamp's record, or a refusal's reason)."""
    over = [(name, part * limit, limit) for name, part, limit in
            (("linear_speed", ratio.linear, robot.linear_speed_mps),
             ("angular_speed", ratio.angular, robot.angular_speed_rps)) if part > 1.0]
    return [name for name, _, _ in over], "; ".join(f"{name}: {speed:.3f} over the limit {limit:.3f}"
                                                    for name, speed, limit in over)


class CommandChecker:
    """Checks desired commands against the limits, the robot's state and the workspace zones."""

    def __init__(self, limits: SafetyLimits, kinematics: ArmKinematics) -> None:
        """``kinematics``: of the arm the commands are for (``kinematics.arm``: its joints, their ranges)."""
        self.limits = limits
        self.kin = kinematics
        self.lower, self.upper = kinematics.arm.model_limits()
        margin = math.radians(limits.joint_limit_margin_deg)
        self.lower_soft, self.upper_soft = self.lower + margin, self.upper - margin
        self.limited = np.isfinite(self.lower)
        #: the last base-frame twist (or joint velocities) forwarded, for the acceleration limits
        self.last_twist_base = np.zeros(6)
        self.last_dq = np.zeros(kinematics.arm.n_joints)

    def reset_motion(self) -> None:
        """Forget the last forwarded motion (after a stop: the next command starts from rest)."""
        self.last_twist_base = np.zeros(6)
        self.last_dq = np.zeros(self.kin.arm.n_joints)

    # ------------------------------------------------------------------ twists
    def check_twist(self, frame: Frame, angular: AngularConvention, twist, q, dt: float,
                    robot: MotionLimits, also_accepted: tuple[AngularConvention, ...] = (),
                    near_singularity: bool = True) -> Decision:
        """``robot``: the limits the robot declares (:func:`services.model.limits.declared`). A twist is taken in the
        robot's convention, or in one of ``also_accepted`` (a command type that defines its own: a jog's ω about the
        hand's axes), and what goes to the robot is in the robot's. ``near_singularity``: a twist toward a
        singularity slowed and stopped before it (its source's rule, services/safety/sources.py NearSingularity)."""
        lim = self.limits
        robot = effective_limits(lim, robot)
        if frame is not Frame.MIXED or (angular is not lim.robot_convention and angular not in also_accepted):
            return Decision(refusal=f"convention: the robot takes mixed twists with '{lim.robot_convention.value}' "
                                    f"angular velocity, this one is {frame.value}/{angular.value}",
                            limits=["convention"])
        q = np.asarray(q, dtype=float)
        R, p, J = self.kin.pose_and_jacobian(q)
        try:
            base = frames.base_twist_from_mixed(np.asarray(twist, dtype=float), R, angular)
        except frames.EulerSingularityError as exc:
            return Decision(refusal=f"orientation: {exc}", limits=["euler_singularity"])
        decision = Decision()

        # near a singularity: a motion toward it slowed, and stopped before it (its direction kept); away from it,
        # not (services/model/singularity.py: MoveIt Servo's rule). Before the acceleration limit, which then brakes
        # to what is left
        near = singularity_scale(self.kin, q, J, base, lim.singularity,
                                 Braking(robot.linear_accel_mps2, robot.angular_accel_rps2, robot.joint_accel_rps2,
                                         lim.singularity.braking_lag_s)) if near_singularity else None
        if near is not None and near.factor < 1.0:
            base = base * near.factor
            decision.limits.append("singularity" if near.factor > 0.0 else "singularity_stop")

        # speeds: the whole twist by one factor (its direction kept), or refused
        limited, ratio = saturation.limit_twist(base, robot.linear_speed_mps, robot.angular_speed_rps)
        if ratio.over > 1.0:
            over, why = _over_speed(ratio, robot)
            if lim.over_limit == "refuse":
                return Decision(refusal=why, limits=over)
            base = limited
            decision.limits += over
        # accelerations, from the last forwarded twist: the change by one factor
        base, cut = saturation.limit_twist_change(self.last_twist_base, base, robot.linear_accel_mps2 * dt,
                                                  robot.angular_accel_rps2 * dt)
        if cut:
            decision.limits.append("acceleration")
        # workspace zones: remove motion into a zone
        base[:3], zones = filter_velocity(lim.zones, p, base[:3], lim.zone_filter, dt)
        decision.limits += [f"zone:{z}" for z in zones]
        # joints: predicted through the Jacobian
        J_pinv = np.linalg.pinv(J)
        dq = J_pinv @ base
        scale = 1.0
        joint_ratio = saturation.over_limit_ratio(dq, robot.joint_speed_rps)
        if joint_ratio > 1.0:
            if lim.over_limit == "refuse":
                return Decision(refusal=f"joint_speed: {joint_ratio:.2f}× the joint speed limit",
                                limits=["joint_speed"])
            scale = 1.0 / joint_ratio
            decision.limits.append("joint_speed")
        scale = min(scale, self._joint_limit_scale(q, dq * scale, decision) * scale)
        base *= scale
        decision.twist = frames.mixed_from_base_twist(base, R, lim.robot_convention)
        self.last_twist_base = base
        self.last_dq = J_pinv @ base
        return decision

    def _joint_limit_scale(self, q, dq, decision: Decision) -> float:
        """The largest factor (≤ 1) for which no joint passes its soft limit within the horizon."""
        h = self.limits.joint_horizon_s
        predicted = q + dq * h
        scale = 1.0
        for i in np.flatnonzero(self.limited):
            if predicted[i] > self.upper_soft[i] and dq[i] > 0:
                scale = min(scale, max(0.0, (self.upper_soft[i] - q[i]) / (dq[i] * h)))
            elif predicted[i] < self.lower_soft[i] and dq[i] < 0:
                scale = min(scale, max(0.0, (self.lower_soft[i] - q[i]) / (dq[i] * h)))
        if scale < 1.0:
            decision.limits.append("joint_limit")
        return scale

    # ------------------------------------------------------------------ joint velocities
    def check_joint_velocity(self, dq, q, dt: float, robot: MotionLimits) -> Decision:
        """``robot``: the limits the robot declares (:func:`services.model.limits.declared`)."""
        lim = self.limits
        robot = effective_limits(lim, robot)
        q = np.asarray(q, dtype=float)
        dq = np.array(dq, dtype=float, copy=True)
        if len(dq) != self.kin.arm.n_joints:
            return Decision(refusal=f"joint_count: {len(dq)} joint velocities for the {self.kin.arm.name}'s "
                                    f"{self.kin.arm.n_joints} joints", limits=["joint_count"])
        decision = Decision()
        limited, ratio = saturation.limit_uniformly(dq, robot.joint_speed_rps)
        if ratio > 1.0:
            if lim.over_limit == "refuse":
                return Decision(refusal=f"joint_speed: {ratio:.2f}× the joint speed limit", limits=["joint_speed"])
            dq = limited
            decision.limits.append("joint_speed")
        dq, cut = saturation.limit_change_uniformly(self.last_dq, dq, robot.joint_accel_rps2 * dt)
        if cut:
            decision.limits.append("joint_accel")
        dq *= self._joint_limit_scale(q, dq, decision)
        R, p, J = self.kin.pose_and_jacobian(q)
        twist = J @ dq
        ratio = saturation.twist_ratio(twist, robot.linear_speed_mps, robot.angular_speed_rps)
        if ratio.over > 1.0:
            over, why = _over_speed(ratio, robot)
            if lim.over_limit == "refuse":
                return Decision(refusal=why, limits=over)
            dq, twist = dq / ratio.over, twist / ratio.over  # the joint motion scaled as its twist is
            decision.limits += over
        _, zones = filter_velocity(lim.zones, p, twist[:3], lim.zone_filter, dt)
        if zones:
            # joint motion cannot be bent along a zone's boundary: motion into a zone is refused
            return Decision(refusal=f"zone: joint motion would enter {', '.join(zones)}",
                            limits=[f"zone:{z}" for z in zones])
        decision.joint_velocities = dq
        self.last_dq = dq
        self.last_twist_base = J @ dq
        return decision

    def end_effector_position(self, q) -> np.ndarray:
        return self.kin.pose(q)[1]


class MotionMonitor:
    """Watches what the arm does, not what it was told: from each robot state (q, dq), the end effector's linear
    and angular speed (J(q)·dq) and each joint's speed, against the limits plus ``measured_speed_margin``. Over a
    limit continuously for at least ``measured_overspeed_s`` (by the states' stamps: two consecutive states at
    100 Hz) is an overspeed: :meth:`observe` returns why, once, and the service latches a protective stop."""

    def __init__(self, limits: SafetyLimits, kinematics: ArmKinematics) -> None:
        self.limits = limits
        self.kin = kinematics
        self._since: Optional[int] = None
        #: the largest measured speeds so far, as fractions of their limits (without the margin)
        self.peak_ratio = {"linear": 0.0, "angular": 0.0, "joint": 0.0}
        self.peak_linear_mps = 0.0

    def speeds(self, q, dq) -> tuple[float, float, np.ndarray]:
        twist = self.kin.jacobian_base(np.asarray(q, dtype=float)) @ np.asarray(dq, dtype=float)
        return float(np.linalg.norm(twist[:3])), float(np.linalg.norm(twist[3:])), np.abs(np.asarray(dq, float))

    def observe(self, q, dq, stamp_ns: int, robot: MotionLimits) -> Optional[str]:
        """``robot``: the limits the robot declares in the state that measured ``q`` and ``dq``."""
        lim = self.limits
        robot = effective_limits(lim, robot)
        margin = 1.0 + lim.measured_speed_margin
        joint_limits = np.asarray(robot.joint_speed_rps)
        linear, angular, joints = self.speeds(q, dq)
        self.peak_linear_mps = max(self.peak_linear_mps, linear)
        ratios = {"linear": linear / robot.linear_speed_mps, "angular": angular / robot.angular_speed_rps,
                  "joint": float(np.max(joints / joint_limits))}
        for name, ratio in ratios.items():
            self.peak_ratio[name] = max(self.peak_ratio[name], ratio)
        over = []
        if ratios["linear"] > margin:
            over.append(f"end-effector speed {linear:.3f} m/s over {robot.linear_speed_mps:.3f}")
        if ratios["angular"] > margin:
            over.append(f"end-effector angular speed {angular:.3f} rad/s over {robot.angular_speed_rps:.3f}")
        fast = np.flatnonzero(joints > joint_limits * margin)
        if len(fast):
            i = int(fast[0])
            over.append(f"joint {i + 1} speed {np.degrees(joints[i]):.1f} deg/s over "
                        f"{np.degrees(joint_limits[i]):.0f}")
        if not over:
            self._since = None
            return None
        if self._since is None:
            self._since = stamp_ns
            return None
        lasted = (stamp_ns - self._since) * 1e-9
        if lasted + 1e-9 < lim.measured_overspeed_s:
            return None
        self._since = None
        return f"measured {'; '.join(over)} (+{lim.measured_speed_margin:.0%}) for {lasted * 1e3:.0f} ms"
