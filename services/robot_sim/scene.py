"""The simulated world: the JACO-2 from the shared description, torque actuators, floor, lights, the target (an
AprilTag at its true size, a calibration board, or a markerless object: a textured box face or a cup), the scene's
other objects (clutter, an occluder, a second object that takes the target's place), and an eye-in-hand camera
with exact pinhole intrinsics. A scene that asks for nothing new (a tag, no objects, the default light) compiles to
the very model it did before there were objects (tests/services/robot_sim/test_scene.py).

:func:`build_model` returns an immutable MjModel; the mutable state lives in MjData owned by the simulation.
"""
from __future__ import annotations

import enum
import math
from typing import Literal, Optional, Union

import msgspec
import mujoco
import numpy as np

from protocol.messages import CameraInfo, Header, ImageEncoding, Pose
from services.model import frames
from services.model.arm import EE_LINK, ArmDescription
from services.model.board import BoardConfig, board_image
from services.robot.hardware import CYCLE_NS, DSP_CYCLE_NS
from services.robot_sim.imaging import ImagingConfig
from services.robot_sim.textures import texture_image
from services.model import tag as tags
from services.runtime.config import ConfigStruct
from services.model.frames import PoseConfig

Vec3 = tuple[float, float, float]

#: MuJoCo cameras look along −z with +y up; OpenCV's optical frame looks along +z with +y down.
MUJOCO_FROM_OPTICAL = frames.rot_x(math.pi)

