"""The emulated Kinova DSP high-level controller: what the JACO-2's own firmware does at 100 Hz.

It turns high-level commands (mixed-frame Cartesian velocity, joint velocity, angular and Cartesian position
trajectories, MoveHome) into joint velocity references, which the robot node (:mod:`services.robot.core`)
integrates into the actuators' position targets, reproducing the DSP's behaviour that the rest of mfvs relies on:

* a velocity command lasts one 10 ms cycle and must be resent; with no command for ``watchdog_cycles`` cycles
  the arm decelerates to rest within the acceleration limits;
* speed limits (0.2 m/s, 1.07 rad/s by default, configurable within Kinova's client ranges), acceleration
  limits (0.64 m/s², 2.75 rad/s², 200 deg/s²) and the actuators' joint speeds (36/48 deg/s), each applied by one
  factor on the whole motion, so a limited command keeps its direction;
* Cartesian velocity resolved on the Jacobian with its rows in one unit; a redundant arm's self-motion (while it
  moves) away from joint limits and, near a singularity, up the singularity measure; damped least squares only
  where the arm is truly near one;
* protection zones: the component of end-effector motion into a zone is removed, so it glides along the zone;
* joint limits are never crossed: the speed toward a limit is capped so the joint can always stop before it;
* the angular part of a Cartesian velocity is read in one configured convention; a command that declares
  another convention (or frame) is refused, never reinterpreted.

Two command paths: :meth:`KinovaDSP.send_basic_trajectory` follows the Kinova API (a 2000-point FIFO; each
velocity point is consumed by one cycle, so sending faster than 100 Hz queues motion, as on the real arm);
:meth:`KinovaDSP.submit` takes mfvs robot commands from the safety service: the latest one is applied in the
next cycle (no queue), and it erases the FIFO.

The class is pure: no zenoh, no MuJoCo. A simulator or a gateway calls :meth:`cycle` every 10 ms with the
measured joint state and writes the returned references to its actuators.
"""
from __future__ import annotations

import collections
import enum
import math
from dataclasses import dataclass, field
from typing import Optional

import msgspec
import numpy as np

from protocol import kinova
from protocol.conventions import AngularConvention, Frame
from protocol.messages import CommandMode, ControlMode, Header, MotionLimits, RobotCommand
from services.model import frames, saturation
from services.model.arm import ArmDescription
from services.runtime.config import ConfigStruct
from services.model.kinematics import ArmKinematics, normalized_jacobian, singularity_measure
from services.model.limits import arm_limits
from services.model.zones import Zone, ZoneFilterConfig, default_base_zone, filter_velocity
from services.robot.hardware import DSP_CYCLE_NS


class DeadBandShape(str, enum.Enum):
    #: a command below the dead-band gives no motion at all; above it, the command as it is
    HARD = "hard"
    #: below the dead-band the arm moves at (v/v_d)·v: a tenth of the dead-band moves at a hundredth of it, so
    #: practically nothing, yet the arm still creeps toward where it is told
    CREEP = "creep"


class DeadBand(ConfigStruct):
    """The arm's velocity dead-band: a velocity command that asks the end effector to move slower than
    ``linear_mps`` and turn slower than ``angular_rps`` gives (practically) no motion. Sensors 2022 (section 3.1) met
    it on the JACO-2 near convergence ("it does not move for minimal Cartesian velocities computed by the control
    law"), which is why its adaptive gain matters (Table 3: 446 → 189 iterations). It applies to Cartesian and joint
    velocity commands alike, by the end-effector motion they ask for, and scales the whole command (its direction
    kept). The defaults are not the values users report for the real arm (0.02 m/s, 0.1 rad/s): docs/robot.md says
    why."""

    #: 2 mm/s and 0.01 rad/s (the ratio of the reported 0.02 m/s and 0.1 rad/s, a tenth of their size): with them
    #: Table 3's constant-gain joint law takes 497 iterations from examples/scenarios/table2.yaml (paper: 446),
    #: 209 without
    linear_mps: float = 2e-3
    angular_rps: float = 1e-2
    shape: DeadBandShape = DeadBandShape.CREEP

    def __post_init__(self) -> None:
        for name in ("linear_mps", "angular_rps"):
            value = getattr(self, name)
            if not (value >= 0 and math.isfinite(value)):
                raise ValueError(f"dead_band.{name} must be zero (off) or positive")


