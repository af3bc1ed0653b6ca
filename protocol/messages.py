"""Message types of the wire contract, encoded as MessagePack maps (field name → value).

Every message carries a :class:`Header`. Decoding validates types, lengths, ranges, enum values (conventions),
the schema version and finiteness of every float; any failure raises :class:`ProtocolError`, whose ``field`` names
the offending field as a path (``header.schema``, ``linear[2]``, ...). A plain ``msgpack`` client in any language
reads and writes these messages as maps with the field names below.

Units are SI (m, rad, s, N·m); Kinova units (degrees, XYZ Euler) appear only in :mod:`protocol.kinova`.
"""
from __future__ import annotations

import enum
import math
import re
import threading
from typing import Annotated, Any, Optional, TypeVar

import msgspec

from protocol.conventions import AngularConvention, Frame

#: Bumped on any incompatible change; a message with another version is refused, never guessed at.
#: 2: RobotState.timing, SimClock.frame_stamp_ns, ServiceHealth.degraded.
#: 3: the arm is a choice: RobotState.arm and arm_digest; joint vectors as long as the arm's joints (1-7).
#: 4: LowLevelState.cycle_ns (the bus period is the hardware's: 2, 2.5, 3.33 or 5 ms).
#: 5: Features of N points (ids, weights, pixels; one view per front end: tag, keypoints), the target's lost status
#: (target_lost), desired commands naming their source, SafetyStatus.in_control.
#: 6: the hand's fingers, a second actuator group: RobotCommand.fingers, RobotState.fingers.
#: 7: the grasp task: TaskPlan grasp and release, TaskStatus.grasp (the hand's verdict); SimObjects.
#: 8: contact detection: RobotState.contact (the robot's momentum observer, its residuals and its contacts).
SCHEMA_VERSION = 9

#: The most joints an arm has (the Kinova API's AngularInfo: Actuator1..7). A joint vector on the wire has the
#: robot's arm's length (RobotState.arm: 6 for the j2n6s300, 7 for the j2s7s300); each reader checks it against the
#: arm it runs.
MAX_JOINTS = 7
#: The most fingers a hand has (the Kinova API's FingersPosition: Finger1..3). A finger vector on the wire has the
#: robot's hand's length (the arm description's ``hand``), checked by each reader as joint vectors are.
MAX_FINGERS = 3

MAX_IMAGE_SIDE = 8192


class ProtocolError(ValueError):
    """A payload that is not a valid message. ``field`` is the path of the bad field ('' for the whole payload)."""

    def __init__(self, message_type: str, reason: str, field: str = "") -> None:
        self.message_type = message_type
        self.reason = reason
        self.field = field
        where = f" at field '{field}'" if field else ""
        super().__init__(f"invalid {message_type}{where}: {reason}")


def _non_finite_path(value: Any, path: str) -> Optional[str]:
    """The path of the first NaN or infinity in ``value`` (None: there is none). Every message is checked on
    decode, so a list of numbers is summed first (one C loop; a sum is finite when every term is, and a
    non-finite or overflowing sum sends it to the item-by-item search); paths are built only on the way to a
    bad number."""
    kind = type(value)
    if kind is float:
        return None if math.isfinite(value) else path
    if kind is list or kind is tuple:
        if not value:
            return None
        try:
            if math.isfinite(sum(value)):
                return None
        except TypeError:  # not all numbers: nested lists, tuples, structs or strings
            pass
        for i, item in enumerate(value):
            if type(item) in _SCALARS_WITHOUT_FLOATS:
                continue
            if _non_finite_path(item, "") is not None:
                return _non_finite_path(item, f"{path}[{i}]")
        return None
    if kind is dict:
        for k, item in value.items():
            if _non_finite_path(item, "") is not None:
                return _non_finite_path(item, f"{path}.{k}")
    return None


_SCALARS_WITHOUT_FLOATS = (int, bool, str, bytes, type(None))

_inspect = msgspec.inspect
#: types whose values hold no float, or whose floats are checked where they are (a nested struct: a message checks
#: its own fields as it is decoded or made); msgspec has no float enums or literals
_WITHOUT_FLOATS_OF_THEIR_OWN = (_inspect.IntType, _inspect.BoolType, _inspect.StrType, _inspect.BytesType,
                                _inspect.ByteArrayType, _inspect.MemoryViewType, _inspect.EnumType,
                                _inspect.LiteralType, _inspect.NoneType, _inspect.StructType)


def _may_hold_floats(info: _inspect.Type) -> bool:
    """Whether a value of this (msgspec.inspect) type may hold a float that :func:`_non_finite_path` would reach."""
    while isinstance(info, _inspect.Metadata):
        info = info.type
    if isinstance(info, _WITHOUT_FLOATS_OF_THEIR_OWN):
        return False
    if isinstance(info, (_inspect.ListType, _inspect.VarTupleType, _inspect.SetType, _inspect.FrozenSetType)):
        return _may_hold_floats(info.item_type)
    if isinstance(info, _inspect.TupleType):
        return any(_may_hold_floats(item) for item in info.item_types)
    if isinstance(info, _inspect.DictType):
        return _may_hold_floats(info.value_type)  # (the search looks at the values)
    if isinstance(info, _inspect.UnionType):
        return any(_may_hold_floats(member) for member in info.types)
    return True  # a float, or a type this does not know: searched


#: per message type, the fields its finiteness check searches (:func:`_float_fields`)
_FLOAT_FIELDS: dict[type, tuple[str, ...]] = {}


def _float_fields(message_type: type) -> tuple[str, ...]:
    """The fields of ``message_type`` whose types may hold a float of their own (the others cannot hold a NaN the
    check would find: a state's 17 fields are searched as its three joint vectors). Made once per type, with its
    decoder (:func:`prepare_decoders`), or at the first message of a type made elsewhere."""
    fields = _FLOAT_FIELDS.get(message_type)
    if fields is None:
        with _decoders_lock:
            fields = _float_fields_now(message_type)
    return fields


def _float_fields_now(message_type: type) -> tuple[str, ...]:
    if message_type not in _FLOAT_FIELDS:
        _FLOAT_FIELDS[message_type] = tuple(field.name for field in _inspect.type_info(message_type).fields
                                            if _may_hold_floats(field.type))
    return _FLOAT_FIELDS[message_type]


class Message(msgspec.Struct, forbid_unknown_fields=True, kw_only=True):
    """Base of every wire type: refuses unknown fields and non-finite floats."""

    def __post_init__(self) -> None:
        for name in _FLOAT_FIELDS.get(type(self)) or _float_fields(type(self)):
            bad = _non_finite_path(getattr(self, name), name)
            if bad is not None:
                raise ValueError(f"non-finite number (NaN or Inf) at field '{bad}'")


