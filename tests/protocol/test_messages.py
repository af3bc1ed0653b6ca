import math

import msgpack
import pytest

from protocol import messages as m
from protocol.conventions import AngularConvention, Frame
from tests.helpers import ARM_DECLARED


def header(**kw):
    hop = m.Hop(service="vision", recv_ns=950, pub_ns=960)
    return m.Header(seq=7, stamp_ns=1_000, source_stamp_ns=900, trace=[hop], **kw)


def j7(v=0.1):
    return [v * (i + 1) for i in range(7)]


SAMPLES = [
    m.Image(header=header(), width=4, height=2, encoding=m.ImageEncoding.RGB8, data=bytes(range(24))),
    m.CameraInfo(header=header(), width=640, height=480, fx=615.0, fy=615.0, cx=320.0, cy=240.0,
                 camera_in_ee=m.Pose(xyz=(0.0, 0.05, 0.1), quat_wxyz=(0.0, 0.0, 0.0, 1.0))),
    m.Features(header=header(), status=m.FeatureStatus.OK,
               points=[(0.1, 0.1), (-0.1, 0.1), (-0.1, -0.1), (0.1, -0.1)], depths=[0.5] * 4, ids=[0, 1, 2, 3],
               weights=[1.0] * 4, goal_points=[(0.2, 0.2), (-0.2, 0.2), (-0.2, -0.2), (0.2, -0.2)],
               goal_depths=[0.3] * 4, error=[-0.1, -0.1, 0.1, -0.1, 0.1, 0.1, -0.1, 0.1], error_norm=0.2828,
               error_rms=0.1414,
               tag=m.TagView(id=0, pose_in_camera=m.Pose(xyz=(0.0, 0.0, 0.5), quat_wxyz=(0.0, 1.0, 0.0, 0.0)))),
    m.Features(header=header(), status=m.FeatureStatus.TARGET_LOST),
    m.Twist(header=header(), frame=Frame.MIXED, angular=AngularConvention.SEED000, linear=(0.01, -0.02, 0.03),
            rotational=(0.1, 0.2, -0.3)),
    m.JointVelocity(header=header(), velocities=j7()),
    m.RobotCommand(header=header(), mode=m.CommandMode.CARTESIAN_VELOCITY,
                   twist=m.Twist(header=header(), frame=Frame.MIXED, angular=AngularConvention.OMEGA,
                                 linear=(0.0, 0.0, 0.1), rotational=(0.0, 0.0, 0.0))),
    m.RobotCommand(header=header(), mode=m.CommandMode.JOINT_VELOCITY, joint_velocities=j7(-0.01)),
    m.RobotCommand(header=header(), mode=m.CommandMode.STOP, reason="stale image"),
    m.RobotCommand(header=header(), mode=m.CommandMode.STOP,
                   fingers=m.FingerCommand(mode=m.FingerMode.VELOCITY, values=[0.5, 0.5, -0.25])),
    m.RobotState(**ARM_DECLARED, header=header(), q=j7(), dq=j7(0.0), tau=j7(1.0),
                 pose=m.KinovaPose(X=0.1, Y=-0.4, Z=0.5, ThetaX=1.5, ThetaY=0.1, ThetaZ=-0.2),
                 control_mode=m.ControlMode.CARTESIAN_VELOCITY,
                 fingers=m.FingerState(position=[0.1, 0.2, 0.3], velocity=[0.0, 0.01, 0.0], current_a=[0.1] * 3,
                                       target=[1.2, 1.2, 1.2])),
    m.RobotState(**ARM_DECLARED, header=header(), q=j7(), dq=j7(0.0), tau=j7(1.0),
                 pose=m.KinovaPose(X=0.1, Y=-0.4, Z=0.5, ThetaX=1.5, ThetaY=0.1, ThetaZ=-0.2),
                 control_mode=m.ControlMode.CARTESIAN_VELOCITY, fifo_count=3, faults=["zone"],
                 applied_command=header()),
    m.TorqueCommand(header=header(), torques=j7(0.5)),
    m.LowLevelState(header=header(), mode=m.ActuatorMode.TORQUE, q=j7(), dq=j7(), tau=j7(), current_a=j7(),
                    temperature_c=j7(30.0)),
    m.SimClock(header=header(), sim_time_ns=123_456_789, mode="lockstep"),
    m.SafetyStatus(header=header(), state=m.SafetyState.LIMITING, active_limits=["linear_speed"],
                   last_refusal="", counters={"refused.nan": 2}),
    m.EStop(header=header(), operator="caregiver", reason="test"),
    m.ServiceHealth(header=header(), service="vision", pid=42, healthy=True, state="running", uptime_s=3.5,
                    rates_hz={"image": 30.0}, errors={"rejected.image": 1}),
    m.Features(header=header(), status=m.FeatureStatus.OK, front_end=m.FrontEnd.KEYPOINTS,
               points=[(0.1, 0.1), (-0.1, 0.1), (0.0, -0.1)], depths=[0.5, 0.52, 0.49], ids=[3, 17, 250],
               weights=[1.0, 0.4, 1.0], pixels=[(381.5, 301.5), (258.5, 301.5), (320.0, 178.5)],
               goal_points=[(0.1, 0.1), (-0.1, 0.1), (0.0, -0.1)], goal_depths=[0.5, 0.52, 0.49],
               error=[0.0] * 6,
               keypoints=m.KeypointView(goal="cup", goal_digest="0123456789abcdef", detector="sift", search="detect",
                                        candidates=40, inliers=3, median_error_px=0.2, max_error_px=0.4,
                                        model="epipolar", region_px=[(200.0, 150.0), (440.0, 150.0),
                                                                     (440.0, 330.0), (200.0, 330.0)])),
]