CAMERA_NAME = "eye_in_hand"
FLOOR_RGBA = [0.44, 0.44, 0.4, 1.0]
TAG_BODY = "target"
#: where in the DSP's 10 ms cycle the camera may be triggered: at a bus cycle's boundary, where the world is
TRIGGER_OFFSETS_MS = tuple(range(0, DSP_CYCLE_NS // 1_000_000, CYCLE_NS // 1_000_000))
#: the trigger when ``trigger_offset_ms`` is null, by where the DSP that applies the commands runs (robot_sim's
#: ``mode``), measured on this kind of host (docs/latency.md): robot_sim's own DSP takes a command ~0.7 ms after its
#: tick, and one that comes up to 1.3 ms later in its command window, so a frame taken at the tick has 11 ms for its
#: way there; robot_gateway's DSP runs on the tick's reading, which reaches it with the next bus exchange and some
#: 4-5 ms after the tick, so a frame taken 2 ms after the tick has as long. ``auto`` starts there too.
DEFAULT_TRIGGER_MS = {"api": 0, "actuator_bus": 2}


def trigger_offset(camera: "CameraConfig", mode: str) -> Union[int, Literal["auto"]]:
    """The camera's trigger offset (ms after the tick) as configured, or the mode's measured default when null."""
    return DEFAULT_TRIGGER_MS[mode] if camera.trigger_offset_ms is None else camera.trigger_offset_ms


def _default_camera_in_ee() -> PoseConfig:
    # On top of the gripper, 6.5 cm off the approach axis, looking along it (optical z = end-effector z), image
    # upright (optical x horizontal) at the home pose.
    return PoseConfig(xyz=(0.065, 0.0, -0.02), rpy_deg=(0.0, 0.0, 90.0))


class CameraConfig(ConfigStruct):
    """Pinhole camera like a RealSense D415 colour stream, published grey by default (``encoding``). cx/cy default
    to the image centre in OpenCV pixel coordinates ((width−1)/2, (height−1)/2)."""

    width: int = 640
    height: int = 480
    fx: float = 615.0
    fy: float = 615.0
    cx: Optional[float] = None
    cy: Optional[float] = None
    rate_hz: float = 30.0
    camera_in_ee: PoseConfig = msgspec.field(default_factory=_default_camera_in_ee)
    #: what the camera publishes: rgb8, or mono8 (the detector's input: a third of the bytes to copy, send and
    #: decode, converted as vision would convert rgb8, so the corners are the same to the bit)
    encoding: ImageEncoding = ImageEncoding.MONO8
    #: false: no rendering, no images and no camera info from robot_sim (the camera service publishes them: a real
    #: camera beside the emulated arm; realtime only, as the camera service is)
    enabled: bool = True
    #: a camera as imperfect as a real one (noise, motion blur over the exposure, JPEG; services/robot_sim/imaging.py);
    #: null: the ideal camera (noiseless, instantaneous), which the seed papers' experiments and thresholds assume;
    #: ``{}``: a common USB webcam's defaults
    imaging: Optional[ImagingConfig] = None
    #: realtime: the camera is triggered this long after the arm's 10 ms DSP tick (a whole number of 2 ms bus
    #: cycles below 10), as a hardware-triggered camera wired to the robot's controller is: a command derived from
    #: the frame should reach the DSP just before it plans, or it waits a whole cycle for the next
    #: (docs/latency.md). null: the measured default for where the DSP runs (:data:`DEFAULT_TRIGGER_MS`).
    #: ``auto``: moved to where the commands' measured paths are applied soonest (trigger_phase.py; not the
    #: default, docs/latency.md). Lockstep takes each frame at a tick and answers it there, whatever this says.
    trigger_offset_ms: Union[int, Literal["auto"], None] = None

    def __post_init__(self) -> None:
        if self.trigger_offset_ms not in ("auto", None) and self.trigger_offset_ms not in TRIGGER_OFFSETS_MS:
            raise ValueError(f"camera trigger_offset_ms must be null, auto or one of {TRIGGER_OFFSETS_MS} (a whole number "
                             f"of 2 ms bus cycles after the 10 ms DSP tick), not {self.trigger_offset_ms}")
        if self.encoding is ImageEncoding.BGR8:
            raise ValueError("camera encoding must be rgb8 or mono8")
        if not (8 <= self.width <= 4096 and 8 <= self.height <= 4096):
            raise ValueError("camera width and height must be within 8..4096 pixels")
        if not (self.fx > 0 and self.fy > 0 and math.isfinite(self.fx) and math.isfinite(self.fy)):
            raise ValueError("camera fx and fy must be positive")
        if not (0 < self.rate_hz <= 120):
            raise ValueError("camera rate_hz must be within (0, 120]")

    @property
    def principal_point(self) -> tuple[float, float]:
        cx = (self.width - 1) / 2.0 if self.cx is None else self.cx
        cy = (self.height - 1) / 2.0 if self.cy is None else self.cy
        return cx, cy

    def matrix(self) -> np.ndarray:
        cx, cy = self.principal_point
        return np.array([[self.fx, 0.0, cx], [0.0, self.fy, cy], [0.0, 0.0, 1.0]])


def default_target_in_camera() -> PoseConfig:
    """The tag's pose when a scene gives none: 0.5 m ahead of the camera, squarely facing it."""
    return PoseConfig(xyz=(0.0, 0.0, 0.5), rpy_deg=(180.0, 0.0, 0.0))


class TargetKind(str, enum.Enum):
    #: an AprilTag (or, with ``board``, a ChArUco board): what vision's tag front end finds
    TAG = "tag"
    #: a textured box face, ``plane_m`` across (a planar markerless object: a cereal box, a book)
    PLANE = "plane"
    #: a textured cup with a handle (a non-planar markerless object)
    CUP = "cup"


class CupShape(ConfigStruct):
    """A mug (our choice of size: 8 cm across, 9.5 cm tall, the common one), its print all round its wall; the handle
    on its +x side (right, as the camera sees it at the goal)."""

    radius_m: float = 0.04
    height_m: float = 0.095
    handle: bool = True

    def __post_init__(self) -> None:
        if not (0.01 <= self.radius_m <= 0.2 and 0.02 <= self.height_m <= 0.4):
            raise ValueError("cup radius_m must be within 0.01..0.2 m and height_m within 0.02..0.4 m")


#: a markerless object's default print: the procedural texture of this seed (services/robot_sim/textures.py)
DEFAULT_TEXTURE_SEED = 7


class TargetConfig(ConfigStruct):
    #: what the target is: a tag (or board), a textured plane, or a cup
    kind: TargetKind = TargetKind.TAG
    family: str = "tag36h11"
    id: int = 0
    size_m: float = 0.0962
    #: one of the two: in the robot base frame, or in the camera frame at the initial configuration
    pose_in_base: Optional[PoseConfig] = None
    pose_in_camera: Optional[PoseConfig] = None
    #: constant velocity of the target in the base frame (Nelson 1995's moving target)
    velocity_mps: Vec3 = (0.0, 0.0, 0.0)
    #: which image the tag carries: official (as printed from AprilRobotics/apriltag-imgs) or opencv (OpenCV's
    #: drawing); vision is told the same (services.model.tag)
    layout: tags.TagLayout = tags.TagLayout.OFFICIAL
    #: a ChArUco calibration board instead of the tag (`mfvs calibrate --simulate`); family, id, size_m and layout
    #: are then unused
    board: Optional[BoardConfig] = None
    #: a plane or cup: its print (an image file; null: the procedural print of ``texture_seed``)
    texture: Optional[str] = None
    texture_seed: int = DEFAULT_TEXTURE_SEED
    #: a plane: its face's width and height (m; our choice: a small box's face, 16 × 12 cm, fits the camera's view
    #: at Table 2's goal depth)
    plane_m: tuple[float, float] = (0.16, 0.12)
    cup: CupShape = msgspec.field(default_factory=CupShape)
    #: the target leaves the scene at this time (s of simulated time; null: never): an object that takes its place
    #: (``objects``) is then what the camera sees
    leaves_at_s: Optional[float] = None
    #: the target stuck on a free object of the scene (its name): a tag card on a cup, a print on a box. It then
    #: goes where the object goes (placed, pushed, grasped, lifted), at ``pose_in_object`` in the object's frame
    on_object: Optional[str] = None
    pose_in_object: Optional[PoseConfig] = None

    def __post_init__(self) -> None:
        if not all(0.02 <= side <= 1.0 for side in self.plane_m):
            raise ValueError("target plane_m must be within 0.02..1 m a side")
        if self.family not in tags.FAMILIES:
            raise ValueError(f"unknown tag family {self.family!r}")
        if not 0.005 <= self.size_m <= 1.0:
            raise ValueError("target size_m must be within 0.005..1 m")
        if self.pose_in_base is not None and self.pose_in_camera is not None:
            raise ValueError("give the target pose_in_base or pose_in_camera, not both")
        if (self.on_object is None) != (self.pose_in_object is None):
            raise ValueError("a target on an object needs both on_object and pose_in_object")
        if self.on_object is not None and (self.pose_in_base is not None or self.pose_in_camera is not None
                                           or any(self.velocity_mps) or self.leaves_at_s is not None):
            raise ValueError("a target on an object is where the object is: no pose_in_base, pose_in_camera, "
                             "velocity_mps or leaves_at_s")


class ObjectKind(str, enum.Enum):
    PLANE = "plane"
    CUP = "cup"
    #: a plain grey box (an occluder: a hand, a sheet of paper)
    BOX = "box"
    #: a plain ball, ``size_m[0]`` across (what the grip is measured on: dm_control's kinova_test.py)
    SPHERE = "sphere"


class SceneObject(ConfigStruct):
    """One of the scene's other objects: clutter beside the target, an occluder that crosses the view, an object
    that takes the target's place, a thing to grasp. Without a mass, a mocap body: it moves as told
    (``velocity_mps`` from its pose, within ``arrives_at_s`` .. ``leaves_at_s``) and nothing pushes it. With a mass
    (``mass_kg``), a free body: it falls, rests on the table, and moves as the fingers and what else it touches push
    it (it is then where its pose puts it at time 0, and nothing else moves it)."""

    name: str
    kind: ObjectKind = ObjectKind.PLANE
    #: one of the two: in the robot base frame, or in the camera frame at the initial configuration
    pose_in_base: Optional[PoseConfig] = None
    pose_in_camera: Optional[PoseConfig] = None
    #: a plane's face (width, height), a box's size (x, y, z), a ball's diameter (the first), m
    size_m: tuple[float, float, float] = (0.16, 0.12, 0.004)
    cup: CupShape = msgspec.field(default_factory=CupShape)
    texture: Optional[str] = None
    texture_seed: int = 1
    #: constant velocity in the base frame (m/s), from the pose above at time 0
    velocity_mps: Vec3 = (0.0, 0.0, 0.0)
    #: in the scene from ... to (s of simulated time; null: from the start, to the end)
    arrives_at_s: Optional[float] = None
    leaves_at_s: Optional[float] = None
    #: a mocap body the fingers and free objects touch (it does not move when they push it); false: it is seen only.
    #: A free object (``mass_kg``) is always solid
    solid: bool = False
    #: its mass (kg): a free body; null: a mocap body
    mass_kg: Optional[float] = None
    #: a free object's sliding friction coefficient, which its contacts with the fingers and the table use (it takes
    #: precedence over theirs): MuJoCo's default 1.0 (rubber finger pads on a dry mug); a wet glass is nearer 0.1
    friction: float = 1.0

    def __post_init__(self) -> None:
        if not (1 <= len(self.name) <= 32 and self.name.replace("_", "").isalnum()):
            raise ValueError(f"scene object name {self.name!r}: 1-32 letters, digits and _")
        if (self.pose_in_base is None) == (self.pose_in_camera is None):
            raise ValueError(f"scene object {self.name}: give pose_in_base or pose_in_camera, exactly one")
        if not all(0.001 <= side <= 2.0 for side in self.size_m):
            raise ValueError(f"scene object {self.name}: size_m within 0.001..2 m")
        if self.mass_kg is not None:
            if not (math.isfinite(self.mass_kg) and 0.001 <= self.mass_kg <= 5.0):
                raise ValueError(f"scene object {self.name}: mass_kg within 0.001..5 kg")
            if any(self.velocity_mps) or self.arrives_at_s is not None or self.leaves_at_s is not None:
                raise ValueError(f"scene object {self.name}: a free object (mass_kg) moves only as it is pushed: no "
                                 "velocity_mps, arrives_at_s or leaves_at_s")
        if not (math.isfinite(self.friction) and 0.01 <= self.friction <= 2.0):
            raise ValueError(f"scene object {self.name}: friction within 0.01..2")

    @property
    def free(self) -> bool:
        """A free body (it has a mass), not a mocap one."""
        return self.mass_kg is not None


class TableConfig(ConfigStruct):
    """A table the arm is mounted beside, for objects to stand on: a slab whose top is at ``top_z_m`` in the base
    frame; the floor a table's height below it. By default (our choice) a wheelchair user's table: a JACO-2 on a
    wheelchair's frame has its base about at the seat's height (ISO 7176-7's seat heights are about 0.5 m), a table's
    top is 0.72 m from the floor, so the top is 0.2 m above the base."""

    top_z_m: float = 0.2
    #: the top's centre (x, y) in the base frame and its size (m): our choice, a 0.8 × 1.2 m table in front of the
    #: arm, its near edge 0.2 m ahead of the base
    centre_xy_m: tuple[float, float] = (0.6, 0.0)
    size_xy_m: tuple[float, float] = (0.8, 1.2)
    thickness_m: float = 0.03
    #: the floor this far below the top (m): a table's height (EN 1729 / common 0.72 m)
    height_m: float = 0.72

    def __post_init__(self) -> None:
        if not all(0.05 <= v <= 3.0 for v in self.size_xy_m):
            raise ValueError("table size_xy_m within 0.05..3 m a side")
        if not (-1.0 <= self.top_z_m <= 1.0 and 0.005 <= self.thickness_m <= 0.2
                and self.thickness_m < self.height_m <= 1.5):
            raise ValueError("table top_z_m within -1..1 m, thickness_m 0.005..0.2 m, height_m above it up to 1.5 m")


class LightConfig(ConfigStruct):
    """The scene's directional light (the camera's headlight beside it is fixed): its strength and direction, to
    light the servo otherwise than the teach (Sensors 2022 was lit by a lab's ceiling)."""

    #: a scale of the light's diffuse 0.6 (0.5 .. 1.5: ±50 %)
    intensity: float = 1.0
    #: its direction in the base frame (it shines along it)
    direction: Vec3 = (0.0, 0.2, -1.0)

    def __post_init__(self) -> None:
        if not 0.0 <= self.intensity <= 3.0:
            raise ValueError("light intensity must be within 0..3")
        if not math.hypot(*self.direction) > 1e-6:
            raise ValueError("light direction must not be zero")


class SceneConfig(ConfigStruct):
    """The world around the arm (the arm itself is the robot's config: ``arm``)."""

    #: physical joint angles (deg) as GetAngularPosition reports them, one per joint of the arm; null: its home
    initial_joints_deg: Optional[list[float]] = None
    camera: CameraConfig = msgspec.field(default_factory=CameraConfig)
    target: TargetConfig = msgspec.field(default_factory=TargetConfig)
    #: the scene's other objects (none by default)
    objects: list[SceneObject] = msgspec.field(default_factory=list)
    light: LightConfig = msgspec.field(default_factory=LightConfig)
    timestep_s: float = 0.001
    floor: bool = True
    #: a table for objects to stand on (none by default: the floor at the base's height, which nothing touches)
    table: Optional[TableConfig] = None

    def __post_init__(self) -> None:
        if not 1e-4 <= self.timestep_s <= 0.001:
            raise ValueError("timestep_s must be within 0.1..1 ms (physics at 1 kHz or faster)")

    def check(self, arm: ArmDescription) -> None:
        """The scene against the arm it holds (its initial angles). Raises ValueError."""
        if self.initial_joints_deg is not None:
            check_joints_deg(arm, self.initial_joints_deg, "initial_joints_deg")
        names = [obj.name for obj in self.objects]
        if len(set(names)) != len(names):
            raise ValueError(f"scene objects named twice: {sorted({n for n in names if names.count(n) > 1})}")
        carrier = self.target.on_object
        if carrier is not None and carrier not in {obj.name for obj in self.free_objects}:
            raise ValueError(f"the target is on object {carrier!r}, which is not a free object of the scene "
                             f"(free objects: {', '.join(obj.name for obj in self.free_objects) or 'none'})")

    def carrier(self) -> Optional[SceneObject]:
        """The free object the target is stuck on (None: the target is where its pose puts it)."""
        return next((obj for obj in self.objects if obj.name == self.target.on_object), None)

    @property
    def floor_z_m(self) -> float:
        """Where the floor is (base frame, m): at the base's height, or a table's height below the table's top."""
        return 0.0 if self.table is None else self.table.top_z_m - self.table.height_m

    @property
    def free_objects(self) -> list[SceneObject]:
        return [obj for obj in self.objects if obj.free]

    def start_deg(self, arm: ArmDescription) -> list[float]:
        """Where the arm starts (physical deg): ``initial_joints_deg``, or the arm's home."""
        return list(self.initial_joints_deg) if self.initial_joints_deg is not None else arm.home_deg.tolist()


def check_joints_deg(arm: ArmDescription, joints_deg, name: str) -> None:
    """Physical angles (deg) for ``arm``: one per joint, within its limits. Raises ValueError saying which."""
    if len(joints_deg) != arm.n_joints:
        raise ValueError(f"{name} has {len(joints_deg)} angles; the {arm.name} has {arm.n_joints} joints")
    if not all(math.isfinite(v) for v in joints_deg):
        raise ValueError(f"{name} must be finite")
    if not arm.within_limits(arm.physical_deg_to_model(joints_deg)):
        raise ValueError(f"{name} are outside the {arm.name}'s joint limits")





def camera_in_ee(cfg: SceneConfig) -> np.ndarray:
    return cfg.camera.camera_in_ee.matrix()


def target_in_base(cfg: SceneConfig, arm: ArmDescription) -> np.ndarray:
    """The target's initial pose in the base frame (resolving pose_in_camera at ``arm``'s initial configuration; on
    an object, where the object starts)."""
    carrier = cfg.carrier()
    if carrier is not None:
        return object_in_base(cfg, arm, carrier) @ cfg.target.pose_in_object.matrix()
    return _in_base(cfg, arm, cfg.target.pose_in_base, cfg.target.pose_in_camera or default_target_in_camera())


def object_in_base(cfg: SceneConfig, arm: ArmDescription, obj: SceneObject) -> np.ndarray:
    """A scene object's initial pose in the base frame."""
    return _in_base(cfg, arm, obj.pose_in_base, obj.pose_in_camera)


def _in_base(cfg: SceneConfig, arm: ArmDescription, in_base: Optional[PoseConfig],
             in_camera: Optional[PoseConfig]) -> np.ndarray:
    if in_base is not None:
        return in_base.matrix()
    T_be = arm.dh_forward_kinematics(arm.physical_deg_to_model(cfg.start_deg(arm)))
    return T_be @ camera_in_ee(cfg) @ in_camera.matrix()


def cup_outline(cup: CupShape, around: int = 12) -> np.ndarray:
    """Points on a cup's silhouette in its frame (axis y, the handle's side +x, z toward the camera at the goal):
    its rim and base rings, and the handle's far edge."""
    a = np.linspace(0.0, 2.0 * np.pi, around, endpoint=False)
    ring = np.column_stack([cup.radius_m * np.cos(a), np.zeros(around), cup.radius_m * np.sin(a)])
    points = [ring + [0.0, cup.height_m / 2, 0.0], ring - [0.0, cup.height_m / 2, 0.0]]
    if cup.handle:
        points.append(np.array([[cup.radius_m + _handle_reach(cup), 0.0, 0.0]]))
    return np.vstack(points)


def target_outline(target: TargetConfig) -> np.ndarray:
    """Points that bound what the camera sees of the target, in its frame (n×3): a tag's printed corners, a plane's
    four corners, a cup's silhouette. What every start must keep in the image (services/experiments/starts.py)."""
    if target.kind == TargetKind.CUP:
        return cup_outline(target.cup)
    if target.kind == TargetKind.PLANE:
        half_x, half_y = (side / 2.0 for side in target.plane_m)
        return np.array([[-half_x, half_y, 0.0], [half_x, half_y, 0.0], [half_x, -half_y, 0.0],
                         [-half_x, -half_y, 0.0]])
    return tags.corners_in_tag(target.size_m)


def renderer(model: mujoco.MjModel, height: int, width: int) -> mujoco.Renderer:
    """An offscreen renderer for ``model``'s scene, its geometry buffer sized to the model (the default's 10,000
    geoms held 9 MB for a scene of about ten; the margin covers what the scene adds to the model's geoms)."""
    return mujoco.Renderer(model, height, width, max_geom=model.ngeom + 100)


def build_model(cfg: SceneConfig, arm: ArmDescription) -> mujoco.MjModel:
    """The scene on ``arm``'s description, compiled: its rendering options, the arm's truth and motors, the light and
    the floor, the target, the eye-in-hand camera (added in this order: MuJoCo numbers what it holds as it comes)."""
    spec = arm.mujoco_spec()
    _set_options(spec, cfg)
    _add_arm(spec, arm)
    if arm.hand is not None:
        _add_hand(spec, arm)
    _add_light_and_floor(spec, cfg)
    if cfg.table is not None:
        _add_table(spec, cfg.table)
    _add_target(spec, cfg, arm)
    for obj in cfg.objects:
        _add_object(spec, cfg, arm, obj)
    _add_camera(spec, cfg)
    return spec.compile()


def _set_options(spec: mujoco.MjSpec, cfg: SceneConfig) -> None:
    """The physics step and integrator, and the offscreen rendering's buffers and light."""
    spec.option.timestep = cfg.timestep_s
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    if cfg.free_objects:
        # what a grasp needs of MuJoCo's contacts (its documentation's advice for grasping, which dm_control's
        # manipulation tasks follow): elliptic friction cones, their friction stiffer than the normal by IMPRATIO,
        # or a held object creeps down through soft friction. Only where a free object can be held: the tag
        # scenes have no contacts and stay as they were
        spec.option.cone = mujoco.mjtCone.mjCONE_ELLIPTIC
        spec.option.impratio = IMPRATIO
        spec.option.noslip_iterations = NOSLIP_ITERATIONS
    cam = cfg.camera
    spec.visual.global_.offwidth = max(cam.width, 640)
    spec.visual.global_.offheight = max(cam.height, 480)
    # No multisampling: on Mesa's EGL/llvmpipe the 4x buffer gave the very same pixels (checksum-identical frames)
    # at twice the cost (11 ms against 5.5 ms a 640x480 frame)
    spec.visual.quality.offsamples = 0
    # No shadow map: no light casts shadows (below), and MuJoCo's default 4096² depth texture held 64 MB in every
    # renderer's GL context for nothing (the same pixels without it, measured)
    spec.visual.quality.shadowsize = 0
    spec.visual.headlight.ambient = [0.35, 0.35, 0.35]
    spec.visual.headlight.diffuse = [0.4, 0.4, 0.4]


#: the ratio of frictional to normal constraint impedance of a grasp's contacts (MuJoCo's documentation, "impratio":
#: values above 1 for grasping, to prevent slip; dm_control's manipulation tasks use 10)
IMPRATIO = 10.0
#: MuJoCo's noslip solver's iterations: its documentation's remedy for the slow creep of soft contacts, which let a
#: cup held still in a 25 N grip slide out of the hand by 1 mm/s (measured); MuJoCo's examples use 10 or fewer
NOSLIP_ITERATIONS = 10


def _add_arm(spec: mujoco.MjSpec, arm: ArmDescription) -> None:
    """The emulated arm's own truth, a torque motor on each joint, and the arm's colour."""
    # the emulated arm's own truth, where it departs from the description (the controllers' model): heavier links
    # where the description says, Coulomb friction at every joint (arm.true_link_mass_scale, true_friction_nm)
    for i, (link, scale) in enumerate(zip(arm.link_names, arm.true_link_mass_scale)):
        if scale != 1.0:
            body = spec.body(link)
            body.mass = body.mass * float(scale)
            # (the URDF's inertia is the body's full inertia: MuJoCo compiles that, not the principal moments)
            body.fullinertia = [float(v) * float(scale) for v in body.fullinertia]
        spec.joint(arm.joints[i].name).frictionloss = float(arm.true_friction_nm[i])

    for i, joint_spec in enumerate(arm.joints):
        motor = spec.add_actuator(name=f"motor_{i + 1}", target=joint_spec.name)
        motor.trntype = mujoco.mjtTrn.mjTRN_JOINT
        motor.gainprm[0] = 1.0
        motor.ctrllimited = mujoco.mjtLimited.mjLIMITED_TRUE
        motor.ctrlrange = [-joint_spec.max_torque_nm, joint_spec.max_torque_nm]

    for geom in spec.geoms:  # (the arm's alone: nothing else is in the scene yet)
        geom.rgba = [0.15, 0.15, 0.17, 1.0]


#: the collision classes (MuJoCo's contype/conaffinity bits): a finger's geoms collide with solid objects and the
#: table, never with each other, the arm or the scene's visual geometry (contype 0); a free object's with the
#: fingers, the table, the floor, solid objects and other free objects
FINGER_CONTACT = 2
OBJECT_CONTACT = 4
#: a free object's geoms' contact priority: its friction is what its contacts use (MuJoCo otherwise takes the larger
#: of the pair's, so a slippery object would grip as the finger pads do)
OBJECT_CONTACT_PRIORITY = 1
#: a finger's contacts: MuJoCo's elliptic friction cone with torsional friction (condim 4, as dm_control's
#: jaco_hand.xml gives its fingers), MuJoCo's default sliding friction (dm_control sets none)
FINGER_CONDIM = 4
#: each finger actuator's servo: stiff enough that a finger blocked on an object reaches its force limit within a
#: degree of where it stopped (mfvs's choice, as a geared finger motor's position loop is; the real one's gains are
#: not public), critically damped for the finger's inertia about its hinge
FINGER_FULL_FORCE_WITHIN = math.radians(1.0)
#: the reflected inertia of a finger's motor at its hinge (kg·m²): mfvs's choice, of the order of the finger's own
#: (about 1e-4 kg·m²), so the servo's bandwidth stays within what the 1 ms physics step integrates
FINGER_ARMATURE = 2e-4


#: the palm's face: a disc across the hand (m; mfvs's choice, no public drawing: the KG-3's palm is about as wide as
#: the ring of its finger hinges, 3 cm from the axis), just ahead of the hinges
PALM_RADIUS_M = 0.035
PALM_DEPTH_M = 0.02
PALM_AHEAD_OF_HINGES_M = 0.005


def _palm_face_z(arm: ArmDescription) -> float:
    """Where the palm's face is along the end effector's z (its approach axis, m): just ahead of the finger hinges."""
    return max(float(T[2, 3]) for T in arm.hand.finger_origins) + PALM_AHEAD_OF_HINGES_M


def finger_names(arm: ArmDescription) -> list[tuple[str, str, str]]:
    """Each finger's (body, hinge joint, motor) names in the scene's model."""
    return [(f"{name}_proximal", f"{name}_hinge", f"{name}_motor") for name in arm.hand.finger_names]


def finger_torque_limit_nm(arm: ArmDescription) -> float:
    """The most torque a finger's motor gives (N·m): its share of the grip (a third) at the pinch, where the distal
    link holds an object, half-way along it from the hinge (:func:`pinch_lever_m`)."""
    hand = arm.hand
    return hand.grip_force_n / hand.n_fingers * pinch_lever_m(arm)


def pinch_lever_m(arm: ArmDescription) -> float:
    """How far from its hinge a finger holds an object at the pinch: to the middle of its distal link (m)."""
    hand = arm.hand
    x, y, z = hand.distal_offset_m
    return math.hypot(x + hand.distal_length_m / 2.0, y, z)


def _add_hand(spec: mujoco.MjSpec, arm: ArmDescription) -> None:
    """The hand's fingers on the end effector: per finger a proximal body on an actuated hinge at its origin, its
    distal link rigid on it, capsules along the finger's x; a position servo on each hinge, its force limited to the
    finger's share of the grip. The palm keeps what the fingers leave of the last link's mass (inertia scaled with
    it), so the arm weighs what its description says."""
    hand = arm.hand
    # the description's last link carries the fingers' masses where they are, open (the controllers' model,
    # arm.py); here they are bodies of their own, and the palm is what the emulated arm's truth leaves of it
    palm = spec.body(arm.link_names[-1])
    truth = arm.joints[-1].link_mass_kg * float(arm.true_link_mass_scale[-1])
    palm_mass = truth - hand.n_fingers * hand.finger_mass_kg
    if palm_mass <= 0.0:
        raise ValueError(f"the {hand.name}'s fingers weigh more than the {arm.name}'s last link")
    mass, centre, inertia = arm.palm_inertia(palm_mass)
    moments, axes = np.linalg.eigh(inertia)
    if np.linalg.det(axes) < 0:
        axes[:, 0] = -axes[:, 0]
    palm.mass = float(mass)
    palm.ipos = centre.tolist()
    palm.iquat = frames.matrix_to_quat_wxyz(axes).tolist()
    palm.inertia = moments.tolist()
    palm.fullinertia = [math.nan] * 6  # (the principal moments and axes above are the body's inertia)
    ee = spec.body(EE_LINK)
    # the palm's face, what a power grasp presses an object against (massless: the palm's mass is the link's)
    ee.add_geom(name="palm", type=mujoco.mjtGeom.mjGEOM_CYLINDER, size=[PALM_RADIUS_M, PALM_DEPTH_M / 2, 0.0],
                pos=[0.0, 0.0, _palm_face_z(arm) - PALM_DEPTH_M / 2], density=0.0, contype=FINGER_CONTACT,
                conaffinity=0, condim=FINGER_CONDIM, rgba=[0.15, 0.15, 0.17, 1.0])
    torque = finger_torque_limit_nm(arm)
    radius = hand.link_radius_m
    # the finger about its hinge, as a servo sees it: the two links' masses at their centres, plus the motor
    lever_proximal = hand.proximal_length_m / 2.0
    lever_distal = pinch_lever_m(arm)
    inertia = (hand.proximal_mass_kg * lever_proximal ** 2 + hand.distal_mass_kg * lever_distal ** 2
               + FINGER_ARMATURE)
    kp = torque / FINGER_FULL_FORCE_WITHIN
    kv = 2.0 * math.sqrt(kp * inertia)
    for T, (body_name, joint_name, motor_name) in zip(hand.finger_origins, finger_names(arm)):
        proximal = ee.add_body(name=body_name, pos=T[:3, 3].tolist(),
                               quat=frames.matrix_to_quat_wxyz(T[:3, :3]).tolist())
        proximal.add_joint(name=joint_name, type=mujoco.mjtJoint.mjJNT_HINGE, axis=[0.0, 0.0, 1.0],
                           range=[0.0, hand.closed_angle], limited=mujoco.mjtLimited.mjLIMITED_TRUE,
                           armature=FINGER_ARMATURE)
        proximal.add_geom(name=f"{body_name}_link", type=mujoco.mjtGeom.mjGEOM_CAPSULE,
                          fromto=[0.0, 0.0, 0.0, hand.proximal_length_m, 0.0, 0.0], size=[radius, 0.0, 0.0],
                          mass=hand.proximal_mass_kg, contype=FINGER_CONTACT, conaffinity=0, condim=FINGER_CONDIM,
                          rgba=[0.15, 0.15, 0.17, 1.0])
        distal = proximal.add_body(name=body_name.replace("_proximal", "_distal"), pos=list(hand.distal_offset_m))
        distal.add_geom(name=body_name.replace("_proximal", "_distal_link"), type=mujoco.mjtGeom.mjGEOM_CAPSULE,
                        fromto=[0.0, 0.0, 0.0, hand.distal_length_m, 0.0, 0.0], size=[radius, 0.0, 0.0],
                        mass=hand.distal_mass_kg, contype=FINGER_CONTACT, conaffinity=0, condim=FINGER_CONDIM,
                        rgba=[0.15, 0.15, 0.17, 1.0])
        motor = spec.add_actuator(name=motor_name, target=joint_name)
        motor.trntype = mujoco.mjtTrn.mjTRN_JOINT
        motor.set_to_position(kp=kp, kv=kv)
        motor.forcelimited = mujoco.mjtLimited.mjLIMITED_TRUE
        motor.forcerange = [-torque, torque]
        motor.ctrllimited = mujoco.mjtLimited.mjLIMITED_TRUE
        motor.ctrlrange = [0.0, hand.closed_angle]


def _add_light_and_floor(spec: mujoco.MjSpec, cfg: SceneConfig) -> None:
    """One directional light, and the floor unless ``cfg.floor`` is off."""
    world = spec.worldbody
    # No shadows: shadow maps cost ~40 ms a frame on a CPU renderer (Mesa llvmpipe) and the tag needs none.
    light = cfg.light
    world.add_light(name="sun", pos=[0.0, -0.5, 2.5], dir=[float(v) for v in light.direction],
                    diffuse=[0.6 * light.intensity] * 3, type=mujoco.mjtLightType.mjLIGHT_DIRECTIONAL,
                    castshadow=False)
    if cfg.floor:
        # Plain: a textured floor fills most of the image, and sampling its mipmapped texture took 5 of the 13 ms
        # a 640x480 frame cost on llvmpipe in a running stack (15 % of a core at 30 Hz). The detector needs no
        # background texture; the floor's grey is the checker's mean brightness.
        spec.add_material(name="floor", rgba=FLOOR_RGBA, reflectance=0.0)
        floor = world.add_geom(name="floor", type=mujoco.mjtGeom.mjGEOM_PLANE, size=[3.0, 3.0, 0.05],
                               material="floor", contype=0, conaffinity=0)
        if cfg.floor_z_m != 0.0:
            floor.pos = [0.0, 0.0, cfg.floor_z_m]
        if cfg.free_objects:  # what falls off the table lands on it
            floor.conaffinity = OBJECT_CONTACT


#: the table's colour (a light wood laminate; the tag and the objects stand out on it)
TABLE_RGBA = [0.62, 0.52, 0.40, 1.0]


def _add_table(spec: mujoco.MjSpec, table: TableConfig) -> None:
    """The table: a static slab, its top at ``top_z_m``, that the fingers and free objects touch."""
    half = [table.size_xy_m[0] / 2, table.size_xy_m[1] / 2, table.thickness_m / 2]
    spec.worldbody.add_geom(name="table", type=mujoco.mjtGeom.mjGEOM_BOX, size=half, rgba=TABLE_RGBA,
                            pos=[*table.centre_xy_m, table.top_z_m - table.thickness_m / 2],
                            contype=OBJECT_CONTACT, conaffinity=FINGER_CONTACT | OBJECT_CONTACT)


def _add_target(spec: mujoco.MjSpec, cfg: SceneConfig, arm: ArmDescription) -> None:
    """The target, a mocap body at its initial pose (:func:`target_in_base`): the AprilTag, a thin box whose +z face
    carries the tag upright (texture top = tag +y); or a board; or a markerless object (a textured box face, a cup).
    Raises ValueError for a target below the floor."""
    if cfg.target.kind != TargetKind.TAG:
        T_bt = target_in_base(cfg, arm)
        _above_floor(cfg, T_bt)
        body = spec.worldbody.add_body(name=TAG_BODY, mocap=True, pos=T_bt[:3, 3].tolist(),
                                       quat=frames.matrix_to_quat_wxyz(T_bt[:3, :3]).tolist())
        t = cfg.target
        if t.kind == TargetKind.PLANE:
            _textured_plane(spec, body, "target", (*t.plane_m, 0.01), t.texture, t.texture_seed)
        else:
            _textured_cup(spec, body, "target", t.cup, t.texture, t.texture_seed)
        return
    if cfg.target.board is not None:
        image = board_image(cfg.target.board)
        half_x, half_y = (side / 2.0 for side in cfg.target.board.size_m)
    else:
        image = tags.tag_image(cfg.target.id, cfg.target.family, layout=cfg.target.layout)
        half_x = half_y = tags.printed_edge(cfg.target.size_m) / 2.0
    rgb = np.repeat(image[:, :, None], 3, axis=2)
    texture = spec.add_texture(name="tag", type=mujoco.mjtTexture.mjTEXTURE_2D, width=rgb.shape[1],
                               height=rgb.shape[0], nchannel=3)
    texture.data = rgb.tobytes()
    spec.add_material(name="tag", textures=["", "tag"], texrepeat=[1, 1], texuniform=False, specular=0.0,
                      shininess=0.0, reflectance=0.0)
    T_bt = target_in_base(cfg, arm)
    _above_floor(cfg, T_bt)
    target = spec.worldbody.add_body(name=TAG_BODY, mocap=True, pos=T_bt[:3, 3].tolist(),
                                     quat=frames.matrix_to_quat_wxyz(T_bt[:3, :3]).tolist())
    thickness = 0.002
    target.add_geom(name="tag", type=mujoco.mjtGeom.mjGEOM_BOX, size=[half_x, half_y, thickness / 2],
                    pos=[0.0, 0.0, -thickness / 2], material="tag", contype=0, conaffinity=0)


def _above_floor(cfg: SceneConfig, T_bt: np.ndarray) -> None:
    below = cfg.floor_z_m - T_bt[2, 3]
    if cfg.floor and below > 0.0:
        raise ValueError(f"the target's centre is {below:.3f} m below the floor; move it or disable the floor")


def _material(spec: mujoco.MjSpec, name: str, texture_path: Optional[str], seed: int, aspect: float = 1.0) -> str:
    """A matte material printed with the texture asked for (services/robot_sim/textures.py); its name."""
    rgb = texture_image(texture_path, seed, aspect)
    texture = spec.add_texture(name=name, type=mujoco.mjtTexture.mjTEXTURE_2D, width=rgb.shape[1],
                               height=rgb.shape[0], nchannel=3)
    texture.data = np.ascontiguousarray(rgb).tobytes()
    spec.add_material(name=name, textures=["", name], texrepeat=[1, 1], texuniform=False, specular=0.0,
                      shininess=0.0, reflectance=0.0)
    return name


def _textured_plane(spec: mujoco.MjSpec, body, name: str, size_m, texture_path: Optional[str], seed: int) -> None:
    """A box whose +z face (width × height, the body's x and y) carries the print upright; ``size_m[2]`` deep."""
    material = _material(spec, name, texture_path, seed, aspect=size_m[0] / size_m[1])
    body.add_geom(name=name, type=mujoco.mjtGeom.mjGEOM_BOX, size=[size_m[0] / 2, size_m[1] / 2, size_m[2] / 2],
                  pos=[0.0, 0.0, -size_m[2] / 2], material=material, contype=0, conaffinity=0)


#: a cup's wall in segments around (a 48-gon: within 0.1 mm of the circle at a 4 cm radius)
CUP_SEGMENTS = 48


def _handle_reach(cup: CupShape) -> float:
    """How far the handle stands out of the wall (m): a mug's, about two thirds of its radius."""
    return 0.6 * cup.radius_m


def _textured_cup(spec: mujoco.MjSpec, body, name: str, cup: CupShape, texture_path: Optional[str],
                  seed: int) -> None:
    """A cup in the body's frame: its axis along y, its print wrapped round its wall (the print's middle facing
    +z), a base, and a handle (capsules in an arc) on its +x side. The wall is a mesh with texture coordinates:
    MuJoCo's primitive cylinder takes no wrapped print."""
    r, h = cup.radius_m, cup.height_m
    material = _material(spec, name, texture_path, seed, aspect=2.0 * math.pi * r / h)
    vertices, uv, faces = [], [], []
    for i in range(CUP_SEGMENTS + 1):
        u = i / CUP_SEGMENTS
        angle = 2.0 * math.pi * (u - 0.5)  # from +z toward +x: the print's middle faces +z, and reads left to right
        x, z = r * math.sin(angle), r * math.cos(angle)
        for j, y in enumerate((-h / 2, h / 2)):
            vertices += [x, y, z]
            uv += [u, 1.0 - j]
    for i in range(CUP_SEGMENTS):
        a, b, c, d = 2 * i, 2 * i + 1, 2 * i + 2, 2 * i + 3
        faces += [a, c, b, b, c, d]  # counter-clockwise seen from outside: the wall's outer side is drawn
    mesh = spec.add_mesh(name=f"{name}_wall")
    mesh.uservert, mesh.usertexcoord, mesh.userface, mesh.userfacetexcoord = vertices, uv, faces, faces
    body.add_geom(name=name, type=mujoco.mjtGeom.mjGEOM_MESH, meshname=f"{name}_wall", material=material,
                  contype=0, conaffinity=0)
    grey = [0.85, 0.85, 0.82, 1.0]
    body.add_geom(name=f"{name}_base", type=mujoco.mjtGeom.mjGEOM_CYLINDER, size=[r * 0.995, 0.002, 0.0],
                  pos=[0.0, -h / 2 + 0.002, 0.0], quat=frames.matrix_to_quat_wxyz(frames.rot_x(math.pi / 2)).tolist(),
                  rgba=grey, contype=0, conaffinity=0)
    if cup.handle:
        reach, thick = _handle_reach(cup), 0.2 * r
        arc = [(-0.3 * h, 0.0), (-0.3 * h, reach), (0.3 * h, reach), (0.3 * h, 0.0)]
        for k, ((y0, x0), (y1, x1)) in enumerate(zip(arc, arc[1:])):
            body.add_geom(name=f"{name}_handle{k}", type=mujoco.mjtGeom.mjGEOM_CAPSULE, size=[thick / 2, 0.0, 0.0],
                          fromto=[r + x0 - thick / 2, y0, 0.0, r + x1 - thick / 2, y1, 0.0], rgba=grey,
                          contype=0, conaffinity=0)


def object_body(obj: SceneObject) -> str:
    """A scene object's body in the model."""
    return f"object_{obj.name}"


def _add_object(spec: mujoco.MjSpec, cfg: SceneConfig, arm: ArmDescription, obj: SceneObject) -> None:
    """One of the scene's other objects at its initial pose: a mocap body, or a free one (:func:`_make_free`)."""
    T = object_in_base(cfg, arm, obj)
    name = object_body(obj)
    body = spec.worldbody.add_body(name=name, mocap=not obj.free, pos=T[:3, 3].tolist(),
                                   quat=frames.matrix_to_quat_wxyz(T[:3, :3]).tolist())
    if obj.kind == ObjectKind.PLANE:
        _textured_plane(spec, body, name, obj.size_m, obj.texture, obj.texture_seed)
    elif obj.kind == ObjectKind.CUP:
        _textured_cup(spec, body, name, obj.cup, obj.texture, obj.texture_seed)
    elif obj.kind == ObjectKind.SPHERE:
        body.add_geom(name=name, type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[obj.size_m[0] / 2, 0.0, 0.0],
                      rgba=[0.55, 0.5, 0.45, 1.0], contype=0, conaffinity=0)
    else:
        body.add_geom(name=name, type=mujoco.mjtGeom.mjGEOM_BOX, size=[s / 2 for s in obj.size_m],
                      rgba=[0.55, 0.5, 0.45, 1.0], contype=0, conaffinity=0)
    if obj.free:
        _make_free(spec, body, obj)
    elif obj.solid:
        for geom in body.geoms:
            geom.conaffinity = FINGER_CONTACT | OBJECT_CONTACT


def _make_free(spec: mujoco.MjSpec, body, obj: SceneObject) -> None:
    """A free object: a free joint, its look massless, and one collision shape carrying its whole mass (a uniform
    solid, mfvs's choice: a mug's mass is in its wall and base, which moves its inertia, not its contacts) with its
    friction. A cup's shape is its wall's cylinder (the handle touches nothing); a plane's its slab."""
    body.add_freejoint(name=f"{object_body(obj)}_free")
    for geom in body.geoms:
        geom.density = 0.0
    friction = [obj.friction, 0.005, 0.0001]  # (torsional and rolling: MuJoCo's defaults)
    common = dict(mass=obj.mass_kg, contype=OBJECT_CONTACT, conaffinity=FINGER_CONTACT | OBJECT_CONTACT,
                  condim=FINGER_CONDIM, friction=friction, priority=OBJECT_CONTACT_PRIORITY, group=3,
                  rgba=[0.0, 0.0, 0.0, 0.0])
    name = f"{object_body(obj)}_shape"
    if obj.kind == ObjectKind.CUP:
        body.add_geom(name=name, type=mujoco.mjtGeom.mjGEOM_CYLINDER, size=[obj.cup.radius_m, obj.cup.height_m / 2, 0.0],
                      quat=frames.matrix_to_quat_wxyz(frames.rot_x(math.pi / 2)).tolist(), **common)
    elif obj.kind == ObjectKind.SPHERE:
        body.add_geom(name=name, type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[obj.size_m[0] / 2, 0.0, 0.0], **common)
    else:
        depth = obj.size_m[2]
        pos = [0.0, 0.0, -depth / 2] if obj.kind == ObjectKind.PLANE else [0.0, 0.0, 0.0]
        body.add_geom(name=name, type=mujoco.mjtGeom.mjGEOM_BOX, size=[s / 2 for s in obj.size_m], pos=pos, **common)


def _add_camera(spec: mujoco.MjSpec, cfg: SceneConfig) -> None:
    """The eye-in-hand camera with exact intrinsics: MuJoCo's principal_pixel is the offset of the image centre from
    the principal point, in pixels (verified by rendering)."""
    cam = cfg.camera
    T_ec = camera_in_ee(cfg)
    ee = spec.body(EE_LINK)
    camera = ee.add_camera(name=CAMERA_NAME, pos=T_ec[:3, 3].tolist(),
                           quat=frames.matrix_to_quat_wxyz(T_ec[:3, :3] @ MUJOCO_FROM_OPTICAL).tolist())
    cx, cy = cam.principal_point
    camera.resolution = [cam.width, cam.height]
    camera.sensor_size = [cam.width * 1e-5, cam.height * 1e-5]  # any pixel pitch: intrinsics are in pixels
    camera.focal_pixel = [cam.fx, cam.fy]
    camera.principal_pixel = [(cam.width - 1) / 2.0 - cx, (cam.height - 1) / 2.0 - cy]


def camera_info(camera: CameraConfig, header: Header) -> CameraInfo:
    """The CameraInfo message that describes this camera (an ideal pinhole: no distortion)."""
    cx, cy = camera.principal_point
    T = camera.camera_in_ee.matrix()
    return CameraInfo(header=header, width=camera.width, height=camera.height, fx=camera.fx, fy=camera.fy, cx=cx,
                      cy=cy, distortion=[0.0] * 5,
                      camera_in_ee=Pose(xyz=tuple(T[:3, 3]), quat_wxyz=tuple(frames.matrix_to_quat_wxyz(T[:3, :3]))))
