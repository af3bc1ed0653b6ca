"""The CDR codec against bytes the real ROS 2 serializer made (fixtures/, make_fixtures.py), against rosbags' codec
as a second implementation, and against payloads that are wrong in every way a network can make them."""
import dataclasses
import json
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from protocol.ros2 import cdr

FIXTURES = Path(__file__).parent / "fixtures"
SAMPLES = json.loads((FIXTURES / "fixtures.json").read_text())["samples"]


def message_from_values(message_type: type[cdr.Message], values: dict) -> cdr.Message:
    """The message the fixtures' values describe (make_fixtures.py writes them: hex for bytes, lists for arrays)."""
    fields = {}
    for item in dataclasses.fields(message_type):
        if item.name not in values:
            continue
        kind, value = item.metadata["cdr"], values[item.name]
        if isinstance(kind, type):
            value = message_from_values(kind, value)
        elif isinstance(kind, cdr.Sequence) and isinstance(kind.element, type):
            value = tuple(message_from_values(kind.element, v) for v in value)
        elif isinstance(kind, cdr.Sequence) and kind.element is cdr.UINT8:
            value = bytes.fromhex(value)
        elif isinstance(kind, cdr.Sequence) and kind.element is cdr.STRING:
            value = tuple(value)
        elif isinstance(kind, (cdr.Sequence, cdr.FixedFloat64Array)):
            value = np.array(value, dtype=np.float64)
        fields[item.name] = value
    return message_type(**fields)


def sample(name: str) -> cdr.Message:
    entry = SAMPLES[name]
    return message_from_values(cdr.MESSAGE_TYPES[entry["type"]], entry["values"])


def padding_positions(message: cdr.Message) -> set[int]:
    """Where the encoder pads: the bytes that differ between two fill bytes."""
    zeros, ones = cdr.serialize(message, padding_byte=0x00), cdr.serialize(message, padding_byte=0xFF)
    return {i for i, (a, b) in enumerate(zip(zeros, ones)) if a != b}


def assert_same_but_padding(mine: bytes, theirs: bytes, padding: set[int]) -> None:
    assert theirs[:4] == cdr.ENCAPSULATION_HEADER
    assert 0 <= len(theirs) - len(mine) <= cdr.MAX_TRAILING_PADDING, (len(mine), len(theirs))
    differing = [i for i in range(len(mine)) if mine[i] != theirs[i] and i not in padding]
    assert not differing, [(i, mine[i], theirs[i]) for i in differing]


REAL_SERIALIZER = sorted(name for name, entry in SAMPLES.items() if "rclpy" in entry)


def test_every_type_of_the_codec_has_a_fixture_made_by_ros_tooling():
    published_or_accepted = {"sensor_msgs/msg/Image", "sensor_msgs/msg/CameraInfo", "sensor_msgs/msg/JointState",
                             "tf2_msgs/msg/TFMessage", "geometry_msgs/msg/TransformStamped",
                             "geometry_msgs/msg/PoseStamped", "geometry_msgs/msg/TwistStamped",
                             "sensor_msgs/msg/Joy", "std_msgs/msg/String",
                             "diagnostic_msgs/msg/DiagnosticArray", "std_srvs/srv/Trigger_Request",
                             "std_srvs/srv/Trigger_Response", "builtin_interfaces/msg/Time", "std_msgs/msg/Header"}
    assert published_or_accepted <= {entry["type"] for entry in SAMPLES.values()}
    # only tf2_msgs has no Jazzy wheel, so only TFMessage lacks the real serializer's bytes (fixtures.json says so)
    assert {entry["type"] for entry in SAMPLES.values() if "rclpy" not in entry} == {"tf2_msgs/msg/TFMessage"}


@pytest.mark.parametrize("name", REAL_SERIALIZER)
def test_encoding_equals_the_real_serializers_bytes_padding_aside(name):
    message = sample(name)
    assert_same_but_padding(cdr.serialize(message), (FIXTURES / SAMPLES[name]["rclpy"]).read_bytes(),
                            padding_positions(message))


@pytest.mark.parametrize("name", sorted(SAMPLES))
def test_encoding_equals_rosbags_bytes(name):
    # rosbags zeroes its padding and adds none at the end: byte for byte
    assert cdr.serialize(sample(name)) == (FIXTURES / SAMPLES[name]["rosbags"]).read_bytes()


@pytest.mark.parametrize("name", REAL_SERIALIZER)
def test_decoding_the_real_serializers_bytes_gives_the_sample_back(name):
    payload = (FIXTURES / SAMPLES[name]["rclpy"]).read_bytes()
    assert cdr.deserialize(payload, type(sample(name))) == sample(name)


