"""The viewer's translations of mfvs messages into Foxglove's well-known messages, logged through ViewChannels
into an MCAP file and decoded back through the schemas the file carries."""
import cv2
import numpy as np

import foxglove
from protocol import messages as m
from protocol.conventions import AngularConvention, Frame
from protocol.keys import Keys
from protocol.topics import topic_of
from services.model.kinematics import ArmKinematics
from services.observe import foxglove_view as fv
from services.runtime.jsonsafe import json_safe
from tests.services.observe.mcap_files import read_mcap
from services.model.arm import EE_LINK, BASE_LINK, load_arm
from tests.helpers import ARM_DECLARED

ARM = load_arm("j2s7s300")

KEYS = Keys()
INFO = m.CameraInfo(header=m.Header(stamp_ns=5), width=640, height=480, fx=600.0, fy=610.0, cx=320.0, cy=240.0,
                    camera_in_ee=m.Pose(xyz=(0.0, 0.05, 0.1)))
GOAL = [(-0.1, -0.1), (0.1, -0.1), (0.1, 0.1), (-0.1, 0.1)]
HEADER = m.Header(stamp_ns=2_500_000_000, source_stamp_ns=2_500_000_000)


def features(status=m.FeatureStatus.OK):
    points = [(x + 0.01, y) for x, y in GOAL]
    error = [c for (x, y), (gx, gy) in zip(points, GOAL) for c in (x - gx, y - gy)]
    return m.Features(header=HEADER, status=status, points=points, depths=[0.3] * 4, ids=[0, 1, 2, 3],
                      weights=[1.0] * 4, goal_points=GOAL,
                      goal_depths=[0.3] * 4, error=error, error_norm=float(np.linalg.norm(error)),
                      pixels=[(250.0, 170.0), (390.0, 170.0), (390.0, 310.0), (250.0, 310.0)],
                      tag=m.TagView(id=0, pose_in_camera=m.Pose(xyz=(0.0, 0.0, 0.3))))


def robot_state(q=ARM.home, faults=()):
    return m.RobotState(**ARM_DECLARED, header=HEADER, q=list(q), dq=[0.1] * 7, tau=[0.0] * 7,
                        pose=m.KinovaPose(X=0, Y=0, Z=0, ThetaX=0, ThetaY=0, ThetaZ=0),
                        control_mode=m.ControlMode.CARTESIAN_VELOCITY, faults=list(faults))


def shown(tmp_path, messages) -> dict:
    """What the viewer's channels hold after ``messages`` ((key, message) in order)."""
    context = foxglove.Context()
    path = tmp_path / "view.mcap"
    writer = foxglove.open_mcap(str(path), allow_overwrite=True, context=context)
    view = fv.ViewChannels(context)
    for i, (key, message) in enumerate(messages):
        view.on_message(topic_of(key), message, 1000 + i)
    writer.close()
    return read_mcap(path)


def test_the_camera_with_the_detected_corners_and_the_goal_where_the_lens_puts_it(tmp_path):
    pixels = np.zeros((480, 640, 3), dtype=np.uint8)
    pixels[:, :320] = (255, 0, 0)  # red on the left, in RGB
    image = m.Image(header=m.Header(stamp_ns=1_000_000_123), width=640, height=480, encoding=m.ImageEncoding.RGB8,
                    data=pixels.tobytes())
    out = shown(tmp_path, [(KEYS.camera_image, image), (KEYS.camera_info, INFO), (KEYS.features, features())])
    schema, _, jpeg = out["/view/camera/image"][0]
    assert schema == "foxglove.CompressedImage" and jpeg.format == "jpeg" and jpeg.frame_id == fv.CAMERA_FRAME
    assert (jpeg.timestamp.seconds, jpeg.timestamp.nanos) == (1, 123)
    back = cv2.imdecode(np.frombuffer(jpeg.data, np.uint8), cv2.IMREAD_COLOR)
    assert back.shape == (480, 640, 3) and back[240, 100, 2] > 200 and back[240, 500, 2] < 50  # red stays left
    schema, _, annotations = out["/view/camera/annotations"][0]
    assert schema == "foxglove.ImageAnnotations"
    detected, goal = annotations.points
    assert [(p.x, p.y) for p in detected.points] == features().pixels
    # (x, y) normalized → (fx x + cx, fy y + cy) for this distortion-free camera
    assert [(round(p.x, 6), round(p.y, 6)) for p in goal.points] == [(260.0, 179.0), (380.0, 179.0),
                                                                     (380.0, 301.0), (260.0, 301.0)]
    assert "ok" in annotations.texts[-1].text
    calibration = out["/view/camera/calibration"][0][2]
    assert (calibration.width, calibration.K[0], calibration.K[2]) == (640, 600.0, 320.0)


def test_before_the_intrinsics_arrive_only_the_detected_corners_are_drawn(tmp_path):
    annotations = shown(tmp_path, [(KEYS.features, features())])["/view/camera/annotations"][0][2]
    assert len(annotations.points) == 1


