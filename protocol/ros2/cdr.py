"""A small CDR codec for the ROS 2 messages mfvs publishes and the few it accepts, as rmw_zenoh carries them.

The format is what ROS 2's Fast-CDR type support writes and rmw_zenoh_cpp sends as the sample's payload
(docs/ros2.md, "The wire"): a 4-byte encapsulation header ``00 01 00 00`` (CDR, little-endian: XCDR1 PLAIN_CDR_LE),
then the fields in declaration order, each primitive aligned to its own size (8 at most) counted from the first
byte after the header; a string is a uint32 length that counts a terminating NUL, its UTF-8 bytes and the NUL; a
sequence is a uint32 element count and its elements; a fixed array is its elements alone; a nested message is its
fields, with no alignment of its own; a message without fields carries one uint8 (ROS's
``structure_needs_at_least_one_member``).

A message here is a frozen dataclass (``Image``, ``JointState``, ...) whose fields have the ROS field names, in
the ROS order. Values: Python ints and floats for primitives; ``str`` for strings; ``bytes`` for ``uint8[]``
(Image.data); a numpy array for ``float64[]`` and ``float64[N]`` (float64), ``float32[]`` (float32) and ``int32[]``
(int32) (decoded arrays are read-only views of the payload, no copy); a tuple for sequences of strings or messages. Two messages are equal when every field is (arrays
element by element).

Decoding is tolerant where ROS's serializer differs from the rule and strict everywhere else: fewer than 8 bytes
after the last field are padding (rclpy's serializer pads some messages: fixtures/trigger_request.rclpy.cdr), and
padding bytes are never read (the same serializer leaves stale bytes in them); anything else wrong raises
``CdrError`` naming the field, and no length read from the payload allocates more than the payload holds.
"""
from __future__ import annotations

import dataclasses
import math
import struct
from dataclasses import dataclass, field
from typing import ClassVar, TypeVar

import numpy as np

#: CDR little-endian (PLAIN_CDR_LE of the XTypes 1.3 spec's encapsulation identifiers, 0x0001) with no options:
#: what ROS 2's Fast-CDR type support writes (every fixture's first 4 bytes)
ENCAPSULATION_HEADER = b"\x00\x01\x00\x00"
#: the big-endian identifier (PLAIN_CDR_BE, 0x0000): valid CDR that ROS 2 never sends on x86 or ARM; refused
_BIG_ENDIAN_ID = b"\x00\x00"
#: the most bytes a serializer may leave after the last field: padding to the largest alignment, 8 (float64)
MAX_TRAILING_PADDING = 7


class CdrError(ValueError):
    """A payload that is not the CDR of the message type asked for, or a value that cannot be encoded."""


# ---------------------------------------------------------------------------------------------------------------
# Field kinds: each knows its alignment, its smallest encoding (to bound counts), how to write and read itself.

@dataclass(frozen=True)
class _Primitive:
    name: str
    struct_format: str  # little-endian struct format of one value
    low: float
    high: float

    @property
    def size(self) -> int:
        return struct.calcsize(self.struct_format)

    def check(self, value, where: str):
        if self.name == "bool":
            if not isinstance(value, (bool, np.bool_)):
                raise CdrError(f"{where}: a bool is needed, got {value!r}")
            return bool(value)
        if self.name in ("float64", "float32"):
            if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
                raise CdrError(f"{where}: a float is needed, got {value!r}")
            if self.name == "float32" and math.isfinite(value) and not math.isfinite(np.float32(value)):
                raise CdrError(f"{where}: {value} is beyond float32's range")
            return float(value)
        if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
            raise CdrError(f"{where}: an integer is needed, got {value!r}")
        if not self.low <= value <= self.high:
            raise CdrError(f"{where}: {value} is outside {self.name}'s range [{self.low}, {self.high}]")
        return int(value)


INT32 = _Primitive("int32", "<i", -2**31, 2**31 - 1)
UINT32 = _Primitive("uint32", "<I", 0, 2**32 - 1)
UINT8 = _Primitive("uint8", "<B", 0, 255)
BOOL = _Primitive("bool", "<?", 0, 1)
FLOAT64 = _Primitive("float64", "<d", float("-inf"), float("inf"))
FLOAT32 = _Primitive("float32", "<f", float("-inf"), float("inf"))

#: the primitives whose sequences are numpy arrays, and each one's little-endian dtype
_ARRAY_DTYPES = {FLOAT64: "<f8", FLOAT32: "<f4", INT32: "<i4"}


