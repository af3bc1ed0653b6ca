"""A servo task's scenario (YAML; every field has the default shown in :class:`Scenario`): where the arm starts,
where the target is and how it moves, the goal, the law and its gains, when to stop, the camera; and the stack
configuration it makes (:func:`stack_config`)."""
from __future__ import annotations

from typing import Optional

import msgspec

from protocol.conventions import ClockMode, DepthSource
from services.controller.law import Gains, LawConfig
from services.controller.laws import LAW_NAMES
from services.controller.phases import GraspConfig
from services.controller.service import ControllerConfig
from services.model.arm import DEFAULT_ARM, load_arm
from services.robot.dsp import DSPConfig, for_arm
from services.robot_sim.scene import (CameraConfig, LightConfig, SceneConfig, SceneObject, TableConfig,
                                      TargetConfig, check_joints_deg)
from services.robot_sim.service import RobotSimConfig
from services.runtime.config import ConfigError, ConfigStruct, load_config
from services.safety.service import SafetyConfig
from services.stack.local import StackConfig
from services.vision.service import GoalConfig, TagConfig, VisionConfig


class ScenarioRobot(ConfigStruct):
    #: the arm (services/model/arms/<arm>.yaml: j2s7s300, Sensors 2022's 7-DoF; j2n6s300, the JACO thesis's 6-DoF);
    #: the whole stack runs it
    arm: str = DEFAULT_ARM
    #: physical angles (deg), as GetAngularPosition reports them, one per joint of the arm; null: its home
    initial_joints_deg: Optional[list[float]] = None
    #: the arm's DSP as robot_sim's config has it: the convention it reads for Cartesian angular velocity (the
    #: controller and safety are set to the same), its speed limits, its velocity dead-band, its protection zones
    #: (safety guards the same zones)
    dsp: DSPConfig = msgspec.field(default_factory=DSPConfig)

    def __post_init__(self) -> None:
        arm = load_arm(self.arm)  # an unknown arm is refused here, naming the ones there are
        if self.initial_joints_deg is not None:
            check_joints_deg(arm, self.initial_joints_deg, "robot.initial_joints_deg")
        for_arm(self.dsp, arm)


#: Sensors 2022's threshold on ‖e‖ over its tag's four points
TAG_ERROR_NORM = 5.0e-5


class ScenarioConvergence(ConfigStruct):
    """When the task has converged: the features' per-point RMS error below ``error_rms``, whatever the number of
    points; or, as Sensors 2022 states it for its tag, ‖e‖ over four points below ``error_norm`` (the same test:
    error_rms = error_norm/√4). Give one of the two; neither: Sensors 2022's 5e-5 on ‖e‖."""

    error_norm: Optional[float] = None
    error_rms: Optional[float] = None
    max_iterations: int = 1000

    def __post_init__(self) -> None:
        if self.error_norm is not None and self.error_rms is not None:
            raise ValueError("give convergence error_norm (a tag's four points) or error_rms (per point), not both")
        if self.error_norm is None and self.error_rms is None:
            self.error_norm = TAG_ERROR_NORM
        if not (self.rms > 0 and self.max_iterations >= 1):
            raise ValueError("convergence needs a positive error_norm or error_rms and max_iterations >= 1")

    @property
    def rms(self) -> float:
        """The per-point RMS threshold (the controller's ``convergence_error_rms``)."""
        return self.error_rms if self.error_rms is not None else self.error_norm / 2.0


