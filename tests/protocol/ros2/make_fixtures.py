"""Write the golden fixtures of tests/protocol/ros2 with real ROS 2 tooling, never with mfvs's own code.

The bytes come from the ROS 2 Jazzy client library (``rclpy.serialization.serialize_message``: rosidl's Fast-CDR
type support, the serializer rmw_zenoh_cpp's type support is built on), the type hashes from the type descriptions
the Jazzy interface packages ship (``share/<pkg>/msg/<Name>.json``, written by rosidl_generator_type_description,
the values rosidl compiles into the type support), and, as a second and independent check, both again from
``rosbags`` (pure Python, its own CDR serializer and REP-2011 hasher, with type stores for Jazzy, Kilted and
Lyrical). ``tf2_msgs`` has no Jazzy wheel on PyPI, so TFMessage's bytes and hash come from rosbags alone, and the
fixtures say so. The GIDs are XXH3-128 of liveliness tokens by the ``xxhash`` package (the reference C library's
binding), the hash rmw_zenoh_cpp takes of an entity's token (its simplified_xxhash3.cpp).

Run it in an environment of its own, outside the project's (the ROS wheels pin their own numpy and want Python
3.12, the Jazzy release's)::

    ~/.pyenv/versions/3.12.1/bin/python -m venv /tmp/ros-venv
    /tmp/ros-venv/bin/pip install rosbags xxhash 'ros-jazzy-rclpy[fastrtps]' ros-jazzy-sensor-msgs \
        ros-jazzy-std-msgs ros-jazzy-geometry-msgs ros-jazzy-diagnostic-msgs ros-jazzy-std-srvs \
        ros-jazzy-builtin-interfaces
    cd <repository> && /tmp/ros-venv/bin/python tests/protocol/ros2/make_fixtures.py

It writes ``fixtures/<sample>.rclpy.cdr`` and ``fixtures/<sample>.rosbags.cdr`` (the serialized bytes, the 4-byte
encapsulation header included) and ``fixtures/fixtures.json``: each sample's values (the same values the tests build
their messages from), the files, the type hashes from each source, and the GIDs. Versions used for the committed
fixtures: ros-jazzy-rclpy 7.1.6, the message packages 5.3.6 (builtin_interfaces 2.0.3), rosbags 0.11.9,
xxhash 4.1.0. A second run rewrites some ``*.rclpy.cdr`` files with other bytes in the same places: the serializer
leaves whatever its buffer held in alignment gaps, which is why the tests compare those files padding aside.
"""
from __future__ import annotations

import importlib.metadata
import json
import sys
from pathlib import Path

import numpy as np
import xxhash
from rclpy.serialization import serialize_message
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

import builtin_interfaces.msg as builtin
import diagnostic_msgs.msg as diagnostic
import geometry_msgs.msg as geometry
import sensor_msgs.msg as sensor
import std_msgs.msg as std
import std_srvs.srv as std_srvs

FIXTURES = Path(__file__).resolve().parent / "fixtures"
SHARE = Path(sys.prefix) / "share"

STAMP = {"sec": 1767225600, "nanosec": 123456789}
CAMERA_HEADER = {"stamp": STAMP, "frame_id": "camera_optical"}
BASE_HEADER = {"stamp": {"sec": 1767225601, "nanosec": 5}, "frame_id": "base_link"}
TRANSFORM = {"translation": {"x": 0.125, "y": -0.25, "z": 0.5},
             "rotation": {"x": 0.0, "y": 0.7071067811865476, "z": 0.0, "w": 0.7071067811865476}}