@pytest.mark.parametrize("message", SAMPLES, ids=lambda s: type(s).__name__)
def test_round_trip(message):
    assert m.decode(m.encode(message), type(message)) == message


@pytest.mark.parametrize("message", SAMPLES, ids=lambda s: type(s).__name__)
def test_plain_msgpack_reads_and_writes(message):
    # A client that only has the msgpack package sees a map of field names ...
    plain = msgpack.unpackb(m.encode(message), raw=False)
    assert plain == m.to_builtins(message)
    assert plain["header"]["schema"] == m.SCHEMA_VERSION
    # ... and what it writes back with msgpack is accepted as the same message.
    assert m.decode(msgpack.packb(plain, use_bin_type=True), type(message)) == message


def test_plain_msgpack_client_writes_a_twist_from_scratch():
    payload = msgpack.packb({
        "header": {"schema": m.SCHEMA_VERSION, "seq": 3, "stamp_ns": 5, "source_stamp_ns": 4, "trace": []},
        "frame": "mixed", "angular": "euler_xyz_rates", "linear": [0.1, 0, 0], "rotational": [0, 0, 1],
    })
    twist = m.decode(payload, m.Twist)
    assert twist.angular is AngularConvention.EULER_XYZ_RATES
    assert twist.linear == (0.1, 0.0, 0.0)  # msgpack ints are accepted where floats are due


def _mutated(message, mutate):
    plain = m.to_builtins(message)
    mutate(plain)
    return msgpack.packb(plain, use_bin_type=True)


TWIST = SAMPLES[4]


