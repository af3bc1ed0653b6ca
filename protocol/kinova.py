"""Kinova JACO-2 high-level API types (USB command layer), with Kinova's names, numeric values and units.

These are the types the emulated API (robot_sim) and the gateway speak on ``…/robot/api/<Function>``. Units are
Kinova's: CartesianInfo in metres and radians (m/s and rad/s in velocity mode, XYZ Euler angles R = Rx·Ry·Rz),
AngularInfo in degrees (deg/s in velocity mode). Facts from ``shared/reference/kinova.md``.
"""
from __future__ import annotations

import enum
from typing import Annotated

import msgspec

from protocol.messages import Message, prepare_decoders, wire_types

#: Maximum number of points in the DSP's trajectory FIFO.
TRAJECTORY_FIFO_SIZE = 2000
#: Maximum number of protection zones in a ZoneList.
MAX_ZONES = 10
#: Points per zone shape.
ZONE_SHAPE_POINTS = 8
#: Length of the float arrays of the torque API (SendAngularTorqueCommand, SendCartesianForceCommand).
TORQUE_COMMAND_SIZE = 70
MAX_ACTUATORS = 7


class ErrorCode(enum.IntEnum):
    """Return codes of the API functions (1 is success)."""

    NO_ERROR_KINOVA = 1
    UNKNOWN_ERROR = 666
    # 1001-1022 are USB/RS-485 errors and 2001-2015 initialisation errors; only these two are named publicly
    ERROR_RS485_TIMEOUT = 1020
    ERROR_COMMUNICATION_TIMEOUT = 1022
    ERROR_INVALID_PARAM = 2100
    ERROR_API_NOT_INITIALIZED = 2101
    ERROR_NACK_RECEIVED = 9999


#: Code ranges documented for the API, for validating codes from a real SDK that are not named above.
ERROR_CODE_RANGES = ((1, 1), (666, 666), (1001, 1022), (2001, 2015), (2100, 2101), (9999, 9999))


def is_known_error_code(code: int) -> bool:
    return any(lo <= code <= hi for lo, hi in ERROR_CODE_RANGES)


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


class GENERALCONTROL_TYPE(enum.IntEnum):
    """Argument of SwitchTrajectoryTorque."""

    POSITION = 0
    TORQUE = 1


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
        values = [float(v) for v in values]
        if len(values) != MAX_ACTUATORS:
            raise ValueError(f"AngularInfo needs {MAX_ACTUATORS} values, got {len(values)}")
        return cls(**{f"Actuator{i + 1}": v for i, v in enumerate(values)})


class FingersPosition(Message):
    Finger1: float = 0.0
    Finger2: float = 0.0
    Finger3: float = 0.0


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
MUTATING_API_FUNCTIONS = frozenset({
    "MoveHome", "SetCartesianControl", "SetAngularControl", "SendBasicTrajectory", "EraseAllTrajectories",
    "SetProtectionZone", "EraseAllProtectionZones", "SetClientConfigurations",
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
    "GetCartesianPosition": (None, CartesianPositionReply),
    "GetCartesianCommand": (None, CartesianPositionReply),
    "SetProtectionZone": (ZoneList, ApiReply),
    "GetProtectionZone": (None, ZoneListReply),
    "EraseAllProtectionZones": (None, ApiReply),
    "GetClientConfigurations": (None, ClientConfigurationsReply),
    "SetClientConfigurations": (ClientConfigurations, ApiReply),
}

prepare_decoders(wire_types(globals()))
