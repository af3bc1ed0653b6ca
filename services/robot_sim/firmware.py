"""The JACO-2 actuators' own firmware, emulated on the MuJoCo joints: what each actuator does with the
commands its bus brings, one bus cycle (2 ms) at a time, on the simulated arm's timeline.

Nothing here knows about buses, threads or wall time: :class:`~services.robot_sim.bus_device.ActuatorBusDevice`
turns RS-485 frames into these calls, and the in-process hardware of robot_sim makes the same calls directly, so
both drive the arm through exactly the same arithmetic.

Per actuator:

* Position mode (interpolated): a target received during a cycle is taken at the next cycle boundary (if several
  arrived, the newest wins; the others are counted as ``superseded``), and the reference moves from where it is to
  that target across the host's period (its bus cycle: one 2 ms cycle, or 2.5-5 ms when the host runs slower,
  :meth:`ActuatorFirmware.set_host_period`), arriving at its end, as the host planned it. A servo critically damped at
  ``SERVO_BANDWIDTH_RPS`` for the joint's current inertia follows the reference, with the reference's rate and its
  change of rate as feed-forward (inertia, friction, gravity). A cycle without a target (``missed``) goes on along
  the reference's rate for that one cycle (where the host's next target would have taken it: a frame that is only
  late then continues the motion without a jump), and after it the reference holds. A late host therefore shows
  up as missed cycles and lost motion (a cycle's pause, when its target comes a cycle late), never as a faster
  joint.
* Torque mode: the target's position is the host's idea of where the joint is (more than
  ``reference_tolerance_deg`` off latches a RELATIVE_POSITION fault), its torque is clamped to the actuator's
  limit (a TORQUE report once), gravity compensation is added (the real DSP's option; never on the RS-485 bus,
  :meth:`ActuatorFirmware.bypass_dsp`), and after
  ``torque_timeout_s`` (250 ms) without a torque command the actuator falls back to holding its position.
* Switching to torque mode needs a torque validation of the last ``validation_lifetime_s``: the host's expected
  torque must match the measured one.
* Faults (joint limits, torque, reference mismatch, a bad command) latch, are reported once, and make the
  actuator hold its position until CLEAR_FAULT_FLAG.
* In both modes the motors give at most their data sheet's peak torque and, in the direction they turn, what the
  torque-speed line allows; the joints' Coulomb friction acts in torque mode only; the torque sensors read a bias
  and noise of the data sheet's (docs/robot.md, "The actuators as their data sheets give them").

Where the emulation departs from the real actuators (whose firmware is not public): the 0x17 layout, the
interpolation across the host's period and the one cycle of extrapolation on a missed target are mfvs's choices (what
servo drives commonly do); the torque timeout and the gravity compensation follow kinova.md.
"""
from __future__ import annotations

import math
from typing import Optional

import msgspec
import mujoco
import numpy as np

from protocol import rs485 as r
from services.model.arm import ArmDescription
from services.robot.hardware import CYCLE_S, EXTRAPOLATED_CYCLES, ActuatorValues
from services.runtime.arrays import clip as _clip, constant as _constant
from services.runtime.config import ConfigStruct
from services.runtime.metrics import Counters


class ActuatorConfig(ConfigStruct):
    #: the actuators' bus addresses, joint by joint; null: the arm description's
    addresses: Optional[list[int]] = None
    torque_timeout_s: float = 0.25
    #: torque mode adds the arm's gravity, as Kinova's DSP does (robot_sim's api mode, where the node stands for the
    #: DSP); over the RS-485 bus (actuator_bus mode) the DSP is bypassed and it is off whatever this says
    gravity_compensation: bool = True
    reference_tolerance_deg: float = 10.0
    #: torque validation: the host's expected torque must match the measured one within this (N·m or fraction)
    validation_tolerance_nm: float = 2.0
    validation_tolerance_fraction: float = 0.2
    validation_lifetime_s: float = 1.0
    #: joints (1-7) whose actuator turns the other way from the arm description, about the home angle (where the
    #: two agree): an emulated arm that disagrees with its description, as the JACO-2's joint 1 may with a
    #: kinova-ros-like one (`mfvs check arm --simulate --mirror-joint N`); empty for an arm that agrees
    mirrored_joints: list[int] = msgspec.field(default_factory=list)

    def __post_init__(self) -> None:
        if not 0 < self.torque_timeout_s:
            raise ValueError("torque_timeout_s must be positive")


def actuator_addresses(config: ActuatorConfig, arm: ArmDescription) -> list[int]:
    """The actuators' bus addresses: the config's, else the arm description's."""
    return list(arm.bus_addresses) if config.addresses is None else list(config.addresses)