def test_the_fixtures_do_pad_where_the_decoder_must_tolerate_it():
    """Not a vacuous tolerance: rclpy's bytes pad after the last field and leave non-zero bytes in alignment gaps."""
    trailing = {name: len((FIXTURES / SAMPLES[name]["rclpy"]).read_bytes()) - len(cdr.serialize(sample(name)))
                for name in REAL_SERIALIZER}
    assert trailing["trigger_request"] == 3 and trailing["joint_state"] == 4
    payload = (FIXTURES / SAMPLES["trigger_response"]["rclpy"]).read_bytes()
    assert payload[5] != 0 and 5 in padding_positions(sample("trigger_response"))


def test_decoded_values_have_the_documented_python_types():
    image = cdr.deserialize((FIXTURES / SAMPLES["image_rgb8"]["rclpy"]).read_bytes(), cdr.Image)
    assert isinstance(image.data, bytes) and image.data == bytes(range(36))
    info = cdr.deserialize((FIXTURES / SAMPLES["camera_info"]["rclpy"]).read_bytes(), cdr.CameraInfo)
    assert info.k.dtype == np.float64 and info.k.shape == (9,) and info.p.shape == (12,) and info.d.shape == (5,)
    assert info.roi.do_rectify is True
    joints = cdr.deserialize((FIXTURES / SAMPLES["joint_state"]["rclpy"]).read_bytes(), cdr.JointState)
    assert joints.name[0] == "j2n6s300_joint_1" and isinstance(joints.name, tuple) and joints.effort.shape == (0,)
    text = cdr.deserialize((FIXTURES / SAMPLES["robot_description"]["rclpy"]).read_bytes(), cdr.String)
    assert "270°" in text.data
    joy = cdr.deserialize((FIXTURES / SAMPLES["joy"]["rclpy"]).read_bytes(), cdr.Joy)
    assert joy.axes.dtype == np.float32 and joy.buttons.dtype == np.int32 and joy.header.frame_id == "joy"
    assert list(joy.axes[1:4]) == [0.5, -1.0, 0.25] and list(np.flatnonzero(joy.buttons)) == [4, 7]
    assert np.signbit(joy.axes[0])  # -0.0 kept as sent
    twist = cdr.deserialize((FIXTURES / SAMPLES["twist_stamped_hand"]["rosbags"]).read_bytes(), cdr.TwistStamped)
    assert (twist.header.frame_id, twist.twist.angular.x, twist.twist.linear.z) == ("end_effector", 0.3, 0.0)


def test_messages_compare_by_value_arrays_included():
    assert cdr.JointState(position=np.array([1.0, 2.0])) == cdr.JointState(position=np.array([1.0, 2.0]))
    assert cdr.JointState(position=np.array([1.0, 2.0])) != cdr.JointState(position=np.array([1.0, 2.5]))
    assert cdr.JointState(position=np.array([1.0])) != cdr.JointState(position=np.array([1.0, 1.0]))
    assert cdr.Time(1, 2) != cdr.Time(1, 3) and cdr.Time(1, 2) != cdr.Header()


# --- round trips, and rosbags reading what this codec writes --------------------------------------------------

names = st.text(st.characters(blacklist_characters="\x00", blacklist_categories=("Cs",)), max_size=12)
floats = st.floats(allow_nan=False, width=64)
float_arrays = st.lists(floats, max_size=6).map(lambda v: np.array(v, dtype=np.float64))
times = st.builds(cdr.Time, st.integers(-2**31, 2**31 - 1), st.integers(0, 2**32 - 1))
headers = st.builds(cdr.Header, times, names)
uint32 = st.integers(0, 2**32 - 1)
images = st.builds(cdr.Image, headers, uint32, uint32, names, st.integers(0, 255), uint32, st.binary(max_size=40))
rois = st.builds(cdr.RegionOfInterest, uint32, uint32, uint32, uint32, st.booleans())
camera_infos = st.builds(
    cdr.CameraInfo, headers, uint32, uint32, names, float_arrays,
    *(st.lists(floats, min_size=n, max_size=n).map(np.array) for n in (9, 9, 12)), uint32, uint32, rois)
joint_states = st.builds(cdr.JointState, headers, st.lists(names, max_size=4).map(tuple), float_arrays,
                         float_arrays, float_arrays)
