"""The bridge's pure side, without zenoh: mfvs messages as ROS 2 messages (decoded back through protocol/ros2's
codec), the node's keys, tokens and GIDs, the subscriptions it watches, and every ROS 2 input it refuses."""
import math

import numpy as np
import pinocchio as pin
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from protocol import messages as m
from protocol.ros2 import cdr
from protocol.ros2.attachment import Attachment, encode as encode_attachment
from protocol.ros2.gid import entity_gid
from protocol.ros2.keys import (HUMBLE_TYPE_HASH, Distro, Durability, EntityKind, Reliability, endpoint_token,
                                parse_token)
from protocol.ros2 import types as ros_types
from services.model import frames
from services.model.arm import BASE_LINK, EE_LINK, load_arm
from services.model.kinematics import ArmKinematics
from services.ros2_bridge import core
from tests.helpers import ARM_DECLARED

ARM = load_arm("j2s7s300")
ZID = "8b20917502ee955ac4476e0266340d5c"
HEADER = m.Header(stamp_ns=2_500_000_123)
INFO = m.CameraInfo(header=HEADER, width=640, height=480, fx=600.0, fy=610.0, cx=320.0, cy=240.0,
                    distortion=[-0.3, 0.1, 0.001, 0.002, 0.0],
                    camera_in_ee=m.Pose(xyz=(0.0, 0.05, 0.1), quat_wxyz=(math.cos(0.3), 0.0, 0.0, math.sin(0.3))))


def roundtrip(message):
    return cdr.deserialize(cdr.serialize(message), type(message))


def robot_state(q):
    return m.RobotState(**ARM_DECLARED, header=HEADER, q=list(q), dq=[0.1] * 7, tau=[0.5] * 7,
                        pose=m.KinovaPose(X=0, Y=0, Z=0, ThetaX=0, ThetaY=0, ThetaZ=0),
                        control_mode=m.ControlMode.CARTESIAN_VELOCITY)


def homogeneous(transform: cdr.TransformStamped) -> np.ndarray:
    t, r = transform.transform.translation, transform.transform.rotation
    T = np.eye(4)
    T[:3, :3] = frames.quat_wxyz_to_matrix((r.w, r.x, r.y, r.z))
    T[:3, 3] = (t.x, t.y, t.z)
    return T


# ------------------------------------------------------------------------------------------------ the graph
def test_every_endpoint_has_the_token_key_and_gid_rmw_zenoh_makes_of_it():
    graph = core.NodeGraph.build(0, "/", "mfvs", Distro.JAZZY, ZID)
    assert graph.node_token == f"@ros2_lv/0/{ZID}/0/0/NN/%/%/mfvs"
    gids = set()
    for entity_id, endpoint in enumerate(core.ENDPOINTS, start=1):
        declared = graph.endpoints[endpoint]
        token = parse_token(declared.token)
        assert (token.kind, token.entity_id, token.node_id, token.node_name) == (endpoint.kind, entity_id, 0, "mfvs")
        assert token.name == declared.fully_qualified_name and token.type_hash == endpoint.ros_type.rihs01
        assert declared.key == f"0{declared.fully_qualified_name}/{token.dds_type}/{endpoint.ros_type.rihs01}"
        assert declared.gid == entity_gid(declared.token)
        gids.add(declared.gid)
    assert len(gids) == len(core.ENDPOINTS)
    tokens = {e: parse_token(graph.endpoints[e].token) for e in core.ENDPOINTS}
    # latched as tf2's static broadcaster and robot_state_publisher latch them; the camera as sensor data
    assert tokens[core.TF_STATIC].qos.durability is Durability.TRANSIENT_LOCAL
    assert tokens[core.ROBOT_DESCRIPTION].qos.durability is Durability.TRANSIENT_LOCAL
    assert tokens[core.IMAGE].qos.reliability is Reliability.BEST_EFFORT
    assert graph.endpoints[core.TF_STATIC].token.endswith("/:1:,1:,:,:,,")
    assert graph.endpoints[core.START_TASK].key == \
        f"0/mfvs/start_task/std_srvs::srv::dds_::Trigger_/{ros_types.TRIGGER.rihs01}"


