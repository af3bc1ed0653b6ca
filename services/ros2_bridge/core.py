"""The ROS 2 bridge's pure side: what mfvs's messages are as ROS 2 messages, the node's graph as rmw_zenoh writes it
(keys, liveliness tokens, GIDs), and what a ROS 2 input may ask of the stack. No zenoh, no threads, no locks: the
service (services/ros2_bridge/service.py) feeds it and puts what it returns on the wire.

The frames are the ones ``mfvs view`` shows in Foxglove (services/observe/foxglove_view.py): the arm's links from
its description's kinematics, the camera (OpenCV's optical frame, which is ROS's ``*_optical_frame`` convention:
z forward, x right, y down) mounted on the end effector, and the tag where vision sees it.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Optional

import msgspec
import numpy as np

from protocol import messages as m
from protocol.messages import JOG_SPEED_LEVELS, JogMode
from protocol.ros2 import cdr, keys as ros_keys, types as ros_types
from protocol.ros2.attachment import Attachment, AttachmentError, decode as decode_attachment
from protocol.ros2.gid import entity_gid
from protocol.ros2.keys import Distro, Durability, EntityKind, Qos, Reliability
from services.jog.mapping import MODE_CYCLE, JogMapping, JogMotion, JogSpeeds, StickInput, StickMapper
from services.jog.sender import JogStamper
from services.model import frames
from services.model.arm import BASE_LINK, EE_LINK, ArmDescription
from services.observe.foxglove_view import CAMERA_FRAME, TAG_FRAME, target_pose
from services.runtime.config import ConfigStruct

#: what ROS 2 calls mfvs's image encodings (sensor_msgs/image_encodings.hpp spells the same three the same way)
ROS_ENCODINGS = {m.ImageEncoding.RGB8: "rgb8", m.ImageEncoding.BGR8: "bgr8", m.ImageEncoding.MONO8: "mono8"}


# ------------------------------------------------------------------------------------------------ the node's graph
@dataclass(frozen=True)
class Endpoint:
    """One publisher, subscription or service server of the bridge's node."""
    kind: EntityKind
    #: as the node asks for it: relative names go under the namespace (ROS's own resolution)
    name: str
    ros_type: ros_types.RosType
    qos: Qos


# QoS as the usual ROS 2 publishers of these topics ask (rclcpp's SensorDataQoS for the camera, tf2's broadcasters,
# robot_state_publisher), so that a ROS tool that checks compatibility finds what it expects
_SENSOR = Qos(reliability=Reliability.BEST_EFFORT, depth=5)
_RELIABLE_10 = Qos(depth=10)
_LATCHED = Qos(durability=Durability.TRANSIENT_LOCAL, depth=1)

#: what the bridge publishes (names as a ROS camera driver, tf2 and robot_state_publisher use them)
IMAGE = Endpoint(EntityKind.PUBLISHER, "camera/image_raw", ros_types.IMAGE, _SENSOR)
CAMERA_INFO = Endpoint(EntityKind.PUBLISHER, "camera/camera_info", ros_types.CAMERA_INFO, _SENSOR)
JOINT_STATES = Endpoint(EntityKind.PUBLISHER, "joint_states", ros_types.JOINT_STATE, _RELIABLE_10)
TF = Endpoint(EntityKind.PUBLISHER, "/tf", ros_types.TF_MESSAGE, Qos(depth=100))
TF_STATIC = Endpoint(EntityKind.PUBLISHER, "/tf_static", ros_types.TF_MESSAGE, _LATCHED)
ROBOT_DESCRIPTION = Endpoint(EntityKind.PUBLISHER, "robot_description", ros_types.STRING, _LATCHED)
DIAGNOSTICS = Endpoint(EntityKind.PUBLISHER, "/diagnostics", ros_types.DIAGNOSTIC_ARRAY, _RELIABLE_10)
#: what it accepts: the task and the e-stop as services, the goal as a topic
START_TASK = Endpoint(EntityKind.SERVICE_SERVER, "mfvs/start_task", ros_types.TRIGGER, _RELIABLE_10)
STOP_TASK = Endpoint(EntityKind.SERVICE_SERVER, "mfvs/stop_task", ros_types.TRIGGER, _RELIABLE_10)
#: goes on with a task the person's stick paused (the controller's resume_task, as `mfvs task resume`)
RESUME_TASK = Endpoint(EntityKind.SERVICE_SERVER, "mfvs/resume_task", ros_types.TRIGGER, _RELIABLE_10)
ESTOP = Endpoint(EntityKind.SERVICE_SERVER, "mfvs/estop", ros_types.TRIGGER, _RELIABLE_10)
GOAL_POSE = Endpoint(EntityKind.SUBSCRIPTION, "mfvs/goal_pose", ros_types.POSE_STAMPED, _RELIABLE_10)
#: a person's stick, as jog requests: the ROS joy driver's topic and QoS (joy.cpp: "joy", depth 10, reliable), and
#: MoveIt Servo's Cartesian input (its cartesian_command_in_topic "~/delta_twist_cmds", depth 10: servo_node.cpp)
JOY = Endpoint(EntityKind.SUBSCRIPTION, "joy", ros_types.JOY, _RELIABLE_10)
DELTA_TWIST = Endpoint(EntityKind.SUBSCRIPTION, "~/delta_twist_cmds", ros_types.TWIST_STAMPED, _RELIABLE_10)