vectors = st.builds(cdr.Vector3, floats, floats, floats)
quaternions = st.builds(cdr.Quaternion, floats, floats, floats, floats)
transforms = st.builds(cdr.TransformStamped, headers, names, st.builds(cdr.Transform, vectors, quaternions))
tf_messages = st.builds(cdr.TFMessage, st.lists(transforms, max_size=3).map(tuple))
poses = st.builds(cdr.PoseStamped, headers,
                  st.builds(cdr.Pose, st.builds(cdr.Point, floats, floats, floats), quaternions))
float32s = st.floats(allow_nan=False, width=32)
joys = st.builds(cdr.Joy, headers, st.lists(float32s, max_size=9).map(lambda v: np.array(v, dtype=np.float32)),
                 st.lists(st.integers(-2**31, 2**31 - 1), max_size=13).map(lambda v: np.array(v, dtype=np.int32)))
twists = st.builds(cdr.TwistStamped, headers, st.builds(cdr.Twist, vectors, vectors))
key_values = st.builds(cdr.KeyValue, names, names)
statuses = st.builds(cdr.DiagnosticStatus, st.integers(0, 3), names, names, names,
                     st.lists(key_values, max_size=3).map(tuple))
diagnostics = st.builds(cdr.DiagnosticArray, headers, st.lists(statuses, max_size=3).map(tuple))
any_message = st.one_of(
    times, headers, images, camera_infos, joint_states, transforms, tf_messages, poses, joys, twists,
    st.builds(cdr.String, names), diagnostics, st.just(cdr.TriggerRequest()),
    st.builds(cdr.TriggerResponse, st.booleans(), names))


@given(any_message)
def test_every_message_survives_a_round_trip(message):
    assert cdr.deserialize(cdr.serialize(message), type(message)) == message


@given(any_message, st.integers(0, cdr.MAX_TRAILING_PADDING), st.integers(0, 255))
def test_decoding_tolerates_padding_after_the_last_field(message, count, fill):
    assert cdr.deserialize(cdr.serialize(message) + bytes([fill]) * count, type(message)) == message


ROSBAGS = get_typestore(Stores.ROS2_JAZZY)
ROSBAGS.register({**get_types_from_msg("uint8 structure_needs_at_least_one_member", "std_srvs/msg/Trigger_Request"),
                  **get_types_from_msg("bool success\nstring message", "std_srvs/msg/Trigger_Response")})


def as_plain(value):
    """A message of either codec as nested plain values, for comparing the two."""
    if dataclasses.is_dataclass(value):  # either codec's message (rosbags' also list __msgtype__ and constants)
        return {item.name: as_plain(getattr(value, item.name)) for item in dataclasses.fields(value)
                if item.name not in ("structure_needs_at_least_one_member", "__msgtype__") and not item.name.isupper()}
    if isinstance(value, np.ndarray):
        return bytes(value.astype(np.uint8)) if value.dtype == np.uint8 else [float(v) for v in value]
    if isinstance(value, (tuple, list)):
        return [as_plain(v) for v in value]
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    return value


@settings(max_examples=60)
@given(any_message)
def test_rosbags_reads_what_this_codec_writes(message):
    ros_type = message.ROS_TYPE.replace("/srv/", "/msg/")
    theirs = ROSBAGS.deserialize_cdr(cdr.serialize(message), ros_type)
    assert as_plain(theirs) == as_plain(message)
    assert ROSBAGS.serialize_cdr(theirs, ros_type) == cdr.serialize(message)


# --- what must be refused ----------------------------------------------------------------------------------------

@pytest.mark.parametrize("name", sorted(SAMPLES))
def test_every_truncation_is_refused_with_a_clear_error(name):
    message = sample(name)
    payload = cdr.serialize(message)
    for end in range(len(payload)):
        with pytest.raises(cdr.CdrError, match=type(message).__name__):
            cdr.deserialize(payload[:end], type(message))


def test_wrong_encapsulation_headers_are_refused():
    payload = cdr.serialize(sample("header"))
    with pytest.raises(cdr.CdrError, match="big-endian"):
        cdr.deserialize(b"\x00\x00" + payload[2:], cdr.Header)
    for header in (b"\x00\x07\x00\x00", b"\x01\x01\x00\x00", b"\x00\x01\x01\x00", b"\x00\x01\x00\x04"):
        with pytest.raises(cdr.CdrError, match="encapsulation header"):
            cdr.deserialize(header + payload[4:], cdr.Header)
    with pytest.raises(cdr.CdrError, match="shorter than the 4-byte"):
        cdr.deserialize(b"\x00\x01", cdr.Header)
    # the options' padding count (XTypes: its two low bits) is accepted
    assert cdr.deserialize(b"\x00\x01\x00\x03" + payload[4:], cdr.Header) == sample("header")