def test_distortion_moves_the_goal_as_the_lens_moves_the_image():
    fields = {f: getattr(INFO, f) for f in INFO.__struct_fields__}
    barrel = m.CameraInfo(**{**fields, "distortion": [-0.3, 0.1, 0.0, 0.0, 0.0]})
    straight = fv.normalized_to_pixels([(0.3, 0.2)], INFO)[0]
    bent = fv.normalized_to_pixels([(0.3, 0.2)], barrel)[0]
    assert np.allclose(straight, [600 * 0.3 + 320, 610 * 0.2 + 240])
    radial = 1 - 0.3 * 0.13 + 0.1 * 0.13**2  # OpenCV's model: 1 + k1 r² + k2 r⁴, r² = 0.3² + 0.2²
    assert np.allclose(bent, [600 * 0.3 * radial + 320, 610 * 0.2 * radial + 240])


def test_the_arm_in_3d_and_its_joints_against_their_limits(tmp_path):
    q = ARM.home.copy()
    out = shown(tmp_path, [(KEYS.robot_state, robot_state(q)), (KEYS.camera_info, INFO), (KEYS.features, features())])
    transforms = [t for _, _, msg in out["/tf"] for t in msg.transforms]
    links = ArmKinematics(ARM).link_poses(q)
    by_child = {t.child_frame_id: t for t in transforms}
    assert set(links) - {BASE_LINK} | {fv.CAMERA_FRAME, fv.TAG_FRAME} == set(by_child)
    _, p = ArmKinematics(ARM).pose(q)
    ee = by_child[EE_LINK].translation
    assert np.allclose([ee.x, ee.y, ee.z], p)
    assert by_child[fv.CAMERA_FRAME].parent_frame_id == EE_LINK
    assert by_child[fv.TAG_FRAME].translation.z == 0.3
    scene = out["/view/robot/arm"][0][2]
    assert len(scene.entities[0].lines[0].points) == len(links)
    joints = out["/view/robot/joints"][0][2].joints
    assert [j.name for j in joints] == list(ARM.joint_names) and joints[3].position == q[3]
    margins = out["/view/joint_margins"][0][2]
    assert margins["minimum_deg"] == min(ARM.limit_margins_deg(q))


def test_series_are_plottable_json_and_statuses_are_logged_when_they_change(tmp_path):
    twist = m.Twist(header=HEADER, frame=Frame.MIXED, angular=AngularConvention.SEED000, linear=(0.01, 0.0, 0.0),
                    rotational=(0.0, 0.0, 0.2))
    status = m.ControllerStatus(header=HEADER, law="adaptive-pd-mixed", status=m.ControllerState.CONVERGING,
                                iteration=4, error_norm=0.02)
    estop = m.SafetyStatus(header=HEADER, state=m.SafetyState.ESTOP, last_refusal="e-stop engaged")
    out = shown(tmp_path, [(KEYS.desired_twist, twist), (KEYS.controller_status, status),
                           (KEYS.controller_status, status), (KEYS.safety_status, estop),
                           (KEYS.safety_status, estop), (KEYS.robot_state, robot_state(faults=["actuator 3: 2"]))])
    assert out["/view/twist"][0][0] == "mfvs.Twist" and out["/view/twist"][0][2]["rotational"] == [0.0, 0.0, 0.2]
    assert [r[2]["iteration"] for r in out["/view/controller"]] == [4, 4]
    logs = [(entry.name, entry.message) for _, _, entry in out["/rosout"]]
    assert logs == [("controller", "adaptive-pd-mixed: converging"),
                    ("safety", "estop; last refusal: e-stop engaged"), ("robot", "actuator 3: 2")]


def test_a_missing_figure_is_null_in_a_series(tmp_path):
    lost = m.Features(header=HEADER, status=m.FeatureStatus.TARGET_LOST)
    command = m.RobotCommand(header=HEADER, mode=m.CommandMode.STOP, reason="held")
    out = shown(tmp_path, [(KEYS.features, lost), (KEYS.robot_command, command)])
    assert out["/view/features"][0][2]["status"] == "target_lost"
    assert out["/view/command"][0][2]["mode"] == "stop"
    assert json_safe({"a": float("nan"), "b": [1.0, float("inf")]}) == {"a": None, "b": [1.0, None]}


def test_a_markerless_targets_pose_is_its_taught_views_frame():
    kp = m.KeypointView(goal="cup", goal_digest="0123456789abcdef", detector="sift", search="detect",
                        object_pose_in_camera=m.Pose(xyz=(0.01, 0.0, 0.3)))
    features = m.Features(header=HEADER, status=m.FeatureStatus.TARGET_LOST, front_end=m.FrontEnd.KEYPOINTS,
                          keypoints=kp)
    frame, pose = fv.target_pose(features)
    assert frame == "taught_view" and pose.xyz == (0.01, 0.0, 0.3) and fv.tag_transform(features) is not None
    assert fv.target_pose(m.Features(header=HEADER, status=m.FeatureStatus.TARGET_LOST)) is None