NonNegInt = Annotated[int, msgspec.Meta(ge=0)]
#: a time stamp or sequence number: an int64 (what every clock and counter here fits, what a peer in C expects)
Stamp = Annotated[int, msgspec.Meta(ge=0, le=2**63 - 1)]
Vec3 = tuple[float, float, float]
JointVector = Annotated[list[float], msgspec.Meta(min_length=1, max_length=MAX_JOINTS)]
FingerVector = Annotated[list[float], msgspec.Meta(min_length=1, max_length=MAX_FINGERS)]
#: an arm description's name (services/model/arms/<name>.yaml) and its fingerprint (the file's SHA-256, 16 hex)
ArmName = Annotated[str, msgspec.Meta(pattern=r"^[a-z0-9_]{1,32}$")]
ArmDigest = Annotated[str, msgspec.Meta(pattern=r"^[0-9a-f]{16}$")]
ServiceName = Annotated[str, msgspec.Meta(pattern=r"^[A-Za-z0-9_\-.]{1,64}$")]


def _same_length(message: Message, *names: str) -> None:
    """Joint (or finger) vectors of one message have one length (the arm's joints, the hand's fingers)."""
    lengths = {name: len(getattr(message, name)) for name in names}
    if len(set(lengths.values())) > 1:
        raise ValueError("vectors of different lengths: " + ", ".join(f"{k} {v}" for k, v in lengths.items()))


class Hop(Message):
    """One service's passage: when it received the input and when it published the output (ns, its clock)."""

    service: ServiceName
    recv_ns: Stamp
    pub_ns: Stamp


class Header(Message):
    schema: int = SCHEMA_VERSION
    seq: Stamp = 0
    #: time this message's content refers to (ns; wall or simulated per the clock mode)
    stamp_ns: Stamp = 0
    #: capture time of the image this message derives from (0 when it derives from no image)
    source_stamp_ns: Stamp = 0
    trace: Annotated[list[Hop], msgspec.Meta(max_length=32)] = []

    def __post_init__(self) -> None:
        if self.schema != SCHEMA_VERSION:
            raise ValueError(
                f"unsupported schema version {self.schema} at field 'schema', this build speaks {SCHEMA_VERSION}"
            )

    def with_hop(self, service: str, recv_ns: int, pub_ns: int) -> "Header":
        """A copy with this service's hop appended (the trace is never shared between messages)."""
        return msgspec.structs.replace(self, trace=[*self.trace, Hop(service=service, recv_ns=recv_ns, pub_ns=pub_ns)])


class Pose(Message):
    """A rigid transform: position (m) and unit quaternion (w, x, y, z)."""

    xyz: Vec3 = (0.0, 0.0, 0.0)
    quat_wxyz: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        super().__post_init__()
        norm = math.sqrt(sum(c * c for c in self.quat_wxyz))
        if abs(norm - 1.0) > 1e-4:
            raise ValueError(f"quat_wxyz must be a unit quaternion, its norm is {norm:.6g}")


# --------------------------------------------------------------------------------------------------- camera


class ImageEncoding(str, enum.Enum):
    RGB8 = "rgb8"
    BGR8 = "bgr8"
    MONO8 = "mono8"


CHANNELS = {ImageEncoding.RGB8: 3, ImageEncoding.BGR8: 3, ImageEncoding.MONO8: 1}

ImageSide = Annotated[int, msgspec.Meta(ge=1, le=MAX_IMAGE_SIDE)]


class Image(Message):
    header: Header
    width: ImageSide
    height: ImageSide
    encoding: ImageEncoding
    data: bytes

    def __post_init__(self) -> None:
        expected = self.width * self.height * CHANNELS[self.encoding]
        if len(self.data) != expected:
            raise ValueError(
                f"data holds {len(self.data)} bytes, {self.width}x{self.height} {self.encoding.value} needs {expected}"
            )


Positive = Annotated[float, msgspec.Meta(gt=0.0)]


class CameraInfo(Message):
    header: Header
    width: ImageSide
    height: ImageSide
    fx: Positive
    fy: Positive
    cx: float
    cy: float
    #: OpenCV's (k1, k2, p1, p2, k3); all zero for the simulated pinhole camera
    distortion: Annotated[list[float], msgspec.Meta(max_length=14)] = msgspec.field(default_factory=lambda: [0.0] * 5)
    camera_in_ee: Pose = msgspec.field(default_factory=Pose)


# --------------------------------------------------------------------------------------------------- vision


class FeatureStatus(str, enum.Enum):
    #: the target was found; points, depths and error are valid
    OK = "ok"
    #: the target was found but touches the image border (points may be clipped); features are given, use with care
    PARTIAL = "partial"
    #: the configured target is not in this image, or what is there fails the front end's checks (too few inliers,
    #: a reprojection error over its bound, a degenerate view, another object): ``detail`` says which
    TARGET_LOST = "target_lost"
    #: the image was older than the freshness budget when it was processed: no features
    STALE = "stale"
    #: the image could not be used (wrong size, all black, no valid camera info): no features
    INVALID_IMAGE = "invalid_image"


#: statuses whose features may drive a controller
USABLE_FEATURE_STATUSES = frozenset({FeatureStatus.OK, FeatureStatus.PARTIAL})


class FrontEnd(str, enum.Enum):
    """Which of vision's front ends measured the features (services/vision/front_end.py)."""

    #: an AprilTag's four corners
    TAG = "tag"
    #: the taught view's keypoints matched in the image (a markerless target)
    KEYPOINTS = "keypoints"


#: the most points a features message carries (a keypoint target's inliers; a tag has 4)
MAX_FEATURE_POINTS = 512

Point2 = tuple[float, float]
Points = Annotated[list[Point2], msgspec.Meta(max_length=MAX_FEATURE_POINTS)]
PointDepths = Annotated[list[Positive], msgspec.Meta(max_length=MAX_FEATURE_POINTS)]
#: a point's id: stable from frame to frame for the same physical point (a tag's corner 0-3; a taught keypoint's
#: index in its goal), so that a controller pairs it with its goal and fades it in and out
PointIds = Annotated[list[Annotated[int, msgspec.Meta(ge=0, le=2**31 - 1)]], msgspec.Meta(max_length=MAX_FEATURE_POINTS)]
Weight = Annotated[float, msgspec.Meta(ge=0.0, le=1.0)]


class TagView(Message):
    """What the tag front end saw: the tag's id and its pose in the camera frame (IPPE_SQUARE on its corners)."""

    id: Annotated[int, msgspec.Meta(ge=0)]
    pose_in_camera: Pose


