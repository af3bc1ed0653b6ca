"""The simulated arm as the robot node's hardware, in this process: each exchange is one bus cycle of
:class:`~services.robot_sim.sim.Simulation` (the actuators take the targets at the boundary, report their values,
physics runs to the next boundary).

Targets and readings pass through float32, as the RS-485 frames carry them, so the same arm gives the node the same
numbers whether it sits in this process or behind the bus (robot_sim's actuator-bus mode and robot_gateway).
"""
from __future__ import annotations

from typing import Callable, Optional

import numpy as np

from protocol import rs485 as r
from services.model.arm import ArmDescription
from services.robot.hardware import (DEFAULT_TIMING, ActuatorValues, FingerReading, HardwareError, JointReading,
                                     JointTargets, physical_targets, reading_from_physical)
from services.robot_sim.sim import Simulation
from services.runtime.arrays import constant


def float32(values) -> np.ndarray:
    """What a float32 field of an RS-485 frame makes of these numbers (an array, or a sequence of them: one
    conversion for all)."""
    return np.array(values, dtype=np.float32).astype(np.float64)


def reading_from_values(values: ActuatorValues, arm: ArmDescription, epoch_ns: int = 0) -> JointReading:
    """The reading the 0x15-0x17 replies of this cycle carry (float32 values, the 0x16 temperature in 0.01 °C)."""
    position_deg, velocity_dps, torque_nm, current_a = float32(
        (values.position_deg, values.velocity_dps, values.torque_nm, values.current_a))
    return reading_from_physical(ActuatorValues(
        position_deg=position_deg, velocity_dps=velocity_dps, torque_nm=torque_nm, current_a=current_a,
        temperature_c=np.rint(values.temperature_c / _CENTI) * _CENTI, mode=values.mode, fault=values.fault,
        stamp_ns=epoch_ns + values.stamp_ns), arm)


_CENTI = constant(0.01)


class SimulatedHardware:
    simulated_in_process = True
    #: the exchanges are the arm's cycles one for one: every fifth is on its grid
    arm_timeline = False
    #: the simulated actuators' own cycle
    timing = DEFAULT_TIMING

    def __init__(self, sim: Simulation, epoch_ns: int = 0,
                 on_boundary: Optional[Callable[[ActuatorValues], None]] = None) -> None:
        self.sim = sim
        #: stamps are ``epoch_ns`` plus the arm's time (wall-like in realtime, from 1 s in lockstep)
        self.epoch_ns = epoch_ns
        #: called at each cycle boundary, before physics moves on (robot_sim snapshots camera frames there)
        self.on_boundary = on_boundary

    def read(self) -> JointReading:
        """The joints now, without a cycle (at start)."""
        reading = reading_from_values(self.sim.firmware.values(self.sim.time_ns), self.sim.arm, self.epoch_ns)
        reading.arm_pose = self.sim.ee_pose()
        reading.fingers = self._fingers()
        return reading

    def _fingers(self) -> Optional[FingerReading]:
        """The fingers' values now, through float32 as a bus frame carries them (None: no hand)."""
        fingers = self.sim.fingers
        if fingers is None:
            return None
        values = fingers.reading()
        position, velocity, current = float32((values.position, values.velocity, values.current_a))
        return FingerReading(position=position, velocity=velocity, current_a=current)

    def exchange(self, targets: JointTargets) -> JointReading:
        position_deg, torque_nm = float32(physical_targets(targets, self.sim.arm))  # as a 0x14 carries them
        firmware = self.sim.firmware
        firmware.command_all(position_deg, torque_nm)
        if targets.fingers is not None and self.sim.fingers is not None:
            self.sim.fingers.command(float32(targets.fingers))
        values = self.sim.begin_cycle()
        fingers = self._fingers()
        # the physical arm's own report, whatever its description says (MuJoCo's last kinematics: a physics step,
        # 1 ms, behind a moving arm, as a real arm's report lags its joints)
        arm_pose = self.sim.ee_pose()
        firmware.reports.clear()  # the faults are in the values; a bus would carry them as REPORT_ERROR too
        if self.on_boundary is not None:
            self.on_boundary(values)
        self.sim.end_cycle()
        reading = reading_from_values(values, self.sim.arm, self.epoch_ns)
        reading.arm_pose = arm_pose
        reading.fingers = fingers
        return reading

    def enter_torque_mode(self, expected_torques: np.ndarray) -> None:
        firmware = self.sim.firmware
        n = self.sim.arm.n_joints
        expected = float32(self.sim.arm.sign * np.asarray(expected_torques, dtype=float))
        invalid = [i for i in range(n) if not firmware.validate_torque(i, float(expected[i]))]
        if invalid:
            raise HardwareError(f"torque validation failed for actuators {[i + 1 for i in invalid]}")
        refused = [i for i in range(n)
                   if firmware.switch_mode(i, r.ControlModeRequest.TORQUE) is not r.ControlModeReply.TORQUE_OK]
        if refused:
            raise HardwareError(f"torque mode refused by actuators {[i + 1 for i in refused]}")

    def leave_torque_mode(self) -> None:
        for i in range(self.sim.arm.n_joints):
            self.sim.firmware.switch_mode(i, r.ControlModeRequest.POSITION)

    def zero_torque_sensor(self, joint: int) -> None:
        """SetTorqueZero: the actuator's torque sensor reads 0 where it stands."""
        self.sim.firmware.zero_torque(joint)

    @property
    def actuators_compensate_gravity(self) -> bool:
        """The simulator's actuators in this process stand for Kinova's DSP driving the arm: they add its gravity
        unless their config says they have no compensation (``actuators.gravity_compensation``)."""
        return self.sim.firmware.gravity_compensation_available

    def set_gravity_compensation(self, on: bool) -> bool:
        self.sim.firmware.set_gravity_compensation(on)
        return True

    def close(self) -> None:
        pass
