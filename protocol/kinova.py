"""Kinova JACO-2 high-level API types (USB command layer), with Kinova's names, numeric values and units.

These are the types the emulated API (robot_sim) and the gateway speak on ``…/robot/api/<Function>``. Units are
Kinova's: CartesianInfo in metres and radians (m/s and rad/s in velocity mode, XYZ Euler angles R = Rx·Ry·Rz),
AngularInfo in degrees (deg/s in velocity mode). Facts from ``shared/reference/kinova.md``; the names and values
of the codes and enums are those of Kinova's headers (``shared/reference/kinova-sdk/include``; the tests check them
against the headers with the C++ compiler where the SDK is present).
"""
from __future__ import annotations

import enum
import re
from typing import Annotated, NamedTuple

import msgspec

from protocol.messages import Message, prepare_decoders, wire_types

#: Maximum number of points in the DSP's trajectory FIFO.
TRAJECTORY_FIFO_SIZE = 2000
#: Maximum number of protection zones in a ZoneList.
MAX_ZONES = 10
#: Points per zone shape.
ZONE_SHAPE_POINTS = 8
#: Length of the float arrays of the torque API (SendAngularTorqueCommand, SendCartesianForceCommand,
#: SetTorqueActuatorGain, SetTorqueActuatorDamping): COMMAND_SIZE in Kinova's header.
TORQUE_COMMAND_SIZE = 70
MAX_ACTUATORS = 7
#: Length of SetGravityOptimalZParam's array (GRAVITY_PARAM_SIZE), and how many of them the arm's optimal-Z
#: estimate fills: OPTIMAL_Z_PARAM_SIZE for a 6-DoF arm, OPTIMAL_Z_PARAM_SIZE_7DOF for a 7-DoF one.
GRAVITY_PARAM_SIZE = 42
OPTIMAL_Z_PARAM_SIZE = 16
OPTIMAL_Z_PARAM_SIZE_7DOF = 19


class ErrorCode(enum.IntEnum):
    """Return codes of the API functions (1 is success), every one Kinova's headers define, with their names:
    Kinova.API.USBCommLayerUbuntu.h (the comm layer: 1, 666, 1001-1022, 9999), Kinova.API.USBCommandLayerUbuntu.h
    (the command layer: 2001-2015, 2100-2102) and KinovaTypes.h (5001-5003)."""

    NO_ERROR_KINOVA = 1
    #: an error occurred, and where is not known
    UNKNOWN_ERROR = 666
    # the comm layer: USB (libusb) and RS-485
    ERROR_LOAD_USB_LIBRARY = 1001
    ERROR_OPEN_METHOD = 1002
    ERROR_WRITE_METHOD = 1003
    ERROR_READ_METHOD = 1004
    ERROR_READ_INT_METHOD = 1005
    ERROR_FREE_LIBRARY = 1006
    #: a problem with the USB connection between the arm and the computer
    ERROR_JACO_CONNECTION = 1007
    #: the USB interface could not be claimed (another program holds the arm)
    ERROR_CLAIM_INTERFACE = 1008
    ERROR_UNKNOWN_DEVICE = 1009
    #: the functionality used has not been initialised (Ethernet: the local address could not be bound)
    ERROR_NOT_INITIALIZED = 1010
    ERROR_LIBUSB_NO_DEVICE = 1011
    ERROR_LIBUSB_BUSY = 1012
    ERROR_LIBUSB_NOT_SUPPORTED = 1013
    ERROR_SENDPACKET_UNKNOWN = 1014
    #: no arm found
    ERROR_NO_DEVICE_FOUND = 1015
    ERROR_OPERATION_INCOMPLETED = 1016
    ERROR_RS485_INVALID_HANDLE = 1017
    ERROR_RS485_IO_PENDING = 1018
    ERROR_RS485_NOT_ENOUGH_MEMORY = 1019
    ERROR_RS485_TIMEOUT = 1020
    ERROR_FUNCTION_NOT_ACCESSIBLE = 1021
    #: no answer within the comm layer's timeout (5 s on USB)
    ERROR_COMM_TIMEOUT = 1022
    #: the arm answered a NACK
    ERROR_NACK_RECEIVED = 9999
    # the command layer: initialisation
    ERROR_INIT_API = 2001
    #: the command layer could not load its comm layer (USBCommLayerUbuntu.so, by bare name)
    ERROR_LOAD_COMM_DLL = 2002
    JACO_NACK_FIRST = 2003
    JACO_COMM_FAILED = 2004
    JACO_NACK_NORMAL = 2005
    ERROR_INIT_COMM_METHOD = 2006
    ERROR_CLOSE_METHOD = 2007
    ERROR_GET_DEVICE_COUNT_METHOD = 2008
    ERROR_SEND_PACKET_METHOD = 2009
    ERROR_SET_ACTIVE_DEVICE_METHOD = 2010
    ERROR_GET_DEVICES_LIST_METHOD = 2011
    ERROR_SEMAPHORE_FAILED = 2012
    ERROR_SCAN_FOR_NEW_DEVICE = 2013
    ERROR_GET_ACTIVE_DEVICE_METHOD = 2014
    ERROR_OPEN_RS485_ACTIVATE = 2015
    ERROR_INVALID_PARAM = 2100
    ERROR_API_NOT_INITIALIZED = 2101
    ERROR_INIT_DATA_STRUCTURES_METHOD = 2102
    # KinovaTypes.h: files (firmware programming)
    ERROR_UNKNOWFILE = 5001
    ERROR_MEMORY = 5002
    ERROR_FILEREADING = 5003