ENDPOINTS = (IMAGE, CAMERA_INFO, JOINT_STATES, TF, TF_STATIC, ROBOT_DESCRIPTION, DIAGNOSTICS, START_TASK, STOP_TASK,
             RESUME_TASK, ESTOP, GOAL_POSE, JOY, DELTA_TWIST)


@dataclass(frozen=True)
class Declared:
    """An endpoint as the node declares it on zenoh: its data key, its liveliness token and the GID rmw_zenoh
    derives from that token."""
    endpoint: Endpoint
    fully_qualified_name: str
    key: str
    token: str
    gid: bytes


@dataclass(frozen=True)
class NodeGraph:
    """The node's token and every endpoint's key, token and GID, from the settings and the session's zenoh id. The
    node's id is 0 and its endpoints count from 1 in ENDPOINTS' order (rmw_zenoh counts both per context; a
    bridge is one context with one node)."""
    domain_id: int
    namespace: str
    node_name: str
    distro: Distro
    zenoh_id: str
    node_token: str
    endpoints: dict[Endpoint, Declared]

    @classmethod
    def build(cls, domain_id: int, namespace: str, node_name: str, distro: Distro, zenoh_id: str) -> "NodeGraph":
        node_id = 0
        declared = {}
        for entity_id, endpoint in enumerate(ENDPOINTS, start=1):
            name = ros_keys.fully_qualified_name(namespace, endpoint.name, node_name)
            token = ros_keys.endpoint_token(endpoint.kind, domain_id, zenoh_id, node_id, entity_id, namespace,
                                            node_name, name, endpoint.ros_type.name, endpoint.ros_type.rihs01,
                                            endpoint.qos, distro)
            key = ros_keys.data_key(domain_id, name, endpoint.ros_type.name, endpoint.ros_type.rihs01, distro)
            declared[endpoint] = Declared(endpoint, name, key, token, entity_gid(token))
        return cls(domain_id, namespace, node_name, distro, zenoh_id,
                   ros_keys.node_token(domain_id, zenoh_id, node_id, namespace, node_name), declared)

    def watch_key(self) -> str:
        """Every token of the domain: what a graph watcher subscribes to (here, for the image's subscribers)."""
        return ros_keys.liveliness_subscription_key(self.domain_id)


class SubscriberWatch:
    """Which topics have a subscription somewhere in the ROS graph, from the liveliness tokens seen come and go:
    rmw_zenoh (2026) publishes a ``uint8[]`` type only while one is visible, and so does the bridge for the
    image (an image nobody reads is 900 kB of CDR for nothing)."""

    def __init__(self, domain_id: int) -> None:
        self.domain_id = domain_id
        self._subscribers: dict[str, tuple[str, str]] = {}  # token -> (topic, DDS type)

    def on_token(self, token: str, alive: bool) -> None:
        if not alive:
            self._subscribers.pop(token, None)
            return
        try:
            parsed = ros_keys.parse_token(token)
        except ros_keys.InvalidName:
            return  # a token of something else in the admin space: not a subscription we could serve
        if parsed.kind is EntityKind.SUBSCRIPTION and parsed.domain_id == self.domain_id:
            self._subscribers[token] = (parsed.name, parsed.dds_type)

    def has_subscriber(self, name: str, ros_type: str) -> bool:
        wanted = (name, ros_keys.dds_type_name(ros_type))
        return wanted in self._subscribers.values()


# ------------------------------------------------------------------------------------------------ outputs
class Untranslatable(ValueError):
    """An mfvs message that has no faithful ROS 2 form (counted by the service, never published half-right)."""