def check_actuators(config: ActuatorConfig, arm: ArmDescription) -> None:
    """The actuators' config against the arm: one distinct address per joint, mirrored joints that exist."""
    addresses = actuator_addresses(config, arm)
    if len(addresses) != arm.n_joints or len(set(addresses)) != arm.n_joints:
        raise ValueError(f"actuators.addresses must be {arm.n_joints} distinct bus addresses (the {arm.name}'s "
                         f"joints), not {[hex(a) for a in addresses]}")
    if any(not 1 <= j <= arm.n_joints for j in config.mirrored_joints):
        raise ValueError(f"actuators.mirrored_joints are joint numbers 1..{arm.n_joints}")


# the modes and errors as plain ints, for the arrays (an IntEnum's members are slow to look up in a hot path)
POSITION, TORQUE = int(r.ControlModeRequest.POSITION), int(r.ControlModeRequest.TORQUE)
#: a value that crossed the bus as float32 may exceed its float64 original by this factor (2^-24 relative)
FLOAT32_MARGIN = 1.0 + 2.0 ** -23
NO_FAULT = int(r.ActuatorError.NONE)
#: a steady temperature: an emulation constant for the reported temperature (nothing in the simulation heats up)
ACTUATOR_TEMPERATURE_C = 35.0
#: how long a target's reference moves past its segment (which spans the host's period: :meth:`ActuatorFirmware.
#: set_host_period`): on along its rate for the extrapolated cycles
GOES_ON_PAST_SEGMENT_S = EXTRAPOLATED_CYCLES * CYCLE_S
#: bounds of the reference's rate and acceleration (well beyond the arm's 48 deg/s and the DSP's 200 deg/s², so
#: they only cut glitches)
MAX_REFERENCE_RATE_DPS = 120.0
MAX_REFERENCE_ACCEL_DPS2 = 2000.0
#: a host silent this long has stopped (or not started) sending: its silence is not counted as missed cycles
HOST_GONE_S = 0.25
#: position-mode servo of each actuator: critically damped at this natural frequency for the inertia the joint
#: currently drives, so that the shoulder follows its targets as promptly as the wrist (a fixed PD would leave
#: the heavy joints ~30 ms behind the light ones, and a Cartesian motion that needs both would come out
#: distorted)
SERVO_BANDWIDTH_RPS = 150.0
# the servo law's gains and apply's other constants as operands (_constant)
_BANDWIDTH_SQUARED, _TWICE_BANDWIDTH = _constant(SERVO_BANDWIDTH_RPS**2), _constant(2.0 * SERVO_BANDWIDTH_RPS)
_ZERO, _ONE = _constant(0.0), _constant(1.0)
_CYCLE = _constant(CYCLE_S)
_RATE_BOUNDS = _constant(-MAX_REFERENCE_RATE_DPS), _constant(MAX_REFERENCE_RATE_DPS)
_ACCEL_BOUNDS = _constant(-MAX_REFERENCE_ACCEL_DPS2), _constant(MAX_REFERENCE_ACCEL_DPS2)


class ActuatorView:
    """One actuator's state as its firmware holds it (read-only: the firmware's arrays, element ``index``)."""

    def __init__(self, firmware: "ActuatorFirmware", index: int, address: int) -> None:
        self._firmware, self.index, self.address = firmware, index, address

    @property
    def mode(self) -> r.ControlModeRequest:
        return r.ControlModeRequest(int(self._firmware.mode[self.index]))

    @property
    def fault(self) -> r.ActuatorError:
        return r.ActuatorError(int(self._firmware.fault_code[self.index]))

    @property
    def pending(self) -> Optional[tuple[float, float]]:
        """The newest 0x14 of this cycle (position deg, torque N·m), not yet taken; None if none came."""
        f, i = self._firmware, self.index
        return (float(f.pending_deg[i]), float(f.pending_torque_nm[i])) if f.pending_count[i] else None

    def __getattr__(self, name: str):
        if name in ActuatorFirmware.PER_ACTUATOR:
            return float(getattr(self._firmware, name)[self.index])
        raise AttributeError(name)