#: a taught goal's name (the file's stem) and its fingerprint (the file's SHA-256, 16 hex): as RobotState names its arm
GoalName = Annotated[str, msgspec.Meta(pattern=r"^[A-Za-z0-9_.\-]{1,64}$")]
GoalDigest = Annotated[str, msgspec.Meta(pattern=r"^[0-9a-f]{16}$")]


class KeypointView(Message):
    """What the keypoint front end saw in one image, against its taught goal."""

    goal: GoalName
    goal_digest: GoalDigest
    #: the detector (sift, orb)
    detector: Annotated[str, msgspec.Meta(max_length=16)]
    #: how the points were found this frame: detect (matched against the taught descriptors) or track (followed
    #: from the last frame by optical flow)
    search: Annotated[str, msgspec.Meta(pattern="^(detect|track)$")]
    #: candidates (matches that passed the ratio test, or points tracked) and inliers (what survived the robust
    #: model and the reprojection check)
    candidates: NonNegInt = 0
    inliers: NonNegInt = 0
    #: the inliers' median and largest reprojection error under the object's estimated pose (px)
    median_error_px: Annotated[float, msgspec.Meta(ge=0.0)] = 0.0
    max_error_px: Annotated[float, msgspec.Meta(ge=0.0)] = 0.0
    #: the robust model: homography (a planar target) or epipolar (a non-planar one)
    model: Annotated[str, msgspec.Meta(pattern="^(homography|epipolar)$")] = "homography"
    #: the object's pose in the camera frame (its taught camera frame moved), when estimated
    object_pose_in_camera: Optional[Pose] = None
    #: the taught region's outline in this image (px), where the pose is known
    region_px: Points = []
    #: how long the front end took on this image (ms of wall time, for the figures: not part of what it measured)
    took_ms: Annotated[float, msgspec.Meta(ge=0.0)] = 0.0


class Features(Message):
    """N point features in normalized image coordinates (x = X/Z, y = Y/Z), OpenCV optical camera frame, each with a
    stable id, a depth, a weight (1: fully in; a point fading in or out has less) and its pixel; the goal of each
    point in the same order; one view of the front end that measured them."""

    header: Header
    status: FeatureStatus
    front_end: FrontEnd = FrontEnd.TAG
    points: Points = []
    depths: PointDepths = []
    #: one per point; empty: 0, 1, ... n−1 in order (a client that sends a fixed set of points)
    ids: PointIds = []
    #: one per point; empty: every weight 1
    weights: Annotated[list[Weight], msgspec.Meta(max_length=MAX_FEATURE_POINTS)] = []
    #: each point in pixels, for display and logs
    pixels: Points = []
    goal_points: Points = []
    goal_depths: PointDepths = []
    #: e = s - s*, stacked (x0, y0, x1, y1, ...)
    error: Annotated[list[float], msgspec.Meta(max_length=2 * MAX_FEATURE_POINTS)] = []
    #: ‖e‖ (grows with the number of points: Sensors 2022's figure for its four)
    error_norm: Annotated[float, msgspec.Meta(ge=0.0)] = 0.0
    #: the points' error as a weighted root mean square per point, √(Σ wᵢ‖eᵢ‖² / Σ wᵢ): what convergence is
    #: judged on, whatever the number of points (‖e‖/2 for a tag's four)
    error_rms: Annotated[float, msgspec.Meta(ge=0.0)] = 0.0
    tag: Optional[TagView] = None
    keypoints: Optional[KeypointView] = None
    #: why the status is what it is (e.g. which check refused the image, or lost the target)
    detail: Annotated[str, msgspec.Meta(max_length=256)] = ""

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.status in USABLE_FEATURE_STATUSES:
            n = len(self.points)
            if n == 0:
                raise ValueError(f"status {self.status.value} needs points")
            for name, length in (("depths", n), ("goal_points", n), ("goal_depths", n), ("error", 2 * n)):
                if len(getattr(self, name)) != length:
                    raise ValueError(f"{name} has {len(getattr(self, name))} entries, {length} expected for {n} points")
            for name in ("ids", "weights", "pixels"):
                if getattr(self, name) and len(getattr(self, name)) != n:
                    raise ValueError(f"{name} has {len(getattr(self, name))} entries, {n} expected for {n} points "
                                     "(or none)")
            if len(set(self.ids)) != len(self.ids):
                raise ValueError("ids must be unique: each names one point")
            if self.weights and not any(w > 0.0 for w in self.weights):
                raise ValueError("at least one point needs a weight above 0")

    def point_ids(self) -> list[int]:
        """Each point's id (0..n−1 when the message gives none)."""
        return list(self.ids) if self.ids else list(range(len(self.points)))

    def point_weights(self) -> list[float]:
        """Each point's weight (1 each when the message gives none)."""
        return list(self.weights) if self.weights else [1.0] * len(self.points)


#: the largest taught-goal file a message carries (services/vision/taught.py)
MAX_GOAL_FILE_BYTES = 16 * 1024 * 1024


class VisionGoal(Message):
    """The goal of the visual task: explicit features with one depth (like Sensors 2022 Table 2), the desired
    camera pose in the tag frame (vision computes the features), ``teach``: the current features, or
    ``taught_file``: a taught goal's file (``mfvs teach``; the keypoint front end then finds it), as the person
    keeps it."""

    header: Header
    features: Optional[Points] = None
    depth_m: Optional[Positive] = None
    camera_in_tag: Optional[Pose] = None
    teach: bool = False
    taught_file: Optional[Annotated[bytes, msgspec.Meta(max_length=MAX_GOAL_FILE_BYTES)]] = None

    def __post_init__(self) -> None:
        super().__post_init__()
        given = sum([self.features is not None, self.camera_in_tag is not None, self.teach,
                     self.taught_file is not None])
        if given != 1:
            raise ValueError("give exactly one of features (with depth_m), camera_in_tag, teach, or taught_file")
        if self.features is not None and (self.depth_m is None or len(self.features) == 0):
            raise ValueError("explicit goal features need depth_m and at least one point")


class VisionGoalReply(Message):
    ok: bool
    message: Annotated[str, msgspec.Meta(max_length=256)] = ""
    goal_points: Points = []
    goal_depths: PointDepths = []
    #: the front end the goal is measured by, and a taught goal's name and digest
    front_end: FrontEnd = FrontEnd.TAG
    goal: Optional[GoalName] = None
    goal_digest: Optional[GoalDigest] = None


class TeachPhase(str, enum.Enum):
    """The steps of teaching a view (services/vision/teach.py): the first view; the second, after the arm moved a
    known few centimetres (its depths by triangulation); the goal made and kept; or given up."""

    BEGIN = "begin"
    SECOND_VIEW = "second_view"
    FINISH = "finish"
    CANCEL = "cancel"


