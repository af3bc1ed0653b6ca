"""The robot's one hardware interface, in the shape of ros2_control's: what the robot node needs from an arm's
joints, whatever drives them (the simulated arm in robot_sim's process, or actuators on an RS-485 bus).

One call per bus cycle, :meth:`RobotHardware.exchange`, writes that cycle's targets and reads the joints back, as
the actuators' 0x14 command and its 0x15-0x17 replies do on the real bus. The readings are what the bus carries
(physical degrees as float32), converted to model units by :func:`reading_from_physical`, so that the simulated
arm in-process and the same arm behind the bus give the node identical numbers.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Protocol

import numpy as np

from services.model.arm import ArmDescription

#: the actuators' bus cycle (500 Hz)
CYCLE_S = 0.002
CYCLE_NS = 2_000_000
#: the DSP (the arm's 100 Hz high-level loop) runs every this many bus cycles (10 ms)
CYCLES_PER_DSP = 5
DSP_CYCLE_NS = CYCLE_NS * CYCLES_PER_DSP
#: cycles an actuator goes on along its last target's rate when no target comes, before it holds (robot_sim's
#: firmware emulates one, as servo drives commonly do; the real actuators' behaviour is not public)
EXTRAPOLATED_CYCLES = 1


class HardwareError(RuntimeError):
    """An exchange that did not deliver a complete reading (bus timeout, NACK, a failed bus): the node holds the
    arm at its last measured angles."""


@dataclass
class JointReading:
    """The joints at one bus cycle, model units (rad, rad/s, N·m; current in A, temperature in °C)."""

    q: np.ndarray
    dq: np.ndarray
    tau: np.ndarray
    #: (None: zeros, one per joint)
    current_a: Optional[np.ndarray] = None
    temperature_c: Optional[np.ndarray] = None
    #: per actuator: 0 position mode, 1 torque mode
    mode: Optional[np.ndarray] = None
    #: per actuator: the latched fault (protocol.rs485.ActuatorError), 0 for none
    fault: Optional[np.ndarray] = None
    #: when the reading was taken: on the emulated arm's own timeline (robot_sim), or on the host's clock when
    #: the bus gives no better (a real arm); 0 when unknown
    stamp_ns: int = 0
    #: the end effector's pose (4×4, base frame) as the arm itself reports it (Kinova's DSP through the SDK, the
    #: simulator's physics), when it does: an RS-485 bus carries joints only
    arm_pose: Optional[np.ndarray] = None

    def __post_init__(self) -> None:
        n = len(self.q)
        for name in ("current_a", "temperature_c"):
            if getattr(self, name) is None:
                setattr(self, name, np.zeros(n))
        for name in ("mode", "fault"):
            if getattr(self, name) is None:
                setattr(self, name, np.zeros(n, dtype=int))

    def faults(self) -> list[str]:
        return [f"actuator {i + 1}: fault {int(code)}" for i, code in enumerate(self.fault) if code]


@dataclass
class JointTargets:
    """One bus cycle's command, model units: position targets; in torque mode ``torques`` (model sign, N·m, on
    top of whatever gravity the actuators add themselves: none on an RS-485 bus, where the host's gravity is in
    ``torques``; see :attr:`RobotHardware.actuators_compensate_gravity`) with ``q`` the actuators' safety reference
    (where the joints are)."""

    q: np.ndarray
    torques: Optional[np.ndarray] = None


def physical_targets(targets: JointTargets, arm: ArmDescription) -> tuple[np.ndarray, np.ndarray]:
    """(position deg, torque N·m) in the actuators' own (physical) units and signs, as 0x14 carries them."""
    torques = np.zeros(arm.n_joints) if targets.torques is None else arm.sign * np.asarray(targets.torques)
    return arm.model_to_physical_deg(targets.q), torques


@dataclass
class ActuatorValues:
    """What the arm's actuators report for one cycle (the 0x15-0x17 replies), in their own units and signs:
    physical degrees and deg/s, N·m, A, °C, and per actuator the mode (0 position, 1 torque) and the fault code.
    The emulated firmware produces them (float64), the bus link decodes them (float32 on the wire)."""

    position_deg: np.ndarray
    velocity_dps: np.ndarray
    torque_nm: np.ndarray
    current_a: np.ndarray
    temperature_c: np.ndarray
    mode: np.ndarray
    fault: np.ndarray
    #: the cycle's time on the arm's timeline (an emulated arm), or when the replies came (a real one)
    stamp_ns: int = 0


def reading_from_physical(values: ActuatorValues, arm: ArmDescription) -> JointReading:
    """A reading in model units from the actuators' own values: the one conversion both the bus link and the
    in-process simulated arm use."""
    return JointReading(q=arm.physical_deg_to_model(values.position_deg),
                        dq=arm.physical_rate_to_model(values.velocity_dps),
                        tau=arm.sign * np.asarray(values.torque_nm, dtype=float),
                        current_a=arm.sign * np.asarray(values.current_a, dtype=float),
                        temperature_c=np.asarray(values.temperature_c, dtype=float),
                        mode=np.asarray(values.mode, dtype=int), fault=np.asarray(values.fault, dtype=int),
                        stamp_ns=int(values.stamp_ns))


class RobotHardware(Protocol):
    """An arm's joints, one bus cycle at a time."""

    #: True when the arm is simulated in this process and steps only when exchanged with: the node may then run
    #: cycles it was late for back to back (the arm's time is the node's). A remote arm keeps its own time: a late
    #: cycle is skipped and counted, never sent as a burst of targets (which the arm would follow faster).
    simulated_in_process: bool
    #: True when the readings are stamped on the arm's own timeline, whose 10 ms grid is the arm's DSP cycle (the
    #: emulated actuators', whose camera is triggered on it): the robot node then runs its DSP when a reading's
    #: stamp crosses that grid, in phase with the camera. False (a real arm: receive times): every fifth cycle.
    arm_timeline: bool
    #: True when the actuators add the arm's gravity themselves in torque mode (Kinova's DSP does, through the SDK;
    #: the simulator's actuators in robot_sim's process stand for it), which :meth:`set_gravity_compensation` may
    #: switch off. False on an RS-485 bus: the base's DSP is bypassed and a single actuator cannot compute the
    #: arm's gravity (kinova.md; abr/abr_jaco2 sends host-computed gravity torques), so the host sends its model's
    #: gravity with every torque (services.robot.lowlevel)
    actuators_compensate_gravity: bool

    def exchange(self, targets: JointTargets) -> JointReading:
        """Send this cycle's targets, return the joints' state (raises :class:`HardwareError`)."""

    def enter_torque_mode(self, expected_torques: np.ndarray) -> None:
        """The torque-mode handshake: ``expected_torques`` (model sign) are what the host's model expects the
        joints to measure now (gravity); raises :class:`HardwareError` when the actuators refuse."""

    def leave_torque_mode(self) -> None:
        """Back to position mode, holding where the joints are (raises :class:`HardwareError`)."""

    def zero_torque_sensor(self, joint: int) -> None:
        """SetTorqueZero: the joint's torque sensor reads 0 where it stands (raises :class:`HardwareError` where the
        hardware cannot)."""

    def set_gravity_compensation(self, on: bool) -> bool:
        """The actuators' own gravity compensation in torque mode on or off (Table 5.1's gravity setup), where
        :attr:`actuators_compensate_gravity`; False where the hardware has no way to switch it (the host then takes
        its model's gravity back out of what it sends)."""

    def close(self) -> None: ...