class _StringKind:
    name = "string"


STRING = _StringKind()


@dataclass(frozen=True)
class FixedFloat64Array:
    """``float64[length]``: the elements alone, no count."""
    length: int


@dataclass(frozen=True)
class Sequence:
    """An unbounded sequence (``T[]``) of a primitive, of strings, or of a message type."""
    element: object


def ros_field(kind, **options):
    """A dataclass field carrying its CDR kind (the order of fields is the order on the wire)."""
    return field(metadata={"cdr": kind}, **options)


class Message:
    """A ROS 2 message type: a frozen dataclass with ``ros_field`` fields, ``ROS_TYPE`` its ROS 2 name."""

    ROS_TYPE: ClassVar[str]

    def __eq__(self, other) -> bool:
        if type(other) is not type(self):
            return NotImplemented
        for item in dataclasses.fields(self):
            mine, theirs = getattr(self, item.name), getattr(other, item.name)
            if isinstance(mine, np.ndarray) or isinstance(theirs, np.ndarray):
                if not np.array_equal(np.asarray(mine, dtype=np.float64), np.asarray(theirs, dtype=np.float64),
                                      equal_nan=True):
                    return False
            elif mine != theirs:
                return False
        return True

    __hash__ = None  # mutable arrays inside: not hashable


def _float64_array(values, length: int | None = None, dtype=np.float64) -> np.ndarray:
    array = np.asarray(values)
    if array.dtype.kind not in "biuf" or array.dtype.kind == "b":
        raise CdrError(f"numbers are needed, got {array.dtype} values")
    if np.dtype(dtype).kind == "i":
        if array.dtype.kind == "f" and not np.array_equal(array, np.trunc(array)):
            raise CdrError("integers are needed, got fractions")
        info = np.iinfo(dtype)
        if array.size and (array.min() < info.min or array.max() > info.max):
            raise CdrError(f"a value beyond {np.dtype(dtype).name}'s range [{info.min}, {info.max}]")
    elif np.dtype(dtype) == np.float32 and array.size:
        wide = array.astype(np.float64)
        if np.any(np.isfinite(wide) & (np.abs(wide) > np.finfo(np.float32).max)):
            raise CdrError("a value beyond float32's range")
    array = array.astype(dtype)
    if array.ndim != 1 or (length is not None and array.shape[0] != length):
        want = f"{length} values" if length is not None else "a flat sequence"
        raise CdrError(f"{want} are needed, got shape {array.shape}")
    return array


def _empty_floats() -> np.ndarray:
    return np.zeros(0)


def _empty_float32() -> np.ndarray:
    return np.zeros(0, dtype=np.float32)


def _empty_int32() -> np.ndarray:
    return np.zeros(0, dtype=np.int32)


# ---------------------------------------------------------------------------------------------------------------
# The message types: field names and order from the ROS 2 Jazzy interface definitions (common_interfaces 5.3.6,
# rcl_interfaces 2.0.3 for builtin_interfaces; tf2_msgs and std_srvs as released for Jazzy), which the fixtures'
# bytes confirm field by field.

@dataclass(frozen=True, eq=False)
class Time(Message):
    ROS_TYPE = "builtin_interfaces/msg/Time"
    sec: int = ros_field(INT32, default=0)
    nanosec: int = ros_field(UINT32, default=0)


@dataclass(frozen=True, eq=False)
class Header(Message):
    ROS_TYPE = "std_msgs/msg/Header"
    stamp: Time = ros_field(Time, default_factory=Time)
    frame_id: str = ros_field(STRING, default="")


@dataclass(frozen=True, eq=False)
class Image(Message):
    ROS_TYPE = "sensor_msgs/msg/Image"
    header: Header = ros_field(Header, default_factory=Header)
    height: int = ros_field(UINT32, default=0)
    width: int = ros_field(UINT32, default=0)
    encoding: str = ros_field(STRING, default="")
    is_bigendian: int = ros_field(UINT8, default=0)
    step: int = ros_field(UINT32, default=0)
    data: bytes = ros_field(Sequence(UINT8), default=b"")


@dataclass(frozen=True, eq=False)
class RegionOfInterest(Message):
    ROS_TYPE = "sensor_msgs/msg/RegionOfInterest"
    x_offset: int = ros_field(UINT32, default=0)
    y_offset: int = ros_field(UINT32, default=0)
    height: int = ros_field(UINT32, default=0)
    width: int = ros_field(UINT32, default=0)
    do_rectify: bool = ros_field(BOOL, default=False)