def test_the_namespace_takes_relative_names_and_leaves_tf_absolute_and_humble_has_no_hashes():
    graph = core.NodeGraph.build(7, "/robot1", "arm", Distro.HUMBLE, ZID)
    assert graph.endpoints[core.IMAGE].key == "7/robot1/camera/image_raw/sensor_msgs::msg::dds_::Image_/" \
                                              + HUMBLE_TYPE_HASH
    assert graph.endpoints[core.TF].key.startswith("7/tf/tf2_msgs::msg::dds_::TFMessage_/")
    assert graph.node_token == f"@ros2_lv/7/{ZID}/0/0/NN/%/%robot1/arm"
    assert all(HUMBLE_TYPE_HASH in d.token for d in graph.endpoints.values())


def test_the_watch_sees_a_subscription_of_the_image_come_and_go():
    graph = core.NodeGraph.build(0, "/", "mfvs", Distro.JAZZY, ZID)
    image = graph.endpoints[core.IMAGE]
    watch = core.SubscriberWatch(0)
    rviz = endpoint_token(EntityKind.SUBSCRIPTION, 0, "aac3178e146ba6f1fc6e6a4085e77f21", 0, 12, "/", "rviz",
                          image.fully_qualified_name, ros_types.IMAGE.name, ros_types.IMAGE.rihs01, core.IMAGE.qos,
                          Distro.JAZZY)
    other_domain = rviz.replace("@ros2_lv/0/", "@ros2_lv/1/", 1)
    has = lambda: watch.has_subscriber(image.fully_qualified_name, ros_types.IMAGE.name)  # noqa: E731
    watch.on_token(image.token, True)  # the bridge's own publisher is no reader
    watch.on_token(other_domain, True)
    watch.on_token("@ros2_lv/0/garbage", True)
    assert not has()
    watch.on_token(rviz, True)
    assert has()
    watch.on_token(rviz, False)
    assert not has()


# ------------------------------------------------------------------------------------------------ outputs
def test_an_image_is_sensor_msgs_image_in_the_camera_frame():
    data = bytes(range(256)) * 3 * 4 * 2
    frame = m.Image(header=HEADER, width=32, height=24, encoding=m.ImageEncoding.RGB8, data=data[:32 * 24 * 3])
    ros = roundtrip(core.image(frame))
    assert (ros.width, ros.height, ros.encoding, ros.step, ros.is_bigendian) == (32, 24, "rgb8", 96, 0)
    assert ros.data == frame.data and ros.header.frame_id == "camera"
    assert (ros.header.stamp.sec, ros.header.stamp.nanosec) == (2, 500_000_123)


def test_camera_info_states_k_r_p_and_the_distortion_model_by_its_coefficients():
    ros = roundtrip(core.camera_info(INFO))
    K = ros.k.reshape(3, 3)
    assert np.allclose(K, [[600, 0, 320], [0, 610, 240], [0, 0, 1]]) and np.allclose(ros.r.reshape(3, 3), np.eye(3))
    assert np.allclose(ros.p.reshape(3, 4)[:, :3], K) and np.allclose(ros.p.reshape(3, 4)[:, 3], 0)
    assert ros.distortion_model == "plumb_bob" and list(ros.d) == INFO.distortion
    eight = m.CameraInfo(**{**{f: getattr(INFO, f) for f in INFO.__struct_fields__}, "distortion": [0.1] * 8})
    assert core.camera_info(eight).distortion_model == "rational_polynomial"
    fourteen = m.CameraInfo(**{**{f: getattr(INFO, f) for f in INFO.__struct_fields__}, "distortion": [0.1] * 14})
    with pytest.raises(core.Untranslatable, match="14 distortion coefficients"):
        core.camera_info(fourteen)


def test_joint_states_carry_the_urdf_joint_names():
    q = ARM.home + 0.1
    ros = roundtrip(core.joint_state(robot_state(q), ARM))
    assert ros.name == ARM.joint_names and np.allclose(ros.position, q)
    assert np.allclose(ros.velocity, 0.1) and np.allclose(ros.effort, 0.5)
    urdf = core.robot_description(ARM).data
    assert all(f'<joint name="{name}" type="revolute">' in urdf for name in ARM.joint_names)


