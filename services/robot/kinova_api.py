"""The Kinova high-level API (the functions of ``protocol.kinova.API_FUNCTIONS``) on top of the emulated DSP, for
any robot: robot_sim's simulated arm or robot_gateway's real one. A :class:`RobotView` gives the measured state."""
from __future__ import annotations

from typing import Callable, Optional, Protocol

import numpy as np

from protocol import kinova
from protocol.messages import FingerCommand, FingerMode
from services.model import frames
from services.robot.dsp import CommandRefused, KinovaDSP
from services.robot.torque_setup import TORQUE_SETUP_SETTERS, TorqueSetup, configure, joint_of_address
from services.model.zones import zone_from_kinova, zone_to_kinova


class RobotView(Protocol):
    """What the API reads of a robot (model units)."""

    @property
    def q(self) -> np.ndarray: ...

    @property
    def dq(self) -> np.ndarray: ...

    @property
    def tau(self) -> np.ndarray: ...

    @property
    def q_ref(self) -> np.ndarray: ...

    #: the actuators' currents (A, model sign)
    @property
    def current_a(self) -> np.ndarray: ...

    #: the fingers as measured, and the targets they hold (None: the robot reports no fingers)
    @property
    def fingers(self): ...

    @property
    def finger_targets(self) -> Optional[np.ndarray]: ...

    def ee_pose(self) -> np.ndarray: ...

    def command_fingers(self, command: FingerCommand) -> Optional[str]:
        """Take a finger command with the next DSP cycle; why not, if it cannot."""


class SensorZeroing(Protocol):
    """What SetTorqueZero needs of the joints (a hardware that cannot raises HardwareError saying why)."""

    def zero_torque_sensor(self, joint: int) -> None: ...


