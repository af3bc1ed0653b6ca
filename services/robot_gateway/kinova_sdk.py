"""robot_gateway's ``kinova_sdk`` backend: the arm through Kinova's USB command layer
(``Kinova.API.USBCommandLayerUbuntu.so``) loaded with ctypes. The arm's own DSP interprets the commands, so the
gateway forwards rather than emulates:

* robot commands → ``SendBasicTrajectory`` every DSP cycle (10 ms, latest command wins, like the ROS driver):
  a mixed twist as a CARTESIAN_VELOCITY point (m/s, rad/s in the convention the arm is configured with; another
  convention is refused, as robot_sim's DSP does), joint velocities as an ANGULAR_VELOCITY point (deg/s, physical
  signs); stop and emergency stop erase the trajectories and send a zero-velocity point;
* state ← ``GetAngularPosition`` / ``GetAngularVelocity`` / ``GetAngularForce`` / ``GetCartesianPosition``;
* the ``robot/api/*`` queryables ← the SDK functions of the same name that the backend knows the signature of.

The structs mirror KinovaTypes.h (all fields 4 bytes, no padding); getters take a pointer, SendBasicTrajectory
takes the TrajectoryPoint by value. There is no low-level torque API through the USB layer.
"""
from __future__ import annotations

import ctypes
import time
from typing import Optional

import msgspec
import numpy as np

from protocol import kinova
from protocol.conventions import AngularConvention
from protocol.messages import CommandMode, ControlMode, MotionLimits, RobotCommand
from services.model import frames, jaco2
from services.robot.dsp import CommandRefused, DSPConfig, DSPStatus, motion_limits
from services.robot.hardware import JointReading

KINOVA_SDK_LIBRARY = "Kinova.API.USBCommandLayerUbuntu.so"


class SdkError(RuntimeError):
    def __init__(self, function: str, code: int) -> None:
        try:
            name = kinova.ErrorCode(code).name
        except ValueError:
            name = "unknown code"
        super().__init__(f"Kinova SDK {function} returned {code} ({name})")
        self.function, self.code = function, code


def _floats(*names: str) -> list:
    return [(name, ctypes.c_float) for name in names]


class CartesianInfo(ctypes.Structure):
    _fields_ = _floats("X", "Y", "Z", "ThetaX", "ThetaY", "ThetaZ")


class AngularInfo(ctypes.Structure):
    _fields_ = _floats(*(f"Actuator{i}" for i in range(1, kinova.MAX_ACTUATORS + 1)))


class FingersPosition(ctypes.Structure):
    _fields_ = _floats("Finger1", "Finger2", "Finger3")


class AngularPosition(ctypes.Structure):
    _fields_ = [("Actuators", AngularInfo), ("Fingers", FingersPosition)]


class CartesianPosition(ctypes.Structure):
    _fields_ = [("Coordinates", CartesianInfo), ("Fingers", FingersPosition)]


class UserPosition(ctypes.Structure):
    _fields_ = [("Type", ctypes.c_int), ("Delay", ctypes.c_float), ("CartesianPosition", CartesianInfo),
                ("Actuators", AngularInfo), ("HandMode", ctypes.c_int), ("Fingers", FingersPosition)]


class Limitation(ctypes.Structure):
    _fields_ = _floats(*(f"{kind}Parameter{i}" for kind in ("speed", "force", "acceleration") for i in (1, 2, 3)))


class TrajectoryPoint(ctypes.Structure):
    _fields_ = [("Position", UserPosition), ("LimitationsActive", ctypes.c_int), ("SynchroType", ctypes.c_int),
                ("Limitations", Limitation)]


class TrajectoryFIFO(ctypes.Structure):
    _fields_ = [("TrajectoryCount", ctypes.c_uint), ("UsedPercentage", ctypes.c_float), ("MaxSize", ctypes.c_uint)]


def to_c(message, c_type):
    """A protocol.kinova message as its ctypes struct (field names are the SDK's on both sides)."""
    out = c_type()
    for name, field_type in c_type._fields_:
        value = getattr(message, name)
        if isinstance(field_type, type) and issubclass(field_type, ctypes.Structure):
            value = to_c(value, field_type)
        setattr(out, name, int(value) if field_type in (ctypes.c_int, ctypes.c_uint) else value)
    return out


def from_c(struct, message_type):
    """A ctypes struct as the protocol.kinova message of the same shape (validated like any decoded message)."""
    def plain(value):
        if isinstance(value, ctypes.Structure):
            return {name: plain(getattr(value, name)) for name, _ in value._fields_}
        return value
    return msgspec.convert(plain(struct), message_type, strict=False)


