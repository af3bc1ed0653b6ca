"""What a person watching a run sees: each mfvs message as Foxglove's well-known messages (the camera image with
the detected and goal corners, the feature error and the twists as plottable series, the joints against their
limits, the arm, camera and tag in 3D, the services' statuses as logs), and the stack's own MessagePack payloads
kept byte for byte beside them.

The translations are pure functions of the messages (and of the one JACO-2 description, for the arm's links);
:class:`ViewChannels` logs them on the channels of a ``foxglove.Context``, whose sinks are an MCAP file
(``mfvs record``), a live WebSocket server (``mfvs view``) or both. :class:`RawChannels` logs the payloads as
received, one channel per key, for ``mfvs replay``.
"""
from __future__ import annotations

from typing import Optional

import cv2
import msgspec
import numpy as np

import foxglove
from foxglove import channels as fc
from foxglove import messages as fm

from protocol import messages as m
from protocol.topics import Topic
from services.model import frames
from services.model.arm import BASE_LINK, EE_LINK, ArmDescription, declared_arm
from services.model.kinematics import ArmKinematics
from services.runtime.jsonsafe import json_safe

#: the viewer's channels are under this prefix (the raw payloads keep their zenoh keys)
VIEW = "/view"
BASE_FRAME = BASE_LINK
CAMERA_FRAME = "camera"
TAG_FRAME = "tag"
#: a markerless target's frame: the camera's frame at the teach, where the keypoint front end has its pose
TAUGHT_FRAME = "taught_view"
#: the raw channels: MessagePack, described by the message type's JSON schema, the type's name in the metadata
RAW_ENCODING = "msgpack"
RAW_TYPE = "mfvs.type"
RAW_SCHEMA_VERSION = "mfvs.schema_version"

GREEN = fm.Color(r=0.1, g=0.9, b=0.2, a=1.0)
MAGENTA = fm.Color(r=1.0, g=0.2, b=0.9, a=1.0)
GREY = fm.Color(r=0.6, g=0.6, b=0.6, a=1.0)
WHITE = fm.Color(r=1.0, g=1.0, b=1.0, a=1.0)
TRANSLUCENT = fm.Color(r=0.0, g=0.0, b=0.0, a=0.6)