@pytest.mark.parametrize(
    "mutate, field, words",
    [
        (lambda d: d["linear"].__setitem__(1, math.nan), "linear[1]", "NaN"),
        (lambda d: d["rotational"].__setitem__(2, math.inf), "rotational[2]", "NaN or Inf"),
        (lambda d: d["header"].__setitem__("schema", m.SCHEMA_VERSION + 1), "header.schema",
         f"schema version {m.SCHEMA_VERSION + 1}"),
        (lambda d: d.__setitem__("angular", "quaternion_rates"), "angular", "Invalid enum value"),
        (lambda d: d.__setitem__("frame", "tool"), "frame", "Invalid enum value"),
        (lambda d: d.__setitem__("linear", [0.1, 0.2]), "linear", "length 3"),
        (lambda d: d.pop("angular"), "angular", "missing required field"),
        (lambda d: d.__setitem__("extra", 1), "extra", "unknown field"),
        (lambda d: d["header"].__setitem__("seq", -1), "header.seq", ">= 0"),
        (lambda d: d["header"]["trace"][0].__setitem__("service", "a/b"), "header.trace[0].service", "regex"),
        (lambda d: d.__setitem__("linear", "fast"), "linear", "Expected `array`"),
    ],
)
def test_twist_rejections_name_the_field(mutate, field, words):
    with pytest.raises(m.ProtocolError) as err:
        m.decode(_mutated(TWIST, mutate), m.Twist)
    assert err.value.field == field
    assert words in str(err.value)
    assert "Twist" in str(err.value)


@pytest.mark.parametrize("payload", [b"", b"\xc1", b"\x81\xa1", m.encode(TWIST)[:-5], b"not msgpack at all"])
def test_malformed_and_truncated_payloads(payload):
    with pytest.raises(m.ProtocolError, match="invalid Twist"):
        m.decode(payload, m.Twist)


def test_wrong_message_type_is_refused():
    with pytest.raises(m.ProtocolError):
        m.decode(m.encode(SAMPLES[0]), m.Twist)


def test_image_size_must_match_data():
    plain = m.to_builtins(SAMPLES[0])
    plain["data"] = plain["data"][:-1]
    with pytest.raises(m.ProtocolError, match="needs 24"):
        m.decode(msgpack.packb(plain, use_bin_type=True), m.Image)


def test_image_encoding_must_be_known():
    with pytest.raises(m.ProtocolError) as err:
        m.decode(_mutated(SAMPLES[0], lambda d: d.__setitem__("encoding", "yuv422")), m.Image)
    assert err.value.field == "encoding"


def test_camera_info_rejects_non_positive_focal_length_and_bad_pose():
    with pytest.raises(m.ProtocolError) as err:
        m.decode(_mutated(SAMPLES[1], lambda d: d.__setitem__("fx", 0.0)), m.CameraInfo)
    assert err.value.field == "fx"
    with pytest.raises(m.ProtocolError, match="unit quaternion"):
        m.decode(_mutated(SAMPLES[1], lambda d: d["camera_in_ee"].__setitem__("quat_wxyz", [1, 1, 0, 0])),
                 m.CameraInfo)


def test_features_ok_needs_consistent_lengths():
    with pytest.raises(m.ProtocolError, match="error has 7 entries"):
        m.decode(_mutated(SAMPLES[2], lambda d: d["error"].pop()), m.Features)


def test_joint_vectors_have_seven_entries():
    with pytest.raises(m.ProtocolError) as err:
        m.decode(_mutated(SAMPLES[5], lambda d: d["velocities"].append(0.0)), m.JointVelocity)
    assert err.value.field == "velocities"


def test_robot_command_mode_needs_its_payload():
    with pytest.raises(m.ProtocolError, match="needs twist"):
        m.decode(_mutated(SAMPLES[8], lambda d: d.__setitem__("mode", "cartesian_velocity")), m.RobotCommand)


def test_nan_in_nested_command_twist_is_refused():
    bad = _mutated(SAMPLES[6], lambda d: d["twist"]["linear"].__setitem__(0, math.nan))
    with pytest.raises(m.ProtocolError) as err:
        m.decode(bad, m.RobotCommand)
    assert err.value.field == "twist.linear[0]"


def test_constructing_a_message_with_nan_fails_too():
    with pytest.raises(ValueError, match="NaN"):
        m.JointVelocity(header=m.Header(), velocities=[math.nan] * 7)


def test_header_with_hop_appends_without_sharing():
    h = m.Header(seq=1, source_stamp_ns=10)
    h2 = h.with_hop("controller", 11, 12)
    assert h.trace == [] and [hop.service for hop in h2.trace] == ["controller"]
    assert h2.source_stamp_ns == 10