@dataclass(frozen=True, eq=False)
class CameraInfo(Message):
    ROS_TYPE = "sensor_msgs/msg/CameraInfo"
    header: Header = ros_field(Header, default_factory=Header)
    height: int = ros_field(UINT32, default=0)
    width: int = ros_field(UINT32, default=0)
    distortion_model: str = ros_field(STRING, default="")
    d: np.ndarray = ros_field(Sequence(FLOAT64), default_factory=_empty_floats)
    k: np.ndarray = ros_field(FixedFloat64Array(9), default_factory=lambda: np.zeros(9))
    r: np.ndarray = ros_field(FixedFloat64Array(9), default_factory=lambda: np.zeros(9))
    p: np.ndarray = ros_field(FixedFloat64Array(12), default_factory=lambda: np.zeros(12))
    binning_x: int = ros_field(UINT32, default=0)
    binning_y: int = ros_field(UINT32, default=0)
    roi: RegionOfInterest = ros_field(RegionOfInterest, default_factory=RegionOfInterest)


@dataclass(frozen=True, eq=False)
class JointState(Message):
    ROS_TYPE = "sensor_msgs/msg/JointState"
    header: Header = ros_field(Header, default_factory=Header)
    name: tuple[str, ...] = ros_field(Sequence(STRING), default=())
    position: np.ndarray = ros_field(Sequence(FLOAT64), default_factory=_empty_floats)
    velocity: np.ndarray = ros_field(Sequence(FLOAT64), default_factory=_empty_floats)
    effort: np.ndarray = ros_field(Sequence(FLOAT64), default_factory=_empty_floats)


@dataclass(frozen=True, eq=False)
class Vector3(Message):
    ROS_TYPE = "geometry_msgs/msg/Vector3"
    x: float = ros_field(FLOAT64, default=0.0)
    y: float = ros_field(FLOAT64, default=0.0)
    z: float = ros_field(FLOAT64, default=0.0)


@dataclass(frozen=True, eq=False)
class Point(Message):
    ROS_TYPE = "geometry_msgs/msg/Point"
    x: float = ros_field(FLOAT64, default=0.0)
    y: float = ros_field(FLOAT64, default=0.0)
    z: float = ros_field(FLOAT64, default=0.0)


@dataclass(frozen=True, eq=False)
class Quaternion(Message):
    ROS_TYPE = "geometry_msgs/msg/Quaternion"
    x: float = ros_field(FLOAT64, default=0.0)
    y: float = ros_field(FLOAT64, default=0.0)
    z: float = ros_field(FLOAT64, default=0.0)
    w: float = ros_field(FLOAT64, default=1.0)  # the ROS definition's default: the identity rotation


@dataclass(frozen=True, eq=False)
class Transform(Message):
    ROS_TYPE = "geometry_msgs/msg/Transform"
    translation: Vector3 = ros_field(Vector3, default_factory=Vector3)
    rotation: Quaternion = ros_field(Quaternion, default_factory=Quaternion)


@dataclass(frozen=True, eq=False)
class TransformStamped(Message):
    ROS_TYPE = "geometry_msgs/msg/TransformStamped"
    header: Header = ros_field(Header, default_factory=Header)
    child_frame_id: str = ros_field(STRING, default="")
    transform: Transform = ros_field(Transform, default_factory=Transform)


@dataclass(frozen=True, eq=False)
class TFMessage(Message):
    ROS_TYPE = "tf2_msgs/msg/TFMessage"
    transforms: tuple[TransformStamped, ...] = ros_field(Sequence(TransformStamped), default=())


@dataclass(frozen=True, eq=False)
class Pose(Message):
    ROS_TYPE = "geometry_msgs/msg/Pose"
    position: Point = ros_field(Point, default_factory=Point)
    orientation: Quaternion = ros_field(Quaternion, default_factory=Quaternion)


@dataclass(frozen=True, eq=False)
class PoseStamped(Message):
    ROS_TYPE = "geometry_msgs/msg/PoseStamped"
    header: Header = ros_field(Header, default_factory=Header)
    pose: Pose = ros_field(Pose, default_factory=Pose)


@dataclass(frozen=True, eq=False)
class Twist(Message):
    ROS_TYPE = "geometry_msgs/msg/Twist"
    linear: Vector3 = ros_field(Vector3, default_factory=Vector3)
    angular: Vector3 = ros_field(Vector3, default_factory=Vector3)