class KinovaApi:
    """The Kinova high-level API functions, on a robot (its measured state) and its DSP. Calls must run in the
    thread that runs the DSP (between cycles)."""

    def __init__(self, robot: "RobotView", dsp: KinovaDSP, torque_setup: Optional[TorqueSetup] = None,
                 sensors: Optional[SensorZeroing] = None) -> None:
        self.robot = robot
        self.dsp = dsp
        #: Table 5.1's torque-mode setup, shared with low-level control
        self.torque_setup = torque_setup if torque_setup is not None else TorqueSetup(dsp.arm)
        self.sensors = sensors
        self.arm = dsp.arm
        self.builtin_zones = list(dsp.zones)
        self.kinova_zones: list = []
        self.last_command = np.zeros(self.arm.n_joints)

    def call(self, function: str, argument) -> kinova.ApiReply:
        if function in TORQUE_SETUP_SETTERS:
            return self._configure(function, argument)
        handler: Callable = getattr(self, f"_{function}")
        return handler(argument)

    def _InitAPI(self, _):
        return kinova.ApiReply()

    _CloseAPI = _SetCartesianControl = _SetAngularControl = _InitAPI

    def _MoveHome(self, _):
        self.dsp.move_home()
        return kinova.ApiReply()

    def _SendBasicTrajectory(self, point: kinova.TrajectoryPoint):
        """The point to the DSP and its hand part to the fingers: HAND_NOMOVEMENT leaves them, POSITION_MODE sets
        their targets, VELOCITY_MODE their rates for a cycle, in every point type, as Kinova's arm does. So
        UserPosition::InitStruct()'s point (POSITION_MODE, fingers at 0) opens the hand here as on the real arm."""
        position = point.Position
        hand = None
        if position.HandMode not in (kinova.HAND_MODE.HAND_NOMOVEMENT, kinova.HAND_MODE.POSITION_MODE,
                                     kinova.HAND_MODE.VELOCITY_MODE):
            return kinova.ApiReply(code=int(kinova.ErrorCode.ERROR_INVALID_PARAM), message=(
                f"HandMode {position.HandMode.name} in a trajectory point: the fingers take HAND_NOMOVEMENT, "
                "POSITION_MODE or VELOCITY_MODE"))
        if position.HandMode is not kinova.HAND_MODE.HAND_NOMOVEMENT:
            hand = self.arm.hand
            if hand is None or self.robot.fingers is None:
                return kinova.ApiReply(code=int(kinova.ErrorCode.ERROR_INVALID_PARAM),
                                       message=f"HandMode {position.HandMode.name}, and this arm reports no fingers")
        if position.Type != kinova.POSITION_TYPE.NOMOVEMENT_POSITION:
            code = self.dsp.send_basic_trajectory(point)
            if code != kinova.ErrorCode.NO_ERROR_KINOVA:
                return kinova.ApiReply(code=int(code), message="point refused (FIFO full, target outside the joint "
                                                                "limits, or unsupported type)")
        elif hand is None:
            return kinova.ApiReply(code=int(kinova.ErrorCode.ERROR_INVALID_PARAM),
                                   message="a point of type NOMOVEMENT_POSITION with no hand part moves nothing")
        if hand is not None:
            values = hand.units_to_angle(position.Fingers.as_list()[:hand.n_fingers])
            mode = FingerMode.POSITION if position.HandMode is kinova.HAND_MODE.POSITION_MODE else FingerMode.VELOCITY
            problem = self.robot.command_fingers(FingerCommand(mode=mode, values=values.tolist()))
            if problem:
                return kinova.ApiReply(code=int(kinova.ErrorCode.ERROR_INVALID_PARAM), message=problem)
        return kinova.ApiReply()

    def _EraseAllTrajectories(self, _):
        self.dsp.erase_all_trajectories()
        return kinova.ApiReply()

    def _GetGlobalTrajectoryInfo(self, _):
        n = self.dsp.fifo_count
        return kinova.TrajectoryFIFOReply(result=kinova.TrajectoryFIFO(
            TrajectoryCount=n, UsedPercentage=100.0 * n / kinova.TRAJECTORY_FIFO_SIZE))

    def _angular(self, values_deg, fingers=None) -> kinova.AngularPositionReply:
        return kinova.AngularPositionReply(result=kinova.AngularPosition(
            Actuators=kinova.AngularInfo.from_list(values_deg), Fingers=self._fingers(fingers)))

    @staticmethod
    def _fingers(values) -> kinova.FingersPosition:
        return kinova.FingersPosition() if values is None else kinova.FingersPosition.from_list(values)

    def _finger_units(self, which: str):
        """The fingers' angles (``position``), rates (``velocity``) or targets (``target``) in Kinova's finger units
        (None: no fingers reported)."""
        fingers, hand = self.robot.fingers, self.arm.hand
        if fingers is None or hand is None:
            return None
        values = self.robot.finger_targets if which == "target" else getattr(fingers, which)
        return None if values is None else hand.angle_to_units(values)

    def _GetAngularPosition(self, _):
        return self._angular(self.arm.model_to_physical_deg(self.robot.q), self._finger_units("position"))

    def _GetAngularVelocity(self, _):
        return self._angular(self.arm.model_rate_to_physical(self.robot.dq), self._finger_units("velocity"))

    def _GetAngularForce(self, _):
        return self._angular(self.arm.sign * self.robot.tau)

    def _GetAngularCommand(self, _):
        return self._angular(self.arm.model_to_physical_deg(self.robot.q_ref), self._finger_units("target"))

    def _GetAngularCurrent(self, _):
        fingers = self.robot.fingers
        return self._angular(self.arm.sign * self.robot.current_a, None if fingers is None else fingers.current_a)

    def _cartesian(self, T, fingers=None) -> kinova.CartesianPositionReply:
        return kinova.CartesianPositionReply(result=kinova.CartesianPosition(Coordinates=kinova.CartesianInfo(
            **frames.kinova_pose(T[:3, :3], T[:3, 3])), Fingers=self._fingers(fingers)))

    def _GetCartesianPosition(self, _):
        return self._cartesian(self.robot.ee_pose(), self._finger_units("position"))

    def _GetCartesianCommand(self, _):
        return self._cartesian(self.arm.dh_forward_kinematics(self.robot.q_ref), self._finger_units("target"))

    def _SetProtectionZone(self, zones: kinova.ZoneList):
        try:
            boxes = [zone_from_kinova(z) for z in zones.Zones]
        except ValueError as exc:
            return kinova.ApiReply(code=int(kinova.ErrorCode.ERROR_INVALID_PARAM), message=str(exc))
        self.kinova_zones = boxes
        self.dsp.zones = self.builtin_zones + boxes
        return kinova.ApiReply()

    def _GetProtectionZone(self, _):
        zones = [zone_to_kinova(box, i + 1) for i, box in enumerate(self.kinova_zones)]
        return kinova.ZoneListReply(result=kinova.ZoneList(NbZones=len(zones), Zones=zones))

    def _EraseAllProtectionZones(self, _):
        self.kinova_zones = []
        self.dsp.zones = list(self.builtin_zones)
        return kinova.ApiReply()

    def _GetClientConfigurations(self, _):
        cfg = self.dsp.config
        return kinova.ClientConfigurationsReply(result=kinova.ClientConfigurations(
            MaxTranslationVelocity=self.dsp.max_linear, MaxOrientationVelocity=self.dsp.max_angular,
            MaxTranslationAcceleration=cfg.linear_accel_mps2, MaxOrientationAcceleration=cfg.angular_accel_rps2))

    def _SetClientConfigurations(self, conf: kinova.ClientConfigurations):
        try:
            self.dsp.set_max_velocities(conf.MaxTranslationVelocity, conf.MaxOrientationVelocity)
        except CommandRefused as exc:
            return kinova.ApiReply(code=int(kinova.ErrorCode.ERROR_INVALID_PARAM), message=str(exc))
        return kinova.ApiReply()

    # ------------------------------------------------------------------ the torque-mode setup (Table 5.1)
    def _configure(self, function: str, argument) -> kinova.ApiReply:
        problem = configure(self.torque_setup, function, argument)
        if problem:
            return kinova.ApiReply(code=int(kinova.ErrorCode.ERROR_INVALID_PARAM), message=problem)
        return kinova.ApiReply()

    def _SetTorqueZero(self, argument: kinova.ActuatorAddress):
        joint = joint_of_address(self.arm, argument.address)
        if joint is None:
            return kinova.ApiReply(code=int(kinova.ErrorCode.ERROR_INVALID_PARAM), message=(
                f"no actuator at address {argument.address} on the {self.arm.name} (its actuators: "
                f"{', '.join(str(a) for a in self.arm.bus_addresses)})"))
        if self.sensors is None or not hasattr(self.sensors, "zero_torque_sensor"):
            return kinova.ApiReply(code=int(kinova.ErrorCode.ERROR_INVALID_PARAM),
                                   message="this robot's joints cannot zero their torque sensors")
        try:
            self.sensors.zero_torque_sensor(joint)
        except Exception as exc:  # HardwareError: the hardware says why
            return kinova.ApiReply(code=int(kinova.ErrorCode.ERROR_INVALID_PARAM), message=str(exc))
        return kinova.ApiReply()

    def _SetJointZero(self, argument: kinova.ActuatorAddress):
        return kinova.ApiReply(code=int(kinova.ErrorCode.ERROR_INVALID_PARAM), message=(
            "SetJointZero re-references an actuator's absolute position sensor: the emulated sensors never slip, "
            "and which angle the call assigns is not public, so the emulation does not run it "
            "(services/robot/torque_setup.py)"))