def dead_band(twist: np.ndarray, band: DeadBand) -> float:
    """The factor a velocity command that asks for the end-effector ``twist`` [v; ω] is multiplied by: 1 when its
    linear or its angular speed reaches its dead-band (a zero threshold is no dead-band); below both, 0 when hard,
    else the larger of the two speeds as a fraction of its dead-band."""
    ratios = [float(np.linalg.norm(twist[part])) / threshold
              for (part, _), threshold in zip(saturation.TWIST_PARTS, (band.linear_mps, band.angular_rps))
              if threshold > 0.0]
    if not ratios or max(ratios) >= 1.0:
        return 1.0
    return 0.0 if DeadBandShape(band.shape) is DeadBandShape.HARD else max(ratios)


class DSPConfig(ConfigStruct):
    #: the DSP's tick (s): the arm's 100 Hz (services.robot.hardware.DSP_CYCLE_NS, which the robot node ticks on);
    #: a config may state it, not change it (integrated on another step than it ticks, the arm would move faster or
    #: slower than commanded)
    cycle_s: float = DSP_CYCLE_NS * 1e-9
    #: how the angular part of a Cartesian velocity is read (seed000, euler_xyz_rates or omega: docs/contracts.md)
    angular_convention: AngularConvention = AngularConvention.SEED000
    #: the top translation (m/s) and orientation (rad/s) speeds, within the client configuration ranges of the arm's
    #: description, and the accelerations; null: the arm's own (its description)
    max_linear_speed_mps: Optional[float] = None
    max_angular_speed_rps: Optional[float] = None
    linear_accel_mps2: Optional[float] = None
    angular_accel_rps2: Optional[float] = None
    joint_accel_dps2: Optional[float] = None
    dead_band: DeadBand = msgspec.field(default_factory=DeadBand)
    #: fraction of the actuators' rated speeds (36/48 deg/s) the DSP may use
    joint_speed_scale: float = 1.0
    watchdog_cycles: int = 2
    #: a velocity command takes effect this many cycles later than the next one (the command-to-motion delay of
    #: the arm's USB link and firmware; not measured on a JACO-2: 0 by default). A stop acts at once and drops the
    #: velocity commands still on their way
    command_delay_cycles: int = 0
    #: joints stop this far inside their limits
    joint_limit_margin_deg: float = 2.0
    #: singularities, judged by :func:`~services.model.kinematics.singularity_measure` (the smallest singular value
    #: of J with its linear rows over the arm's reach: no units; 0.13 at the j2s7s300's home, 0.025 with its elbow
    #: 10° from straight). Below ``avoid_singularity_below`` a redundant arm's self-motion climbs the measure
    #: (null space, while moving), at full ``singularity_avoidance_gain`` from ``damp_singularity_below`` down;
    #: the end effector's motion is not changed by it
    avoid_singularity_below: float = 0.06
    singularity_avoidance_gain: float = 0.6
    #: only this near a singularity, where self-motion could not keep the arm away, is the motion resolved by
    #: damped least squares, the damping reaching ``max_damping`` as the measure goes to 0 (our choice: no public
    #: figure; docs/robot.md)
    damp_singularity_below: float = 0.02
    max_damping: float = 0.02
    #: null-space gain (while moving) away from joint limits
    joint_limit_gain: float = 0.6
    #: position trajectories: proportional gain (1/s) before the speed and acceleration profile
    position_gain: float = 3.0
    #: emergency stop: the end effector brakes along its path at these decelerations (whichever binds)
    emergency_linear_decel_mps2: float = 1.5
    emergency_angular_decel_rps2: float = 6.0
    emergency_joint_decel_dps2: float = 600.0
    zones: list[Zone] = msgspec.field(default_factory=lambda: [default_base_zone()])
    zone_filter: ZoneFilterConfig = msgspec.field(default_factory=ZoneFilterConfig)

    def __post_init__(self) -> None:
        for name in ("cycle_s", "max_linear_speed_mps", "max_angular_speed_rps", "linear_accel_mps2",
                     "angular_accel_rps2", "joint_accel_dps2"):
            value = getattr(self, name)
            if value is not None and not (value > 0 and math.isfinite(value)):
                raise ValueError(f"{name} must be positive")
        if self.cycle_s != DSP_CYCLE_NS * 1e-9:
            raise ValueError(f"dsp.cycle_s is the arm's DSP tick, {DSP_CYCLE_NS * 1e-9:g} s (its 100 Hz), not "
                             f"{self.cycle_s:g}: the robot node ticks on it")
        if not 0 < self.joint_speed_scale <= 1:
            raise ValueError("joint_speed_scale must be within (0, 1]")
        if self.watchdog_cycles < 1:
            raise ValueError("watchdog_cycles must be at least 1")
        if not 0.0 <= self.damp_singularity_below <= self.avoid_singularity_below < 1.0:
            raise ValueError("the singularity thresholds need 0 <= damp_singularity_below <= avoid_singularity_below < 1")
        for name in ("max_damping", "singularity_avoidance_gain", "joint_limit_gain"):
            value = getattr(self, name)
            if not (value >= 0 and math.isfinite(value)):
                raise ValueError(f"{name} must be zero or positive")
        if not 0 <= self.command_delay_cycles <= 100:
            raise ValueError("command_delay_cycles must be within [0, 100]")


