"""The simulated world: the JACO-2 from the shared description, torque actuators, floor, lights, an AprilTag
target at its true size, and an eye-in-hand camera with exact pinhole intrinsics.

:func:`build_model` returns an immutable MjModel; the mutable state lives in MjData owned by the simulation.
"""
from __future__ import annotations

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


class TargetConfig(ConfigStruct):
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

    def __post_init__(self) -> None:
        if self.family not in tags.FAMILIES:
            raise ValueError(f"unknown tag family {self.family!r}")
        if not 0.005 <= self.size_m <= 1.0:
            raise ValueError("target size_m must be within 0.005..1 m")
        if self.pose_in_base is not None and self.pose_in_camera is not None:
            raise ValueError("give the target pose_in_base or pose_in_camera, not both")


class SceneConfig(ConfigStruct):
    """The world around the arm (the arm itself is the robot's config: ``arm``)."""

    #: physical joint angles (deg) as GetAngularPosition reports them, one per joint of the arm; null: its home
    initial_joints_deg: Optional[list[float]] = None
    camera: CameraConfig = msgspec.field(default_factory=CameraConfig)
    target: TargetConfig = msgspec.field(default_factory=TargetConfig)
    timestep_s: float = 0.001
    floor: bool = True

    def __post_init__(self) -> None:
        if not 1e-4 <= self.timestep_s <= 0.001:
            raise ValueError("timestep_s must be within 0.1..1 ms (physics at 1 kHz or faster)")

    def check(self, arm: ArmDescription) -> None:
        """The scene against the arm it holds (its initial angles). Raises ValueError."""
        if self.initial_joints_deg is not None:
            check_joints_deg(arm, self.initial_joints_deg, "initial_joints_deg")

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
    """The target's initial pose in the base frame (resolving pose_in_camera at ``arm``'s initial configuration)."""
    if cfg.target.pose_in_base is not None:
        return cfg.target.pose_in_base.matrix()
    pose_in_camera = (cfg.target.pose_in_camera or default_target_in_camera()).matrix()
    T_be = arm.dh_forward_kinematics(arm.physical_deg_to_model(cfg.start_deg(arm)))
    return T_be @ camera_in_ee(cfg) @ pose_in_camera


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
    _add_light_and_floor(spec, cfg)
    _add_target(spec, cfg, arm)
    _add_camera(spec, cfg)
    return spec.compile()


def _set_options(spec: mujoco.MjSpec, cfg: SceneConfig) -> None:
    """The physics step and integrator, and the offscreen rendering's buffers and light."""
    spec.option.timestep = cfg.timestep_s
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
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


def _add_arm(spec: mujoco.MjSpec, arm: ArmDescription) -> None:
    """The emulated arm's own truth, a torque motor on each joint, and the arm's colour."""
    # the emulated arm's own truth, where it departs from the description (the controllers' model): heavier links
    # where the description says, Coulomb friction at every joint (arm.true_link_mass_scale, true_friction_nm)
    for i, (link, scale) in enumerate(zip(arm.link_names, arm.true_link_mass_scale)):
        if scale != 1.0:
            body = spec.body(link)
            body.mass = body.mass * float(scale)
            body.inertia = [float(v) * float(scale) for v in body.inertia]
        spec.joint(arm.joints[i].name).frictionloss = float(arm.true_friction_nm[i])

    for i, joint_spec in enumerate(arm.joints):
        motor = spec.add_actuator(name=f"motor_{i + 1}", target=joint_spec.name)
        motor.trntype = mujoco.mjtTrn.mjTRN_JOINT
        motor.gainprm[0] = 1.0
        motor.ctrllimited = mujoco.mjtLimited.mjLIMITED_TRUE
        motor.ctrlrange = [-joint_spec.max_torque_nm, joint_spec.max_torque_nm]

    for geom in spec.geoms:  # (the arm's alone: nothing else is in the scene yet)
        geom.rgba = [0.15, 0.15, 0.17, 1.0]


def _add_light_and_floor(spec: mujoco.MjSpec, cfg: SceneConfig) -> None:
    """One directional light, and the floor unless ``cfg.floor`` is off."""
    world = spec.worldbody
    # No shadows: shadow maps cost ~40 ms a frame on a CPU renderer (Mesa llvmpipe) and the tag needs none.
    world.add_light(name="sun", pos=[0.0, -0.5, 2.5], dir=[0.0, 0.2, -1.0], diffuse=[0.6, 0.6, 0.6],
                    type=mujoco.mjtLightType.mjLIGHT_DIRECTIONAL, castshadow=False)
    if cfg.floor:
        # Plain: a textured floor fills most of the image, and sampling its mipmapped texture took 5 of the 13 ms
        # a 640x480 frame cost on llvmpipe in a running stack (15 % of a core at 30 Hz). The detector needs no
        # background texture; the floor's grey is the checker's mean brightness.
        spec.add_material(name="floor", rgba=FLOOR_RGBA, reflectance=0.0)
        world.add_geom(name="floor", type=mujoco.mjtGeom.mjGEOM_PLANE, size=[3.0, 3.0, 0.05], material="floor",
                       contype=0, conaffinity=0)


def _add_target(spec: mujoco.MjSpec, cfg: SceneConfig, arm: ArmDescription) -> None:
    """The AprilTag target: a thin box whose +z face carries the tag upright (texture top = tag +y); or a board. A
    mocap body, at its initial pose (:func:`target_in_base`). Raises ValueError for a target below the floor."""
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
    if cfg.floor and T_bt[2, 3] < 0.0:
        raise ValueError(f"the target's centre is {-T_bt[2, 3]:.3f} m below the floor; move it or disable the floor")
    target = spec.worldbody.add_body(name=TAG_BODY, mocap=True, pos=T_bt[:3, 3].tolist(),
                                     quat=frames.matrix_to_quat_wxyz(T_bt[:3, :3]).tolist())
    thickness = 0.002
    target.add_geom(name="tag", type=mujoco.mjtGeom.mjGEOM_BOX, size=[half_x, half_y, thickness / 2],
                    pos=[0.0, 0.0, -thickness / 2], material="tag", contype=0, conaffinity=0)


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
