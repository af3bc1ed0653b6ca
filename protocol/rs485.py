"""The JACO-2 low-level RS-485 message: 20 bytes, little-endian, as the SDK's ``RS485_Message`` lays it out.

    int16 Command; uint8 SourceAddress; uint8 DestinationAddress; 16 data bytes
    (viewed as uint8[16], float32[4] or uint32[4])

Command IDs and payload layouts follow ``shared/reference/kinova.md`` (SDK header and a third-party torque
driver). Decoding is strict: a frame of the wrong length or with an unknown command ID raises
:class:`RS485Error`, so a garbled frame never reaches an actuator model or the arm.
"""
from __future__ import annotations

import enum
import math
import struct
from dataclasses import dataclass

import numpy as np

MESSAGE_SIZE = 20
DATA_SIZE = 16
#: Up to this many messages travel in one 64-byte USB packet; batches hold up to 50.
MESSAGES_PER_USB_PACKET = 3
MAX_BATCH = 50

_HEADER = struct.Struct("<hBB")
_FRAME = struct.Struct("<hBB16s")
_FLOATS = struct.Struct("<4f")
_UINTS = struct.Struct("<4I")
_TORQUE_CMD = struct.Struct("<fIfI")
_POSITION_CMD = struct.Struct("<2f2I")
#: 0x14's uint32[2] in position mode: 1 asks for the extended answer, 0x15, 0x16 and 0x17 (Kinova's RS-485 example);
#: libkinova sends 0 to a single actuator and expects two replies
EXTENDED_ANSWER = 1
#: 0x14's torque-mode gain word: Kp ×1000 as a u16 and the damping (abr/abr_jaco2 sends Kp 1000-1750 with damping
#: 0 to a 6-DoF arm; what the gain scales is not public): 1000, the least it sends, and no damping: our choice
TORQUE_KP = 1000
TORQUE_DAMPING = 0


class RS485Error(ValueError):
    """A frame or payload that is not a valid RS-485 message."""


class Command(enum.IntEnum):
    SET_ADDRESS = 0x00
    GET_ACTUAL_POSITION = 0x01
    SEND_ACTUAL_POSITION = 0x02
    START_SERVO = 0x03
    STOP_SERVO = 0x04
    #: host → a finger actuator (0x16-0x18): float[0] = float[1] = the finger's target in Kinova's finger units
    #: (abr/abr_jaco2's jaco2_rs485.cpp sends them so); Kinova's header: "position command"
    GET_POSITION_COMMAND = 0x10
    #: its reply, Kinova's header: "actual position and current consumption"; the float layout is not public: mfvs
    #: gives it 0x02's (float[0] current A, float[1] position in finger units, float[2] velocity in units/s,
    #: float[3] 0), where abr_jaco2 reads a joint's position
    SEND_POSITION_CURRENT = 0x11
    #: the PID bypass (Kinova's header): float[0] = float[1] = the value, -1..1, with Kp, Ki, Kd set to 0 first
    FEEDTHROUGH = 0x09
    #: host → actuator: position and torque command; the actuator answers 0x15, 0x16 and 0x17
    POSITION_AND_TORQUE_COMMAND = 0x14
    SEND_ALL_VALUES_1 = 0x15
    SEND_ALL_VALUES_2 = 0x16
    SEND_ALL_VALUES_3 = 0x17
    POSITION_MAX_MIN = 0x21
    #: farmange/libkinova's (a stand-alone actuator's)
    SPEED_ACCEL_MAX = 0x22
    CURRENT_TORQUE_MAX = 0x23
    KP_GAIN = 0x24
    KI_KD_GAIN = 0x25
    PROGRAM_JOINT_ZERO = 0x26
    GET_CODE_VERSION = 0x27
    SEND_CODE_VERSION = 0x28
    GET_DEVICE_INFO = 0x29
    SEND_DEVICE_INFO = 0x2A
    GET_TEMPERATURE = 0x2E
    SEND_TEMPERATURE = 0x2F
    REPORT_ERROR = 0x30
    CLEAR_FAULT_FLAG = 0x33
    # in Kinova's header, never sent by mfvs: known so that a real actuator's use of them is not garbage to the codec
    SET_PID_FILTERS = 0x40
    SET_ZERO_TORQUESENSOR = 0x41
    SET_GAIN_TORQUESENSOR = 0x42
    SET_CONTROL_WITH_ENCODER = 0x43
    GET_ENCODER_STATUSES = 0x44
    SET_PID_ADVANCED_PARAMETERS = 0x45
    NACK = 0x3E
    ACK = 0x3F
    #: a variant of 0x14 with fewer replies
    POSITION_AND_TORQUE_COMMAND_REDUCED = 0x200
    GET_TORQUE_VALIDATION_REQUEST = 0x201
    SEND_TORQUE_VALIDATION = 0x202
    SWITCH_CONTROL_MODE_REQUEST = 0x203
    SWITCH_CONTROL_MODE_REPLY = 0x204
    TORQUE_CONFIG_SAFETY = 0x208
    TORQUE_CONFIG_FILTERS = 0x209
    TORQUE_CONFIG_CONTROL_LIMITS = 0x212
    TORQUE_CONFIG_FEEDFORWARD = 0x213
    TORQUE_CONFIG_CONTROL_PARAMS_1 = 0x214
    TORQUE_CONFIG_CONTROL_PARAMS_2 = 0x215