def for_arm(config: DSPConfig, arm: ArmDescription) -> DSPConfig:
    """``config`` with what it leaves to the arm filled in from ``arm``'s description, and checked against it (the
    top speeds within the arm's client configuration ranges). Raises ValueError."""
    def own(value: Optional[float], default: float) -> float:
        return default if value is None else value

    resolved = msgspec.structs.replace(
        config, max_linear_speed_mps=own(config.max_linear_speed_mps, arm.max_linear_speed_mps),
        max_angular_speed_rps=own(config.max_angular_speed_rps, arm.max_angular_speed_rps),
        linear_accel_mps2=own(config.linear_accel_mps2, arm.linear_accel_mps2),
        angular_accel_rps2=own(config.angular_accel_rps2, arm.angular_accel_rps2),
        joint_accel_dps2=own(config.joint_accel_dps2, arm.joint_accel_dps2))
    check_speeds(arm, resolved.max_linear_speed_mps, resolved.max_angular_speed_rps, ValueError,
                 ("dsp.max_linear_speed_mps", "dsp.max_angular_speed_rps"))
    return resolved


def check_speeds(arm: ArmDescription, linear_mps: Optional[float], angular_rps: Optional[float],
                 error: type[Exception], names: tuple[str, str] = ("max translation velocity",
                                                                   "max orientation velocity")) -> None:
    """Top speeds a client sets must be within the arm's client configuration ranges (SetCartesianMaxVelocities, a
    DSP's config: ``names`` says what they are called there)."""
    if linear_mps is not None and not arm.linear_speed_range_mps[0] <= linear_mps <= arm.linear_speed_range_mps[1]:
        raise error(f"{names[0]} must be within the {arm.name}'s range {arm.linear_speed_range_mps} m/s")
    if angular_rps is not None and not arm.angular_speed_range_rps[0] <= angular_rps <= arm.angular_speed_range_rps[1]:
        raise error(f"{names[1]} must be within the {arm.name}'s range {arm.angular_speed_range_rps} rad/s")


def motion_limits(config: DSPConfig, arm: ArmDescription, linear_speed_mps: float | None = None,
                  angular_speed_rps: float | None = None) -> MotionLimits:
    """The limits ``arm`` with this DSP configuration applies (the Cartesian speeds as set at run time, when they
    were: SetCartesianMaxVelocities)."""
    config = for_arm(config, arm)
    return arm_limits(arm, config.max_linear_speed_mps if linear_speed_mps is None else linear_speed_mps,
                      config.max_angular_speed_rps if angular_speed_rps is None else angular_speed_rps,
                      config.joint_speed_scale, config.linear_accel_mps2, config.angular_accel_rps2,
                      config.joint_accel_dps2)


class CommandRefused(ValueError):
    """A command the DSP will not execute (the reason is the message)."""


# ------------------------------------------------------------------------------------------ segments


@dataclass
class _CartesianVelocity:
    #: (linear m/s base, angular in ``convention``)
    twist: np.ndarray
    convention: AngularConvention
    source: Optional[Header] = None


@dataclass
class _JointVelocity:
    dq: np.ndarray
    source: Optional[Header] = None


@dataclass
class _AngularPosition:
    q: np.ndarray
    max_speed: Optional[np.ndarray] = None