@dataclass(frozen=True, eq=False)
class TwistStamped(Message):
    """A velocity (MoveIt Servo's input): m/s and rad/s in the frame its header names."""
    ROS_TYPE = "geometry_msgs/msg/TwistStamped"
    header: Header = ros_field(Header, default_factory=Header)
    twist: Twist = ros_field(Twist, default_factory=Twist)


@dataclass(frozen=True, eq=False)
class Joy(Message):
    """A joystick as the ROS ``joy`` driver reports it: every axis in [-1, 1], every button 0 or 1."""
    ROS_TYPE = "sensor_msgs/msg/Joy"
    header: Header = ros_field(Header, default_factory=Header)
    axes: np.ndarray = ros_field(Sequence(FLOAT32), default_factory=_empty_float32)
    buttons: np.ndarray = ros_field(Sequence(INT32), default_factory=_empty_int32)


@dataclass(frozen=True, eq=False)
class String(Message):
    """std_msgs/String: the robot description (the URDF) is published as one."""
    ROS_TYPE = "std_msgs/msg/String"
    data: str = ros_field(STRING, default="")


@dataclass(frozen=True, eq=False)
class KeyValue(Message):
    ROS_TYPE = "diagnostic_msgs/msg/KeyValue"
    key: str = ros_field(STRING, default="")
    value: str = ros_field(STRING, default="")


@dataclass(frozen=True, eq=False)
class DiagnosticStatus(Message):
    ROS_TYPE = "diagnostic_msgs/msg/DiagnosticStatus"
    # the definition's constants (diagnostic_msgs/msg/DiagnosticStatus.msg)
    OK: ClassVar[int] = 0
    WARN: ClassVar[int] = 1
    ERROR: ClassVar[int] = 2
    STALE: ClassVar[int] = 3
    level: int = ros_field(UINT8, default=0)  # ROS ``byte``: one octet on the wire
    name: str = ros_field(STRING, default="")
    message: str = ros_field(STRING, default="")
    hardware_id: str = ros_field(STRING, default="")
    values: tuple[KeyValue, ...] = ros_field(Sequence(KeyValue), default=())


@dataclass(frozen=True, eq=False)
class DiagnosticArray(Message):
    ROS_TYPE = "diagnostic_msgs/msg/DiagnosticArray"
    header: Header = ros_field(Header, default_factory=Header)
    status: tuple[DiagnosticStatus, ...] = ros_field(Sequence(DiagnosticStatus), default=())


@dataclass(frozen=True, eq=False)
class TriggerRequest(Message):
    """std_srvs/Trigger's empty request: one placeholder byte on the wire (rosidl adds the member to every empty
    structure; fixtures/trigger_request.rclpy.cdr)."""
    ROS_TYPE = "std_srvs/srv/Trigger_Request"
    structure_needs_at_least_one_member: int = ros_field(UINT8, default=0)


@dataclass(frozen=True, eq=False)
class TriggerResponse(Message):
    ROS_TYPE = "std_srvs/srv/Trigger_Response"
    success: bool = ros_field(BOOL, default=False)
    message: str = ros_field(STRING, default="")


#: every message type of this module by its ROS 2 name
MESSAGE_TYPES: dict[str, type[Message]] = {cls.ROS_TYPE: cls for cls in (
    Time, Header, Image, RegionOfInterest, CameraInfo, JointState, Vector3, Point, Quaternion, Transform,
    TransformStamped, TFMessage, Pose, PoseStamped, Twist, TwistStamped, Joy, String, KeyValue, DiagnosticStatus,
    DiagnosticArray, TriggerRequest, TriggerResponse)}


def _fields(message_type: type[Message]):
    return [(item.name, item.metadata["cdr"]) for item in dataclasses.fields(message_type)]


def _alignment(kind) -> int:
    if isinstance(kind, _Primitive):
        return kind.size
    if kind is STRING or isinstance(kind, Sequence):
        return 4
    if isinstance(kind, FixedFloat64Array):
        return 8
    return _alignment(_fields(kind)[0][1])


def _smallest_size(kind) -> int:
    """The fewest bytes one value of ``kind`` takes (alignment aside): bounds a count before anything is made."""
    if isinstance(kind, _Primitive):
        return kind.size
    if kind is STRING:
        return 5  # its length and the NUL
    if isinstance(kind, Sequence):
        return 4
    if isinstance(kind, FixedFloat64Array):
        return 8 * kind.length
    return sum(_smallest_size(sub) for _, sub in _fields(kind))