#: getter → (the ctypes struct it fills through a pointer, the protocol.kinova type of the value); replies are
#: the types of kinova.API_FUNCTIONS, as with the emulated API
_GETTERS = {
    "GetAngularPosition": (AngularPosition, kinova.AngularPosition),
    "GetAngularVelocity": (AngularPosition, kinova.AngularPosition),
    "GetAngularForce": (AngularPosition, kinova.AngularPosition),
    "GetAngularCommand": (AngularPosition, kinova.AngularPosition),
    "GetCartesianPosition": (CartesianPosition, kinova.CartesianPosition),
    "GetCartesianCommand": (CartesianPosition, kinova.CartesianPosition),
    "GetGlobalTrajectoryInfo": (TrajectoryFIFO, kinova.TrajectoryFIFO),
}
#: functions without arguments
_ACTIONS = ("InitAPI", "CloseAPI", "MoveHome", "EraseAllTrajectories", "SetCartesianControl", "SetAngularControl")


class KinovaSdk:
    """The shared library with its functions declared; every call returns the SDK's code (1 = success)."""

    def __init__(self, path: str = KINOVA_SDK_LIBRARY) -> None:
        try:
            self.lib = ctypes.CDLL(path)
        except OSError as exc:
            raise RuntimeError(f"the Kinova SDK library {path!r} is not installed or not loadable ({exc}); "
                               "install Kinova's SDK or use the rs485 backend") from None
        missing = [name for name in (*_ACTIONS, "SendBasicTrajectory", *_GETTERS) if not hasattr(self.lib, name)]
        if missing:
            raise RuntimeError(f"{path!r} is not Kinova's USB command layer: no {', '.join(missing)}")
        for name in _ACTIONS:
            getattr(self.lib, name).argtypes, getattr(self.lib, name).restype = [], ctypes.c_int
        self.lib.SendBasicTrajectory.argtypes = [TrajectoryPoint]
        self.lib.SendBasicTrajectory.restype = ctypes.c_int
        for name, (c_type, _) in _GETTERS.items():
            getattr(self.lib, name).argtypes = [ctypes.POINTER(c_type)]
            getattr(self.lib, name).restype = ctypes.c_int

    def action(self, name: str) -> int:
        return int(getattr(self.lib, name)())

    def send_basic_trajectory(self, point: kinova.TrajectoryPoint) -> int:
        return int(self.lib.SendBasicTrajectory(to_c(point, TrajectoryPoint)))

    def get(self, name: str):
        """(code, value as a protocol.kinova message) of a getter."""
        c_type, message_type = _GETTERS[name]
        out = c_type()
        code = int(getattr(self.lib, name)(ctypes.byref(out)))
        return code, from_c(out, message_type)

    def checked(self, name: str):
        code, value = self.get(name)
        if code != kinova.ErrorCode.NO_ERROR_KINOVA:
            raise SdkError(name, code)
        return value

    def call(self, function: str, argument) -> kinova.ApiReply:
        """A Kinova API call by name (the robot/api/* queryables). The session belongs to the gateway: InitAPI
        and CloseAPI from a client are answered without touching it (as the emulated API does)."""
        if function in ("InitAPI", "CloseAPI"):
            return kinova.ApiReply()
        if function in _ACTIONS:
            return kinova.ApiReply(code=self.action(function))
        if function == "SendBasicTrajectory":
            problem = float32_problem(argument)
            if problem:
                return kinova.ApiReply(code=int(kinova.ErrorCode.ERROR_INVALID_PARAM), message=problem)
            return kinova.ApiReply(code=self.send_basic_trajectory(argument))
        if function in _GETTERS:
            code, value = self.get(function)
            return kinova.API_FUNCTIONS[function][1](code=code, result=value)
        # zones and client configurations: the SDK's structs hold more than mfvs's types describe
        return kinova.ApiReply(code=int(kinova.ErrorCode.ERROR_INVALID_PARAM),
                               message=f"{function} is not available through the kinova_sdk backend")


FLOAT32_MAX = 3.4028234663852886e38


def float32_problem(message, path: str = "") -> str:
    """Why a message cannot travel as the SDK's float32 fields (a float beyond float32 would arrive as inf)."""
    for name in message.__struct_fields__:
        value = getattr(message, name)
        if isinstance(value, float) and not abs(value) <= FLOAT32_MAX:
            return f"{path}{name} = {value} does not fit a float32"
        if hasattr(value, "__struct_fields__"):
            problem = float32_problem(value, f"{path}{name}.")
            if problem:
                return problem
    return ""