@dataclass
class _CartesianPosition:
    R: np.ndarray
    p: np.ndarray
    max_linear: Optional[float] = None
    max_angular: Optional[float] = None


_VELOCITY = (_CartesianVelocity, _JointVelocity)


@dataclass
class DSPStatus:
    mode: ControlMode = ControlMode.IDLE
    watchdog_tripped: bool = False
    #: limits that shaped this cycle's motion: zone:<name>, joint_limit, singularity, speed, acceleration
    active_limits: list[str] = field(default_factory=list)
    applied: Optional[Header] = None
    cycles: int = 0
    #: the last command was an emergency stop (cleared by the next motion command)
    emergency_stop: bool = False


class KinovaDSP:
    def __init__(self, config: DSPConfig, kinematics: ArmKinematics) -> None:
        """``config`` as given (what it leaves to the arm is filled in from ``kinematics.arm``'s description)."""
        self.kin = kinematics
        self.arm = kinematics.arm
        self.config = for_arm(config, self.arm)
        self.fifo: collections.deque = collections.deque()
        self.zones: list[Zone] = list(self.config.zones)
        self.max_linear = self.config.max_linear_speed_mps
        self.max_angular = self.config.max_angular_speed_rps
        self._motion_limits: Optional[tuple[tuple[float, float], MotionLimits]] = None
        self.status = DSPStatus()
        self._direct: Optional[object] = None
        self._last_velocity: Optional[object] = None
        self._missed = 0
        self._dq_prev = np.zeros(self.arm.n_joints)
        self._twist_prev = np.zeros(6)
        self._lower, self._upper = self.arm.model_limits()
        margin = math.radians(self.config.joint_limit_margin_deg)
        self._lower_soft, self._upper_soft = self._lower + margin, self._upper - margin
        self._limited = np.isfinite(self._lower)
        lower = np.where(self._limited, self._lower, -1.0)
        upper = np.where(self._limited, self._upper, 1.0)
        self._mid, self._half_range = (lower + upper) / 2.0, (upper - lower) / 2.0
        self._joint_max_speed = self.arm.max_speed * self.config.joint_speed_scale
        self._joint_accel = math.radians(self.config.joint_accel_dps2)
        self._moving_mode = ControlMode.IDLE
        #: emergency braking in progress: [scale, joint velocities at the trigger, scale rate (1/s)]
        self._braking: Optional[list] = None
        #: velocity commands on their way (command_delay_cycles): (the cycle they take effect in, segment)
        self._delayed: collections.deque = collections.deque()

    # ------------------------------------------------------------------------------ commands (mfvs path)
    def submit(self, command: RobotCommand) -> None:
        """Apply an mfvs robot command in the next cycle. Raises :class:`CommandRefused` (the arm then behaves
        as if no command had come: it keeps the last one for the watchdog's grace and then stops)."""
        if command.mode is CommandMode.EMERGENCY_STOP:
            self._begin_emergency_stop()
            return
        if command.mode is CommandMode.STOP:
            self._direct = None
            self._delayed.clear()
            self._last_velocity = None
            self._missed = self.config.watchdog_cycles  # stop now, without the watchdog's grace
            self.fifo.clear()
            return
        if command.mode is CommandMode.CARTESIAN_VELOCITY:
            twist = command.twist
            if twist.frame is not Frame.MIXED:
                raise CommandRefused(f"Cartesian velocity must be in the mixed frame, got frame '{twist.frame.value}'")
            if twist.angular is not self.config.angular_convention:
                raise CommandRefused(
                    f"this arm reads angular velocity as '{self.config.angular_convention.value}', the command "
                    f"declares '{twist.angular.value}'"
                )
            segment = _CartesianVelocity(np.array([*twist.linear, *twist.rotational]), twist.angular, command.header)
        else:
            if len(command.joint_velocities) != self.arm.n_joints:
                raise CommandRefused(f"this arm has {self.arm.n_joints} joints, the command "
                                     f"{len(command.joint_velocities)} joint velocities")
            segment = _JointVelocity(np.asarray(command.joint_velocities, dtype=float), command.header)
        if self.config.command_delay_cycles:
            self._delayed.append((self.status.cycles + 1 + self.config.command_delay_cycles, segment))
            return
        self._take(segment)

    def _take(self, segment) -> None:
        """A velocity command takes effect (in the coming cycle): it erases the FIFO and ends any braking."""
        self.fifo.clear()
        self._direct = segment
        self._braking = None

    def _begin_emergency_stop(self) -> None:
        self._direct = None
        self._delayed.clear()
        self._last_velocity = None
        self._missed = self.config.watchdog_cycles
        self.fifo.clear()
        if self._braking is None and np.any(self._dq_prev):
            self._braking = [1.0, self._dq_prev.copy(), None]  # scale, joint velocities at the trigger, rate
        self.status.emergency_stop = True

    # ------------------------------------------------------------------------------ commands (Kinova API)
    def send_basic_trajectory(self, point: kinova.TrajectoryPoint) -> kinova.ErrorCode:
        if len(self.fifo) >= kinova.TRAJECTORY_FIFO_SIZE:
            return kinova.ErrorCode.ERROR_INVALID_PARAM
        position = point.Position
        kind = position.Type
        limits = point.Limitations if point.LimitationsActive else None
        if kind == kinova.POSITION_TYPE.CARTESIAN_VELOCITY:
            c = position.CartesianPosition
            segment = _CartesianVelocity(np.array([c.X, c.Y, c.Z, c.ThetaX, c.ThetaY, c.ThetaZ]),
                                         self.config.angular_convention)
        elif kind == kinova.POSITION_TYPE.ANGULAR_VELOCITY:
            segment = _JointVelocity(self.arm.physical_rate_to_model(position.Actuators.as_list()[:self.arm.n_joints]))
        elif kind == kinova.POSITION_TYPE.ANGULAR_POSITION:
            q = self.arm.physical_deg_to_model(position.Actuators.as_list()[:self.arm.n_joints])
            if np.any(q < self._lower) or np.any(q > self._upper):
                return kinova.ErrorCode.ERROR_INVALID_PARAM
            speed = None
            if limits is not None and limits.speedParameter1 > 0 and limits.speedParameter2 > 0:
                # speedParameter1: actuators 1-3, speedParameter2: the others (kinova.md)
                speed = np.radians([limits.speedParameter1] * 3 + [limits.speedParameter2] * (self.arm.n_joints - 3))
            segment = _AngularPosition(q, speed)
        elif kind == kinova.POSITION_TYPE.CARTESIAN_POSITION:
            c = position.CartesianPosition
            segment = _CartesianPosition(
                frames.euler_xyz_to_matrix((c.ThetaX, c.ThetaY, c.ThetaZ)), np.array([c.X, c.Y, c.Z]),
                limits.speedParameter1 if limits is not None and limits.speedParameter1 > 0 else None,
                limits.speedParameter2 if limits is not None and limits.speedParameter2 > 0 else None,
            )
        else:
            return kinova.ErrorCode.ERROR_INVALID_PARAM
        self._direct = None
        self.fifo.append(segment)
        return kinova.ErrorCode.NO_ERROR_KINOVA

    def joints_held(self) -> None:
        """The main board held the joints where they are (its DSP was late, or an exchange failed): they are at
        rest, so the next cycle starts from rest. Without this the DSP would go on from the velocity it last
        planned, and the arm, stopped, would jump back to it (a stall in the middle of a deceleration re-started
        the arm at 26 mm/s on a slow host) instead of ramping within the acceleration limits."""
        self._dq_prev = np.zeros(self.arm.n_joints)
        self._twist_prev = np.zeros(6)
        self._braking = None  # nothing left to brake

    def move_home(self) -> None:
        self.erase_all_trajectories()
        self.fifo.append(_AngularPosition(self.arm.home.copy()))

    def erase_all_trajectories(self) -> None:
        self.fifo.clear()
        self._direct = None
        self._delayed.clear()
        self._last_velocity = None
        self._missed = self.config.watchdog_cycles

    def set_max_velocities(self, linear_mps: float | None = None, angular_rps: float | None = None) -> None:
        check_speeds(self.arm, linear_mps, angular_rps, CommandRefused)
        if linear_mps is not None:
            self.max_linear = min(linear_mps, self.config.max_linear_speed_mps)
        if angular_rps is not None:
            self.max_angular = min(angular_rps, self.config.max_angular_speed_rps)

    @property
    def fifo_count(self) -> int:
        return len(self.fifo)

    # ------------------------------------------------------------------------------ the 100 Hz cycle
    def cycle(self, joints) -> np.ndarray:
        """One DSP cycle on the measured joints (``joints.q``, ``joints.dq``: a
        :class:`~services.robot.hardware.JointReading`): returns joint velocity references (model rad/s) for the
        next cycle_s."""
        cfg = self.config
        dt = cfg.cycle_s
        q = np.asarray(joints.q, dtype=float)
        self._last_q = q
        R, p, J = self.kin.pose_and_jacobian(q)
        self.status.cycles += 1
        self.status.active_limits = []
        segment = self._next_segment(q, R, p)
        if segment is not None:
            self.status.emergency_stop = False

        if self._braking is not None and segment is None:
            dq = self._emergency_brake(J, dt)
        elif isinstance(segment, _CartesianVelocity):
            self.status.applied = segment.source
            twist_base = frames.base_twist_from_mixed(segment.twist, R, segment.convention)
            twist_base = self._dead_band(twist_base, twist_base)
            dq = self._cartesian(q, p, J, twist_base, dt, self.max_linear, self.max_angular)
            self._moving_mode = ControlMode.CARTESIAN_VELOCITY
        elif isinstance(segment, _JointVelocity):
            self.status.applied = segment.source
            dq = self._joint(q, self._dead_band(segment.dq, J @ segment.dq), dt, self._joint_max_speed)
            self._moving_mode = ControlMode.ANGULAR_VELOCITY
        elif isinstance(segment, _AngularPosition):
            speed = self._joint_max_speed if segment.max_speed is None else np.minimum(segment.max_speed,
                                                                                      self._joint_max_speed)
            error = segment.q - q
            desired = np.sign(error) * np.minimum(speed, np.minimum(
                cfg.position_gain * np.abs(error), np.sqrt(2.0 * self._joint_accel * np.abs(error))))
            dq = self._joint(q, desired, dt, speed)
            self._moving_mode = ControlMode.ANGULAR_POSITION
            if np.max(np.abs(error)) < math.radians(0.05) and np.max(np.abs(joints.dq)) < math.radians(0.5):
                self.fifo.popleft()
        elif isinstance(segment, _CartesianPosition):
            max_lin = self.max_linear if segment.max_linear is None else min(segment.max_linear, self.max_linear)
            max_ang = self.max_angular if segment.max_angular is None else min(segment.max_angular, self.max_angular)
            e_p = segment.p - p
            e_r = frames.rotation_log(segment.R @ R.T)
            twist_base = np.concatenate([
                self._profile(e_p, max_lin, cfg.linear_accel_mps2), self._profile(e_r, max_ang, cfg.angular_accel_rps2)
            ])
            dq = self._cartesian(q, p, J, twist_base, dt, max_lin, max_ang)
            self._moving_mode = ControlMode.CARTESIAN_POSITION
            if np.linalg.norm(e_p) < 5e-4 and np.linalg.norm(e_r) < math.radians(0.2):
                self.fifo.popleft()
        else:
            dq = self._stop(q, p, J, dt)

        self._dq_prev = dq
        self._twist_prev = J @ dq
        self.status.mode = self._moving_mode if np.any(dq != 0.0) or self.fifo else ControlMode.IDLE
        return dq

    def motion_limits(self) -> MotionLimits:
        """The limits this DSP applies now (what the robot node declares in its states, 100 times a second: made
        again only when the Cartesian speeds change, the rest being the DSP's configuration and the arm's)."""
        speeds = (self.max_linear, self.max_angular)
        if self._motion_limits is None or self._motion_limits[0] != speeds:
            self._motion_limits = (speeds, motion_limits(self.config, self.arm, *speeds))
        return self._motion_limits[1]

    def _dead_band(self, command: np.ndarray, twist_base: np.ndarray) -> np.ndarray:
        """``command`` (a twist or joint velocities) scaled by the dead-band of the end-effector motion it asks."""
        factor = dead_band(twist_base, self.config.dead_band)
        if factor < 1.0 and np.any(command):
            self._flag("dead_band")
            return command * factor
        return command

    def _next_segment(self, q, R, p):
        """This cycle's segment; runs the watchdog for velocity commands."""
        cfg = self.config
        while self._delayed and self._delayed[0][0] <= self.status.cycles:
            self._take(self._delayed.popleft()[1])
        if self._direct is not None:
            segment, self._direct = self._direct, None
            self._last_velocity, self._missed = segment, 0
            self.status.watchdog_tripped = False
            return segment
        if self.fifo:
            head = self.fifo[0]
            if isinstance(head, _VELOCITY):
                self.fifo.popleft()
                self._last_velocity, self._missed = head, 0
                self.status.watchdog_tripped = False
                return head
            self._last_velocity = None
            self.status.watchdog_tripped = False
            return head
        # no command this cycle: keep the last velocity through the grace cycles, then stop
        self._missed += 1
        if self._last_velocity is not None and self._missed < cfg.watchdog_cycles:
            return self._last_velocity
        if self._last_velocity is not None:
            self.status.watchdog_tripped = True
        self._last_velocity = None
        return None

    # ------------------------------------------------------------------------------ motion resolution
    @staticmethod
    def _profile(error: np.ndarray, max_speed: float, accel: float, gain: float = 3.0) -> np.ndarray:
        """Velocity toward a target: proportional near it, at most what can still stop, at most max_speed."""
        distance = float(np.linalg.norm(error))
        if distance < 1e-12:
            return np.zeros(3)
        speed = min(max_speed, gain * distance, math.sqrt(2.0 * accel * distance))
        return error / distance * speed

    def _limit_twist(self, twist: np.ndarray, dt: float, max_lin: float, max_ang: float) -> np.ndarray:
        """The speed and acceleration limits, each by one factor on the whole twist: Kinova documents a limit per
        part (translation and orientation speeds) but not how a twist over one of them is brought within it, so
        the emulated arm keeps the direction it was asked for."""
        cfg = self.config
        out, ratio = saturation.limit_twist(np.asarray(twist, dtype=float), max_lin, max_ang)
        if ratio.over > 1.0:
            self._flag("speed")
        out, cut = saturation.limit_twist_change(self._twist_prev, out, cfg.linear_accel_mps2 * dt,
                                                 cfg.angular_accel_rps2 * dt)
        if cut:
            self._flag("acceleration")
        return np.array(out, dtype=float, copy=True)

    def _cartesian(self, q, p, J, twist_base, dt, max_lin, max_ang) -> np.ndarray:
        cfg = self.config
        twist = self._limit_twist(twist_base, dt, max_lin, max_ang)
        twist[:3], zones = filter_velocity(self.zones, p, twist[:3], cfg.zone_filter, dt)
        for name in zones:
            self._flag(f"zone:{name}")
        # resolved on J with its rows in one unit (services.model.kinematics.normalized_jacobian): the same joint
        # motion as J⁺ wherever the arm is not near a singularity, and a measure of how near it is
        length = self.kin.characteristic_length_m
        Jn = normalized_jacobian(J, length)
        twist_n = twist.copy()
        twist_n[:3] /= length
        U, s, Vt = np.linalg.svd(Jn)
        measure = s[-1]
        damping2 = 0.0
        if measure < cfg.damp_singularity_below:
            damping2 = (1.0 - (measure / cfg.damp_singularity_below) ** 2) * cfg.max_damping**2
            self._flag("singularity")
        dq = Jn.T @ np.linalg.solve(Jn @ Jn.T + damping2 * np.eye(6), twist_n)
        # self-motion away from joint limits and singularities, in proportion to how fast the end effector moves:
        # a fine approach stays fine (the joints never cancel each other's self-motion exactly, so self-motion
        # faster than the task itself shakes the end effector), and the arm at rest does not drift
        moving = min(1.0, np.linalg.norm(twist[:3]) / max_lin + np.linalg.norm(twist[3:]) / max_ang)
        if moving > 0.0 and len(q) > 6:
            s_inv = np.where(s > 1e-6, 1.0 / np.maximum(s, 1e-12), 0.0)
            Jn_pinv = Vt.T[:, :6] @ np.diag(s_inv) @ U.T
            null = np.eye(len(q)) - Jn_pinv @ Jn
            dq += moving * (null @ self._secondary_task(q, measure))
        return self._joint(q, dq, dt, self._joint_max_speed, uniform=True)

    def _secondary_task(self, q, measure: float) -> np.ndarray:
        """Joint rates the null space takes from: toward the middle of the joints' ranges, and, near a singularity,
        up the gradient of the singularity measure's logarithm (a barrier: the nearer, the harder it pushes),
        scaled by how near."""
        cfg = self.config
        xi = np.zeros(len(q))
        limited = self._limited
        xi[limited] = -cfg.joint_limit_gain * (q[limited] - self._mid[limited]) / self._half_range[limited]
        nearness = self._singularity_nearness(measure)
        if nearness > 0.0 and cfg.singularity_avoidance_gain > 0.0:
            length = self.kin.characteristic_length_m
            h = 1e-6
            grad_log = np.array([math.log(max(singularity_measure(self.kin.jacobian_base(q + h * e), length), 1e-12)
                                          / max(measure, 1e-12)) / h for e in np.eye(len(q))])
            xi += cfg.singularity_avoidance_gain * nearness * grad_log
            self._flag("singularity_avoidance")
        return xi

    def _singularity_nearness(self, measure: float) -> float:
        """0 at or above ``avoid_singularity_below``, rising linearly to 1 at ``damp_singularity_below`` and below."""
        cfg = self.config
        if measure >= cfg.avoid_singularity_below:
            return 0.0
        span = cfg.avoid_singularity_below - cfg.damp_singularity_below
        return 1.0 if span <= 0.0 else min(1.0, (cfg.avoid_singularity_below - measure) / span)

    def _joint(self, q, dq_desired, dt, max_speed, uniform: bool = False) -> np.ndarray:
        """Joint speed (uniform scaling keeps a Cartesian direction), joint acceleration, joint limits."""
        dq = np.array(dq_desired, dtype=float, copy=True)
        limited, ratio = saturation.limit_uniformly(dq, max_speed)
        if ratio > 1.0:
            dq = limited if uniform else np.clip(dq, -max_speed, max_speed)
            self._flag("speed")
        dq, cut = saturation.limit_change_uniformly(self._dq_prev, dq, self._joint_accel * dt)
        if cut:
            self._flag("acceleration")
        return self._joint_limits(q, dq, dt)

    def _joint_limits(self, q, dq, dt) -> np.ndarray:
        """Cap the speed toward each limit so the joint can stop at the soft limit with the joint deceleration."""
        limited = self._limited
        room_up = np.maximum(self._upper_soft - q, 0.0)
        room_down = np.maximum(q - self._lower_soft, 0.0)
        cap_up = np.minimum(np.sqrt(2.0 * self._joint_accel * room_up), room_up / dt)
        cap_down = np.minimum(np.sqrt(2.0 * self._joint_accel * room_down), room_down / dt)
        capped = dq.copy()
        capped[limited] = np.clip(dq[limited], -cap_down[limited], cap_up[limited])
        if np.any(capped != dq):
            self._flag("joint_limit")
        return capped

    def _emergency_brake(self, J, dt) -> np.ndarray:
        """Scale the joint velocities at the trigger down linearly: the end effector keeps its path and stops in
        the shortest time the emergency decelerations (linear, angular, joint) allow."""
        cfg = self.config
        scale, dq0, rate = self._braking
        if rate is None:
            twist0 = J @ dq0
            times = [np.linalg.norm(twist0[:3]) / cfg.emergency_linear_decel_mps2,
                     np.linalg.norm(twist0[3:]) / cfg.emergency_angular_decel_rps2,
                     float(np.max(np.abs(dq0))) / math.radians(cfg.emergency_joint_decel_dps2)]
            rate = 1.0 / max(max(times), dt)
            self._braking[2] = rate
        scale = max(0.0, scale - rate * dt)
        self._braking[0] = scale
        self._flag("emergency_stop")
        if scale == 0.0:
            self._braking = None
        return self._joint_limits(self._last_q, scale * dq0, dt)

    def _stop(self, q, p, J, dt) -> np.ndarray:
        """Decelerate to rest within the acceleration limits of the mode the arm was moving in."""
        if not np.any(self._dq_prev):
            return np.zeros(self.arm.n_joints)
        if self._moving_mode in (ControlMode.CARTESIAN_VELOCITY, ControlMode.CARTESIAN_POSITION):
            dq = self._cartesian(q, p, J, np.zeros(6), dt, self.max_linear, self.max_angular)
        else:
            dq = self._joint(q, np.zeros(self.arm.n_joints), dt, self._joint_max_speed)
        if np.max(np.abs(dq)) < 1e-4:
            dq = np.zeros(self.arm.n_joints)
        return dq

    def _flag(self, name: str) -> None:
        if name not in self.status.active_limits:
            self.status.active_limits.append(name)