def test_tf_chains_the_urdf_links_to_the_end_effector_where_the_kinematics_put_it(rng):
    kinematics = ArmKinematics(ARM)
    q = ARM.home + rng.uniform(-0.5, 0.5, ARM.n_joints)
    tf = roundtrip(core.arm_tf(kinematics.link_poses(q), ARM, HEADER.stamp_ns))
    pairs = [(t.header.frame_id, t.child_frame_id) for t in tf.transforms]
    assert pairs[0][0] == BASE_LINK and pairs[-1][1] == EE_LINK
    assert all(a[1] == b[0] for a, b in zip(pairs, pairs[1:]))  # one chain, parent to child
    T = np.eye(4)
    for transform in tf.transforms:
        T = T @ homogeneous(transform)
    R, p = kinematics.pose(q)
    assert np.allclose(T[:3, :3], R, atol=1e-9) and np.allclose(T[:3, 3], p, atol=1e-9)


def test_the_camera_mount_is_static_and_the_tag_is_under_the_camera_when_seen():
    (mount,) = roundtrip(core.camera_mount(INFO)).transforms
    assert (mount.header.frame_id, mount.child_frame_id) == (EE_LINK, "camera")
    assert np.allclose(homogeneous(mount)[:3, :3], frames.quat_wxyz_to_matrix(INFO.camera_in_ee.quat_wxyz))
    seen = m.Features(header=HEADER, status=m.FeatureStatus.TARGET_LOST,
                      tag=m.TagView(id=0, pose_in_camera=m.Pose(xyz=(0.0, 0.1, 0.3))))
    (tag,) = roundtrip(core.tag_tf(seen)).transforms
    assert (tag.header.frame_id, tag.child_frame_id) == ("camera", "tag") and tag.transform.translation.z == 0.3
    assert core.tag_tf(m.Features(header=HEADER, status=m.FeatureStatus.TARGET_LOST)) is None


def test_pinocchio_loads_the_published_description_to_the_same_kinematics(rng):
    """The URDF as a ROS subscriber receives it (the CDR String decoded) builds the model mfvs computes with."""
    urdf = roundtrip(core.robot_description(ARM)).data
    model = pin.buildModelFromXML(urdf)
    data = model.createData()
    kinematics = ArmKinematics(ARM)
    for _ in range(5):
        q = ARM.home + rng.uniform(-1.0, 1.0, ARM.n_joints)
        pin.framesForwardKinematics(model, data, q)
        placement = data.oMf[model.getFrameId(EE_LINK)]
        R, p = kinematics.pose(q)
        assert np.allclose(placement.rotation, R, atol=1e-12) and np.allclose(placement.translation, p, atol=1e-12)


def health(name, healthy=True, degraded=()):
    return m.ServiceHealth(header=HEADER, service=name, pid=1, healthy=healthy, state="running", uptime_s=3.0,
                           rates_hz={"image": 30.0}, errors={"rejected.x": 2}, degraded=list(degraded))


def test_diagnostics_rate_each_service_the_task_and_safety_and_say_stale():
    board = core.Diagnostics("jaco")
    second = 1_000_000_000
    board.on_health(health("vision"), 10 * second)
    board.on_health(health("controller", degraded=["law at 20 Hz (nominal 30)"]), 10 * second)
    board.on_health(health("robot_sim", healthy=False), 10 * second)
    board.on_health(health("camera"), 1 * second)
    board.on_controller(m.ControllerStatus(header=HEADER, law="ibvs", status=m.ControllerState.CONVERGING,
                                           iteration=4, error_norm=0.2), 10 * second)
    board.on_safety(m.SafetyStatus(header=HEADER, state=m.SafetyState.ESTOP), 10 * second)
    array = roundtrip(board.array(now_ns=11 * second, stamp_ns=HEADER.stamp_ns))
    levels = {s.name: s.level for s in array.status}
    S = cdr.DiagnosticStatus
    assert levels == {"mfvs/jaco/vision": S.OK, "mfvs/jaco/controller": S.WARN, "mfvs/jaco/robot_sim": S.ERROR,
                      "mfvs/jaco/camera": S.STALE, "mfvs/jaco/task": S.OK, "mfvs/jaco/safety": S.ERROR}
    vision = next(s for s in array.status if s.name == "mfvs/jaco/vision")
    assert {kv.key: kv.value for kv in vision.values}["errors.rejected.x"] == "2"
    task = next(s for s in array.status if s.name == "mfvs/jaco/task")
    assert task.message == "converging" and {kv.key: kv.value for kv in task.values}["iteration"] == "4"