class ActuatorFirmware:
    """The arm's actuators on a MuJoCo arm: bus commands go in between cycle boundaries (:meth:`command`,
    :meth:`validate_torque`, :meth:`switch_mode`, :meth:`clear_fault`); :meth:`begin_cycle` takes them at a
    boundary; :meth:`apply` sets the joint torques every physics step.

    Each actuator's state is an element of arrays, one array per quantity (:attr:`PER_ACTUATOR` and the modes,
    faults and pending commands), so that a boundary and a physics step are a few whole-array operations for the
    whole arm, not Python per actuator; :attr:`actuators` views them one actuator at a time."""

    #: the reference's segment across the cycle from ``target_time_s``: start position (deg), rate (deg/s) and the
    #: change of rate from the segment before (deg/s²); it ends at ``last_target_deg``, the last target taken, where
    #: the reference arrives and holds until the next. Then: when the host last sent a command, the torque
    #: commanded (torque mode), when it came, when the torque was last validated
    PER_ACTUATOR = ("target_deg", "target_rate_dps", "target_accel_dps2", "target_time_s", "last_target_deg",
                    "last_command_s", "torque_nm", "last_torque_s", "validated_s")

    def __init__(self, model: mujoco.MjModel, data: mujoco.MjData, arm: ArmDescription,
                 config: ActuatorConfig | None = None, counters: Counters | None = None) -> None:
        self.model, self.data = model, data
        self.arm = arm
        self.config = config or ActuatorConfig()
        check_actuators(self.config, arm)
        self.counters = counters or Counters()
        n = self.n = arm.n_joints
        self.torque_limit = model.actuator_ctrlrange[: self.n, 1].copy()
        #: the torque each actuator gives at most in torque mode, as its host configured it (0x208, the torque
        #: safety configuration: abr/abr_jaco2 sends the arm's maximum torques); at most ``torque_limit``
        self.configured_torque_limit = self.torque_limit.copy()
        specs = [j.spec for j in arm.joints]
        #: the motors' torque-speed line (the data sheets' stall torque falling to 0 at the no-load speed): the most
        #: torque each actuator gives in the direction it turns, besides its peak (software limitation)
        self._stall = np.array([a.stall_torque_nm for a in specs])
        self._no_load = np.array([a.no_load_speed for a in specs])
        #: output torque per motor current (the data sheets' torque gradient): the current each actuator reports
        self._torque_per_ampere = np.array([a.torque_gradient_nm_per_a for a in specs])
        #: the joints' Coulomb friction (the emulated arm's, arm.true_friction_nm; see :meth:`apply` for where)
        self._coulomb = arm.true_friction_nm.copy()
        #: whether torque mode can add the arm's gravity compensation at all (the DSP's, as the config says; never
        #: once driven over the bus, :meth:`bypass_dsp`), and whether it does now (Table 5.1's gravity setup
        #: switches it off)
        self.gravity_compensation_available = self.config.gravity_compensation
        self.compensating_gravity = self.gravity_compensation_available
        #: the torque sensors: noise of the data sheets' precision (±2σ), a bias within their temperature drift
        #: (fixed per arm and joint) that SetTorqueZero's offset (:meth:`zero_torque`) takes out where it is
        #: called; seeded, so a lockstep run repeats to the bit
        self._sensor_sigma = np.array([a.torque_sensor_precision_nm / 2.0 for a in specs])
        sensors = np.random.default_rng(list(arm.name.encode()))
        self._sensor_bias = sensors.uniform(-1.0, 1.0, self.n) * np.array([a.torque_sensor_drift_nm for a in specs])
        self._sensor_zero = np.zeros(self.n)
        self._sensor_noise = np.random.default_rng(0)
        self._temperature_c = np.full(n, ACTUATOR_TEMPERATURE_C)
        self.lower, self.upper = arm.model_limits()
        self.addresses = np.array(actuator_addresses(self.config, arm))
        self.set_host_period(CYCLE_S)
        # the state (class docstring)
        for name in self.PER_ACTUATOR:  # times (``_s``) start at never
            setattr(self, name, np.full(n, -math.inf if name.endswith("_s") else 0.0))
        self.mode = np.full(n, POSITION)
        self.fault_code = np.full(n, NO_FAULT)
        #: the newest 0x14 of the cycle (position deg, torque N·m), taken at the next boundary, and how many came
        self.pending_deg, self.pending_torque_nm = np.zeros(n), np.zeros(n)
        self.pending_count = np.zeros(n, dtype=int)
        #: a clamped torque is reported once (until the fault flag is cleared), not latched
        self.torque_reported = np.zeros(n, dtype=bool)
        self.actuators = [ActuatorView(self, i, int(address)) for i, address in enumerate(self.addresses)]
        self.by_address = {a.address: a for a in self.actuators}
        self._mass = np.zeros((model.nv, model.nv))
        # views of what apply reads and writes every physics step (MjData's arrays stay where they are: its
        # attributes make a new view at each access)
        self._joint_mass, self._inertia = self._mass[:n, :n], self._mass.diagonal()[:n]
        # (qfrc_bias: at rest the gravity torque; it also cancels Coriolis terms)
        self._q, self._dq, self._gravity = data.qpos[:n], data.qvel[:n], data.qfrc_bias[:n]
        self._ctrl = data.ctrl[:n]
        self._negative_torque_limit = -self.torque_limit
        self._friction = model.dof_damping[: self.n].copy()
        # the actuators' encoders and motors against the model's joints: model = _pivot_model + _deg_to_model·deg
        # (physical degrees, the bus's unit, to the model's radians, sign included); a mirrored joint turns the other
        # way about its home angle
        direction = np.array([-1.0 if i + 1 in self.config.mirrored_joints else 1.0 for i in range(self.n)])
        self._deg_to_model = arm.sign * direction * (math.pi / 180.0)
        self._zero_rate = self._deg_to_model * 0.0  # a reference at rest, as apply's product gives it (signed zeros)
        self._zero_friction = self._friction * self._zero_rate
        # below this speed (rad/s) the torque-speed line is above the peak torque, with a margin far beyond the
        # line's rounding (see apply); 0 where the stall torque is not above the peak (the line always computed)
        self._full_torque_below = np.where(self._stall > self.torque_limit,
                                           self._no_load * (1.0 - self.torque_limit / self._stall) * (1.0 - 1e-6), 0.0)
        self._pivot_model = arm.sign * np.radians(arm.home_deg * (1.0 - direction)) + arm.offset
        #: an actuator's torque (its sign) to the model's joint torque
        self._torque_sign = arm.sign * direction
        #: the current cycle boundary's time (s) on the arm's timeline
        self.now_s = 0.0
        #: reports raised at a boundary (joint limits) for the bus to carry: (address, error)
        self.reports: list[tuple[int, r.ActuatorError]] = []
        #: bumped by every change of an actuator's reference or mode (what apply derives from them follows it)
        self._version, self._segments_version, self._segment_arrays = 0, -1, ()
        self.hold_all()

    # ------------------------------------------------------------------ state in actuator units
    def model_from_physical_deg(self, position_deg) -> np.ndarray:
        """The model's joint angles (rad) at these actuator angles (physical degrees)."""
        return self._pivot_model + self._deg_to_model * np.asarray(position_deg, dtype=float)

    def physical_deg(self, q) -> np.ndarray:
        """What the actuators' encoders read (physical degrees) at these model angles."""
        return (np.asarray(q, dtype=float) - self._pivot_model) / self._deg_to_model

    def applied_torque_nm(self) -> np.ndarray:
        """What each motor gives now, in the actuators' own sign (N·m)."""
        return self._torque_sign * self.data.actuator_force[: self.n]

    def sensed_torque_nm(self, applied_nm: Optional[np.ndarray] = None) -> np.ndarray:
        """What each actuator's torque sensor reads: the applied torque (``applied_nm``, else now's), its bias less
        its zero, and its noise."""
        applied_nm = self.applied_torque_nm() if applied_nm is None else applied_nm
        # σ·z: the draws of Generator.normal(0, σ), which returns 0.0 + σ·z, at a quarter of its cost
        noise = self._sensor_sigma * self._sensor_noise.standard_normal(self.n)
        return applied_nm + self._sensor_bias - self._sensor_zero + noise

    def set_gravity_compensation(self, on: bool) -> None:
        """The arm's own gravity compensation in torque mode, on or off (Table 5.1's ``SetGravityType`` and
        ``SetGravityOptimalZParam``, as the robot's torque setup applies them)."""
        self.compensating_gravity = bool(on) and self.gravity_compensation_available

    def bypass_dsp(self) -> None:
        """The actuators driven over their RS-485 bus: the base's DSP, which computes the arm's gravity, is
        bypassed, and a single actuator cannot compute it, so torque mode adds no gravity compensation (kinova.md:
        "In RS-485 mode the base's DSP is bypassed: no gravity compensation"; abr/abr_jaco2's torque driver sends
        host-computed gravity torques). The host holds the arm up (services.robot.lowlevel)."""
        self.gravity_compensation_available = self.compensating_gravity = False

    def zero_torque(self, i: int) -> None:
        """SetTorqueZero: actuator ``i``'s torque sensor reads 0 now (its bias, and whatever load it carries, taken
        as zero: right only where gravity puts no torque on the joint, the JACO thesis's calibration pose)."""
        self._sensor_zero[i] = self.applied_torque_nm()[i] + self._sensor_bias[i]

    def values(self, stamp_ns: int) -> ActuatorValues:
        applied = self.applied_torque_nm()
        return ActuatorValues(
            position_deg=self.physical_deg(self._q), velocity_dps=self._dq / self._deg_to_model,
            torque_nm=self.sensed_torque_nm(applied), current_a=applied / self._torque_per_ampere,
            temperature_c=self._temperature_c.copy(), mode=self.mode.copy(),
            fault=self.fault_code.copy(), stamp_ns=stamp_ns)

    def commanded(self) -> tuple[np.ndarray, np.ndarray]:
        """The newest position target and torque each actuator received (what its 0x17 reports), taken or not."""
        pending = self.pending_count > 0
        return (np.where(pending, self.pending_deg, self.last_target_deg),
                np.where(pending, self.pending_torque_nm, self.torque_nm))

    def position_deg(self, i: int) -> float:
        return float((self.data.qpos[i] - self._pivot_model[i]) / self._deg_to_model[i])

    def hold_all(self) -> None:
        """Every actuator in position mode, holding where its joint is (at start and after a reset)."""
        self.fault_code[:] = NO_FAULT
        self.torque_reported[:] = False
        self.pending_count[:] = 0
        self.last_command_s[:] = -math.inf
        self._hold(slice(None))

    def _hold(self, which) -> None:
        """The actuators ``which`` (an index, a mask or a slice) in position mode, holding where they are."""
        self._version += 1
        self.mode[which] = POSITION
        self.target_deg[which] = self.last_target_deg[which] = self.physical_deg(self._q)[which]
        self.target_rate_dps[which] = self.target_accel_dps2[which] = 0.0
        self.target_time_s[which] = -math.inf
        self.torque_nm[which] = 0.0

    # ------------------------------------------------------------------ commands (between boundaries)
    def command(self, i: int, position_deg: float, torque_nm: float) -> None:
        """A 0x14 for actuator ``i``: taken at the next boundary (the newest of a cycle wins)."""
        self.pending_deg[i], self.pending_torque_nm[i] = position_deg, torque_nm
        self.pending_count[i] += 1

    def command_all(self, position_deg: np.ndarray, torque_nm: np.ndarray) -> None:
        """A 0x14 for every actuator, in joint order (the in-process host's batch)."""
        self.pending_deg[:], self.pending_torque_nm[:] = position_deg, torque_nm
        self.pending_count += 1

    def validate_torque(self, i: int, expected_nm: float) -> bool:
        cfg = self.config
        measured = float(self.sensed_torque_nm()[i])
        ok = math.isfinite(expected_nm) and abs(expected_nm - measured) <= max(
            cfg.validation_tolerance_nm, cfg.validation_tolerance_fraction * abs(measured))
        if ok:
            self.validated_s[i] = self.now_s
        return ok

    def switch_mode(self, i: int, wanted: int) -> r.ControlModeReply:
        self._version += 1
        if wanted == POSITION:
            self._hold(i)
            return r.ControlModeReply.POSITION_OK
        recent = self.now_s - self.validated_s[i] <= self.config.validation_lifetime_s
        if wanted == TORQUE and recent and self.fault_code[i] == NO_FAULT:
            self.mode[i] = TORQUE
            self.torque_nm[i] = 0.0
            self.last_torque_s[i] = self.now_s
            self.pending_count[i] = 0
            return r.ControlModeReply.TORQUE_OK
        self.counters.inc("mode_switch_refused")
        return r.ControlModeReply.REFUSED

    def configure_torque_limit(self, i: int, limit_nm: float) -> bool:
        """0x208: the most torque actuator ``i`` gives in torque mode (N·m); refused (False) unless positive, finite
        and within what the actuator can give."""
        if not (np.isfinite(limit_nm) and 0.0 < limit_nm <= self.torque_limit[i] * FLOAT32_MARGIN):
            self.counters.inc("torque_config_refused")
            return False
        self.configured_torque_limit[i] = min(limit_nm, self.torque_limit[i])
        return True

    def clear_fault(self, i: int) -> None:
        self._version += 1
        self.fault_code[i] = NO_FAULT
        self.torque_reported[i] = False

    def fault(self, i: int, error: r.ActuatorError) -> Optional[r.ActuatorError]:
        """Latch a fault (reported once: returns it when it is new)."""
        if self.fault_code[i] == NO_FAULT:
            self._latch(np.arange(self.n) == i, error)
            return error
        return None

    def _latch(self, new: np.ndarray, error: r.ActuatorError) -> None:
        """Latch ``error`` on the actuators of the mask ``new`` (none of which has a fault): they hold."""
        if not np.count_nonzero(new):
            return
        self.fault_code[new] = error
        self._hold(new)
        self.counters.inc(f"faults.{error.name.lower()}", int(np.count_nonzero(new)))

    # ------------------------------------------------------------------ the cycle boundary
    def begin_cycle(self, now_s: float) -> None:
        """Take the commands of the cycle that ended (the newest per actuator), time out torque mode, check the
        joint limits. Faults to report go to :attr:`reports`, actuator by actuator in order (a command's report
        before a joint limit's)."""
        self._version += 1
        self.now_s = now_s
        n = self.n
        # the joints outside their ranges now (nothing below moves them; an unlimited joint's range is infinite, a
        # NaN angle is outside none)
        outside = (self._q < self.lower) | (self._q > self.upper)
        count = self.pending_count
        came_count = int(np.count_nonzero(count))
        every_one_came = came_count == n
        superseded = int(np.add.reduce(count)) - came_count
        if superseded:
            self.counters.inc("frames.superseded", superseded)
        if every_one_came:
            came = None  # every one (made only where the slow path below needs it)
            self.last_command_s.fill(now_s)
        else:
            came = count > 0
            # a target was due (a host period since the last one) and the host has not gone away
            silent_s = now_s - self.last_command_s
            missed = int(np.count_nonzero(~came & (silent_s >= self.host_period_s - 1e-9) & (silent_s <= HOST_GONE_S)))
            if missed:
                self.counters.inc("frames.missed", missed)
            self.last_command_s[came] = now_s
        count.fill(0)
        torque_mode = self.mode == TORQUE
        if every_one_came and not np.count_nonzero(self.fault_code) and not np.count_nonzero(torque_mode):
            self._follow(slice(None))  # the host's batch, every actuator following it (the hot path)
            command_report = None
        else:
            came = np.ones(n, dtype=bool) if came is None else came
            taken = came & (self.fault_code == NO_FAULT)
            if np.count_nonzero(taken & ~torque_mode):
                self._follow(taken & ~torque_mode)
            command_report = self._take_torques(taken & torque_mode) if np.count_nonzero(taken & torque_mode) else None
            timed_out = (self.mode == TORQUE) & (now_s - self.last_torque_s > self.config.torque_timeout_s)
            if np.count_nonzero(timed_out):
                self._hold(timed_out)
                self.counters.inc("torque_timeouts", int(np.count_nonzero(timed_out)))
        past_limit = None
        if np.count_nonzero(outside):
            past_limit = outside & (self.fault_code == NO_FAULT)
            self._latch(past_limit, r.ActuatorError.POSITION_LIMIT)
        if command_report is not None or past_limit is not None:
            for i in range(n):
                if command_report is not None and command_report[i] != NO_FAULT:
                    self.reports.append((int(self.addresses[i]), r.ActuatorError(int(command_report[i]))))
                if past_limit is not None and past_limit[i]:
                    self.reports.append((int(self.addresses[i]), r.ActuatorError.POSITION_LIMIT))

    def _take_torques(self, taking: np.ndarray) -> np.ndarray:
        """Torque mode takes the commands of the actuators ``taking``: each a torque, checked against where the
        host thinks the joint is; what each reports (ActuatorError codes, NONE for nothing)."""
        report = np.full(self.n, NO_FAULT)
        position = self.physical_deg(self._q)
        off = taking & (np.abs(self.pending_deg - position) > self.config.reference_tolerance_deg)
        if np.count_nonzero(off):
            self._latch(off, r.ActuatorError.RELATIVE_POSITION)
            report[off] = r.ActuatorError.RELATIVE_POSITION
        accepted = taking & ~off
        asked = self.pending_torque_nm[accepted]
        limit = self.configured_torque_limit[accepted]
        torque = _clip(asked, -limit, limit)
        clamped = np.zeros(self.n, dtype=bool)
        clamped[accepted] = torque != asked
        first_clamp = clamped & ~self.torque_reported
        self.torque_reported |= first_clamp  # clamped: reported once, not latched
        report[first_clamp] = r.ActuatorError.TORQUE
        self.torque_nm[accepted] = torque
        self.last_torque_s[accepted] = self.now_s
        return report

    def set_host_period(self, period_s: float) -> None:
        """How often the host sends targets (its bus cycle: services.robot.hardware.BusTiming): each target's
        segment spans that long, so that a host at 5 ms moves the joints as smoothly as one at 2 ms. Our choice:
        how a real actuator moves between its host's targets is not public (a 2 ms host gives the segment of one
        cycle this emulation always had)."""
        self.host_period_s = period_s
        #: a host slower than the actuators' cycle: how long before this boundary its last batch arrived (its
        #: bus loop sets it; segments start there)
        self.host_lead_s = 0.0
        self._segment = _constant(period_s)  # (an operand at every boundary: _constant)
        #: how long the current segment spans: the host's period, and for a slower host what was left of the
        #: segment before when its target came (:meth:`_follow`)
        self.segment_s = period_s
        self._goes_on_s = period_s + GOES_ON_PAST_SEGMENT_S

    def reference(self, t_s: float, which=slice(None)) -> tuple[np.ndarray, np.ndarray]:
        """Where the references of the actuators ``which`` are at ``t_s`` (deg) and their rates (deg/s): along their
        segments (the host's period) and, without a new target, along the same rate for one more cycle; then they
        hold there."""
        position, _, along = self._reference(t_s - self.target_time_s[which], which)
        return position, np.where(along, self.target_rate_dps[which], 0.0)

    def _reference(self, ahead: np.ndarray, which) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`reference`'s position ``ahead`` of each segment's start, whether the segment started, whether the
        reference still moves along it."""
        started = ahead >= 0.0
        goes_on = self._goes_on_s
        along = started & (ahead < goes_on - 1e-9)
        position = np.where(started, self.target_deg[which] + self.target_rate_dps[which] * np.where(
            along, ahead, goes_on), self.last_target_deg[which])
        return position, started, along

    def _common_time(self) -> Optional[float]:
        """The one boundary every reference was taken at (the host sends every joint each cycle), or None."""
        taken_s = self.target_time_s
        first = float(taken_s[0])
        return None if np.count_nonzero(taken_s != first) else first

    def _follow(self, following) -> None:
        """New position targets at this boundary for the actuators ``following`` (a mask or a slice): a segment
        from where each reference is to its target, across the host's period: from this boundary, or for a host
        slower than the actuators' cycle from when its batch arrived (:attr:`host_lead_s`), as an actuator whose own
        loop is far faster than 2 ms would take it (taken on 2 ms boundaries, a 3.33 ms host's targets would come
        2 or 4 ms apart, and each segment would start early or late: 13 % over the commanded speed, measured).

        A slower host's target that comes before the segment before it ended (bunched behind a late one by the host
        or the link: two of its batches 2 ms apart) does not cut that segment short: the new segment carries what
        was left of it and spans the host's period past it (at most one period carried). Cut short, the joints
        would make more than one period's motion in one, up to twice the commanded speed (measured behind a host
        slowed to 0.8 of a core: the end effector 37 % over its limit, and safety's protective stop). Our choice,
        as the spreading is: the arm never moves faster than its host's targets, whenever they come."""
        start_s = self.now_s
        slower_host = self.host_period_s != CYCLE_S
        if slower_host:
            start_s -= min(max(self.host_lead_s, 0.0), CYCLE_S)
        common = self._common_time() if isinstance(following, slice) else None
        segment = self._segment
        if common is not None:  # (the host's batch each cycle) :meth:`_reference`'s choices made once for all
            ahead = start_s - common
            started = ahead >= 0.0
            goes_on = self._goes_on_s
            start = (self.target_deg + self.target_rate_dps * (ahead if ahead < goes_on - 1e-9 else goes_on)
                     if started else self.last_target_deg.copy())
            rate_before = self.target_rate_dps if started and ahead <= goes_on + 1e-9 else _ZERO
            if slower_host:
                carried = min(self.segment_s - ahead, self.host_period_s) if started else 0.0
                self.segment_s = self.host_period_s + (carried if carried > 1e-6 else 0.0)
                segment = self.segment_s
                self._goes_on_s = self.segment_s + GOES_ON_PAST_SEGMENT_S
        else:
            if slower_host:  # (a part of the arm commanded alone: no carry, every segment back to the period)
                self.segment_s, self._goes_on_s = self.host_period_s, self.host_period_s + GOES_ON_PAST_SEGMENT_S
            ahead = start_s - self.target_time_s[following]
            start, started, _ = self._reference(ahead, following)
            rate_before = np.where(started & (ahead <= self._goes_on_s + 1e-9), self.target_rate_dps[following], 0.0)
        # (rate_before: the rate the reference moved at up to now; at the end of its one cycle of going on, it still
        # moved)
        target = self.pending_deg[following]
        # a glitch, not a trajectory: the bounds only cut those
        rate = _clip((target - start) / segment, *_RATE_BOUNDS)
        accel = _clip((rate - rate_before) / _CYCLE, *_ACCEL_BOUNDS)  # (before the new rate replaces the old)
        self.target_deg[following], self.last_target_deg[following] = start, target
        self.target_rate_dps[following], self.target_accel_dps2[following] = rate, accel
        self.target_time_s[following] = start_s

    # ------------------------------------------------------------------ physics
    def _segments(self) -> tuple:
        """What follows for :meth:`apply` from the actuators' references and modes alone (derived again only after
        a change: apply runs every physics step, the references change at boundaries and on mode switches): which
        actuators are in torque mode, whether any is, the reference's rate and change of rate in the model's units,
        the one time every reference was taken at, if there is one, and the joints' viscous friction at that
        rate."""
        if self._segments_version != self._version:
            torque_mode = (self.mode == TORQUE) & (self.fault_code == NO_FAULT)
            rate_model = self._deg_to_model * self.target_rate_dps
            self._segment_arrays = (
                torque_mode, bool(np.count_nonzero(torque_mode)), rate_model,
                self._deg_to_model * self.target_accel_dps2,
                # every reference taken at one boundary (the host sends all joints each cycle): apply's choices
                # are then one per step, not one per joint
                self._common_time(), self._friction * rate_model)
            # the joints' Coulomb friction acts where an actuator is in torque mode (see apply); it changes only
            # with the modes
            self.model.dof_frictionloss[: self.n] = np.where(torque_mode, self._coulomb, 0.0)
            self._segments_version = self._version
        return self._segment_arrays

    def apply(self, t_s: float) -> None:
        """The actuators' torques for the physics step starting at ``t_s`` (the arm's timeline). Runs every physics
        step (1 kHz): a handful of whole-array operations, no per-joint Python."""
        q, dq, gravity = self._q, self._dq, self._gravity
        mujoco.mj_fullM(self.model, self.data, self._mass)
        torque_mode, any_torque, rate_model, accel_model, taken_together, friction_rate = self._segments()
        start_deg, rate_dps, last_deg = self.target_deg, self.target_rate_dps, self.last_target_deg
        goes_on = self._goes_on_s
        # follow the reference (:meth:`reference`, but for the last 1e-9 s of its cycle of going on), with the
        # inertia, friction and gravity its motion needs as feed-forward (the segment's change of rate during the
        # cycle it was taken in)
        if taken_together is not None:  # the same arithmetic, its choices made once for every joint
            ahead = t_s - taken_together
            started = ahead >= 0.0
            reference_deg = start_deg + rate_dps * min(max(ahead, 0.0), goes_on) if started else last_deg
            moving = started and ahead < goes_on - 1e-9
            rate, friction = (rate_model, friction_rate) if moving else (self._zero_rate, self._zero_friction)
            in_first_cycle = started and ahead < CYCLE_S - 1e-9
        else:
            ahead = t_s - self.target_time_s
            started = ahead >= 0.0
            reference_deg = np.where(started, start_deg + rate_dps * np.minimum(np.maximum(ahead, 0.0), goes_on),
                                     last_deg)
            rate = self._deg_to_model * np.where(started & (ahead < self._goes_on_s - 1e-9), rate_dps, 0.0)
            friction = self._friction * rate
            in_first_cycle = started & (ahead < CYCLE_S - 1e-9)
        tau = gravity + friction + self._inertia * (
            _BANDWIDTH_SQUARED * (self._pivot_model + self._deg_to_model * reference_deg - q)
            + _TWICE_BANDWIDTH * (rate - dq))
        # the joints' Coulomb friction acts where an actuator is in torque mode (set with the modes, _segments); in
        # position mode the actuator's own position loop, on the motor's encoder ahead of its 110-160:1 gear, rejects
        # it (the joint-level servo emulated here is far softer than that loop and would leave the friction as an
        # error it never has)
        if any_torque:
            commanded = self._torque_sign * self.torque_nm + (gravity if self.compensating_gravity else 0.0)
            tau = np.where(torque_mode, commanded, tau)
            in_first_cycle = np.logical_and(in_first_cycle, ~torque_mode)
        if isinstance(in_first_cycle, np.ndarray):
            if np.count_nonzero(in_first_cycle):
                tau += self._joint_mass @ np.where(in_first_cycle, accel_model, 0.0)
        elif in_first_cycle:
            tau += self._joint_mass @ accel_model
        # what the motors can give: the peak (software limitation), and, in the direction each turns, the torque-speed
        # line from the stall torque to zero at the no-load speed (which leaves the peak to a joint slower than
        # _full_torque_below: no line to compute while every joint is)
        speed = np.abs(dq)
        if np.count_nonzero(speed >= self._full_torque_below):
            along = np.minimum(self.torque_limit, np.maximum(self._stall * (_ONE - speed / self._no_load), _ZERO))
            upper = np.where(dq > _ZERO, along, self.torque_limit)
            lower = np.where(dq < _ZERO, -along, self._negative_torque_limit)
            ctrl = _clip(tau, lower, upper, out=self._ctrl)
        else:
            ctrl = _clip(tau, self._negative_torque_limit, self.torque_limit, out=self._ctrl)
        if np.count_nonzero(ctrl != tau):
            self.counters.inc("torque.limited_ms")  # a physics step (1 ms) in which some motor gave less than asked