def timestamp(ns: int) -> fm.Timestamp:
    return fm.Timestamp(int(ns // 1_000_000_000), int(ns % 1_000_000_000))


def _vector(v) -> fm.Vector3:
    return fm.Vector3(x=float(v[0]), y=float(v[1]), z=float(v[2]))


def _quaternion(R) -> fm.Quaternion:
    w, x, y, z = frames.matrix_to_quat_wxyz(np.asarray(R, dtype=float))
    return fm.Quaternion(x=float(x), y=float(y), z=float(z), w=float(w))


def _pose_quaternion(pose: m.Pose) -> fm.Quaternion:
    w, x, y, z = pose.quat_wxyz
    return fm.Quaternion(x=x, y=y, z=z, w=w)


# ------------------------------------------------------------------------------------------------ the camera
def pixels(image: m.Image) -> np.ndarray:
    """The frame's pixels as an H×W×channels view of its bytes (no copy)."""
    return np.frombuffer(image.data, dtype=np.uint8).reshape(image.height, image.width, m.CHANNELS[image.encoding])


def jpeg(image: m.Image, quality: int = 90) -> bytes:
    """The frame as JPEG (a tenth of the raw bytes: a viewer's copy; the raw frame is what vision sees)."""
    view = pixels(image)
    if image.encoding is m.ImageEncoding.RGB8:
        view = cv2.cvtColor(view, cv2.COLOR_RGB2BGR)
    ok, encoded = cv2.imencode(".jpg", view, [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise ValueError(f"OpenCV could not encode a {image.width}x{image.height} {image.encoding.value} frame")
    return encoded.tobytes()


def camera_image(image: m.Image, quality: int = 90) -> fm.CompressedImage:
    """The frame as JPEG (the raw frame is in the raw channel)."""
    return fm.CompressedImage(timestamp=timestamp(image.header.stamp_ns), frame_id=CAMERA_FRAME,
                              data=jpeg(image, quality), format="jpeg")


def camera_calibration(info: m.CameraInfo) -> fm.CameraCalibration:
    K = [info.fx, 0.0, info.cx, 0.0, info.fy, info.cy, 0.0, 0.0, 1.0]
    P = [info.fx, 0.0, info.cx, 0.0, 0.0, info.fy, info.cy, 0.0, 0.0, 0.0, 1.0, 0.0]
    return fm.CameraCalibration(timestamp=timestamp(info.header.stamp_ns), frame_id=CAMERA_FRAME, width=info.width,
                                height=info.height, distortion_model="plumb_bob", D=list(info.distortion), K=K,
                                R=[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0], P=P)


def normalized_to_pixels(points, info: m.CameraInfo) -> np.ndarray:
    """Normalized image points (x = X/Z, y = Y/Z) where the camera's lens puts them (its distortion included)."""
    points = np.asarray(points, dtype=float).reshape(-1, 2)
    if len(points) == 0:
        return points
    K = np.array([[info.fx, 0.0, info.cx], [0.0, info.fy, info.cy], [0.0, 0.0, 1.0]])
    rays = np.hstack([points, np.ones((len(points), 1))])
    pixels, _ = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), K, np.asarray(info.distortion, dtype=float))
    return pixels.reshape(-1, 2)


def _polygon(points, color: fm.Color, stamp: fm.Timestamp, thickness: float) -> fm.PointsAnnotation:
    return fm.PointsAnnotation(timestamp=stamp, type=fm.PointsAnnotationType.LineLoop, outline_color=color,
                               thickness=thickness,
                               points=[fm.Point2(x=float(x), y=float(y)) for x, y in points])


def corner_annotations(features: m.Features, info: Optional[m.CameraInfo]) -> fm.ImageAnnotations:
    """Over the camera image: the detected corners (green), the goal (magenta, where the camera's intrinsics are
    known), the corners' numbers, and the status with the error norm."""
    stamp = timestamp(features.header.stamp_ns)
    points, texts = [], []
    if features.pixels and features.front_end is m.FrontEnd.TAG:
        points.append(_polygon(features.pixels, GREEN, stamp, 2.0))
        for i, (x, y) in enumerate(features.pixels):
            texts.append(fm.TextAnnotation(timestamp=stamp, position=fm.Point2(x=x + 6.0, y=y - 6.0), text=str(i),
                                           font_size=14.0, text_color=GREEN, background_color=TRANSLUCENT))
    elif features.pixels:  # a keypoint target's inliers, and its taught region where seen
        points.append(fm.PointsAnnotation(timestamp=stamp, type=fm.PointsAnnotationType.Points, outline_color=GREEN,
                                          thickness=3.0, points=[fm.Point2(x=float(x), y=float(y))
                                                                 for x, y in features.pixels]))
        if features.keypoints is not None and features.keypoints.region_px:
            points.append(_polygon(features.keypoints.region_px, GREEN, stamp, 2.0))
    if features.goal_points and info is not None:
        goal = normalized_to_pixels(features.goal_points, info)
        points.append(_polygon(goal, MAGENTA, stamp, 1.5) if features.front_end is m.FrontEnd.TAG else
                      fm.PointsAnnotation(timestamp=stamp, type=fm.PointsAnnotationType.Points,
                                          outline_color=MAGENTA, thickness=3.0,
                                          points=[fm.Point2(x=float(x), y=float(y)) for x, y in goal]))
    texts.append(fm.TextAnnotation(timestamp=stamp, position=fm.Point2(x=8.0, y=20.0), font_size=16.0,
                                   text=f"{features.status.value}  |e| {features.error_norm:.3g}", text_color=WHITE,
                                   background_color=TRANSLUCENT))
    return fm.ImageAnnotations(timestamp=stamp, points=points, texts=texts)


# ------------------------------------------------------------------------------------------------ series
def _series(header: m.Header, **fields) -> dict:
    return {"stamp_s": header.stamp_ns / 1e9, **fields}


def feature_error(features: m.Features) -> dict:
    return _series(features.header, status=features.status.value, error_norm=features.error_norm,
                   error=list(features.error), points=[list(p) for p in features.points])


def twist(message: m.Twist) -> dict:
    return _series(message.header, frame=message.frame.value, angular=message.angular.value,
                   linear=list(message.linear), rotational=list(message.rotational))


def joint_velocity(message: m.JointVelocity) -> dict:
    return _series(message.header, velocities=list(message.velocities))


def controller(message: m.ControllerStatus) -> dict:
    return _series(message.header, law=message.law, status=message.status.value, iteration=message.iteration,
                   error_norm=message.error_norm, gain=message.gain, saturated=message.saturated,
                   notes=dict(message.notes))


def robot_command(message: m.RobotCommand) -> dict:
    twist_fields = {} if message.twist is None else {"linear": list(message.twist.linear),
                                                       "rotational": list(message.twist.rotational)}
    return _series(message.header, mode=message.mode.value, reason=message.reason,
                   joint_velocities=list(message.joint_velocities or []), **twist_fields)


def joint_states(state: m.RobotState, arm: ArmDescription) -> fm.JointStates:
    return fm.JointStates(timestamp=timestamp(state.header.stamp_ns), joints=[
        fm.JointState(name=name, position=q, velocity=dq, effort=tau)
        for name, q, dq, tau in zip(arm.joint_names, state.q, state.dq, state.tau)])


def joint_margins(state: m.RobotState, arm: ArmDescription) -> dict:
    """Each limited joint's distance to its nearer limit (deg): the joints against their limits, as one plot."""
    limited = [name for name, lower in zip(arm.joint_names, arm.model_limits()[0]) if np.isfinite(lower)]
    margins = arm.limit_margins_deg(np.asarray(state.q))
    return _series(state.header, **{name: float(v) for name, v in zip(limited, margins)},
                   minimum_deg=float(np.min(margins)) if len(margins) else None)


# ------------------------------------------------------------------------------------------------ 3D
def arm_transforms(link_poses: dict, stamp_ns: int) -> fm.FrameTransforms:
    """Every link of the description in the base frame (from :meth:`ArmKinematics.link_poses`)."""
    stamp = timestamp(stamp_ns)
    return fm.FrameTransforms(transforms=[
        fm.FrameTransform(timestamp=stamp, parent_frame_id=BASE_FRAME, child_frame_id=name, translation=_vector(p),
                          rotation=_quaternion(R))
        for name, (R, p) in link_poses.items() if name != BASE_FRAME])


def arm_scene(link_poses: dict, stamp_ns: int) -> fm.SceneUpdate:
    """The arm as a line through its joints' origins (base to end effector), drawn in the base frame."""
    stamp = timestamp(stamp_ns)
    origin = fm.Pose(position=_vector((0, 0, 0)), orientation=fm.Quaternion(w=1.0))
    chain = [p for name, (_, p) in link_poses.items()]
    line = fm.LinePrimitive(type=fm.LinePrimitiveLineType.LineStrip, pose=origin, thickness=0.03,
                            color=GREY, points=[fm.Point3(x=float(p[0]), y=float(p[1]), z=float(p[2]))
                                                for p in chain])
    joints = [fm.SpherePrimitive(pose=fm.Pose(position=_vector(p), orientation=fm.Quaternion(w=1.0)),
                                 size=_vector((0.05, 0.05, 0.05)), color=WHITE) for p in chain[2:-1]]
    return fm.SceneUpdate(entities=[fm.SceneEntity(timestamp=stamp, frame_id=BASE_FRAME, id="arm", lines=[line],
                                                   spheres=joints, frame_locked=False)])


def camera_transform(info: m.CameraInfo) -> fm.FrameTransform:
    pose = info.camera_in_ee
    return fm.FrameTransform(timestamp=timestamp(info.header.stamp_ns), parent_frame_id=EE_LINK,
                             child_frame_id=CAMERA_FRAME, translation=_vector(pose.xyz),
                             rotation=_pose_quaternion(pose))


def target_pose(features: m.Features) -> Optional[tuple[str, m.Pose]]:
    """The target's frame and its pose in the camera's, when vision has one: a tag's, or a keypoint target's (its
    taught view's frame, where the object's points were taught)."""
    if features.tag is not None:
        return TAG_FRAME, features.tag.pose_in_camera
    if features.keypoints is not None and features.keypoints.object_pose_in_camera is not None:
        return TAUGHT_FRAME, features.keypoints.object_pose_in_camera
    return None


def tag_transform(features: m.Features) -> Optional[fm.FrameTransform]:
    found = target_pose(features)
    if found is None:
        return None
    frame, pose = found
    return fm.FrameTransform(timestamp=timestamp(features.header.stamp_ns), parent_frame_id=CAMERA_FRAME,
                             child_frame_id=frame, translation=_vector(pose.xyz), rotation=_pose_quaternion(pose))


# ------------------------------------------------------------------------------------------------ logs
def safety_line(status: m.SafetyStatus) -> tuple[fm.LogLevel, str]:
    """Safety's status as a log line: its level and text."""
    level = {m.SafetyState.OK: fm.LogLevel.Info, m.SafetyState.LIMITING: fm.LogLevel.Warning,
             m.SafetyState.REFUSING: fm.LogLevel.Warning, m.SafetyState.ESTOP: fm.LogLevel.Error}[status.state]
    text = status.state.value
    if status.active_limits:
        text += f" (limits: {', '.join(status.active_limits)})"
    if status.in_control:
        text += f"; in control: {status.in_control}"
    if status.last_refusal:
        text += f"; last refusal: {status.last_refusal}"
    return level, text


def controller_line(status: m.ControllerStatus) -> tuple[fm.LogLevel, str]:
    """The controller's state as a log line (its iteration and error are series, not lines)."""
    bad = status.status in (m.ControllerState.ILL_CONDITIONED, m.ControllerState.CONSTRAINT_ABORT,
                            m.ControllerState.ARM_NOT_CHECKED)
    text = f"{status.law}: {status.status.value}"
    if status.detail:
        text += f" ({status.detail})"
    return (fm.LogLevel.Warning if bad else fm.LogLevel.Info), text


def estop_line(estop: m.EStop) -> tuple[fm.LogLevel, str]:
    verb = "reset" if estop.reset else "engaged"
    return fm.LogLevel.Error, f"e-stop {verb} by {estop.operator or 'someone'}: {estop.reason}"


# ------------------------------------------------------------------------------------------------ channels
def _json_schema(title: str) -> dict:
    return {"type": "object", "title": title}


#: the viewer's JSON series: (channel, the JSON schema's title)
SERIES = {"features": "mfvs.FeatureError", "twist": "mfvs.Twist", "joint_velocity": "mfvs.JointVelocity",
          "controller": "mfvs.Controller", "command": "mfvs.RobotCommand", "joint_margins": "mfvs.JointMargins"}


#: the viewer's channels in Foxglove's well-known schemas (the transforms and logs where Foxglove's panels look)
WELL_KNOWN = {"image": f"{VIEW}/camera/image", "calibration": f"{VIEW}/camera/calibration",
              "annotations": f"{VIEW}/camera/annotations", "joints": f"{VIEW}/robot/joints",
              "arm": f"{VIEW}/robot/arm", "transforms": "/tf", "logs": "/rosout"}


def view_topics() -> set[str]:
    """Every channel :class:`ViewChannels` logs on."""
    return set(WELL_KNOWN.values()) | {f"{VIEW}/{name}" for name in SERIES}


class ViewChannels:
    """The viewer's channels on a foxglove Context, and what each mfvs message puts on them. Statuses are logged
    when they change (a 10 Hz status that says the same thing is not a log line)."""

    def __init__(self, context: foxglove.Context) -> None:
        t = WELL_KNOWN
        self.image = fc.CompressedImageChannel(t["image"], context=context)
        self.calibration = fc.CameraCalibrationChannel(t["calibration"], context=context)
        self.annotations = fc.ImageAnnotationsChannel(t["annotations"], context=context)
        self.joints = fc.JointStatesChannel(t["joints"], context=context)
        self.transforms = fc.FrameTransformsChannel(t["transforms"], context=context)
        self.scene = fc.SceneUpdateChannel(t["arm"], context=context)
        self.logs = fc.LogChannel(t["logs"], context=context)
        self.series = {name: foxglove.Channel(f"{VIEW}/{name}", schema=_json_schema(title), context=context)
                       for name, title in SERIES.items()}
        #: the robot's arm, as its states declare it (the view follows the robot it watches)
        self.kinematics: Optional[ArmKinematics] = None
        self._info: Optional[m.CameraInfo] = None
        self._said: dict[str, str] = {}

    def _series(self, name: str, fields: dict, log_time: int) -> None:
        self.series[name].log(json_safe(fields), log_time=log_time)

    def _say(self, name: str, line: tuple, stamp_ns: int, log_time: int) -> None:
        level, text = line
        if self._said.get(name) != text:
            self._said[name] = text
            self.logs.log(fm.Log(timestamp=timestamp(stamp_ns), level=level, message=text, name=name),
                          log_time=log_time)

    def on_message(self, topic: Topic, message, log_time: int) -> None:
        """Log what ``message`` (of ``topic``'s type) shows; ``log_time`` is when it was received (ns)."""
        kind = topic.message_type
        if kind is m.Image:
            self.image.log(camera_image(message), log_time=log_time)
        elif kind is m.CameraInfo:
            self._info = message
            self.calibration.log(camera_calibration(message), log_time=log_time)
            self.transforms.log(fm.FrameTransforms(transforms=[camera_transform(message)]), log_time=log_time)
        elif kind is m.Features:
            self.annotations.log(corner_annotations(message, self._info), log_time=log_time)
            self._series("features", feature_error(message), log_time)
            tag = tag_transform(message)
            if tag is not None:
                self.transforms.log(fm.FrameTransforms(transforms=[tag]), log_time=log_time)
        elif kind is m.Twist:
            self._series("twist", twist(message), log_time)
        elif kind is m.JointVelocity:
            self._series("joint_velocity", joint_velocity(message), log_time)
        elif kind is m.ControllerStatus:
            self._series("controller", controller(message), log_time)
            self._say("controller", controller_line(message), message.header.stamp_ns, log_time)
        elif kind is m.RobotCommand:
            self._series("command", robot_command(message), log_time)
        elif kind is m.SafetyStatus:
            self._say("safety", safety_line(message), message.header.stamp_ns, log_time)
        elif kind is m.EStop:
            self._say("estop", estop_line(message), message.header.stamp_ns, log_time)
        elif kind is m.RobotState:
            current = self.kinematics.arm if self.kinematics is not None else None
            arm, why = declared_arm(message.arm, message.arm_digest, len(message.q), None,
                                    current if current is not None and current.name == message.arm else None)
            if arm is None:
                self._say("robot", (fm.LogLevel.Error, f"arm: {why}"), message.header.stamp_ns, log_time)
                return
            if arm is not current:
                self.kinematics = ArmKinematics(arm)
            links = self.kinematics.link_poses(message.q)
            self.joints.log(joint_states(message, arm), log_time=log_time)
            self.transforms.log(arm_transforms(links, message.header.stamp_ns), log_time=log_time)
            self.scene.log(arm_scene(links, message.header.stamp_ns), log_time=log_time)
            self._series("joint_margins", joint_margins(message, arm), log_time)
            if message.faults:
                self._say("robot", (fm.LogLevel.Error, "; ".join(message.faults)), message.header.stamp_ns,
                          log_time)


class RawChannels:
    """The stack's payloads as received, one channel per key (the key is the topic), MessagePack described by
    the message type's JSON schema: what ``mfvs replay`` publishes back."""

    def __init__(self, context: foxglove.Context) -> None:
        self.context = context
        self._channels: dict[str, foxglove.Channel] = {}

    def log(self, topic: Topic, payload: bytes, log_time: int) -> None:
        channel = self._channels.get(topic.key)
        if channel is None:
            kind = topic.message_type
            schema = foxglove.Schema(name=f"mfvs.{kind.__name__}", encoding="jsonschema",
                                     data=msgspec.json.encode(msgspec.json.schema(kind)))
            channel = foxglove.Channel(topic.key, message_encoding=RAW_ENCODING, schema=schema, context=self.context,
                                       metadata={RAW_TYPE: kind.__name__,
                                                 RAW_SCHEMA_VERSION: str(m.SCHEMA_VERSION)})
            self._channels[topic.key] = channel
        channel.log(payload, log_time=log_time)