#: where a 0x02 SEND_ACTUAL_POSITION reply (and a 0x15 SEND_ALL_VALUES_1) puts each value among its four floats:
#: float[0] the motor current (A), float[1] the position (deg), float[2] the velocity (deg/s), float[3] the torque
#: (N·m). Kinova's RS-485 examples, abr/abr_jaco2, abr/abr_control, sammy-tri/drake-jaco-driver and
#: farmange/libkinova all read a 0x02's position from float[1]
CURRENT_FLOAT, POSITION_FLOAT, VELOCITY_FLOAT, TORQUE_FLOAT = 0, 1, 2, 3

HOST_ADDRESS = 0x00
#: The actuators' addresses are the arm's (its description's ``bus_addresses``: joints 1-6 at 0x10-0x15; the 7-DoF
#: arm's seventh is not documented publicly, one driver addresses 0x19, which mfvs follows).


class ControlModeRequest(enum.IntEnum):
    POSITION = 0
    TORQUE = 1


class ControlModeReply(enum.IntEnum):
    REFUSED = 0
    POSITION_OK = 1
    TORQUE_OK = 257


class ActuatorError(enum.IntEnum):
    """REPORT_ERROR uint32[1]."""

    NONE = 0
    TEMPERATURE_1 = 1
    TEMPERATURE_2 = 2
    VELOCITY = 3
    POSITION_LIMIT = 4
    ABSOLUTE_POSITION = 5
    RELATIVE_POSITION = 6
    COMMAND = 7
    CURRENT = 8
    TORQUE = 9


