"""The arm's torque-mode setup: the Kinova API functions of the JACO thesis's Table 5.1 and what each does to the joints
in torque mode. A pure core: the robot node holds one :class:`TorqueSetup`, the Kinova API changes it
(:func:`configure`), low-level control applies it (:func:`over_safety_speed`, :func:`damping_torque`,
:func:`arm_compensates_gravity`).

What each function does, as JACO thesis (Table 5.1, L2257-2293) describes it and as mfvs emulates it:

* ``SetTorqueSafetyFactor(f)``: "If the velocity of an actuator gets to a specific threshold the robot stops and
  changes back to trajectory control ... Setting to 1 disables the feature." Neither the thesis nor Kinova gives
  the threshold: mfvs's is each joint's maximum speed (the arm description's) divided by 1 − f, so f = 0 trips at
  the joint's rated speed, f = 0.5 at twice it, f = 1 never. Kinova's default is not public either: mfvs starts
  at 0.5 (its choice: a torque client that never sets it is stopped well before the actuators' no-load speed on
  the wrist, 122 °/s, and kinova-ros, like the thesis, sets 1 first).
* ``SetTorqueActuatorDamping(d[70])``: "Set actuators damping gain": a torque −d·q̇ at each joint in torque mode
  (N·m per rad/s: Kinova gives no unit). Kinova's default is not public: mfvs starts at
  :data:`DEFAULT_ACTUATOR_DAMPING` (its choice, so the thesis's 0 changes something; the thesis still felt "some
  degree of damping" after it, which the emulated joints' own viscous friction, the description's ``damping``,
  keeps).
* ``SetGravityType`` / ``SetGravityOptimalZParam(p[42])``: the arm's own gravity compensation in torque mode. The
  thesis chose OPTIMAL with every parameter 0, which "granted the elimination of the gravity compensation imbued
  in the robot": so does the emulation. Any other set: the arm compensates with its own model (what the 16 or 19
  optimal-Z parameters mean is not public, so mfvs cannot evaluate a given set; MANUAL_INPUT's parameters come
  from a function Table 5.1 does not use).
* ``SetTorqueActuatorGain(g[70])`` and ``SetTorqueVibrationController(s)``: accepted, validated and kept, with no
  emulated effect: the thesis knows of the gain only that 0 "apparently" omitted "some control branches present in
  the DSP", and of the vibration controller that it acts "during contact with stiffness environments"; the
  emulated arm has neither branch nor contact to act on.
* ``SetTorqueZero(address)``: that actuator's torque sensor reads 0 where it stands (robot_sim: the emulated
  sensor's bias taken out; right only where gravity puts no torque on the joint, the thesis's calibration pose).
* ``SetJointZero(address)``: re-references an actuator's absolute position sensor. The emulated actuators' sensors
  never slip, and which angle the call assigns is not public, so the emulation refuses it (the SDK backend passes it
  to the arm).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from protocol import kinova
from services.model.arm import ArmDescription

#: SetTorqueSafetyFactor's value until a client sets it (mfvs's choice; see the module's docstring)
DEFAULT_SAFETY_FACTOR = 0.5
#: SetTorqueActuatorDamping's value until a client sets it, N·m per rad/s (mfvs's choice)
DEFAULT_ACTUATOR_DAMPING = 0.2
#: the most damping a joint may be given, N·m per rad/s: half of what a 2 ms loop damps stably on the lightest
#: joint the arms have (about 0.04 kg·m² at the wrist: 2·0.04/0.002 = 40)
MAX_ACTUATOR_DAMPING = 20.0


def table_5_1() -> list[tuple[str, object]]:
    """The JACO thesis's Table 5.1 (L2257-2293), the setup the thesis made before torque control, as Kinova API calls in
    its order: safety factor 1 (disabled), vibration controller 1, actuator damping 0, gravity type OPTIMAL with
    every optimal-Z parameter 0 (the arm adds no gravity), actuator gain 0. The thesis prints "0" for the arrays;
    every element 0 is the reading (seed003_facts §5). Its calibration (SetTorqueZero in the pose where gravity
    loads no joint, SetJointZero after sudden stops) is not here: it needs that pose, and acts on the sensors."""
    zeros = [0.0] * kinova.TORQUE_COMMAND_SIZE
    return [("SetTorqueSafetyFactor", kinova.FloatArgument(value=1.0)),
            ("SetTorqueVibrationController", kinova.FloatArgument(value=1.0)),
            ("SetTorqueActuatorDamping", kinova.CommandArray(values=zeros)),
            ("SetGravityType", kinova.GravityTypeArgument(type=kinova.GRAVITY_TYPE.OPTIMAL)),
            ("SetGravityOptimalZParam", kinova.GravityParameters(values=[0.0] * kinova.GRAVITY_PARAM_SIZE)),
            ("SetTorqueActuatorGain", kinova.CommandArray(values=zeros))]


#: the functions :func:`configure` applies (the rest of Table 5.1, SetTorqueZero and SetJointZero, act on hardware)
TORQUE_SETUP_SETTERS = frozenset({"SetTorqueSafetyFactor", "SetTorqueVibrationController", "SetTorqueActuatorGain",
                                  "SetTorqueActuatorDamping", "SetGravityType", "SetGravityOptimalZParam"})


@dataclass
class TorqueSetup:
    """The torque-mode setup of one arm (what Table 5.1's functions set)."""

    arm: ArmDescription
    safety_factor: float = DEFAULT_SAFETY_FACTOR
    vibration_controller: float = 1.0
    actuator_gain: np.ndarray = field(default=None)
    actuator_damping: np.ndarray = field(default=None)
    gravity_type: kinova.GRAVITY_TYPE = kinova.GRAVITY_TYPE.OPTIMAL
    #: the optimal-Z parameters a client set (None: the arm's own estimate)
    optimal_z: Optional[np.ndarray] = None

    def __post_init__(self) -> None:
        n = self.arm.n_joints
        if self.actuator_gain is None:
            self.actuator_gain = np.ones(n)
        if self.actuator_damping is None:
            self.actuator_damping = np.full(n, DEFAULT_ACTUATOR_DAMPING)

    def describe(self) -> str:
        """One line for the robot's health."""
        threshold = "off" if self.safety_factor >= 1.0 else f"{self.safety_factor:g}"
        return (f"torque setup: safety factor {threshold}, damping {np.round(self.actuator_damping, 3).tolist()}, "
                f"gravity {'arm' if arm_compensates_gravity(self) else 'none'}")


def safety_speed_threshold(setup: TorqueSetup) -> np.ndarray:
    """The joint speed (rad/s) above which the safety factor returns the arm to trajectory control: the joint's
    maximum speed over 1 − f (infinite at f = 1)."""
    if setup.safety_factor >= 1.0:
        return np.full(setup.arm.n_joints, math.inf)
    return setup.arm.max_speed / (1.0 - setup.safety_factor)


def over_safety_speed(setup: TorqueSetup, dq) -> list[int]:
    """The joints (0-based) moving faster than the safety factor allows."""
    return [int(i) for i in np.flatnonzero(np.abs(np.asarray(dq, dtype=float)) > safety_speed_threshold(setup))]


def damping_torque(setup: TorqueSetup, dq) -> np.ndarray:
    """The actuators' damping in torque mode (model sign, N·m)."""
    return -setup.actuator_damping * np.asarray(dq, dtype=float)


def arm_compensates_gravity(setup: TorqueSetup) -> bool:
    """Whether the arm adds its own gravity compensation in torque mode: not after the thesis's OPTIMAL with
    every optimal-Z parameter 0."""
    return not (setup.gravity_type is kinova.GRAVITY_TYPE.OPTIMAL and setup.optimal_z is not None
                and not np.any(setup.optimal_z))


def _per_actuator(setup: TorqueSetup, values, name: str, upper: float) -> tuple[Optional[np.ndarray], str]:
    mine = np.asarray(values[: setup.arm.n_joints], dtype=float)
    if not np.all(np.isfinite(mine)) or np.any(mine < 0.0) or np.any(mine > upper):
        return None, f"{name}: each of the first {setup.arm.n_joints} values within 0..{upper:g}"
    return mine, ""


def configure(setup: TorqueSetup, function: str, argument) -> str:
    """Apply one of Table 5.1's setters (not the zeroing functions, which act on the hardware). Returns why the
    call is refused ('' when applied); a refused call changes nothing."""
    if function in ("SetTorqueSafetyFactor", "SetTorqueVibrationController"):
        value = float(argument.value)
        if not (math.isfinite(value) and 0.0 <= value <= 1.0):
            return f"{function}: a value within 0..1 (got {value})"
        if function == "SetTorqueSafetyFactor":
            setup.safety_factor = value
        else:
            setup.vibration_controller = value
        return ""
    if function in ("SetTorqueActuatorGain", "SetTorqueActuatorDamping"):
        damping = function == "SetTorqueActuatorDamping"
        values, problem = _per_actuator(setup, argument.values, function,
                                        MAX_ACTUATOR_DAMPING if damping else 1e6)
        if values is None:
            return problem
        if damping:
            setup.actuator_damping = values
        else:
            setup.actuator_gain = values
        return ""
    if function == "SetGravityType":
        setup.gravity_type = kinova.GRAVITY_TYPE(argument.type)
        return ""
    if function == "SetGravityOptimalZParam":
        values = np.asarray(argument.values, dtype=float)
        if not np.all(np.isfinite(values)):
            return f"{function}: finite values"
        setup.optimal_z = values
        return ""
    return f"{function} is not a torque-setup setter"


def joint_of_address(arm: ArmDescription, address: int) -> Optional[int]:
    """The joint (0-based) whose actuator has this RS-485 address on ``arm``."""
    try:
        return list(arm.bus_addresses).index(int(address))
    except ValueError:
        return None