def test_numpy_values_encode_as_plain_numbers():
    import numpy as np

    pose = m.Pose(xyz=tuple(np.array([0.1, 0.2, 0.3])), quat_wxyz=(np.float64(1.0), 0.0, 0.0, 0.0))
    assert msgpack.unpackb(m.encode(pose)) == {"xyz": [0.1, 0.2, 0.3], "quat_wxyz": [1.0, 0.0, 0.0, 0.0]}


def test_the_non_finite_check_names_the_first_bad_number_and_passes_huge_finite_ones():
    # a list is summed first: huge finite numbers overflow the sum, and must still pass
    assert m._non_finite_path([1e308, 1e308, -1e308], "v") is None
    assert m._non_finite_path([(0.0, 1.0), (2.0, math.inf)], "points") == "points[1][1]"
    assert m._non_finite_path({"a": [1.0], "b": [0.0, [1.0, -math.inf]]}, "d") == "d.b[1][1]"
    assert m._non_finite_path(["text", 3, True, None], "mixed") is None
    assert m._non_finite_path([math.inf, -math.inf], "opposite") == "opposite[0]"  # inf - inf is NaN, not 0
    huge = m.JointVelocity(header=m.Header(), velocities=[1e308] * 7)  # finite: accepted
    assert huge.velocities[0] == 1e308


def _float_paths(value, path=""):
    """Every float in a message's plain form, by path (``a.b[2]``)."""
    if isinstance(value, float):
        yield path
    elif isinstance(value, dict):
        for key, item in value.items():
            yield from _float_paths(item, f"{path}.{key}" if path else key)
    elif isinstance(value, list):
        for i, item in enumerate(value):
            yield from _float_paths(item, f"{path}[{i}]")


def _set_at(plain, path, value):
    parts = [p for p in path.replace("[", ".[").split(".") if p]
    *outer, last = parts
    for part in outer:
        plain = plain[int(part[1:-1])] if part.startswith("[") else plain[part]
    if last.startswith("["):
        plain[int(last[1:-1])] = value
    else:
        plain[last] = value


@pytest.mark.parametrize("message", SAMPLES, ids=lambda s: type(s).__name__)
def test_a_nan_at_any_float_of_a_message_is_refused_and_named(message):
    """The finiteness check searches only the fields whose types may hold a float of their own (a nested message
    checks itself): a NaN put at every float of every sample, at any depth, is still refused, at its path."""
    paths = list(_float_paths(m.to_builtins(message)))
    for path in paths:
        plain = m.to_builtins(message)
        _set_at(plain, path, math.nan)
        with pytest.raises(m.ProtocolError) as err:  # (a bounded float's range refuses it first)
            m.decode(msgpack.packb(plain), type(message))
        field = err.value.field  # (msgspec names a map's value by its map: ``rates_hz[...]``)
        assert field == path or field.endswith("[...]") and path.startswith(field[:-5] + "."), err.value


def test_features_points_carry_one_unique_id_and_weight_each_or_none():
    base = dict(header=header(), status=m.FeatureStatus.OK, points=[(0.1, 0.1), (0.2, 0.1)], depths=[0.5, 0.5],
                goal_points=[(0.1, 0.1), (0.2, 0.1)], goal_depths=[0.5, 0.5], error=[0.0] * 4)
    plain = m.Features(**base)
    assert plain.point_ids() == [0, 1] and plain.point_weights() == [1.0, 1.0]
    with pytest.raises(ValueError, match="unique"):
        m.Features(**base, ids=[4, 4])
    with pytest.raises(ValueError, match="ids has 3 entries"):
        m.Features(**base, ids=[1, 2, 3])
    with pytest.raises(ValueError, match="weight above 0"):
        m.Features(**base, weights=[0.0, 0.0])
    with pytest.raises(m.ProtocolError, match="weights"):
        m.decode(_mutated(m.Features(**base, weights=[1.0, 0.5]), lambda d: d["weights"].__setitem__(0, 1.5)),
                 m.Features)