#: sample name -> (ROS type, the values, as the message's fields nest); bytes fields as hex, ``byte`` as an int.
#: Chosen to cross the serializer's corners: odd string lengths before 4- and 8-byte fields, empty sequences and
#: strings, a non-ASCII character, the empty request (one placeholder byte), fixed and unbounded float64 arrays.
SAMPLES = {
    "time": ("builtin_interfaces/msg/Time", STAMP),
    "header": ("std_msgs/msg/Header", CAMERA_HEADER),
    "header_empty_frame": ("std_msgs/msg/Header", {"stamp": {"sec": -1, "nanosec": 999999999}, "frame_id": ""}),
    "image_rgb8": ("sensor_msgs/msg/Image", {
        "header": CAMERA_HEADER, "height": 3, "width": 4, "encoding": "rgb8", "is_bigendian": 0, "step": 12,
        "data": bytes(range(36)).hex()}),
    "image_mono16_odd": ("sensor_msgs/msg/Image", {
        "header": {"stamp": STAMP, "frame_id": "cam"}, "height": 1, "width": 5, "encoding": "mono16",
        "is_bigendian": 0, "step": 10, "data": bytes(range(250, 255)).hex() + "0102030405"}),
    "camera_info": ("sensor_msgs/msg/CameraInfo", {
        "header": CAMERA_HEADER, "height": 480, "width": 640, "distortion_model": "plumb_bob",
        "d": [0.1, -0.25, 0.001, -0.002, 0.05],
        "k": [615.5, 0.0, 320.25, 0.0, 616.0, 240.75, 0.0, 0.0, 1.0],
        "r": [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        "p": [615.5, 0.0, 320.25, 0.0, 0.0, 616.0, 240.75, 0.0, 0.0, 0.0, 1.0, 0.0],
        "binning_x": 0, "binning_y": 2,
        "roi": {"x_offset": 10, "y_offset": 20, "height": 100, "width": 200, "do_rectify": True}}),
    "joint_state": ("sensor_msgs/msg/JointState", {
        "header": BASE_HEADER, "name": [f"j2n6s300_joint_{i}" for i in range(1, 7)] + ["finger"],
        "position": [4.71, 2.84, 0.0, 0.75, 4.62, 4.48, 0.1], "velocity": [0.0, -0.5, 0.25, 0.0, 0.0, 1e-9, 0.0],
        "effort": []}),
    "transform_stamped": ("geometry_msgs/msg/TransformStamped", {
        "header": BASE_HEADER, "child_frame_id": "end_effector", "transform": TRANSFORM}),
    "tf_message": ("tf2_msgs/msg/TFMessage", {"transforms": [
        {"header": BASE_HEADER, "child_frame_id": "end_effector", "transform": TRANSFORM},
        {"header": {"stamp": STAMP, "frame_id": "end_effector"}, "child_frame_id": "camera_optical",
         "transform": {"translation": {"x": 0.0, "y": 0.05, "z": -0.1},
                       "rotation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}}}]}),
    "tf_message_empty": ("tf2_msgs/msg/TFMessage", {"transforms": []}),
    "pose_stamped": ("geometry_msgs/msg/PoseStamped", {
        "header": {"stamp": STAMP, "frame_id": "tag36h11_0"},
        "pose": {"position": {"x": 0.0, "y": 0.0, "z": 0.3},
                 "orientation": {"x": 1.0, "y": 0.0, "z": 0.0, "w": 0.0}}}),
    # a stick as the ROS joy driver sends one (its frame_id "joy", joy.cpp), an odd count of axes before the
    # buttons; and one a driver sends while no device is open (empty axes and buttons)
    "joy": ("sensor_msgs/msg/Joy", {
        "header": {"stamp": STAMP, "frame_id": "joy"}, "axes": [-0.0, 0.5, -1.0, 0.25, 1.0, -0.125, 0.0],
        "buttons": [0, 0, 0, 0, 1, 0, 0, 1, 0, 0, 0]}),
    "joy_empty": ("sensor_msgs/msg/Joy", {"header": {"stamp": STAMP, "frame_id": ""}, "axes": [], "buttons": []}),
    # MoveIt Servo's input: a translation in the base frame, a turn in the hand's frame
    "twist_stamped": ("geometry_msgs/msg/TwistStamped", {
        "header": BASE_HEADER, "twist": {"linear": {"x": 0.05, "y": -0.1, "z": 0.025},
                                         "angular": {"x": 0.0, "y": 0.0, "z": 0.0}}}),
    "twist_stamped_hand": ("geometry_msgs/msg/TwistStamped", {
        "header": {"stamp": STAMP, "frame_id": "end_effector"},
        "twist": {"linear": {"x": 0.0, "y": 0.0, "z": 0.0}, "angular": {"x": 0.3, "y": -0.2, "z": 0.1}}}),
    "robot_description": ("std_msgs/msg/String", {
        "data": '<robot name="j2n6s300"><link name="base_link"/><!-- 270° wrist --></robot>'}),
    "string_empty": ("std_msgs/msg/String", {"data": ""}),
    "diagnostic_array": ("diagnostic_msgs/msg/DiagnosticArray", {
        "header": BASE_HEADER, "status": [
            {"level": 0, "name": "mfvs: controller", "message": "servoing", "hardware_id": "",
             "values": [{"key": "error_px", "value": "1.5"}, {"key": "rate_hz", "value": "30"}]},
            {"level": 2, "name": "mfvs: safety", "message": "e-stop engaged", "hardware_id": "jaco",
             "values": []}]}),
    "trigger_request": ("std_srvs/srv/Trigger_Request", {}),
    "trigger_response": ("std_srvs/srv/Trigger_Response", {"success": True, "message": "started"}),
}

#: every type whose hash the tests check: the published ones, their nested ones, the service
HASHED_TYPES = sorted({ros_type for ros_type, _ in SAMPLES.values() if "_Re" not in ros_type} | {
    "std_srvs/srv/Trigger", "sensor_msgs/msg/RegionOfInterest", "geometry_msgs/msg/Transform",
    "geometry_msgs/msg/Vector3", "geometry_msgs/msg/Quaternion", "geometry_msgs/msg/Pose",
    "geometry_msgs/msg/Point", "geometry_msgs/msg/Twist", "diagnostic_msgs/msg/DiagnosticStatus", "diagnostic_msgs/msg/KeyValue",
    "rcl_interfaces/msg/Log", "rcl_interfaces/msg/ParameterEvent"})

#: the liveliness tokens whose GIDs the tests check: rmw_zenoh's design document's examples (docs/design.md at
#: ros2/rmw_zenoh 99a6a2bd), the tokens of ros2/rmw_zenoh issue 643, and lengths that reach every branch of XXH3
#: (0, 1-3, 4-8, 9-16, 17-128, 129-240, and the long path's one and several stripes and blocks)
GID_INPUTS = [
    "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/0/NN/%/%/listener",
    "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/10/MS/%/%/listener/%chatter/std_msgs::msg::dds_::String_/"
    "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18/::,10:,:,:,,",
    "@ros2_lv/2/8b20917502ee955ac4476e0266340d5c/0/10/MP/%/%/talker/%chatter/std_msgs::msg::dds_::String_/"
    "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18/::,7:,:,:,,",
    "@ros2_lv/0/999bf91283606d2068c7524e5badfa6c/0/1/MP/%/%robot1/talker/%rosout/rcl_interfaces::msg::dds_::Log_/"
    "RIHS01_e28ce254ca8abc06abf92773b74602cdbf116ed34fbaf294fb9f81da9f318eac/:1:,1000:,:10,0:,,",
    "", "a", "abc", "abcd", "abcdefgh", "abcdefghi", "0123456789abcdef", "0123456789abcdefg",
    "x" * 128, "y" * 129, "z" * 240, "w" * 241, "v" * 1024, "".join(chr(33 + i % 90) for i in range(2500)),
]


def rclpy_message(ros_type: str, values: dict):
    """The rclpy message of ``ros_type`` holding ``values`` (nested dicts become nested messages)."""
    package, kind, name = ros_type.split("/")
    module = {"builtin_interfaces": builtin, "std_msgs": std, "sensor_msgs": sensor, "geometry_msgs": geometry,
              "diagnostic_msgs": diagnostic}.get(package)
    if package == "std_srvs":
        service, part = name.rsplit("_", 1)
        cls = getattr(getattr(std_srvs, service), part)
    else:
        cls = getattr(module, name)
    message = cls()
    for field, value in values.items():
        current = getattr(message, field)
        if isinstance(value, dict):
            value = rclpy_message(type(current).__module__.split(".")[0] + "/msg/" + type(current).__name__, value)
        elif field == "data" and ros_type == "sensor_msgs/msg/Image":
            value = bytes.fromhex(value)
        elif field == "level":
            value = bytes([value])
        elif isinstance(value, list) and value and isinstance(value[0], dict):
            value = [rclpy_message(_nested_type(ros_type, field), v) for v in value]
        elif isinstance(current, np.ndarray):
            value = np.array(value, dtype=current.dtype)
        setattr(message, field, value)
    return message


def _nested_type(ros_type: str, field: str) -> str:
    return {("tf2_msgs/msg/TFMessage", "transforms"): "geometry_msgs/msg/TransformStamped",
            ("diagnostic_msgs/msg/DiagnosticArray", "status"): "diagnostic_msgs/msg/DiagnosticStatus",
            ("diagnostic_msgs/msg/DiagnosticStatus", "values"): "diagnostic_msgs/msg/KeyValue"}[(ros_type, field)]


#: rosbags' stores hold no services: Trigger's request and response, registered as messages for their bytes only
#: (a hash covers the type's name, so theirs would not be the service parts' hashes)
ROSBAGS_SERVICE_PARTS = {"std_srvs/srv/Trigger_Request": ("std_srvs/msg/Trigger_Request",
                                                          "uint8 structure_needs_at_least_one_member"),
                         "std_srvs/srv/Trigger_Response": ("std_srvs/msg/Trigger_Response",
                                                           "bool success\nstring message")}


def register_service_parts(typestore) -> None:
    types = {}
    for name, definition in ROSBAGS_SERVICE_PARTS.values():
        types.update(get_types_from_msg(definition, name))
    typestore.register(types)


def rosbags_message(typestore, ros_type: str, values: dict):
    """The rosbags message of ``ros_type`` holding ``values``; rosbags wants every field, in order."""
    ros_type = ROSBAGS_SERVICE_PARTS.get(ros_type, (ros_type,))[0]
    cls = typestore.types[ros_type]
    _, fields = typestore.fielddefs[ros_type]
    arguments = []
    for field, (node_kind, spec) in fields:
        value = values.get(field)
        if field == "structure_needs_at_least_one_member":
            value = 0
        elif node_kind.name == "NAME":
            value = rosbags_message(typestore, spec, value)
        elif node_kind.name in ("ARRAY", "SEQUENCE"):
            element_kind, element_spec = spec[0]
            base = element_spec[0] if isinstance(element_spec, tuple) else element_spec
            if element_kind.name == "NAME":
                value = [rosbags_message(typestore, element_spec, v) for v in value]
            elif base == "string":
                value = list(value)
            elif base in ("uint8", "octet"):
                value = np.frombuffer(bytes.fromhex(value), dtype=np.uint8)
            else:
                value = np.array(value, dtype={"float32": np.float32, "int32": np.int32}.get(base, np.float64))
        arguments.append(value)
    return cls(*arguments)


def shipped_hash(ros_type: str) -> str | None:
    """The RIHS01 hash the Jazzy interface package ships for ``ros_type`` (None when no wheel has it)."""
    package, kind, name = ros_type.split("/")
    path = SHARE / package / kind / f"{name}.json"
    if not path.is_file():
        return None
    hashes = json.loads(path.read_text())["type_hashes"]
    return next(entry["hash_string"] for entry in hashes if entry["type_name"] == ros_type)


def rosbags_hash(typestore, ros_type: str) -> str | None:
    try:
        return typestore.hash_rihs01(ros_type)
    except KeyError:  # services (std_srvs) are not in rosbags' stores
        return None


def main() -> None:
    FIXTURES.mkdir(exist_ok=True)
    stores = {distro: get_typestore(store) for distro, store in
              (("jazzy", Stores.ROS2_JAZZY), ("kilted", Stores.ROS2_KILTED), ("lyrical", Stores.ROS2_LYRICAL))}
    jazzy = stores["jazzy"]
    register_service_parts(jazzy)
    samples = {}
    for sample, (ros_type, values) in SAMPLES.items():
        entry = {"type": ros_type, "values": values}
        if not ros_type.startswith("tf2_msgs/"):
            path = FIXTURES / f"{sample}.rclpy.cdr"
            path.write_bytes(serialize_message(rclpy_message(ros_type, values)))
            entry["rclpy"] = path.name
        path = FIXTURES / f"{sample}.rosbags.cdr"
        rosbags_type = ROSBAGS_SERVICE_PARTS.get(ros_type, (ros_type,))[0]
        path.write_bytes(jazzy.serialize_cdr(rosbags_message(jazzy, ros_type, values), rosbags_type))
        entry["rosbags"] = path.name
        samples[sample] = entry
    hashes = {ros_type: {"jazzy_package": shipped_hash(ros_type),
                         **{f"rosbags_{distro}": rosbags_hash(store, ros_type) for distro, store in stores.items()}}
              for ros_type in HASHED_TYPES}
    gids = {text: xxhash.xxh3_128_intdigest(text.encode()).to_bytes(16, "little").hex() for text in GID_INPUTS}
    versions = {name: importlib.metadata.version(name) for name in
                ("ros-jazzy-rclpy", "ros-jazzy-sensor-msgs", "ros-jazzy-std-srvs", "rosbags", "xxhash")}
    document = {
        "made_by": "tests/protocol/ros2/make_fixtures.py (its docstring says how to run it)",
        "versions": versions,
        "about_bytes": "*.rclpy.cdr: rclpy.serialization.serialize_message (ROS 2 Jazzy, rmw_fastrtps_cpp's Fast-CDR); "
                 "*.rosbags.cdr: rosbags' ros2_jazzy typestore; tf2_msgs has no Jazzy wheel: rosbags only",
        "about_type_hashes": "jazzy_package: share/<pkg>/<kind>/<Name>.json of the Jazzy wheels; rosbags_<distro>: "
                  "rosbags' REP-2011 hasher on its type store for that distro",
        "about_gids": "xxhash.xxh3_128_intdigest(token), written as rmw_zenoh_cpp copies it: low 64 bits then high, "
                "each little-endian",
        "samples": samples, "type_hashes": hashes, "gids": gids,
    }
    (FIXTURES / "fixtures.json").write_text(json.dumps(document, indent=1, ensure_ascii=False) + "\n")
    print(f"wrote {len(samples)} samples, {len(hashes)} type hashes, {len(gids)} GIDs to {FIXTURES}")


if __name__ == "__main__":
    main()