def test_absurd_lengths_are_refused_before_anything_is_allocated():
    header = cdr.ENCAPSULATION_HEADER
    cases = [
        (cdr.String, header + (2**32 - 1).to_bytes(4, "little") + b"abc"),
        (cdr.Image, cdr.serialize(cdr.Image())[:-4] + (2**32 - 1).to_bytes(4, "little")),
        (cdr.JointState, header + bytes(8) + (1).to_bytes(4, "little") + bytes(4) + bytes(4)  # stamp, "", no names
         + (2**31).to_bytes(4, "little") + bytes(12)),  # two billion positions in 12 bytes
        (cdr.TFMessage, header + (2**32 - 1).to_bytes(4, "little") + bytes(64)),
        (cdr.DiagnosticArray, cdr.serialize(cdr.DiagnosticArray())[:-4] + (10**9).to_bytes(4, "little")),
    ]
    for message_type, payload in cases:
        started = time.perf_counter()
        with pytest.raises(cdr.CdrError, match="needs at least"):
            cdr.deserialize(payload, message_type)
        assert time.perf_counter() - started < 0.1


def test_more_than_padding_after_the_last_field_is_refused():
    payload = cdr.serialize(cdr.String("x"))
    with pytest.raises(cdr.CdrError, match="8 bytes after its last field"):
        cdr.deserialize(payload + bytes(8), cdr.String)
    # the classic confusion: a JointState read as a Header leaves most of it unread
    with pytest.raises(cdr.CdrError, match="after its last field"):
        cdr.deserialize((FIXTURES / SAMPLES["joint_state"]["rclpy"]).read_bytes(), cdr.Header)


def test_malformed_strings_and_bools_are_refused():
    header = cdr.ENCAPSULATION_HEADER
    with pytest.raises(cdr.CdrError, match="not terminated by NUL"):
        cdr.deserialize(header + (2).to_bytes(4, "little") + b"ab", cdr.String)
    with pytest.raises(cdr.CdrError, match="length of 0"):
        cdr.deserialize(header + bytes(4), cdr.String)
    with pytest.raises(cdr.CdrError, match="not UTF-8"):
        cdr.deserialize(header + (3).to_bytes(4, "little") + b"\xff\xfe\x00", cdr.String)
    with pytest.raises(cdr.CdrError, match="bool must be 0 or 1"):
        cdr.deserialize(header + b"\x02" + bytes(3) + (1).to_bytes(4, "little") + b"\x00", cdr.TriggerResponse)


@given(st.binary(max_size=200), st.sampled_from(sorted(cdr.MESSAGE_TYPES.values(), key=lambda t: t.ROS_TYPE)))
def test_arbitrary_bytes_decode_or_raise_cdr_error_nothing_else(garbage, message_type):
    try:
        cdr.deserialize(cdr.ENCAPSULATION_HEADER + garbage, message_type)
    except cdr.CdrError:
        pass


def test_values_that_cannot_be_encoded_are_refused_by_name():
    bad = [
        (cdr.Time(sec=2**31), "Time.sec"),
        (cdr.Time(nanosec=-1), "Time.nanosec"),
        (cdr.Image(is_bigendian=256), "Image.is_bigendian"),
        (cdr.Image(data=[1, 2]), "Image.data"),
        (cdr.String("a\x00b"), "String.data"),
        (cdr.String(b"bytes"), "String.data"),
        (cdr.CameraInfo(k=np.zeros(8)), "CameraInfo.k"),
        (cdr.JointState(position=np.zeros((2, 2))), "JointState.position"),
        (cdr.JointState(name="joint_1"), "JointState.name"),
        (cdr.TFMessage(transforms=(cdr.Transform(),)), "TFMessage.transforms[0]"),
        (cdr.TriggerResponse(success=1), "TriggerResponse.success"),
        (cdr.Vector3(x="1"), "Vector3.x"),
        (cdr.Joy(axes=[1e39]), "Joy.axes"),
        (cdr.Joy(buttons=[2**31]), "Joy.buttons"),
        (cdr.Joy(buttons=[0.5]), "Joy.buttons"),
        (cdr.Joy(axes=["a"]), "Joy.axes"),
        (cdr.TwistStamped(twist=cdr.Vector3()), "TwistStamped.twist"),
    ]
    for message, where in bad:
        with pytest.raises(cdr.CdrError, match=where.replace(".", r"\.").replace("[", r"\[").replace("]", r"\]")):
            cdr.serialize(message)
    with pytest.raises(cdr.CdrError, match="not a ROS message"):
        cdr.serialize({"data": "x"})