@dataclass(frozen=True)
class RS485Message:
    command: Command
    source: int
    destination: int
    data: bytes = bytes(DATA_SIZE)

    def __post_init__(self) -> None:
        if not isinstance(self.command, Command):
            try:
                object.__setattr__(self, "command", Command(self.command))
            except ValueError:
                raise RS485Error(f"unknown command id {self.command!r}") from None
        for name in ("source", "destination"):
            value = getattr(self, name)
            if not isinstance(value, int) or not 0 <= value <= 0xFF:
                raise RS485Error(f"{name} address must be 0..255, got {value!r}")
        if len(self.data) != DATA_SIZE:
            raise RS485Error(f"data must be {DATA_SIZE} bytes, got {len(self.data)}")

    # ---- the three views of the data union
    @property
    def floats(self) -> tuple[float, float, float, float]:
        return _FLOATS.unpack(self.data)

    @property
    def uints(self) -> tuple[int, int, int, int]:
        return _UINTS.unpack(self.data)

    @classmethod
    def with_floats(cls, command: Command, source: int, destination: int, values) -> "RS485Message":
        values = [float(v) for v in values] + [0.0] * (4 - len(values))
        if len(values) != 4:
            raise RS485Error("at most 4 float32 values fit in one message")
        return cls(command, source, destination, _FLOATS.pack(*values))

    @classmethod
    def with_uints(cls, command: Command, source: int, destination: int, values) -> "RS485Message":
        values = [int(v) for v in values] + [0] * (4 - len(values))
        if len(values) != 4 or any(not 0 <= v <= 0xFFFFFFFF for v in values):
            raise RS485Error("at most 4 uint32 values (0..2^32-1) fit in one message")
        return cls(command, source, destination, _UINTS.pack(*values))

    # ---- codec
    def encode(self) -> bytes:
        return _FRAME.pack(int(self.command), self.source, self.destination, self.data)

    @classmethod
    def decode(cls, frame: bytes | bytearray | memoryview) -> "RS485Message":
        frame = bytes(frame)
        if len(frame) != MESSAGE_SIZE:
            raise RS485Error(f"an RS-485 message is {MESSAGE_SIZE} bytes, got {len(frame)}")
        command, source, destination, data = _FRAME.unpack(frame)
        try:
            command = Command(command)
        except ValueError:
            raise RS485Error(f"unknown command id 0x{command & 0xFFFF:X}") from None
        return cls(command, source, destination, data)


#: A batch of messages as one array (what OpenRS485_Write/Read exchange: 20 bytes each, little-endian): the data
#: union as float32[4]; its uint32 and int16 views are ``batch["data"].view("<u4")`` and ``.view("<i2")``.
MESSAGE_DTYPE = np.dtype([("command", "<i2"), ("source", "u1"), ("destination", "u1"), ("data", "<f4", (4,))])
assert MESSAGE_DTYPE.itemsize == MESSAGE_SIZE
_KNOWN_COMMANDS = np.zeros(1 << 16, dtype=bool)  # indexed by the command id's 16 bits
_KNOWN_COMMANDS[[c.value for c in Command]] = True


def records(count: int) -> np.ndarray:
    return np.zeros(count, dtype=MESSAGE_DTYPE)


def to_records(messages) -> np.ndarray:
    """Messages as a batch array."""
    payload = b"".join(m.encode() for m in messages)
    return np.frombuffer(payload, dtype=MESSAGE_DTYPE).copy()


def from_records(batch: np.ndarray) -> list[RS485Message]:
    """A batch array as messages (validated one by one: an unknown command raises :class:`RS485Error`)."""
    raw = batch.tobytes()
    return [RS485Message.decode(raw[i : i + MESSAGE_SIZE]) for i in range(0, len(raw), MESSAGE_SIZE)]


def known_commands(batch: np.ndarray) -> np.ndarray:
    """Which records of a batch carry a command id this codec knows (the others are garbage to refuse)."""
    return _KNOWN_COMMANDS[batch["command"].view(np.uint16)]


def position_torque_records(destinations, positions_deg, torques_nm=None, source: int = HOST_ADDRESS,
                            kp: int = TORQUE_KP, damping: int = TORQUE_DAMPING) -> np.ndarray:
    """A batch of 0x14, one per destination, in :class:`PositionTorqueCommand`'s layouts: position mode when
    ``torques_nm`` is None (float[0] = float[1] = the target, the extended-answer flag), torque mode otherwise
    (float[0] the safety reference, float[2] the torque, the Kp/mode/damping word)."""
    positions = np.asarray(positions_deg, dtype=np.float64)
    torque_mode = torques_nm is not None
    torques = np.asarray(torques_nm if torque_mode else np.zeros(len(positions)), dtype=np.float64)
    if not (np.all(np.isfinite(positions)) and np.all(np.isfinite(torques))):
        raise RS485Error("non-finite position or torque in a command batch")
    batch = records(len(positions))
    batch["command"] = Command.POSITION_AND_TORQUE_COMMAND
    batch["source"] = source
    batch["destination"] = destinations
    batch["data"][:, 0] = positions
    words = batch["data"].view("<u4")
    if torque_mode:
        batch["data"][:, 2] = torques
        words[:, 3] = torque_word(kp, damping)
    else:
        batch["data"][:, 1] = positions
        words[:, 2] = EXTENDED_ANSWER
    return batch