# ------------------------------------------------------------------------------------------------ inputs
def pose_payload(xyz=(0.0, 0.0, 0.4), wxyz=(1.0, 0.0, 0.0, 0.0), frame_id="tag") -> bytes:
    w, x, y, z = wxyz
    return cdr.serialize(cdr.PoseStamped(header=cdr.Header(frame_id=frame_id), pose=cdr.Pose(
        position=cdr.Point(*xyz), orientation=cdr.Quaternion(x=x, y=y, z=z, w=w))))


def test_a_goal_pose_is_the_camera_in_the_tag_frame():
    pose = core.goal_pose(pose_payload(xyz=(0.01, -0.02, 0.35), wxyz=(0.0, 1.0000004, 0.0, 0.0)))
    assert pose.xyz == (0.01, -0.02, 0.35) and pose.quat_wxyz == pytest.approx((0.0, 1.0, 0.0, 0.0))


@pytest.mark.parametrize("payload, kind", [
    (b"\x00\x01\x00\x00\x01", "cdr"),
    (pose_payload()[:-8], "cdr"),
    (b"\x00\x00\x00\x00" + pose_payload()[4:], "cdr"),
    (pose_payload(frame_id="base_link"), "frame"),
    (pose_payload(xyz=(0.0, float("nan"), 0.4)), "not_finite"),
    (pose_payload(wxyz=(float("inf"), 0.0, 0.0, 0.0)), "not_finite"),
    (pose_payload(wxyz=(0.0, 0.0, 0.0, 0.0)), "quaternion"),
    (pose_payload(wxyz=(1.0, 1.0, 0.0, 0.0)), "quaternion"),
    (pose_payload(xyz=(0.0, 0.0, 0.01)), "distance"),
    (pose_payload(xyz=(1e6, 0.0, 0.0)), "distance"),
], ids=["short", "truncated", "big-endian", "wrong-frame", "nan", "inf", "zero-quaternion", "not-unit", "too-near",
        "absurd"])
def test_a_goal_pose_that_is_not_a_sane_one_is_refused_saying_why(payload, kind):
    with pytest.raises(core.InputError) as refused:
        core.goal_pose(payload)
    assert refused.value.kind == kind and str(refused.value)


def test_a_service_request_needs_rmw_zenoh_s_attachment_and_its_reply_returns_its_number_and_gid():
    gid = bytes(range(16))
    request = encode_attachment(Attachment(41, 123, gid))
    parsed = core.request_attachment(request)
    reply = core.reply_attachment(parsed, 999)
    assert (reply.sequence_number, reply.source_timestamp_ns, reply.source_gid) == (41, 999, gid)
    for raw in (None, b"", request[:-1], request[:16] + b"\x08" + gid):
        with pytest.raises(core.InputError) as refused:
            core.request_attachment(raw)
        assert refused.value.kind == "attachment"
    assert core.trigger_request(b"\x00\x01\x00\x00\x00") == cdr.TriggerRequest()
    with pytest.raises(core.InputError):
        core.trigger_request(b"\x00\x01\x00\x00" + bytes(12))
    assert cdr.deserialize(core.trigger_response(True, "task running"), cdr.TriggerResponse) == \
        cdr.TriggerResponse(success=True, message="task running")


@settings(max_examples=300, deadline=None)
@given(st.one_of(st.binary(max_size=200),
                 # a real PoseStamped with bytes changed: lengths, frame ids, doubles made NaN or huge
                 st.builds(lambda at, new: (lambda p: p[:at % len(p)] + new + p[at % len(p) + len(new):])(
                     pose_payload()), st.integers(0, 200), st.binary(min_size=1, max_size=8))))
def test_any_bytes_as_a_goal_or_a_request_are_taken_or_refused_with_a_reason_never_an_error(payload):
    """Whatever a ROS 2 peer sends, the bridge gets a goal it checked or an InputError (nothing else escapes)."""
    for parse in (core.goal_pose, core.trigger_request, core.request_attachment):
        try:
            result = parse(payload)
        except core.InputError as refused:
            assert refused.kind and str(refused)
            continue
        if parse is core.goal_pose:
            assert all(math.isfinite(v) for v in (*result.xyz, *result.quat_wxyz))
            assert 0.05 <= math.dist(result.xyz, (0, 0, 0)) <= 2.0