class TeachRequest(Message):
    """vision's ``teach`` function: one step of teaching the current view as a goal."""

    header: Header
    phase: TeachPhase
    operator: Annotated[str, msgspec.Meta(min_length=1, max_length=64)]
    #: begin: the object's region in the image (px, a polygon of 3 or more; empty: the frame less a border)
    region_px: Annotated[list[Point2], msgspec.Meta(max_length=64)] = []
    #: begin: sift or orb ("": vision's configured one)
    detector: Annotated[str, msgspec.Meta(pattern="^(|sift|orb)$")] = ""
    #: finish: the goal's name
    name: GoalName = "taught"


class TeachReply(Message):
    ok: bool
    phase: TeachPhase
    message: Annotated[str, msgspec.Meta(max_length=512)] = ""
    #: begin: keypoints found in the region; second view: the ones triangulated
    keypoints: NonNegInt = 0
    #: second view: whether the object is planar (its plane fits the points), the triangulation's median error
    planar: Optional[bool] = None
    triangulation_error_px: Annotated[float, msgspec.Meta(ge=0.0)] = 0.0
    #: the camera's measured motion between the two views (m, first camera's frame)
    probe_m: Optional[Vec3] = None
    #: finish: the goal (now vision's) and its file, for the person to keep
    goal: Optional[GoalName] = None
    goal_digest: Optional[GoalDigest] = None
    goal_file: Annotated[bytes, msgspec.Meta(max_length=MAX_GOAL_FILE_BYTES)] = b""


# --------------------------------------------------------------------------------------------------- control


#: who a desired command comes from: a command source safety declares, and after a slash what it is doing
#: (``controller/servo``, ``controller/probe``); services/safety/sources.py
SourceName = Annotated[str, msgspec.Meta(pattern=r"^[a-z][a-z0-9_\-]{0,31}(/[a-z0-9_\-]{1,32})?$")]
#: the visual servo: what the controller's commands are unless they say otherwise
SERVO_SOURCE = "controller/servo"


def declared_source(source: str) -> str:
    """The declared command source a command's ``source`` names (``controller/probe`` → ``controller``)."""
    return source.split("/", 1)[0]


class FingerMode(str, enum.Enum):
    """How a finger command's values are read (Kinova's HAND_MODE: POSITION_MODE, VELOCITY_MODE)."""

    #: each finger to an angle: its proximal joint's, rad, 0 open, growing as it closes
    POSITION = "position"
    #: each finger at a rate (rad/s, positive closes) for this control cycle only, as a velocity command is
    VELOCITY = "velocity"


class FingerCommand(Message):
    """The hand's part of a robot command: one value per finger of the robot's hand (the arm description's
    ``hand``). A robot command without one leaves every finger at the target it has: a stop, an e-stop, a stale or
    refused command never moves the fingers, so nothing but a finger command opens the hand."""

    mode: FingerMode
    values: FingerVector


class Twist(Message):
    """A velocity screw with its declared convention. In the mixed frame the linear part is in the base frame and
    ``angular`` says how ``rotational`` is to be read (see :mod:`protocol.conventions`). As a desired command, its
    ``source`` (in a robot command, the source safety approved it from)."""

    header: Header
    frame: Frame
    angular: AngularConvention
    linear: Vec3
    rotational: Vec3
    source: SourceName = SERVO_SOURCE
    #: as a desired command, the hand's part that goes with it (safety forwards it in the robot command with the
    #: approved motion, never by itself); inside a robot command none (the command's own ``fingers`` is the part)
    fingers: Optional[FingerCommand] = None


class JointVelocity(Message):
    """Desired joint velocities in rad/s, one per joint of the robot's arm, model order and sign
    (services.model.arm), and their source."""

    header: Header
    velocities: JointVector
    source: SourceName = SERVO_SOURCE
    #: the hand's part that goes with it, as a desired twist's
    fingers: Optional[FingerCommand] = None


#: the person's joystick: what a jog's commands are unless they say otherwise (``jog/<device>``)
JOG_SOURCE = "jog/stick"
#: the largest speed a jog may ask, each axis (m/s, rad/s): the wire's bound, far above any arm's (safety limits
#: what the arm is given; services/jog/jog.yaml says what a stick asks)
MAX_JOG_SPEED = 2.0
JogComponent = Annotated[float, msgspec.Meta(ge=-MAX_JOG_SPEED, le=MAX_JOG_SPEED)]
JogVec3 = tuple[JogComponent, JogComponent, JogComponent]


class JogMode(str, enum.Enum):
    """What the stick moves, as Kinova's joystick modes do (its mode lists: translation, wrist, fingers)."""

    #: the hand along the base's X, Y, Z (the mixed frame's linear part)
    TRANSLATION = "translation"
    #: the hand about its own axes (the mixed frame's rotation, ω in the end-effector frame)
    WRIST = "wrist"
    #: the fingers, closing (positive) or opening, all at one rate or each its own
    FINGERS = "fingers"


#: Kinova's joystick speed levels (its speed ×2 / ÷2 buttons): 1 the slowest
JOG_SPEED_LEVELS = (1, 2, 3)


class Jog(Message):
    """A person's velocity request from a stick (``Keys.desired_jog``): stamped and sequenced by its sender
    (``header.seq`` rises with every message; ``header.source_stamp_ns``: when the device was last heard, which a
    frozen or unplugged device stops moving on), in the mixed frame: ``linear`` along the base's axes (m/s),
    ``angular`` about the hand's own (ω, rad/s), ``finger_rate`` every finger's (rad/s, positive closes, as
    Kinova's stick moves the fingers together). Only the
    motion of its ``mode`` may be non-zero; with the dead-man not held it asks for rest, whatever its axes.
    Safety limits it as any command (services/safety) and moves the arm only while the dead-man is held."""

    header: Header
    mode: JogMode
    deadman: bool
    speed_level: Annotated[int, msgspec.Meta(ge=1, le=len(JOG_SPEED_LEVELS))] = 1
    source: SourceName = JOG_SOURCE
    linear: JogVec3 = (0.0, 0.0, 0.0)
    angular: JogVec3 = (0.0, 0.0, 0.0)
    finger_rate: JogComponent = 0.0

    def __post_init__(self) -> None:
        super().__post_init__()
        moving = {JogMode.TRANSLATION: any(self.linear), JogMode.WRIST: any(self.angular),
                  JogMode.FINGERS: self.finger_rate != 0.0}
        others = [mode.value for mode, moves in moving.items() if moves and mode is not self.mode]
        if others:
            raise ValueError(f"a {self.mode.value} jog moves only its own mode's part, this one also {others}")

    @property
    def at_rest(self) -> bool:
        """It asks for no motion (its dead-man released, or its axes centred)."""
        return not self.deadman or not (any(self.linear) or any(self.angular) or self.finger_rate != 0.0)