def torque_word(kp: int, damping: int, mode: int = 1) -> int:
    """0x14's uint32[3] in torque mode: (Kp:u16 << 16) | (mode:u8 << 8) | damping:u8 (abr/abr_jaco2)."""
    if not (0 <= kp <= 0xFFFF and 0 <= mode <= 0xFF and 0 <= damping <= 0xFF):
        raise RS485Error("kp must fit u16, mode and damping u8")
    return (kp << 16) | (mode << 8) | damping


def command_targets(batch: np.ndarray, torque_mode: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """What a batch of 0x14 asks of actuators in the given modes (one flag per record): the position (deg), the
    torque (N·m: float[2] in torque mode; in position mode those bytes are the extended-answer flag, no torque)
    and whether the record is valid (finite, and in position mode float[1] equal to float[0]: the SDK's header
    asks both halves to agree before a command is accepted; what a real actuator does otherwise is not public)."""
    data = batch["data"].astype(np.float64)
    position = data[:, 0]
    torque = np.where(torque_mode, data[:, 2], 0.0)
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(position) & np.isfinite(torque) & (torque_mode | (data[:, 1] == position))
    return position, torque, valid


def encode_batch(messages) -> bytes:
    messages = list(messages)
    if len(messages) > MAX_BATCH:
        raise RS485Error(f"a batch holds at most {MAX_BATCH} messages, got {len(messages)}")
    return b"".join(m.encode() for m in messages)


def decode_batch(payload: bytes) -> list[RS485Message]:
    if len(payload) % MESSAGE_SIZE:
        raise RS485Error(f"a batch is a multiple of {MESSAGE_SIZE} bytes, got {len(payload)}")
    count = len(payload) // MESSAGE_SIZE
    if count > MAX_BATCH:
        raise RS485Error(f"a batch holds at most {MAX_BATCH} messages, got {count}")
    return [RS485Message.decode(payload[i : i + MESSAGE_SIZE]) for i in range(0, len(payload), MESSAGE_SIZE)]


# --------------------------------------------------------------------------------------------------- payloads


def _finite(*values: float) -> None:
    if not all(math.isfinite(v) for v in values):
        raise RS485Error(f"non-finite value in {values}")


@dataclass(frozen=True)
class PositionTorqueCommand:
    """0x14, in the two layouts the public drivers use (docs/rs485-sources.md):

    * position mode (``mode`` 0): float[0] = float[1] = the target (deg; Kinova's RS-485 examples, abr/abr_jaco2,
      drake-jaco-driver, libkinova), uint32[2] = 1, the "extended answer" flag (Kinova's example: 0x15, 0x16 and
      0x17 back), uint32[3] = 0; no torque;
    * torque mode (``mode`` 1): float[0] the joint's current position (the actuator's safety reference),
      uint32[1] = 0, float[2] the torque (N·m), uint32[3] = (Kp:u16 << 16) | (mode:u8 << 8) | damping:u8
      (abr/abr_jaco2)."""

    position_deg: float
    torque_nm: float = 0.0
    kp: int = 0
    mode: int = 0
    damping: int = 0

    def to_message(self, destination: int, source: int = HOST_ADDRESS) -> RS485Message:
        _finite(self.position_deg, self.torque_nm)
        if self.mode == 0:
            if self.torque_nm != 0.0 or self.kp or self.damping:
                raise RS485Error("a position-mode 0x14 carries no torque, Kp or damping (its float[2] is the "
                                 "extended-answer flag)")
            data = _POSITION_CMD.pack(self.position_deg, self.position_deg, EXTENDED_ANSWER, 0)
        else:
            data = _TORQUE_CMD.pack(self.position_deg, 0, self.torque_nm, torque_word(self.kp, self.damping,
                                                                                      self.mode))
        return RS485Message(Command.POSITION_AND_TORQUE_COMMAND, source, destination, data)

    @classmethod
    def from_message(cls, message: RS485Message) -> "PositionTorqueCommand":
        if message.command not in (Command.POSITION_AND_TORQUE_COMMAND, Command.POSITION_AND_TORQUE_COMMAND_REDUCED):
            raise RS485Error(f"not a position-and-torque command: {message.command.name}")
        word = message.uints[3]
        mode = (word >> 8) & 0xFF
        if mode == 0:
            position, half, _, _ = _POSITION_CMD.unpack(message.data)
            _finite(position, half)
            if half != position:
                raise RS485Error(f"a position-mode 0x14 with two different targets ({position}, {half})")
            return cls(position)
        position, _, torque, _ = _TORQUE_CMD.unpack(message.data)
        _finite(position, torque)
        return cls(position, torque, word >> 16, mode, word & 0xFF)


@dataclass(frozen=True)
class AllValues1:
    """0x15 reply: current (A), position (deg), velocity (deg/s), torque (N·m)."""

    current_a: float
    position_deg: float
    velocity_dps: float
    torque_nm: float

    def to_message(self, source: int, destination: int = HOST_ADDRESS) -> RS485Message:
        _finite(self.current_a, self.position_deg, self.velocity_dps, self.torque_nm)
        return RS485Message.with_floats(
            Command.SEND_ALL_VALUES_1, source, destination,
            (self.current_a, self.position_deg, self.velocity_dps, self.torque_nm),
        )

    @classmethod
    def from_message(cls, message: RS485Message) -> "AllValues1":
        if message.command is not Command.SEND_ALL_VALUES_1:
            raise RS485Error(f"not an all-values-1 reply: {message.command.name}")
        values = message.floats
        _finite(*values)
        return cls(*values)


_ALL_VALUES_2 = struct.Struct("<2f4h")
#: where a 0x16 keeps its int16 values among its eight: accelerations x, y, z (×0.001), temperature (×0.01 °C)
ACCEL_SHORTS, TEMPERATURE_SHORT = slice(4, 7), 7


@dataclass(frozen=True)
class AllValues2:
    """0x16 reply: float[0] the motor's PWM, float[1] the position (deg, optical encoder), then int16 accelerations
    x, y, z (×0.001) and the temperature (×0.01 °C, signed) in bytes 8-15: Kinova's RS-485 example
    (``accelX = DataLong[2] & 0xFFFF`` ... ``temperature = (short)(DataLong[3] >> 16)``), abr_jaco2's first
    version, libkinova (``DataShort[4..7]``); drake-jaco-driver reads the temperature unsigned (docs/rs485-sources.md).
    """

    pwm: float
    position_deg: float
    accel_g: tuple[float, float, float]
    temperature_c: float

    def to_message(self, source: int, destination: int = HOST_ADDRESS) -> RS485Message:
        _finite(self.pwm, self.position_deg, *self.accel_g, self.temperature_c)
        ints = [round(a / 0.001) for a in self.accel_g] + [round(self.temperature_c / 0.01)]
        if any(not -32768 <= v <= 32767 for v in ints):
            raise RS485Error(f"value out of int16 range after scaling: {ints}")
        return RS485Message(Command.SEND_ALL_VALUES_2, source, destination,
                            _ALL_VALUES_2.pack(self.pwm, self.position_deg, *ints))

    @classmethod
    def from_message(cls, message: RS485Message) -> "AllValues2":
        if message.command is not Command.SEND_ALL_VALUES_2:
            raise RS485Error(f"not an all-values-2 reply: {message.command.name}")
        pwm, position, ax, ay, az, temp = _ALL_VALUES_2.unpack(message.data)
        _finite(pwm, position)
        return cls(pwm, position, (ax * 0.001, ay * 0.001, az * 0.001), temp * 0.01)


@dataclass(frozen=True)
class AllValues3:
    """0x17 reply: float[0] the motor current (A), float[1] the absolute (magnetic) position (deg): Kinova's RS-485
    example, abr_jaco2's first version, drake-jaco-driver. No public source says what floats 2 and 3 hold: mfvs
    sends 0 there and reads nothing from them (no mode, no fault: the host knows the mode from its 0x204 replies
    and the faults from 0x30 reports)."""

    current_a: float
    absolute_position_deg: float

    def to_message(self, source: int, destination: int = HOST_ADDRESS) -> RS485Message:
        _finite(self.current_a, self.absolute_position_deg)
        return RS485Message.with_floats(Command.SEND_ALL_VALUES_3, source, destination,
                                        (self.current_a, self.absolute_position_deg))

    @classmethod
    def from_message(cls, message: RS485Message) -> "AllValues3":
        if message.command is not Command.SEND_ALL_VALUES_3:
            raise RS485Error(f"not an all-values-3 reply: {message.command.name}")
        current, position, _, _ = message.floats
        _finite(current, position)
        return cls(current, position)


def switch_mode_request(mode: ControlModeRequest, destination: int, source: int = HOST_ADDRESS) -> RS485Message:
    return RS485Message.with_uints(Command.SWITCH_CONTROL_MODE_REQUEST, source, destination, [int(mode)])


def switch_mode_reply(reply: ControlModeReply, source: int, destination: int = HOST_ADDRESS) -> RS485Message:
    return RS485Message.with_uints(Command.SWITCH_CONTROL_MODE_REPLY, source, destination, [int(reply)])


def parse_switch_mode_reply(message: RS485Message) -> ControlModeReply:
    if message.command is not Command.SWITCH_CONTROL_MODE_REPLY:
        raise RS485Error(f"not a switch-mode reply: {message.command.name}")
    try:
        return ControlModeReply(message.uints[0])
    except ValueError:
        raise RS485Error(f"unknown switch-mode reply value {message.uints[0]}") from None


def ack(command: Command, source: int, destination: int = HOST_ADDRESS) -> RS485Message:
    """0x3F acknowledging ``command`` (uint32[0], where drake-jaco-driver reads "the command code in ACK")."""
    return RS485Message.with_uints(Command.ACK, source, destination, [int(command)])


def torque_config_safety(max_torque_nm: float, destination: int, source: int = HOST_ADDRESS) -> RS485Message:
    """0x208, the torque safety configuration as abr/abr_jaco2 sends it before torque mode: float[0] the most torque
    the actuator may give (N·m), float[1] the fraction of its top speed past which it reports an error (1: off)."""
    _finite(max_torque_nm)
    return RS485Message.with_floats(Command.TORQUE_CONFIG_SAFETY, source, destination, [max_torque_nm, 1.0])


def report_error(error: ActuatorError, source: int, destination: int = HOST_ADDRESS) -> RS485Message:
    return RS485Message.with_uints(Command.REPORT_ERROR, source, destination, [0, int(error)])


def parse_report_error(message: RS485Message) -> ActuatorError:
    if message.command is not Command.REPORT_ERROR:
        raise RS485Error(f"not an error report: {message.command.name}")
    try:
        return ActuatorError(message.uints[1])
    except ValueError:
        raise RS485Error(f"unknown actuator error code {message.uints[1]}") from None