class SdkArm:
    """The arm behind the SDK as the robot front end sees it: a RobotView (measured state, pose) and the DSP
    surface it drives (submit, erase, status, one cycle per 10 ms)."""

    def __init__(self, sdk: KinovaSdk, config: DSPConfig) -> None:
        self.sdk = sdk
        self.config = config
        self.status = DSPStatus()
        self.fifo_count = 0
        self._pending: Optional[RobotCommand] = None
        self._state = JointReading(q=np.zeros(jaco2.N_JOINTS), dq=np.zeros(jaco2.N_JOINTS),
                                   tau=np.zeros(jaco2.N_JOINTS))
        self._pose = np.eye(4)

    # ---- RobotView
    @property
    def q(self) -> np.ndarray:
        return self._state.q

    @property
    def dq(self) -> np.ndarray:
        return self._state.dq

    @property
    def tau(self) -> np.ndarray:
        return self._state.tau

    def ee_pose(self) -> np.ndarray:
        return self._pose

    def read(self) -> JointReading:
        """Read the arm (4 SDK calls); raises SdkError when one fails."""
        angles = self.sdk.checked("GetAngularPosition").Actuators.as_list()
        rates = self.sdk.checked("GetAngularVelocity").Actuators.as_list()
        forces = self.sdk.checked("GetAngularForce").Actuators.as_list()
        c = self.sdk.checked("GetCartesianPosition").Coordinates
        self._state = JointReading(q=jaco2.physical_deg_to_model(angles), dq=jaco2.physical_rate_to_model(rates),
                                   tau=jaco2.SIGN * np.asarray(forces, dtype=float), stamp_ns=time.time_ns())
        self._pose = frames.homogeneous(frames.euler_xyz_to_matrix([c.ThetaX, c.ThetaY, c.ThetaZ]),
                                        [c.X, c.Y, c.Z])
        self._state.arm_pose = self._pose  # Kinova's DSP's own kinematics: what the commissioning check compares
        return self._state

    # ---- the DSP surface
    def motion_limits(self) -> MotionLimits:
        """The arm's own DSP applies its client configuration, which the gateway's config states."""
        return motion_limits(self.config)

    def submit(self, command: RobotCommand) -> None:
        mode = CommandMode(command.mode)
        if mode is CommandMode.CARTESIAN_VELOCITY:
            twist = command.twist
            if AngularConvention(twist.angular) is not AngularConvention(self.config.angular_convention):
                raise CommandRefused(f"the arm reads {AngularConvention(self.config.angular_convention).value} "
                                     f"angular velocities, the command declares {twist.angular}")
        self._pending = command

    def erase_all_trajectories(self) -> None:
        self._pending = None
        self._check("EraseAllTrajectories", self.sdk.action("EraseAllTrajectories"))

    def cycle(self, _reading=None) -> np.ndarray:
        """Forward this cycle's command (velocity commands last one cycle, so nothing pending means no motion).
        The joints are the arm's own DSP's business: no joint velocities come back (zeros)."""
        command, self._pending = self._pending, None
        self.status.cycles += 1
        if command is None:
            self.status.mode = ControlMode.IDLE
            return np.zeros(jaco2.N_JOINTS)
        mode = CommandMode(command.mode)
        if mode in (CommandMode.STOP, CommandMode.EMERGENCY_STOP):
            self.erase_all_trajectories()
            self.status.emergency_stop = mode is CommandMode.EMERGENCY_STOP
            point = velocity_point(kinova.POSITION_TYPE.ANGULAR_VELOCITY)
        elif mode is CommandMode.CARTESIAN_VELOCITY:
            point = velocity_point(kinova.POSITION_TYPE.CARTESIAN_VELOCITY,
                                   cartesian=[*command.twist.linear, *command.twist.rotational])
            self.status.mode, self.status.emergency_stop = ControlMode.CARTESIAN_VELOCITY, False
        else:
            point = velocity_point(kinova.POSITION_TYPE.ANGULAR_VELOCITY,
                                   angular_dps=jaco2.model_rate_to_physical(command.joint_velocities))
            self.status.mode, self.status.emergency_stop = ControlMode.ANGULAR_VELOCITY, False
        self._check("SendBasicTrajectory", self.sdk.send_basic_trajectory(point))
        return np.zeros(jaco2.N_JOINTS)

    @staticmethod
    def _check(function: str, code: int) -> None:
        if code != kinova.ErrorCode.NO_ERROR_KINOVA:
            raise SdkError(function, code)


def velocity_point(kind: kinova.POSITION_TYPE, cartesian=None, angular_dps=None) -> kinova.TrajectoryPoint:
    """A velocity TrajectoryPoint (zero where not given)."""
    position = kinova.UserPosition(Type=kind)
    if cartesian is not None:
        position.CartesianPosition = kinova.CartesianInfo(**dict(zip(("X", "Y", "Z", "ThetaX", "ThetaY", "ThetaZ"),
                                                                     map(float, cartesian), strict=True)))
    if angular_dps is not None:
        position.Actuators = kinova.AngularInfo.from_list(angular_dps)
    return kinova.TrajectoryPoint(Position=position)