def stamp(ns: int) -> cdr.Time:
    return cdr.Time(sec=int(ns // 1_000_000_000), nanosec=int(ns % 1_000_000_000))


def header(ns: int, frame_id: str) -> cdr.Header:
    return cdr.Header(stamp=stamp(ns), frame_id=frame_id)


def image(message: m.Image) -> cdr.Image:
    channels = m.CHANNELS[message.encoding]
    return cdr.Image(header=header(message.header.stamp_ns, CAMERA_FRAME), height=message.height,
                     width=message.width, encoding=ROS_ENCODINGS[message.encoding], is_bigendian=0,
                     step=message.width * channels, data=message.data)


def camera_info(info: m.CameraInfo) -> cdr.CameraInfo:
    """The intrinsics as ROS states them: K, the identity R (a monocular camera), P = [K | 0], and OpenCV's
    distortion under the ROS model of that many coefficients (plumb_bob: 5, rational_polynomial: 8)."""
    distortion = list(info.distortion)
    if len(distortion) <= 5:
        model, d = "plumb_bob", distortion + [0.0] * (5 - len(distortion))
    elif len(distortion) == 8:
        model, d = "rational_polynomial", distortion
    else:
        raise Untranslatable(f"{len(distortion)} distortion coefficients: ROS models take 5 (plumb_bob) or 8 "
                             "(rational_polynomial)")
    k = [info.fx, 0.0, info.cx, 0.0, info.fy, info.cy, 0.0, 0.0, 1.0]
    p = [info.fx, 0.0, info.cx, 0.0, 0.0, info.fy, info.cy, 0.0, 0.0, 0.0, 1.0, 0.0]
    return cdr.CameraInfo(header=header(info.header.stamp_ns, CAMERA_FRAME), height=info.height, width=info.width,
                          distortion_model=model, d=np.asarray(d, dtype=float), k=np.asarray(k),
                          r=np.eye(3).ravel(), p=np.asarray(p))


def joint_state(state: m.RobotState, arm: ArmDescription) -> cdr.JointState:
    """The joints by the names of the arm's URDF (robot_description), model angles (rad), rates, torques."""
    return cdr.JointState(header=header(state.header.stamp_ns, ""), name=arm.joint_names,
                          position=np.asarray(state.q, dtype=float), velocity=np.asarray(state.dq, dtype=float),
                          effort=np.asarray(state.tau, dtype=float))


def _transform(parent: str, child: str, ns: int, R, p) -> cdr.TransformStamped:
    w, x, y, z = frames.matrix_to_quat_wxyz(np.asarray(R, dtype=float))
    return cdr.TransformStamped(
        header=header(ns, parent), child_frame_id=child,
        transform=cdr.Transform(translation=cdr.Vector3(*(float(v) for v in p)),
                                rotation=cdr.Quaternion(float(x), float(y), float(z), float(w))))


def _pose_transform(parent: str, child: str, ns: int, pose: m.Pose) -> cdr.TransformStamped:
    return _transform(parent, child, ns, frames.quat_wxyz_to_matrix(pose.quat_wxyz), pose.xyz)


def chain(arm: ArmDescription) -> list[str]:
    """The links of the arm's URDF from the base to the end effector, each the parent of the next."""
    return [BASE_LINK, "link_0", *arm.link_names, EE_LINK]


def arm_tf(link_poses: dict, arm: ArmDescription, stamp_ns: int) -> cdr.TFMessage:
    """Every joint of the URDF's chain as parent → child (``link_poses``: ArmKinematics.link_poses, each link in the
    base frame), so the tree is the URDF's and RViz's RobotModel finds every link under base_link."""
    links = chain(arm)
    out = []
    for parent, child in zip(links, links[1:]):
        R_parent, p_parent = link_poses[parent]
        R_child, p_child = link_poses[child]
        out.append(_transform(parent, child, stamp_ns, R_parent.T @ R_child, R_parent.T @ (p_child - p_parent)))
    return cdr.TFMessage(transforms=tuple(out))


def camera_mount(info: m.CameraInfo) -> cdr.TFMessage:
    """The camera on the end effector: what /tf_static carries (a hand-eye calibration changes it; then it is sent
    again)."""
    return cdr.TFMessage(transforms=(_pose_transform(EE_LINK, CAMERA_FRAME, info.header.stamp_ns,
                                                     info.camera_in_ee),))


def tag_tf(features: m.Features) -> Optional[cdr.TFMessage]:
    """The target in the camera frame, when vision has its pose: the tag, or a taught view's object (its frame
    ``taught_view``)."""
    found = target_pose(features)
    if found is None:
        return None
    frame, pose = found
    return cdr.TFMessage(transforms=(_pose_transform(CAMERA_FRAME, frame, features.header.stamp_ns, pose),))


def robot_description(arm: ArmDescription) -> cdr.String:
    """The URDF the arm's description generates, the one Pinocchio and MuJoCo load (ArmDescription.urdf)."""
    return cdr.String(data=arm.urdf())


# ------------------------------------------------------------------------------------------------ diagnostics
#: a service not heard for this long is STALE
STALE_AFTER_NS = 5_000_000_000
HARDWARE_ID = "mfvs"


@dataclass
class Diagnostics:
    """What /diagnostics says: each service's health (its ServiceHealth, heard on health/<name>), the servo task
    (the controller's last status) and safety's state, each with when it was heard (``now_ns`` given by the caller,
    on the clock it hears them by)."""
    robot_id: str
    health: dict[str, tuple[m.ServiceHealth, int]] = field(default_factory=dict)
    controller: Optional[tuple[m.ControllerStatus, int]] = None
    safety: Optional[tuple[m.SafetyStatus, int]] = None

    def on_health(self, health: m.ServiceHealth, now_ns: int) -> None:
        self.health[health.service] = (health, now_ns)

    def on_controller(self, status: m.ControllerStatus, now_ns: int) -> None:
        self.controller = (status, now_ns)

    def on_safety(self, status: m.SafetyStatus, now_ns: int) -> None:
        self.safety = (status, now_ns)

    def _status(self, name: str, level: int, message: str, values: dict, heard_ns: int,
                now_ns: int) -> cdr.DiagnosticStatus:
        if now_ns - heard_ns > STALE_AFTER_NS:
            level, message = cdr.DiagnosticStatus.STALE, f"not heard for {(now_ns - heard_ns) / 1e9:.0f} s: {message}"
        return cdr.DiagnosticStatus(
            level=level, name=f"mfvs/{self.robot_id}/{name}", message=message[:256], hardware_id=HARDWARE_ID,
            values=tuple(cdr.KeyValue(key=str(k), value=str(v)) for k, v in values.items()))

    def array(self, now_ns: int, stamp_ns: int) -> cdr.DiagnosticArray:
        statuses = []
        for name, (health, heard) in sorted(self.health.items()):
            level = (cdr.DiagnosticStatus.ERROR if not health.healthy else
                     cdr.DiagnosticStatus.WARN if health.degraded else cdr.DiagnosticStatus.OK)
            message = "; ".join([health.state, *health.degraded] + ([health.detail] if health.detail else []))
            values = {"pid": health.pid, "uptime_s": f"{health.uptime_s:.0f}",
                      **{f"rate.{k}": f"{v:.1f}" for k, v in sorted(health.rates_hz.items())},
                      **{f"errors.{k}": v for k, v in sorted(health.errors.items())}}
            statuses.append(self._status(name, level, message, values, heard, now_ns))
        if self.controller is not None:
            status, heard = self.controller
            bad = status.status in (m.ControllerState.ILL_CONDITIONED, m.ControllerState.CONSTRAINT_ABORT,
                                    m.ControllerState.ARM_NOT_CHECKED, m.ControllerState.WRONG_ARM)
            message = status.status.value + (f" ({status.detail})" if status.detail else "")
            statuses.append(self._status(
                "task", cdr.DiagnosticStatus.WARN if bad else cdr.DiagnosticStatus.OK, message,
                {"law": status.law, "state": status.status.value, "iteration": status.iteration,
                 "error_norm": f"{status.error_norm:.6g}", "saturated": status.saturated}, heard, now_ns))
        if self.safety is not None:
            status, heard = self.safety
            level = {m.SafetyState.OK: cdr.DiagnosticStatus.OK, m.SafetyState.LIMITING: cdr.DiagnosticStatus.WARN,
                     m.SafetyState.REFUSING: cdr.DiagnosticStatus.WARN,
                     m.SafetyState.ESTOP: cdr.DiagnosticStatus.ERROR}[status.state]
            values = {"state": status.state.value, "active_limits": ", ".join(status.active_limits),
                      "last_refusal": status.last_refusal}
            statuses.append(self._status("safety", level, status.state.value, values, heard, now_ns))
        return cdr.DiagnosticArray(header=header(stamp_ns, ""), status=tuple(statuses))


# ------------------------------------------------------------------------------------------------ inputs
class InputError(ValueError):
    """A ROS 2 input the bridge refuses: ``kind`` names its counter (``rejected.<kind>``), the text says why."""

    def __init__(self, kind: str, message: str) -> None:
        super().__init__(message)
        self.kind = kind


def request_attachment(raw: Optional[bytes]) -> Attachment:
    """The attachment of a service request: rmw_zenoh's client always sends one (its sequence number and GID go
    back in the reply), and a request without one is no ROS 2 client's."""
    if raw is None:
        raise InputError("attachment", "a request without rmw_zenoh's attachment (sequence number, timestamp, GID)")
    try:
        return decode_attachment(raw)
    except (AttachmentError, IndexError) as exc:
        raise InputError("attachment", f"not an rmw_zenoh attachment: {exc}") from None


def reply_attachment(request: Attachment, now_ns: int) -> Attachment:
    """What a service's reply carries: the request's sequence number and client GID, the reply's own time
    (design.md "Service Servers")."""
    return Attachment(request.sequence_number, now_ns, request.source_gid)


def trigger_request(payload: bytes) -> cdr.TriggerRequest:
    try:
        return cdr.deserialize(payload, cdr.TriggerRequest)
    except cdr.CdrError as exc:
        raise InputError("cdr", str(exc)) from None


def trigger_response(success: bool, message: str) -> bytes:
    return cdr.serialize(cdr.TriggerResponse(success=success, message=message))


@dataclass(frozen=True)
class GoalLimits:
    """What a goal pose may be before it is passed to vision (which checks it again against its own model): the
    camera this near the tag at least (m), this far at most."""
    min_distance_m: float = 0.05
    max_distance_m: float = 2.0
    #: how far from 1 the quaternion's norm may be (it is then normalized; ROS tools send rounded quaternions)
    quaternion_tolerance: float = 1e-3


def goal_pose(payload: bytes, limits: GoalLimits = GoalLimits()) -> m.Pose:
    """The goal a geometry_msgs/PoseStamped asks for: the camera's pose in the tag's frame (frame_id ``tag``), as
    vision takes it (``VisionGoal.camera_in_tag``). Malformed CDR, another frame, NaN or infinity, a quaternion that is
    not one, a camera inside the tag or metres away: InputError, nothing sent."""
    try:
        pose = cdr.deserialize(payload, cdr.PoseStamped)
    except cdr.CdrError as exc:
        raise InputError("cdr", str(exc)) from None
    if pose.header.frame_id != TAG_FRAME:
        raise InputError("frame", f"a goal is the camera in the tag's frame: frame_id {TAG_FRAME!r}, got "
                                  f"{pose.header.frame_id[:64]!r}")
    p, o = pose.pose.position, pose.pose.orientation
    values = (p.x, p.y, p.z, o.w, o.x, o.y, o.z)
    if not all(math.isfinite(v) for v in values):
        raise InputError("not_finite", f"a goal pose with NaN or infinity: {values}")
    norm = math.hypot(o.w, o.x, o.y, o.z)  # finite however large the values (squares would overflow)
    if abs(norm - 1.0) > limits.quaternion_tolerance:
        raise InputError("quaternion", f"the orientation is no unit quaternion (norm {norm:.6g})")
    distance = math.hypot(p.x, p.y, p.z)
    if not limits.min_distance_m <= distance <= limits.max_distance_m:
        raise InputError("distance", f"the camera {distance:.3g} m from the tag: a goal is "
                                     f"{limits.min_distance_m:g} to {limits.max_distance_m:g} m from it")
    quat = tuple(v / norm for v in (o.w, o.x, o.y, o.z))
    return m.Pose(xyz=(p.x, p.y, p.z), quat_wxyz=quat)


# ------------------------------------------------------------------------------------------------ a stick from ROS 2
#: the sources the bridge's jog requests carry (safety counts each one's sequence on its own)
JOY_SOURCE = "jog/ros-joy"
TWIST_SOURCE = "jog/ros-twist"


class JoyAxis(ConfigStruct):
    #: the axis's index in sensor_msgs/Joy's ``axes``
    index: int
    #: its sign flipped
    invert: bool = False

    def __post_init__(self) -> None:
        if isinstance(self.index, bool) or not 0 <= self.index < 64:
            raise ValueError(f"axis index {self.index}: 0..63")


#: no button for this role
NO_BUTTON = -1


class JoyMap(ConfigStruct):
    """Which of a sensor_msgs/Joy's axes and buttons do what: the ROS joy driver's (joy_node's) indices. The
    defaults are ours, for an Xbox 360 pad under the joy driver, the same roles as `mfvs jog`'s gamepad map: the
    left stick's vertical (1) and horizontal (0) and the right stick's vertical (4) are the three axes (the driver
    already makes up and left positive: joy.cpp), LB (4) the dead-man, A (0) the mode, RB (5) and X (2) the speed
    level up and down, Start (7) resumes a paused task. MoveIt Servo's xbox360_wired.yaml and joystick_to_servo.yaml
    name the same indices for this pad (axes 1, 0, 4; LB 4, RB 5, X 2, B 1, START 7)."""

    axes: list[JoyAxis] = msgspec.field(default_factory=lambda: [JoyAxis(index=1), JoyAxis(index=0),
                                                                 JoyAxis(index=4)])
    #: held: the arm may move (teleop_twist_joy's enable_button); released: it stops at once
    deadman: int = 4
    #: each press: translation -> wrist -> fingers (-1: none, the mode stays translation)
    mode: int = 0
    #: each press: one speed level up, down (-1: none)
    speed_up: int = 5
    speed_down: int = 2
    #: each press: the controller's resume_task, a task the stick paused goes on (-1: none)
    resume: int = 7

    def __post_init__(self) -> None:
        if len(self.axes) != 3:
            raise ValueError("joy.axes: the stick's three (translation X, Y, Z; wrist about x, y, z)")
        if isinstance(self.deadman, bool) or not 0 <= self.deadman < 128:
            raise ValueError(f"joy.deadman {self.deadman}: a button index 0..127 (a jog always has a dead-man)")
        roles = {"mode": self.mode, "speed_up": self.speed_up, "speed_down": self.speed_down, "resume": self.resume}
        for role, index in roles.items():
            if isinstance(index, bool) or not NO_BUTTON <= index < 128:
                raise ValueError(f"joy.{role} {index}: a button index 0..127, or -1 for none")
        used = [self.deadman] + [index for index in roles.values() if index != NO_BUTTON]
        if len(set(used)) != len(used):
            raise ValueError(f"joy: one button for two roles ({used})")

    @property
    def axes_needed(self) -> int:
        return 1 + max(axis.index for axis in self.axes)

    @property
    def buttons_needed(self) -> int:
        return 1 + max(self.deadman, self.mode, self.speed_up, self.speed_down, self.resume)


class RosJogConfig(ConfigStruct):
    """How the bridge turns a ROS stick (sensor_msgs/Joy) and a ROS velocity (geometry_msgs/TwistStamped) into a
    person's jog requests (docs/ros2.md, "A stick from ROS 2")."""

    #: where a Joy stream's speed level starts (1..3): the slowest, as `mfvs jog`'s, for a person's first touch
    speed_level: int = JOG_SPEED_LEVELS[0]
    #: the dead band 0.05, ours: the joy driver has already taken its own (its ``deadzone``, 0.05 by default) and
    #: rescaled, so the two together leave a stick still within 0.0975 of its centre, `mfvs jog`'s 0.1
    mapping: JogMapping = msgspec.field(default_factory=lambda: JogMapping(dead_band=0.05))
    joy: JoyMap = msgspec.field(default_factory=JoyMap)
    #: a ROS message's header stamp is taken as when its device was heard if it is within this of the bridge's
    #: clock (s); otherwise the receipt is (and counted): 0.05, ours, safety's own future_skew_s
    stamp_skew_s: float = 0.05

    def __post_init__(self) -> None:
        if self.speed_level not in JOG_SPEED_LEVELS:
            raise ValueError(f"jog.speed_level must be one of {JOG_SPEED_LEVELS}")
        if not (math.isfinite(self.stamp_skew_s) and 0.0 <= self.stamp_skew_s <= 0.2):
            raise ValueError("jog.stamp_skew_s must be within 0..0.2 s (safety's device budget is 0.25 s)")


def ros_time_ns(stamp: cdr.Time, what: str) -> int:
    if not 0 <= stamp.nanosec < 1_000_000_000:
        raise InputError("stamp", f"a {what} stamped with nanosec {stamp.nanosec}: 0..999999999")
    return stamp.sec * 1_000_000_000 + stamp.nanosec


def device_heard_ns(stamp_ns: int, receipt_ns: int, skew_s: float) -> tuple[int, bool]:
    """When a ROS message's device was heard, and whether its own stamp says so: the stamp when it lies within
    ``skew_s`` of the receipt (never after the receipt: a stamp ahead of the bridge's clock counts as the receipt),
    else the receipt (a publisher whose clock is off, or an unstamped message: its stamps say nothing the bridge
    can use, and taken as they are they would make safety refuse every request, or accept stale ones)."""
    skew_ns = int(skew_s * 1e9)
    if abs(stamp_ns - receipt_ns) <= skew_ns:
        return min(stamp_ns, receipt_ns), True
    return receipt_ns, False


class JoyStick:
    """A sensor_msgs/Joy stream as a stick: each message checked and read through a :class:`JoyMap` (its axes, its
    dead-man), the mode and speed buttons stepping on a press (a button going from 0 to 1; the first message only
    sets what is held), the resume button's press kept in :attr:`resume_pressed` for the message that made it."""

    def __init__(self, joy_map: JoyMap, speed_level: int) -> None:
        self.map = joy_map
        self.mode_index = 0
        self.speed_level = speed_level
        self._held: Optional[np.ndarray] = None
        #: whether the last message read pressed the resume button
        self.resume_pressed = False

    def read(self, joy: cdr.Joy) -> StickInput:
        cfg = self.map
        axes, buttons = joy.axes, joy.buttons
        if len(axes) < cfg.axes_needed or len(buttons) < cfg.buttons_needed:
            raise InputError("size", f"a Joy of {len(axes)} axes and {len(buttons)} buttons: the map needs "
                                     f"{cfg.axes_needed} axes and {cfg.buttons_needed} buttons (ros2_bridge.yaml "
                                     "jog.joy)")
        if not np.all(np.isfinite(axes)):
            raise InputError("not_finite", f"a Joy with NaN or infinite axes: {list(axes)[:16]}")
        if np.any(np.abs(axes) > 1.0):
            raise InputError("range", f"a Joy axis beyond [-1, 1]: {list(axes)[:16]}")
        if np.any((buttons != 0) & (buttons != 1)):
            raise InputError("button", f"a Joy button neither 0 nor 1: {list(buttons)[:32]}")
        pressed = buttons.astype(bool)
        self.resume_pressed = False
        if self._held is not None and len(self._held) == len(pressed):
            def press(index: int) -> bool:
                return index != NO_BUTTON and bool(pressed[index]) and not self._held[index]
            if press(cfg.mode):
                self.mode_index = (self.mode_index + 1) % len(MODE_CYCLE)
            if press(cfg.speed_up):
                self.speed_level = min(self.speed_level + 1, JOG_SPEED_LEVELS[-1])
            if press(cfg.speed_down):
                self.speed_level = max(self.speed_level - 1, JOG_SPEED_LEVELS[0])
            self.resume_pressed = press(cfg.resume)
        self._held = pressed
        values = tuple(float(-axes[a.index] if a.invert else axes[a.index]) for a in cfg.axes)
        return StickInput(axes=values, mode=MODE_CYCLE[self.mode_index], speed_level=self.speed_level,
                          deadman=bool(pressed[cfg.deadman]))


def twist_motion(twist: cdr.TwistStamped, speeds: JogSpeeds, base_frame: str = BASE_LINK,
                 hand_frame: str = EE_LINK) -> JogMotion:
    """The jog a geometry_msgs/TwistStamped asks for. A jog moves one mode at a time in the mixed frame (Kinova's
    stick): ``linear`` along the base's axes, frame_id the base's (``base_link``): a translation; ``angular`` about the
    hand's own axes, frame_id the hand's (``end_effector``): a wrist turn. A twist that does both, or states one in
    the other's frame, is refused rather than converted (a conversion would rest on the last arm state the bridge
    heard, which it only follows while a ROS tool reads /tf). An all-zero twist is a release (the dead-man let go:
    teleop_twist_joy sends one when its enable button is released); any other is a held dead-man, MoveIt Servo's
    way: a velocity stream is the request while it flows, and its staleness (safety's 100 ms) the release. Faster
    than the stick's full speed of its mode (``speeds``): refused."""
    header = twist.header
    linear = (twist.twist.linear.x, twist.twist.linear.y, twist.twist.linear.z)
    angular = (twist.twist.angular.x, twist.twist.angular.y, twist.twist.angular.z)
    if not all(math.isfinite(v) for v in linear + angular):
        raise InputError("not_finite", f"a twist with NaN or infinity: linear {linear}, angular {angular}")
    frame = header.frame_id
    if frame not in (base_frame, hand_frame):
        raise InputError("frame", f"a twist's frame_id is {base_frame!r} (linear, along the base's axes) or "
                                  f"{hand_frame!r} (angular, about the hand's), got {frame[:64]!r}")
    moves, turns = any(linear), any(angular)
    top = JOG_SPEED_LEVELS[-1]
    if not moves and not turns:
        return JogMotion(JogMode.TRANSLATION if frame == base_frame else JogMode.WRIST, top, deadman=False)
    if moves and turns:
        raise InputError("mixed", "a twist both moving and turning: a jog is one mode at a time; send linear in "
                                  f"{base_frame!r} or angular in {hand_frame!r}")
    if moves and frame != base_frame:
        raise InputError("frame", f"linear velocity in {frame!r}: a jog moves along the base's axes, frame_id "
                                  f"{base_frame!r}")
    if turns and frame != hand_frame:
        raise InputError("frame", f"angular velocity in {frame!r}: a jog turns about the hand's own axes, frame_id "
                                  f"{hand_frame!r}")
    values, limit = (linear, speeds.linear_mps) if moves else (angular, speeds.angular_rps)
    if max(abs(v) for v in values) > limit:
        raise InputError("speed", f"a twist of {values}: {'m/s' if moves else 'rad/s'} up to {limit:g} per axis "
                                  "(ros2_bridge.yaml jog.mapping.speeds)")
    values = tuple(float(v) for v in values)
    if moves:
        return JogMotion(JogMode.TRANSLATION, top, True, linear=values)
    return JogMotion(JogMode.WRIST, top, True, angular=values)


@dataclass
class Relayed:
    """A jog request made of a ROS message, whether that message's own stamp was used (False: the receipt), and
    whether it pressed the stick's resume button."""
    jog: m.Jog
    stamp_used: bool
    resume: bool = False


class JogRelay:
    """ROS 2 sticks and velocities as a person's jog requests, each sequenced per source (``jog/ros-joy``,
    ``jog/ros-twist``) and stamped: ``header.stamp_ns`` the receipt (the bridge's clock), ``source_stamp_ns`` when the
    device was heard (:func:`device_heard_ns`). Pure: the caller gives the times. Not thread-safe: one caller at a
    time."""

    def __init__(self, config: RosJogConfig, base_frame: str = BASE_LINK, hand_frame: str = EE_LINK) -> None:
        self.config = config
        self.base_frame, self.hand_frame = base_frame, hand_frame
        self.stick = JoyStick(config.joy, config.speed_level)
        self.mapper = StickMapper(config.mapping)
        self.joy_stamper = JogStamper(JOY_SOURCE)
        self.twist_stamper = JogStamper(TWIST_SOURCE)

    def joy(self, payload: bytes, receipt_ns: int, monotonic_s: float) -> Relayed:
        """A sensor_msgs/Joy's CDR as a jog request (``monotonic_s``: the spasm filter's time)."""
        try:
            joy = cdr.deserialize(payload, cdr.Joy)
        except cdr.CdrError as exc:
            raise InputError("cdr", str(exc)) from None
        stamp_ns = ros_time_ns(joy.header.stamp, "Joy")
        stick = self.stick.read(joy)
        heard_ns, used = device_heard_ns(stamp_ns, receipt_ns, self.config.stamp_skew_s)
        motion = self.mapper(stick, monotonic_s)
        return Relayed(self.joy_stamper.message(motion, True, now_ns=receipt_ns, heard_ns=heard_ns), used,
                       resume=self.stick.resume_pressed)

    def twist(self, payload: bytes, receipt_ns: int) -> Relayed:
        """A geometry_msgs/TwistStamped's CDR as a jog request (:func:`twist_motion`)."""
        try:
            twist = cdr.deserialize(payload, cdr.TwistStamped)
        except cdr.CdrError as exc:
            raise InputError("cdr", str(exc)) from None
        stamp_ns = ros_time_ns(twist.header.stamp, "TwistStamped")
        motion = twist_motion(twist, self.config.mapping.speeds, self.base_frame, self.hand_frame)
        heard_ns, used = device_heard_ns(stamp_ns, receipt_ns, self.config.stamp_skew_s)
        return Relayed(self.twist_stamper.message(motion, True, now_ns=receipt_ns, heard_ns=heard_ns), used)