_DEFINED_CODES = frozenset(int(code) for code in ErrorCode)


def is_known_error_code(code: int) -> bool:
    """Whether Kinova's headers define this return code."""
    return code in _DEFINED_CODES


def error_name(code: int) -> str:
    """The header's name of a return code, or says it has none."""
    try:
        return ErrorCode(code).name
    except ValueError:
        return "a code Kinova's headers do not define"


class ModelCode(NamedTuple):
    """A Kinova arm's model code, as Kinova writes it (j2n6s300, j2s7s300, m1n6s300): family (j JACO, m MICO,
    r ROCO, c custom), version, wrist (s spherical, n non-spherical), joints, mode (s service, a assistive),
    fingers, and two reserved digits."""

    family: str
    version: int
    wrist: str
    joints: int
    mode: str
    fingers: int

    @property
    def code(self) -> str:
        return f"{self.family}{self.version}{self.wrist}{self.joints}{self.mode}{self.fingers}00"


_MODEL_CODE = re.compile(r"([jmrc])([12])([sn])([467])([sa])([23])00")
_WRISTS = {"s": "spherical", "n": "non-spherical"}
_FAMILIES = {"j": "JACO", "m": "MICO", "r": "ROCO", "c": "custom"}


def parse_model_code(text: str) -> ModelCode | None:
    """The model code in ``text`` (case and surrounding blanks or NULs ignored), or None when it is not one."""
    match = _MODEL_CODE.fullmatch(text.strip().strip("\0").strip().lower())
    if match is None:
        return None
    family, version, wrist, joints, mode, fingers = match.groups()
    return ModelCode(family, int(version), wrist, int(joints), mode, int(fingers))


#: the serial number robot_sim's emulated base reports on USB (services/robot_sim/usb_base.py): no Kinova arm's
#: (theirs start PJ); a host may run such an arm in lockstep, never a real one
EMULATED_SERIAL = "MFVS-EMULATED"


def device_text(raw: bytes) -> str:
    """A string of a Kinova device's record (its serial number, its model) as a person can read it: up to the first
    NUL, printable ASCII only (anything else '?'). The comm layer fills the record from the device's descriptors;
    where it could not (a device that did not answer), the bytes are whatever the memory held, and printed as they
    are they would break the one-line error a person acts on."""
    text = bytes(raw).split(b"\0", 1)[0].decode("ascii", errors="replace")
    return "".join(c if c.isprintable() and c.isascii() else "?" for c in text).strip()


def arm_type_refusal(device_model: str, arm_name: str, n_joints: int) -> str | None:
    """Why an arm that reports ``device_model`` must not be driven as the configured arm ``arm_name`` with
    ``n_joints`` joints (None: it may). The joint count decides; where the configured name is a model code too,
    the family, version and wrist must match as well (a j2s6s300 is not a j2n6s300: other kinematics). A model
    the arm reports that is not a model code is refused: the joint count could not be checked."""
    reported = parse_model_code(device_model)
    if reported is None:
        return (f"the arm reports its model as {device_model.strip()!r}, not a Kinova model code such as j2s7s300: "
                f"its joint count cannot be checked against {arm_name} ({n_joints} joints)")
    if reported.joints != n_joints:
        return (f"the arm is a {reported.code} with {reported.joints} joints; the configured arm {arm_name} has "
                f"{n_joints}")
    configured = parse_model_code(arm_name)
    if configured is None:
        return None
    if reported.wrist != configured.wrist:
        return (f"the arm is a {reported.code} with a {_WRISTS[reported.wrist]} wrist; the configured arm {arm_name} "
                f"has a {_WRISTS[configured.wrist]} one: other kinematics")
    if (reported.family, reported.version) != (configured.family, configured.version):
        return (f"the arm is a {reported.code} ({_FAMILIES[reported.family]} {reported.version}); the configured "
                f"arm {arm_name} is a {_FAMILIES[configured.family]} {configured.version}: other kinematics")
    return None