class CommandMode(str, enum.Enum):
    #: hold still: the robot decelerates to rest within its limits
    STOP = "stop"
    #: stop now: the robot brakes at its emergency decelerations (the safety service's latched e-stop)
    EMERGENCY_STOP = "emergency_stop"
    CARTESIAN_VELOCITY = "cartesian_velocity"
    JOINT_VELOCITY = "joint_velocity"


#: the modes in which a robot command moves the arm (the others stop it)
MOTION_MODES = frozenset({CommandMode.CARTESIAN_VELOCITY, CommandMode.JOINT_VELOCITY})


class RobotCommand(Message):
    """What the robot applies for one control cycle. Only the safety service publishes it."""

    header: Header
    mode: CommandMode
    twist: Optional[Twist] = None
    joint_velocities: Optional[JointVector] = None
    #: why the command is what it is (e.g. the refusal that turned it into a stop)
    reason: Annotated[str, msgspec.Meta(max_length=256)] = ""
    #: the fingers' command, with the arm's (None: the fingers keep their targets)
    fingers: Optional[FingerCommand] = None

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.mode is CommandMode.CARTESIAN_VELOCITY and self.twist is None:
            raise ValueError("mode cartesian_velocity needs twist")
        if self.mode is CommandMode.JOINT_VELOCITY and self.joint_velocities is None:
            raise ValueError("mode joint_velocity needs joint_velocities")
        if self.mode is CommandMode.EMERGENCY_STOP and self.fingers is not None:
            raise ValueError("an emergency stop carries no finger command: the fingers hold their targets")
        if self.twist is not None and self.twist.fingers is not None:
            raise ValueError("a robot command's hand part is its own fingers field, not its twist's")


class ControllerState(str, enum.Enum):
    CONVERGING = "converging"
    CONVERGED = "converged"
    TARGET_LOST = "target_lost"
    STALE_INPUT = "stale_input"
    ILL_CONDITIONED = "ill_conditioned"
    CONSTRAINT_ABORT = "constraint_abort"
    #: no task is running (the stack comes up so): zero output until someone starts one
    IDLE = "idle"
    #: the arm has not passed the commissioning check (`mfvs check arm`) and it is not waived: zero output
    ARM_NOT_CHECKED = "arm_not_checked"
    #: the robot runs another arm than this controller was started for (or one it has no description of): zero
    #: output, until it is restarted for that arm
    WRONG_ARM = "wrong_arm"
    #: the person took control (safety says another source is in control): the task waits, zero output, until it
    #: is resumed (``resume_task``)
    PAUSED = "paused"


class TaskState(str, enum.Enum):
    IDLE = "idle"
    RUNNING = "running"
    #: started, and waiting: another source (the person's stick) took control; only a resume goes on with it
    PAUSED = "paused"


#: the controller's task functions (``Keys.controller_api``): start, stop and resume take a TaskRequest, get_task
#: nothing; each answers a TaskStatus
START_TASK, STOP_TASK, GET_TASK, RESUME_TASK = "start_task", "stop_task", "get_task", "resume_task"
TASK_FUNCTIONS = (START_TASK, STOP_TASK, GET_TASK, RESUME_TASK)


class TaskPlan(str, enum.Enum):
    """What a task does (services/controller/phases.py): its phases, in order."""

    #: the visual servo to vision's goal, until stopped
    SERVO = "servo"
    #: move the end effector by ``move_m`` (in ``move_frame``) from where it is, holding its orientation; then the
    #: task ends (teach's depth probe: a few centimetres sideways and back)
    MOVE = "move"
    #: reach, grasp and lift: the visual servo to the pre-grasp view until converged, the approach along the tool's
    #: axis, the fingers closed until the hand holds something, the lift, and the hold until a release
    GRASP = "grasp"
    #: open the hand: a grasp task's hold ends in it, or, with no task running, the hand opens where it is
    RELEASE = "release"


class MoveFrame(str, enum.Enum):
    #: the camera's optical frame (x right, y down, z ahead), as it is when the move starts
    CAMERA = "camera"
    #: the end effector's frame (its z: the tool's approach axis), as it is when the move starts
    TOOL = "tool"
    #: the robot's base frame
    BASE = "base"


#: the largest move a task may ask, each axis (m): a probe or an approach, not a trajectory
MAX_MOVE_M = 0.15


class TaskRequest(Message):
    """The argument of the controller's ``start_task`` and ``stop_task``: who asks, and why (logged, and kept in
    the task's status); for a start, what the task does."""

    operator: Annotated[str, msgspec.Meta(min_length=1, max_length=64)]
    reason: Annotated[str, msgspec.Meta(max_length=256)] = ""
    plan: TaskPlan = TaskPlan.SERVO
    #: plan move: the displacement (m) in ``move_frame``
    move_m: tuple[Annotated[float, msgspec.Meta(ge=-MAX_MOVE_M, le=MAX_MOVE_M)],
                  Annotated[float, msgspec.Meta(ge=-MAX_MOVE_M, le=MAX_MOVE_M)],
                  Annotated[float, msgspec.Meta(ge=-MAX_MOVE_M, le=MAX_MOVE_M)]] = (0.0, 0.0, 0.0)
    move_frame: MoveFrame = MoveFrame.CAMERA


class ObjectPose(Message):
    """One of the simulator's free objects where it is (base frame)."""

    name: Annotated[str, msgspec.Meta(min_length=1, max_length=32)]
    pose: Pose


class SimObjects(Message):
    """The simulator's free objects at a DSP tick (its truth: what a grasp experiment measures the lift and the slip
    by). Stamped with the tick."""

    header: Header
    objects: Annotated[list[ObjectPose], msgspec.Meta(max_length=64)]


class GraspVerdict(str, enum.Enum):
    """What the hand holds, by its fingers' positions and currents (services/model/grasp.py)."""

    MOVING = "moving"
    REACHED = "reached"
    GRASPED = "grasped"
    EMPTY = "empty"
    SLIPPING = "slipping"


class TaskStatus(Message):
    """The controller's answer to every task query: whether the request was done, and the task as it now is."""

    ok: bool
    state: TaskState
    message: Annotated[str, msgspec.Meta(max_length=256)] = ""
    #: how many tasks were started since the controller started (this one's number while running)
    task: NonNegInt = 0
    #: when the current task started (the controller's clock, ns); 0 when idle
    started_ns: Stamp = 0
    #: the last start's or stop's operator and reason
    by: Annotated[str, msgspec.Meta(max_length=64)] = ""
    reason: Annotated[str, msgspec.Meta(max_length=256)] = ""
    #: the running (or last) task's plan, the phase it is in ("" when idle), and how the last task ended ("" while
    #: it runs or before any: done, stopped, or failed with why)
    plan: TaskPlan = TaskPlan.SERVO
    phase: Annotated[str, msgspec.Meta(max_length=32)] = ""
    outcome: Annotated[str, msgspec.Meta(max_length=256)] = ""
    #: what the hand holds by its fingers (services/model/grasp.py), while a task drives the hand (None otherwise)
    grasp: Optional[GraspVerdict] = None