# ---------------------------------------------------------------------------------------------------------------
# Writing

class _Writer:
    def __init__(self, padding_byte: int) -> None:
        self.buffer = bytearray(ENCAPSULATION_HEADER)
        self.padding_byte = padding_byte

    def align(self, alignment: int) -> None:
        offset = len(self.buffer) - len(ENCAPSULATION_HEADER)
        self.buffer += bytes([self.padding_byte]) * (-offset % alignment)

    def primitive(self, kind: _Primitive, value, where: str) -> None:
        self.align(kind.size)
        self.buffer += struct.pack(kind.struct_format, kind.check(value, where))

    def string(self, value, where: str) -> None:
        if not isinstance(value, str):
            raise CdrError(f"{where}: a str is needed, got {type(value).__name__}")
        encoded = value.encode("utf-8")
        if b"\x00" in encoded:
            raise CdrError(f"{where}: a CDR string ends at its first NUL; this one has one inside")
        self.primitive(UINT32, len(encoded) + 1, where)
        self.buffer += encoded + b"\x00"

    def value(self, kind, value, where: str) -> None:
        if isinstance(kind, _Primitive):
            self.primitive(kind, value, where)
        elif kind is STRING:
            self.string(value, where)
        elif isinstance(kind, FixedFloat64Array):
            array = self._floats(value, kind.length, where)
            self.align(8)
            self.buffer += array.astype("<f8", copy=False).tobytes()
        elif isinstance(kind, Sequence):
            self.sequence(kind.element, value, where)
        else:
            self.message(kind, value, where)

    def sequence(self, element, values, where: str) -> None:
        if element is UINT8:
            if not isinstance(values, (bytes, bytearray, memoryview)):
                raise CdrError(f"{where}: bytes are needed for uint8[], got {type(values).__name__}")
            self.primitive(UINT32, len(values), where)
            self.buffer += values
        elif element in _ARRAY_DTYPES:
            dtype = _ARRAY_DTYPES[element]
            array = self._floats(values, None, where, dtype)
            self.primitive(UINT32, array.shape[0], where)
            if array.shape[0]:
                self.align(element.size)
                self.buffer += array.astype(dtype, copy=False).tobytes()
        else:
            if isinstance(values, (str, bytes)) or not hasattr(values, "__len__"):
                raise CdrError(f"{where}: a sequence is needed, got {type(values).__name__}")
            self.primitive(UINT32, len(values), where)
            for index, item in enumerate(values):
                self.value(element, item, f"{where}[{index}]")

    def message(self, message_type: type[Message], message, where: str) -> None:
        if type(message) is not message_type:
            raise CdrError(f"{where}: a {message_type.__name__} is needed, got {type(message).__name__}")
        for name, kind in _fields(message_type):
            self.value(kind, getattr(message, name), f"{where}.{name}")

    @staticmethod
    def _floats(values, length: int | None, where: str, dtype="<f8") -> np.ndarray:
        try:
            return _float64_array(values, length, np.dtype(dtype).newbyteorder("="))
        except (CdrError, TypeError, ValueError) as error:
            raise CdrError(f"{where}: {error}") from None


def serialize(message: Message, *, padding_byte: int = 0) -> bytes:
    """The CDR payload of ``message``, encapsulation header first, no padding after the last field.

    ``padding_byte`` fills the alignment gaps (ROS's serializer leaves whatever its buffer held; zero is the
    spec's choice); two serializations with different fill bytes differ exactly at the padding."""
    if not isinstance(message, Message):
        raise CdrError(f"not a ROS message of this module: {type(message).__name__}")
    writer = _Writer(padding_byte)
    writer.message(type(message), message, type(message).__name__)
    return bytes(writer.buffer)


# ---------------------------------------------------------------------------------------------------------------
# Reading