class Scenario(ConfigStruct):
    """A servo task: the start, the goal, the law and when to stop. The target and the camera are robot_sim's
    scene configs and the goal is vision's, as they are (one set of keys and checks, not a copy)."""

    robot: ScenarioRobot = msgspec.field(default_factory=ScenarioRobot)
    #: the tag, and where it is (default: 0.5 m ahead of the camera, squarely facing it), as robot_sim's scene
    target: TargetConfig = msgspec.field(default_factory=TargetConfig)
    #: vision's goal (default: Sensors 2022 Table 2's square, ±0.1666 at 0.2888 m; camera_in_tag with features: null)
    goal: GoalConfig = msgspec.field(default_factory=GoalConfig)
    law: str = "adaptive-pd-mixed"
    gains: Gains = msgspec.field(default_factory=Gains)
    #: depth in the interaction matrix: current, goal or mean
    depth: DepthSource = DepthSource.CURRENT
    convergence: ScenarioConvergence = msgspec.field(default_factory=ScenarioConvergence)
    #: robot_sim's camera (intrinsics, rate, mount, encoding)
    camera: CameraConfig = msgspec.field(default_factory=CameraConfig)
    clock: ClockMode = ClockMode.LOCKSTEP
    #: law-specific options (smc, manipulability)
    law_options: dict = msgspec.field(default_factory=dict)
    #: stop after this much wall time whatever happens (s)
    timeout_s: float = 600.0
    #: consecutive iterations without the target after which the run ends as target_lost
    target_lost_iterations: int = 15
    #: the scene's other objects (clutter, an occluder, a swap) and its light, as robot_sim's scene has them
    objects: list[SceneObject] = msgspec.field(default_factory=list)
    light: LightConfig = msgspec.field(default_factory=LightConfig)
    #: a table for objects to stand on (robot_sim's scene's)
    table: Optional[TableConfig] = None
    #: how a grasp task (``mfvs task start --grasp``, ``mfvs experiment grasp``) reaches, grasps and lifts (the
    #: controller's)
    grasp: GraspConfig = msgspec.field(default_factory=GraspConfig)

    def __post_init__(self) -> None:
        if self.law not in LAW_NAMES:
            raise ValueError(f"unknown law {self.law!r}; known: {', '.join(LAW_NAMES)}")


def load_scenario(path) -> Scenario:
    """Load and validate a scenario, including what the services will check of it (so a bad value is named
    before anything starts)."""
    scenario = load_config(path, Scenario)
    try:
        stack_config(scenario)
    except (ValueError, TypeError) as exc:
        raise ConfigError(str(path), str(exc)) from None
    return scenario


def on_arm(scenario: Scenario, arm: Optional[str], name: str = "the scenario") -> Scenario:
    """``scenario`` run on ``arm`` (`--arm NAME`; None: as it says). Its start, when it gives one, must be that arm's
    (one angle per joint): ValueError otherwise, saying so."""
    if arm is None or arm == scenario.robot.arm:
        return scenario
    if scenario.robot.initial_joints_deg is not None:
        raise ValueError(f"{name} starts the {scenario.robot.arm} at initial_joints_deg "
                         f"{scenario.robot.initial_joints_deg}: not a start for the {arm} (give a scenario for it, or "
                         f"leave robot.initial_joints_deg out for the arm's home)")
    robot = msgspec.structs.replace(scenario.robot, arm=arm)
    robot.__post_init__()  # the arm known, and the DSP's limits within its ranges
    return msgspec.structs.replace(scenario, robot=robot)


def stack_config(scenario: Scenario) -> StackConfig:
    s = scenario
    convention = s.robot.dsp.angular_convention
    robot = RobotSimConfig(arm=s.robot.arm, scene=SceneConfig(initial_joints_deg=s.robot.initial_joints_deg,
                                                              camera=s.camera, target=s.target,
                                                              objects=list(s.objects), light=s.light,
                                                              table=s.table), dsp=s.robot.dsp)
    vision = VisionConfig(tag=TagConfig(family=s.target.family, id=s.target.id, size_m=s.target.size_m,
                                        layout=s.target.layout), goal=s.goal)
    control = LawConfig(gains=s.gains, depth=s.depth, target_motion=any(s.target.velocity_mps),
                        robot_convention=convention)
    controller = ControllerConfig(arm=s.robot.arm, law=s.law, control=control,
                                  convergence_error_rms=s.convergence.rms, options=law_options(s), grasp=s.grasp)
    safety = SafetyConfig(arm=s.robot.arm)
    safety.limits.robot_convention = convention
    safety.limits.zones = list(s.robot.dsp.zones)  # the arm's protection zones are the site's: safety guards them too
    return StackConfig(clock=s.clock, robot=robot, vision=vision, controller=controller, safety=safety)


def law_options(scenario: Scenario) -> dict:
    """The scenario's law options, with what the law needs of the scene that the scenario already says once: the
    sliding-mode law's field of view is the scenario camera's image (unless the options give one), its first
    sampling time the camera's period."""
    options = dict(scenario.law_options)
    if scenario.law == "smc" and options.get("fov", {}) is not None:
        camera = scenario.camera
        options["fov"] = {"width": camera.width, "height": camera.height, "fx": camera.fx, "fy": camera.fy,
                          **options.get("fov", {})}
        options.setdefault("nominal_period_s", 1.0 / camera.rate_hz)
    return options