class ControllerStatus(Message):
    """What the controller did with one features message (one iteration). Every status other than converging
    comes with a zero output."""

    header: Header
    law: Annotated[str, msgspec.Meta(max_length=64)]
    status: ControllerState
    iteration: NonNegInt
    error_norm: Annotated[float, msgspec.Meta(ge=0.0)] = 0.0
    #: the features' per-point RMS error (Features.error_rms): what convergence is judged on
    error_rms: Annotated[float, msgspec.Meta(ge=0.0)] = 0.0
    gain: float = 0.0
    #: the output was scaled down to the configured limits
    saturated: bool = False
    #: the task's phase this iteration ran (servo, move; "" when idle)
    phase: Annotated[str, msgspec.Meta(max_length=32)] = ""
    #: the camera twist the law asked for (camera frame), when it has one
    camera_twist: Optional[tuple[float, float, float, float, float, float]] = None
    #: law-specific figures of this iteration (e.g. smc's largest constraint value φ and its band)
    notes: Annotated[dict[str, float], msgspec.Meta(max_length=32)] = {}
    detail: Annotated[str, msgspec.Meta(max_length=256)] = ""


# --------------------------------------------------------------------------------------------------- robot


class ControlMode(str, enum.Enum):
    CARTESIAN_VELOCITY = "cartesian_velocity"
    ANGULAR_VELOCITY = "angular_velocity"
    CARTESIAN_POSITION = "cartesian_position"
    ANGULAR_POSITION = "angular_position"
    TORQUE = "torque"
    IDLE = "idle"


class KinovaPose(Message):
    """The end-effector pose as GetCartesianPosition reports it: metres and XYZ Euler angles in radians."""

    X: float
    Y: float
    Z: float
    ThetaX: float
    ThetaY: float
    ThetaZ: float


class LoopTiming(Message):
    """How the robot's 500 Hz bus loop kept time over the last seconds (per second of wall time)."""

    #: bus cycles per second (nominal 500)
    rate_hz: Annotated[float, msgspec.Meta(ge=0.0)] = 0.0
    #: cycles that started late (more than a fraction of a cycle after their slot)
    late_per_s: Annotated[float, msgspec.Meta(ge=0.0)] = 0.0
    #: cycles the arm ran without a target from this loop (skipped by a late host, failed exchanges)
    missed_per_s: Annotated[float, msgspec.Meta(ge=0.0)] = 0.0


class MotionLimits(Message):
    """The speed and acceleration limits the robot applies now (its DSP's configuration, or the arm's own): the
    one place they are set. The controller saturates its output to them and safety checks against them (or
    stricter limits of its own site configuration). The angular speed is of the end effector's angular velocity."""

    linear_speed_mps: Positive
    angular_speed_rps: Positive
    #: each joint's speed limit (model rad/s)
    joint_speed_rps: Annotated[list[Positive], msgspec.Meta(min_length=1, max_length=MAX_JOINTS)]
    linear_accel_mps2: Positive
    angular_accel_rps2: Positive
    joint_accel_rps2: Positive


class ArmCheckState(str, enum.Enum):
    """Whether the arm description agrees with the arm (the commissioning check, `mfvs check arm`)."""

    NEVER = "never"
    RUNNING = "running"
    PASSED = "passed"
    FAILED = "failed"
    #: not checked, by a setting (a simulated arm, which is its description; an arm the check cannot see)
    WAIVED = "waived"


class FingerState(Message):
    """The hand's fingers as the robot measures them, one value per finger: proximal angle (rad, 0 open), its rate
    (rad/s), the finger actuator's current (A) and the target it holds (rad)."""

    position: FingerVector
    velocity: FingerVector
    current_a: FingerVector
    target: FingerVector

    def __post_init__(self) -> None:
        super().__post_init__()
        _same_length(self, "position", "velocity", "current_a", "target")


class ContactState(Message):
    """The robot's contact monitor (the generalized-momentum observer on its joint torques, docs/contact.md) over
    the DSP cycle a state reports: each joint's residual (N·m, the newest sample's) and threshold, the largest
    |residual|/threshold of the cycle's samples (at or above 1: a contact), the joint its isolation named then
    (1-based; 0: none), the rate the observer runs at, and counts since the robot started: the contacts detected
    (a reader latches on a rise, whatever states it missed) and the observer's restarts after gaps in the
    readings."""

    residual_nm: JointVector
    threshold_nm: JointVector
    ratio: Annotated[float, msgspec.Meta(ge=0.0)]
    joint: Annotated[int, msgspec.Meta(ge=0, le=MAX_JOINTS)]
    rate_hz: Positive
    contacts: NonNegInt = 0
    restarts: NonNegInt = 0
    #: the last contact's joint, residual and threshold (N·m), as it was detected (0, 0.0, 0.0 before any)
    last_joint: Annotated[int, msgspec.Meta(ge=0, le=MAX_JOINTS)] = 0
    last_residual_nm: float = 0.0
    last_threshold_nm: Annotated[float, msgspec.Meta(ge=0.0)] = 0.0

    def __post_init__(self) -> None:
        super().__post_init__()
        _same_length(self, "residual_nm", "threshold_nm")
        if any(not t > 0.0 for t in self.threshold_nm):
            raise ValueError("threshold_nm: every threshold must be positive")
        if self.joint > len(self.residual_nm) or self.last_joint > len(self.residual_nm):
            raise ValueError(f"joint {max(self.joint, self.last_joint)} beyond the arm's {len(self.residual_nm)}")

    def last_contact(self) -> str:
        """The last contact in a line (the robot's log, safety's protective stop, the status)."""
        return contact_line(self.last_joint, self.last_residual_nm, self.last_threshold_nm)


def contact_line(joint: int, residual_nm: float, threshold_nm: float) -> str:
    """How a contact is said wherever it is said: which joint, its residual, its threshold."""
    return f"contact at joint {joint}: residual {residual_nm:+.2f} N·m beyond its {threshold_nm:.2f} N·m threshold"