class _Reader:
    def __init__(self, payload: bytes, message_type: type[Message]) -> None:
        self.data = memoryview(payload)
        self.position = len(ENCAPSULATION_HEADER)
        self.type_name = message_type.__name__

    def fail(self, where: str, problem: str) -> CdrError:
        return CdrError(f"{self.type_name} payload, {where} at byte {self.position}: {problem}")

    def align(self, alignment: int) -> None:
        offset = self.position - len(ENCAPSULATION_HEADER)
        self.position += -offset % alignment

    def take(self, size: int, where: str) -> memoryview:
        end = self.position + size
        if end > len(self.data):
            raise self.fail(where, f"truncated: {size} bytes needed, {max(0, len(self.data) - self.position)} "
                                   f"left of {len(self.data)}")
        chunk = self.data[self.position:end]
        self.position = end
        return chunk

    def primitive(self, kind: _Primitive, where: str):
        self.align(kind.size)
        (value,) = struct.unpack(kind.struct_format, self.take(kind.size, where))
        if kind is BOOL and self.data[self.position - 1] > 1:
            raise self.fail(where, f"a bool must be 0 or 1, got {self.data[self.position - 1]}")
        return value

    def count(self, element_size: int, where: str) -> int:
        """A sequence's or string's length, refused when the rest of the payload cannot hold that many."""
        count = self.primitive(UINT32, where)
        left = len(self.data) - self.position
        if count * element_size > left:
            raise self.fail(where, f"a length of {count} needs at least {count * element_size} bytes, "
                                   f"{left} are left: truncated or not this type")
        return count

    def string(self, where: str) -> str:
        length = self.count(1, where)
        if length == 0:
            raise self.fail(where, "a string length of 0: CDR counts the terminating NUL")
        raw = self.take(length, where)
        if raw[-1] != 0:
            raise self.fail(where, "a string not terminated by NUL")
        try:
            return bytes(raw[:-1]).decode("utf-8")
        except UnicodeDecodeError as error:
            raise self.fail(where, f"not UTF-8 ({error.reason})") from None

    def value(self, kind, where: str):
        if isinstance(kind, _Primitive):
            return self.primitive(kind, where)
        if kind is STRING:
            return self.string(where)
        if isinstance(kind, FixedFloat64Array):
            self.align(8)
            return self.floats(kind.length, where)
        if isinstance(kind, Sequence):
            return self.sequence(kind.element, where)
        return self.message(kind, where)

    def floats(self, count: int, where: str, dtype: str = "<f8") -> np.ndarray:
        size = np.dtype(dtype).itemsize
        chunk = self.take(size * count, where)
        return np.frombuffer(chunk, dtype=dtype, count=count)

    def sequence(self, element, where: str):
        if element is UINT8:
            return bytes(self.take(self.count(1, where), where))
        if element in _ARRAY_DTYPES:
            count = self.count(element.size, where)
            if count:
                self.align(element.size)
            return self.floats(count, where, _ARRAY_DTYPES[element])
        count = self.count(_smallest_size(element), where)
        return tuple(self.value(element, f"{where}[{index}]") for index in range(count))

    def message(self, message_type: type[Message], where: str):
        values = {name: self.value(kind, f"{where}.{name}") for name, kind in _fields(message_type)}
        return message_type(**values)


Decoded = TypeVar("Decoded", bound=Message)


def deserialize(payload: bytes, message_type: type[Decoded]) -> Decoded:
    """The ``message_type`` message a CDR payload holds (encapsulation header included, as rmw_zenoh sends it)."""
    if not (isinstance(message_type, type) and issubclass(message_type, Message)):
        raise CdrError(f"not a ROS message type of this module: {message_type!r}")
    if not isinstance(payload, (bytes, bytearray, memoryview)):
        raise CdrError(f"a CDR payload is bytes, got {type(payload).__name__}")
    header = bytes(payload[:4])
    if len(header) < 4:
        raise CdrError(f"{message_type.__name__} payload of {len(payload)} bytes: shorter than the 4-byte "
                       "encapsulation header")
    if header[:2] == _BIG_ENDIAN_ID:
        raise CdrError(f"{message_type.__name__} payload is big-endian CDR ({header.hex(' ')}): ROS 2 sends "
                       "little-endian (00 01), the only one this codec reads")
    if header[:2] != ENCAPSULATION_HEADER[:2] or header[2] != 0 or header[3] > 3:
        raise CdrError(f"{message_type.__name__} payload starts {header.hex(' ')}: not the CDR little-endian "
                       "encapsulation header 00 01 00 00 (options 00 00 to 00 03)")
    reader = _Reader(payload, message_type)
    message = reader.message(message_type, message_type.__name__)
    trailing = len(reader.data) - reader.position
    if trailing > MAX_TRAILING_PADDING:
        raise CdrError(f"{message_type.__name__} payload has {trailing} bytes after its last field (padding is "
                       f"at most {MAX_TRAILING_PADDING}): not this type, or more than one message")
    return message