class POSITION_TYPE(enum.IntEnum):
    NOMOVEMENT_POSITION = 0
    CARTESIAN_POSITION = 1
    ANGULAR_POSITION = 2
    RETRACTED = 3
    PREDEFINED1 = 4
    PREDEFINED2 = 5
    PREDEFINED3 = 6
    CARTESIAN_VELOCITY = 7
    ANGULAR_VELOCITY = 8
    PREDEFINED4 = 9
    PREDEFINED5 = 10
    ANY_TRAJECTORY = 11
    TIME_DELAY = 12


class HAND_MODE(enum.IntEnum):
    HAND_NOMOVEMENT = 0
    POSITION_MODE = 1
    VELOCITY_MODE = 2
    NO_FINGER = 3
    ONE_FINGER = 4
    TWO_FINGERS = 5
    THREE_FINGERS = 6


class GENERALCONTROL_TYPE(enum.IntEnum):
    """Argument of SwitchTrajectoryTorque."""

    POSITION = 0
    TORQUE = 1


class GRAVITY_TYPE(enum.IntEnum):
    """Argument of SetGravityType: how the arm's gravity compensation in torque mode gets its parameters."""

    MANUAL_INPUT = 0
    OPTIMAL = 1


class ShapeType(enum.IntEnum):
    """Protection-zone shapes. Only PrismSquareBase_Z is documented as used by the DSP."""

    PrismSquareBase_X = 0
    PrismSquareBase_Y = 1
    PrismSquareBase_Z = 2
    PrismTriangularBase_X = 3
    PrismTriangularBase_Y = 4
    PrismTriangularBase_Z = 5
    Pyramid = 6


class CartesianInfo(Message):
    """Metres and radians (XYZ Euler); m/s and rad/s in velocity mode."""

    X: float = 0.0
    Y: float = 0.0
    Z: float = 0.0
    ThetaX: float = 0.0
    ThetaY: float = 0.0
    ThetaZ: float = 0.0


class AngularInfo(Message):
    """Degrees (deg/s in velocity mode), physical actuator angles as the arm reports them (not wrapped)."""

    Actuator1: float = 0.0
    Actuator2: float = 0.0
    Actuator3: float = 0.0
    Actuator4: float = 0.0
    Actuator5: float = 0.0
    Actuator6: float = 0.0
    Actuator7: float = 0.0

    def as_list(self) -> list[float]:
        return [getattr(self, f"Actuator{i}") for i in range(1, MAX_ACTUATORS + 1)]

    @classmethod
    def from_list(cls, values) -> "AngularInfo":
        """One value per joint of the arm (1-7); the actuators an arm does not have read 0, as Kinova's SDK gives
        them for a 6-DoF arm."""
        values = [float(v) for v in values]
        if not 1 <= len(values) <= MAX_ACTUATORS:
            raise ValueError(f"AngularInfo takes 1 to {MAX_ACTUATORS} values, got {len(values)}")
        return cls(**{f"Actuator{i + 1}": v for i, v in enumerate(values)})


class FingersPosition(Message):
    """Kinova's finger units (0 open, about 6800 closed: services/model/hands), units/s in velocity mode, A in
    GetAngularCurrent; the fingers a hand does not have read 0."""

    Finger1: float = 0.0
    Finger2: float = 0.0
    Finger3: float = 0.0

    def as_list(self) -> list[float]:
        return [self.Finger1, self.Finger2, self.Finger3]

    @classmethod
    def from_list(cls, values) -> "FingersPosition":
        values = [float(v) for v in values]
        if len(values) > 3:
            raise ValueError(f"FingersPosition takes at most 3 values, got {len(values)}")
        return cls(**{f"Finger{i + 1}": v for i, v in enumerate(values)})