class RobotState(Message):
    header: Header
    #: the arm the robot runs (its description's name and fingerprint): every reader takes the joint count and the
    #: joints' ranges from that description, and does nothing for an arm it was not started for
    arm: ArmName
    arm_digest: ArmDigest
    #: model joint angles (rad), velocities (rad/s), torques (N·m): one per joint of the arm
    q: JointVector
    dq: JointVector
    tau: JointVector
    pose: KinovaPose
    control_mode: ControlMode
    fifo_count: NonNegInt = 0
    faults: Annotated[list[str], msgspec.Meta(max_length=32)] = []
    watchdog_tripped: bool = False
    #: the angular convention the robot's DSP interprets for Cartesian velocity commands
    angular_convention: AngularConvention = AngularConvention.SEED000
    #: header (with trace) of the command applied in the last DSP cycle, the robot's hop appended (its ``pub_ns``:
    #: when the robot applied it, which can be up to a DSP cycle before this state's stamp)
    applied_command: Optional[Header] = None
    timing: LoopTiming = msgspec.field(default_factory=LoopTiming)
    #: the limits the robot applies (None: not declared; readers then take the arm description's maxima)
    limits: Optional[MotionLimits] = None
    #: the end effector as the arm itself reports it (its own kinematics: Kinova's DSP through the SDK, the
    #: simulator's physics); None where ``pose`` is all there is (the description's kinematics of q: RS-485)
    arm_pose: Optional[KinovaPose] = None
    #: the commissioning check's verdict on this arm; the controller starts tasks only when passed or waived
    arm_check: ArmCheckState = ArmCheckState.NEVER
    #: the hand's fingers (None: the arm has no hand, or its hardware does not report one)
    fingers: Optional[FingerState] = None
    #: the contact monitor (None: the robot runs none)
    contact: Optional[ContactState] = None

    def __post_init__(self) -> None:
        super().__post_init__()
        _same_length(self, "q", "dq", "tau")
        if self.contact is not None and len(self.contact.residual_nm) != len(self.q):
            raise ValueError(f"contact has {len(self.contact.residual_nm)} joints, q {len(self.q)}")
        if self.limits is not None and len(self.limits.joint_speed_rps) != len(self.q):
            raise ValueError(f"limits.joint_speed_rps has {len(self.limits.joint_speed_rps)} joints, q {len(self.q)}")


class ArmCheckRequest(Message):
    """Run the commissioning check: each joint in turn moves by ``step_deg`` at ``speed_dps`` and back."""

    header: Header
    #: the check moves the arm: the caller says it is clear to (`mfvs check arm --yes`)
    confirm: bool = False
    #: which joints (1-based); empty: every joint of the arm
    joints: Annotated[list[Annotated[int, msgspec.Meta(ge=1, le=MAX_JOINTS)]],
                      msgspec.Meta(max_length=MAX_JOINTS)] = []
    step_deg: Annotated[float, msgspec.Meta(ge=1.0, le=10.0)] = 5.0
    speed_dps: Annotated[float, msgspec.Meta(ge=1.0, le=10.0)] = 5.0
    operator: Annotated[str, msgspec.Meta(max_length=64)] = ""


class JointCheck(Message):
    joint: int
    #: how far the joint moved, by its own report (deg)
    moved_deg: float
    #: ok: the arm moved as the description predicts; reversed: as it predicts for the joint turning the other way;
    #: disagrees: neither
    direction: Annotated[str, msgspec.Meta(max_length=16)]
    #: the arm's motion against the description's (end effector: mm and deg)
    motion_error_mm: float
    motion_error_deg: float
    passed: bool
    detail: Annotated[str, msgspec.Meta(max_length=256)] = ""
    #: the joint's zero against the description's, where the poses disagree at rest (deg; fitted over the samples)
    zero_offset_deg: float = 0.0


class ArmCheckReply(Message):
    ok: bool
    passed: bool = False
    state: ArmCheckState = ArmCheckState.NEVER
    message: Annotated[str, msgspec.Meta(max_length=512)] = ""
    joints: Annotated[list[JointCheck], msgspec.Meta(max_length=MAX_JOINTS)] = []
    #: the arm's pose against the description's at the start (mm, deg)
    static_error_mm: float = 0.0
    static_error_deg: float = 0.0
    #: where the static error is a constant turn of the end-effector frame (the arm's frame in the description's)
    ee_frame_rotation_deg: float = 0.0
    ee_frame_axis: tuple[float, float, float] = (0.0, 0.0, 1.0)


class TorqueCommand(Message):
    """Low-level (500 Hz) joint torque command, N·m. With gravity compensation on, the robot adds g(q)."""

    header: Header
    torques: JointVector
    gravity_compensation: bool = True


class ActuatorMode(str, enum.Enum):
    POSITION = "position"
    TORQUE = "torque"


class LowLevelState(Message):
    header: Header
    mode: ActuatorMode
    q: JointVector
    dq: JointVector
    tau: JointVector
    current_a: JointVector
    temperature_c: JointVector
    faults: Annotated[list[str], msgspec.Meta(max_length=32)] = []
    #: the bus's cycle, one state each (ns): a torque client counts the states it did not see on it (1 to 10 ms:
    #: services.robot.hardware.BusTiming's periods, and the DSP's own 10 ms where a backend has no bus)
    cycle_ns: Annotated[int, msgspec.Meta(ge=1_000_000, le=10_000_000)] = 2_000_000

    def __post_init__(self) -> None:
        super().__post_init__()
        _same_length(self, "q", "dq", "tau", "current_a", "temperature_c")


class SimClock(Message):
    header: Header
    sim_time_ns: NonNegInt
    mode: Annotated[str, msgspec.Meta(pattern="^(realtime|lockstep)$")]
    #: the capture stamp of the camera frame taken at this tick (0: none), so that a robot node in another
    #: process knows, in lockstep, that its answer must derive from that frame
    frame_stamp_ns: NonNegInt = 0


# --------------------------------------------------------------------------------------------------- safety


class SafetyState(str, enum.Enum):
    OK = "ok"
    LIMITING = "limiting"
    REFUSING = "refusing"
    ESTOP = "estop"


class SafetyStatus(Message):
    header: Header
    state: SafetyState
    active_limits: Annotated[list[str], msgspec.Meta(max_length=32)] = []
    last_refusal: Annotated[str, msgspec.Meta(max_length=256)] = ""
    counters: dict[str, NonNegInt] = {}
    #: the command source whose command safety holds now (``controller/servo``, ...): who is in control; "" when
    #: safety holds nothing (the arm is stopping or at rest)
    in_control: Annotated[str, msgspec.Meta(max_length=64)] = ""


class EStop(Message):
    """Engage (reset=False) or release (reset=True) the latched emergency stop."""

    header: Header
    reset: bool = False
    operator: Annotated[str, msgspec.Meta(max_length=64)] = ""
    reason: Annotated[str, msgspec.Meta(max_length=256)] = ""