class AngularPosition(Message):
    Actuators: AngularInfo = msgspec.field(default_factory=AngularInfo)
    Fingers: FingersPosition = msgspec.field(default_factory=FingersPosition)


class CartesianPosition(Message):
    Coordinates: CartesianInfo = msgspec.field(default_factory=CartesianInfo)
    Fingers: FingersPosition = msgspec.field(default_factory=FingersPosition)


class UserPosition(Message):
    Type: POSITION_TYPE = POSITION_TYPE.NOMOVEMENT_POSITION
    Delay: Annotated[float, msgspec.Meta(ge=0.0)] = 0.0
    CartesianPosition: CartesianInfo = msgspec.field(default_factory=CartesianInfo)
    Actuators: AngularInfo = msgspec.field(default_factory=AngularInfo)
    HandMode: HAND_MODE = HAND_MODE.HAND_NOMOVEMENT
    Fingers: FingersPosition = msgspec.field(default_factory=FingersPosition)


class Limitation(Message):
    """speedParameter1: translation speed (or actuators 1-3); speedParameter2: orientation speed (or 4-6)."""

    speedParameter1: float = 0.0
    speedParameter2: float = 0.0
    speedParameter3: float = 0.0
    forceParameter1: float = 0.0
    forceParameter2: float = 0.0
    forceParameter3: float = 0.0
    accelerationParameter1: float = 0.0
    accelerationParameter2: float = 0.0
    accelerationParameter3: float = 0.0


class TrajectoryPoint(Message):
    Position: UserPosition = msgspec.field(default_factory=UserPosition)
    LimitationsActive: Annotated[int, msgspec.Meta(ge=0, le=1)] = 0
    SynchroType: int = 0
    Limitations: Limitation = msgspec.field(default_factory=Limitation)


class TrajectoryFIFO(Message):
    TrajectoryCount: Annotated[int, msgspec.Meta(ge=0)] = 0
    UsedPercentage: Annotated[float, msgspec.Meta(ge=0.0, le=100.0)] = 0.0
    MaxSize: Annotated[int, msgspec.Meta(ge=0)] = TRAJECTORY_FIFO_SIZE


class ZoneShape(Message):
    shapeType: ShapeType = ShapeType.PrismSquareBase_Z
    Points: Annotated[list[CartesianInfo], msgspec.Meta(min_length=ZONE_SHAPE_POINTS, max_length=ZONE_SHAPE_POINTS)] = (
        msgspec.field(default_factory=lambda: [CartesianInfo() for _ in range(ZONE_SHAPE_POINTS)])
    )


class Zone(Message):
    """A protection zone. A zone whose speed limitation is 0 is forbidden."""

    ID: int = 0
    zoneShape: ZoneShape = msgspec.field(default_factory=ZoneShape)
    zoneLimitation: CartesianInfo = msgspec.field(default_factory=CartesianInfo)


class ZoneList(Message):
    NbZones: Annotated[int, msgspec.Meta(ge=0, le=MAX_ZONES)] = 0
    Zones: Annotated[list[Zone], msgspec.Meta(max_length=MAX_ZONES)] = []

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.NbZones != len(self.Zones):
            raise ValueError(f"NbZones is {self.NbZones} but {len(self.Zones)} zones are given at field 'NbZones'")


class ClientConfigurations(Message):
    """The subset of Kinova's ClientConfigurations the emulator honours (m/s, rad/s, m/s², rad/s²)."""

    MaxTranslationVelocity: float = 0.2
    MaxOrientationVelocity: float = 1.07
    MaxTranslationAcceleration: float = 0.64
    MaxOrientationAcceleration: float = 2.75


# ---------------------------------------------------------------------- arguments of the torque-mode setup (Table 5.1)
class FloatArgument(Message):
    """The one float of SetTorqueSafetyFactor (factor) and SetTorqueVibrationController (activationStatus)."""

    value: float = 0.0


class CommandArray(Message):
    """A float[COMMAND_SIZE] argument (SetTorqueActuatorGain, SetTorqueActuatorDamping): one value per actuator,
    actuator 1 first; the values past the arm's actuators are not read."""

    values: Annotated[list[float], msgspec.Meta(min_length=TORQUE_COMMAND_SIZE, max_length=TORQUE_COMMAND_SIZE)] = (
        msgspec.field(default_factory=lambda: [0.0] * TORQUE_COMMAND_SIZE))


class GravityParameters(Message):
    """SetGravityOptimalZParam's float[GRAVITY_PARAM_SIZE]."""

    values: Annotated[list[float], msgspec.Meta(min_length=GRAVITY_PARAM_SIZE, max_length=GRAVITY_PARAM_SIZE)] = (
        msgspec.field(default_factory=lambda: [0.0] * GRAVITY_PARAM_SIZE))


class GravityTypeArgument(Message):
    type: GRAVITY_TYPE = GRAVITY_TYPE.OPTIMAL


class ActuatorAddress(Message):
    """SetTorqueZero's and SetJointZero's ActuatorAdress (sic): an actuator's RS-485 address (16 = 0x10 for joint
    1, kinova.md)."""

    address: Annotated[int, msgspec.Meta(ge=0, le=255)] = 0


# ----------------------------------------------------------------------------------------------- the zenoh API
#
# Each Kinova function is a zenoh queryable at ``…/robot/api/<Function>``. The query payload is the function's
# argument (MessagePack of the type below; empty for functions without one); the reply is the function's
# return code and, for getters, the value it fills in.


class ApiReply(Message):
    code: int = ErrorCode.NO_ERROR_KINOVA
    #: why a call failed (empty on success); the SDK has only the code, this is for people
    message: Annotated[str, msgspec.Meta(max_length=512)] = ""


class AngularPositionReply(ApiReply):
    result: AngularPosition = msgspec.field(default_factory=AngularPosition)


class CartesianPositionReply(ApiReply):
    result: CartesianPosition = msgspec.field(default_factory=CartesianPosition)


class TrajectoryFIFOReply(ApiReply):
    result: TrajectoryFIFO = msgspec.field(default_factory=TrajectoryFIFO)


class ZoneListReply(ApiReply):
    result: ZoneList = msgspec.field(default_factory=ZoneList)


class ClientConfigurationsReply(ApiReply):
    result: ClientConfigurations = msgspec.field(default_factory=ClientConfigurations)


#: function name → (argument type or None, reply type)
#: functions that move the arm or change how it moves (zones, limits, control mode): in an authority deployment
#: only the service that commands the robot may call them (services/runtime/authority.py)
#: the torque-mode setup of the JACO thesis's Table 5.1 (services/robot/torque_setup.py says what each does)
TORQUE_SETUP_FUNCTIONS: dict[str, type] = {
    "SetTorqueSafetyFactor": FloatArgument,
    "SetTorqueVibrationController": FloatArgument,
    "SetTorqueActuatorGain": CommandArray,
    "SetTorqueActuatorDamping": CommandArray,
    "SetGravityType": GravityTypeArgument,
    "SetGravityOptimalZParam": GravityParameters,
    "SetTorqueZero": ActuatorAddress,
    "SetJointZero": ActuatorAddress,
}
MUTATING_API_FUNCTIONS = frozenset({
    "MoveHome", "SetCartesianControl", "SetAngularControl", "SendBasicTrajectory", "EraseAllTrajectories",
    "SetProtectionZone", "EraseAllProtectionZones", "SetClientConfigurations", *TORQUE_SETUP_FUNCTIONS,
})

API_FUNCTIONS: dict[str, tuple[type | None, type]] = {
    "InitAPI": (None, ApiReply),
    "CloseAPI": (None, ApiReply),
    "MoveHome": (None, ApiReply),
    "SetCartesianControl": (None, ApiReply),
    "SetAngularControl": (None, ApiReply),
    "SendBasicTrajectory": (TrajectoryPoint, ApiReply),
    "EraseAllTrajectories": (None, ApiReply),
    "GetGlobalTrajectoryInfo": (None, TrajectoryFIFOReply),
    "GetAngularPosition": (None, AngularPositionReply),
    "GetAngularVelocity": (None, AngularPositionReply),
    "GetAngularForce": (None, AngularPositionReply),
    "GetAngularCommand": (None, AngularPositionReply),
    "GetAngularCurrent": (None, AngularPositionReply),
    "GetCartesianPosition": (None, CartesianPositionReply),
    "GetCartesianCommand": (None, CartesianPositionReply),
    "SetProtectionZone": (ZoneList, ApiReply),
    "GetProtectionZone": (None, ZoneListReply),
    "EraseAllProtectionZones": (None, ApiReply),
    "GetClientConfigurations": (None, ClientConfigurationsReply),
    "SetClientConfigurations": (ClientConfigurations, ApiReply),
    **{name: (argument, ApiReply) for name, argument in TORQUE_SETUP_FUNCTIONS.items()},
}

prepare_decoders(wire_types(globals()))