# --------------------------------------------------------------------------------------------------- runtime


class ServiceHealth(Message):
    header: Header
    service: ServiceName
    pid: NonNegInt
    healthy: bool
    state: Annotated[str, msgspec.Meta(max_length=64)]
    uptime_s: Annotated[float, msgspec.Meta(ge=0.0)]
    rates_hz: dict[str, Annotated[float, msgspec.Meta(ge=0.0)]] = {}
    errors: dict[str, NonNegInt] = {}
    detail: Annotated[str, msgspec.Meta(max_length=512)] = ""
    #: why the service is running but not keeping up (a loop below its nominal rate, overruns in the last
    #: health period); empty when it is
    degraded: Annotated[list[Annotated[str, msgspec.Meta(max_length=256)]], msgspec.Meta(max_length=16)] = []


# --------------------------------------------------------------------------------------------------- codec

M = TypeVar("M", bound=msgspec.Struct)

def _encode_hook(obj: Any) -> Any:
    """NumPy scalars and arrays (anything with ``tolist``) encode as the plain numbers and lists they hold."""
    tolist = getattr(obj, "tolist", None)
    if tolist is not None:
        return tolist()
    raise NotImplementedError(f"cannot encode objects of type {type(obj).__name__}")


_encoder = msgspec.msgpack.Encoder(enc_hook=_encode_hook)
_decoders: dict[type, msgspec.msgpack.Decoder] = {}
#: building a decoder fills msgspec's per-type caches, and doing that while another thread decodes crashed a service
#: (a segfault at start-up, two subscriber threads each decoding its first message): the wire's types get their
#: decoders at import (:func:`prepare_decoders`), anything else under this lock
_decoders_lock = threading.Lock()
_AT_PATH = re.compile(r" - at `\$(?P<path>[^`]*)`$")
_INNER_FIELD = re.compile(r"at field '(?P<field>[^']+)'|(?:unknown|missing required) field `(?P<unknown>[^`]+)`")


def encode(message: msgspec.Struct) -> bytes:
    """MessagePack bytes of a message (a map of field names)."""
    return _encoder.encode(message)


def decode(payload: bytes | bytearray | memoryview, message_type: type[M]) -> M:
    """Decode and validate; raises :class:`ProtocolError` naming the bad field."""
    decoder = _decoders.get(message_type)
    if decoder is None:
        decoder = prepare_decoders([message_type])[0]
    try:
        return decoder.decode(payload)
    except msgspec.ValidationError as exc:
        raise _protocol_error(message_type, exc) from None
    except msgspec.DecodeError as exc:
        raise ProtocolError(message_type.__name__, f"malformed MessagePack ({exc})") from None
    except (UnicodeDecodeError, ValueError, TypeError, OverflowError, RecursionError) as exc:
        # what msgspec lets through for some malformed input (an invalid UTF-8 map key raises UnicodeDecodeError):
        # still a malformed message, never an exception of another kind for the service to trip over
        raise ProtocolError(message_type.__name__, f"malformed MessagePack ({type(exc).__name__}: {exc})") from None


def prepare_decoders(message_types) -> list[msgspec.msgpack.Decoder]:
    """Build (once) the decoders of ``message_types``, one thread at a time."""
    with _decoders_lock:
        for message_type in message_types:
            if message_type not in _decoders:
                _decoders[message_type] = msgspec.msgpack.Decoder(message_type)
            if isinstance(message_type, type) and issubclass(message_type, Message):
                _float_fields_now(message_type)
        return [_decoders[message_type] for message_type in message_types]


def wire_types(namespace: dict) -> list[type]:
    """The message types defined in a module's namespace (its ``globals()``)."""
    return [value for value in namespace.values()
            if isinstance(value, type) and issubclass(value, Message) and value is not Message]


def missing_fields(payload: bytes | bytearray | memoryview, message_type: type) -> list[str]:
    """The fields of ``message_type`` (at every level of nesting) that the MessagePack ``payload`` leaves to their
    defaults: a request that changes the robot must say everything it means, since a default (an empty zone
    list, a target of zero angles) is not what a caller who forgot a field wanted. Paths as ``a.b[0].c``; a
    payload that is not even a map names the whole message ("$")."""
    try:
        obj = msgspec.msgpack.decode(payload)
    except Exception:
        return ["$"]
    out: list[str] = []
    _missing(obj, msgspec.inspect.type_info(message_type), "", out)
    return out


def _missing(obj: Any, info, path: str, out: list[str]) -> None:
    while isinstance(info, (msgspec.inspect.Metadata,)):
        info = info.type
    if isinstance(info, msgspec.inspect.StructType):
        if not isinstance(obj, dict):
            out.append(path or "$")
            return
        for field in info.fields:
            name = f"{path}.{field.encode_name}" if path else field.encode_name
            if field.encode_name not in obj:
                out.append(name)
            else:
                _missing(obj[field.encode_name], field.type, name, out)
    elif isinstance(info, (msgspec.inspect.ListType, msgspec.inspect.TupleType, msgspec.inspect.VarTupleType)):
        if isinstance(obj, list):
            item = getattr(info, "item_type", None)
            items = [item] * len(obj) if item is not None else list(info.item_types)
            for i, (value, item_info) in enumerate(zip(obj, items)):
                _missing(value, item_info, f"{path}[{i}]", out)


def to_builtins(message: msgspec.Struct) -> dict:
    """The plain dict/list/bytes form of a message: exactly what a generic msgpack client decodes."""
    return msgspec.msgpack.decode(_encoder.encode(message))


def convert(obj: Any, message_type: type[M]) -> M:
    """Validate a plain dict (e.g. from YAML or JSON) as a message; raises :class:`ProtocolError`."""
    try:
        return msgspec.convert(obj, message_type)
    except msgspec.ValidationError as exc:
        raise _protocol_error(message_type, exc) from None


def validation_error_path(exc: msgspec.ValidationError) -> tuple[str, str]:
    """(field path, reason) of a msgspec validation error: msgspec's ``$.a.b`` plus the inner field that our own
    checks, or msgspec's unknown/missing-field messages, name."""
    text = str(exc)
    match = _AT_PATH.search(text)
    path = match.group("path").lstrip(".") if match else ""
    reason = text[: match.start()] if match else text
    inner = _INNER_FIELD.search(reason)
    if inner:
        leaf = inner.group("field") or inner.group("unknown")
        path = f"{path}.{leaf}" if path else leaf
    return path, reason


def _protocol_error(message_type: type, exc: msgspec.ValidationError) -> ProtocolError:
    path, reason = validation_error_path(exc)
    return ProtocolError(message_type.__name__, reason, path)


prepare_decoders(wire_types(globals()))
