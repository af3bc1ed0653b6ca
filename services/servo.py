"""``mfvs servo``: run one servo task described by a scenario file through the real services and report.

The scenario (YAML; every field has the default shown in :class:`Scenario`) says where the arm starts, where the
target is (and how it moves), the goal, the law and its gains, when to stop, and the camera. The runner starts a
router and the services (robot_sim, vision, controller, safety; lockstep by default), watches the controller's
iterations, stops the services, and returns :class:`ServoResult` (docs/contracts.md). With an output directory it
writes the trajectory log (one JSON line per iteration) and plots.
"""
from __future__ import annotations

import json
import math
import threading
import time
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Optional

import msgspec
import numpy as np

from protocol import messages as m
from protocol.conventions import ClockMode, DepthSource
from protocol.keys import Keys
from services.model.arm import DEFAULT_ARM, load_arm
from services.runtime.config import ConfigError, ConfigStruct, load_config
from services.model.kinematics import ArmKinematics, manipulability
from services.model.zones import nearest_zone
from services.runtime.service import query_health
from services.controller.law import Gains, LawConfig
from services.controller.laws import JOINT_LAWS, LAW_NAMES
from services.controller.service import ControllerConfig
from services.controller.task_client import start_task
from services.robot_sim.scene import CameraConfig, SceneConfig, TargetConfig, check_joints_deg
from services.robot.dsp import DSPConfig, for_arm
from protocol.keys import ROBOT_SERVICES
from services.robot_sim.service import RobotSimConfig
from services.safety.service import SafetyConfig
from services.composed import ComposedStack, composable
from services.stack import LocalStack, StackConfig
from services.runtime.jsonsafe import json_safe
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


class ScenarioConvergence(ConfigStruct):
    error_norm: float = 5.0e-5
    max_iterations: int = 1000

    def __post_init__(self) -> None:
        if not (self.error_norm > 0 and self.max_iterations >= 1):
            raise ValueError("convergence needs error_norm > 0 and max_iterations >= 1")


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
    #: consecutive iterations without the tag after which the run ends as tag_lost
    tag_lost_iterations: int = 15

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
                                                              camera=s.camera, target=s.target), dsp=s.robot.dsp)
    vision = VisionConfig(tag=TagConfig(family=s.target.family, id=s.target.id, size_m=s.target.size_m,
                                        layout=s.target.layout), goal=s.goal)
    control = LawConfig(gains=s.gains, depth=s.depth, target_motion=any(s.target.velocity_mps),
                        robot_convention=convention)
    controller = ControllerConfig(arm=s.robot.arm, law=s.law, control=control,
                                  convergence_error_norm=s.convergence.error_norm, options=law_options(s))
    safety = SafetyConfig(arm=s.robot.arm)
    safety.limits.robot_convention = convention
    safety.limits.zones = list(s.robot.dsp.zones)  # the arm's protection zones are the site's: safety guards them too
    return StackConfig(clock=s.clock, robot=robot, vision=vision, controller=controller, safety=safety)


def write_log(records: list[Iteration], path) -> Path:
    """The trajectory log: one strict-JSON object per iteration (a missing measurement is null)."""
    path = Path(path)
    with path.open("w") as f:
        for record in records:
            f.write(json.dumps(json_safe(record.__dict__), allow_nan=False) + "\n")
    return path


def read_log(path) -> list[dict]:
    """A run's trajectory log (one JSON object per iteration), with the null of a missing measurement (no arm
    state, no error: JSON has no NaN) read back as NaN in the float fields, so the numbers stay numbers."""
    floats = [f.name for f in fields(Iteration) if f.type == "float"]
    records = []
    for line in Path(path).read_text().splitlines():
        record = json.loads(line)
        for name in floats:
            if record.get(name, 0.0) is None:
                record[name] = math.nan
        records.append(record)
    return records


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


@dataclass
class Iteration:
    """One controller iteration as the run log records it."""

    iteration: int
    t_s: float
    #: the stamp of the camera frame this iteration answers
    stamp_ns: int
    status: str
    error_norm: float
    points: list
    error: list
    command: list
    command_kind: str
    q: list
    gain: float
    saturated: bool
    camera_twist: Optional[list]
    manipulability: float
    ee_speed_mps: float
    notes: dict = field(default_factory=dict)
    #: the end effector's measured angular speed (rad/s) at the frame's tick
    ee_angular_speed_rps: float = 0.0
    #: what shaped the arm's motion at the frame's tick (the robot state's faults: the DSP's active limits, e.g.
    #: joint_limit, singularity, zone:base, dead_band, speed)
    robot_faults: list = field(default_factory=list)
    #: the end effector's signed distance to the nearest protection zone of the arm's DSP (m; inside: negative)
    zone_distance_m: Optional[float] = None
    #: safety's answer to the law's command for this frame, when it refused it: why (empty: approved, or no command)
    safety_refusal: str = ""


@dataclass
class ServoResult:
    converged: bool
    iterations: int
    #: the last error the law acted on; None when the tag was never seen (``detail`` says why)
    final_error_norm: Optional[float]
    status: str
    min_manipulability: float
    max_joint_limit_violation_deg: float
    max_linear_speed_mps: float
    trajectory_log: Optional[str] = None
    plots: list = field(default_factory=list)
    law: str = ""
    wall_time_s: float = 0.0
    #: from the first frame the law acted on to the last frame answered (the arm's clock): with
    #: ``frames_answered``, what separates a loop that moves differently from one that sees fewer frames
    servo_time_s: float = 0.0
    #: frames the controller answered in that time, whatever the answer (stale, lost and converged included)
    frames_answered: int = 0
    #: frames that never became an iteration, by where they were lost (the services' counters over the run):
    #: ``camera.dropped`` (the renderer still busy with the last one), ``vision.skipped`` (a newer frame came
    #: before vision took it), ``vision.stale`` (older than vision's image budget)
    frames_lost: dict = field(default_factory=dict)
    #: the largest of each law figure over the run (e.g. smc's max_phi.fov, and its band)
    law_figures: dict = field(default_factory=dict)
    #: why the run ended as it did, in words (empty when it converged)
    detail: str = ""
    #: the first and the largest error the law acted on
    initial_error_norm: Optional[float] = None
    max_error_norm: Optional[float] = None
    #: iterations at whose tick each of the arm's limits shaped its motion (robot state faults)
    robot_limits_hit: dict = field(default_factory=dict)
    #: the closest the end effector came to a protection zone (m; negative: inside)
    min_zone_distance_m: Optional[float] = None
    #: why safety refused the last frame's command it refused (per frame, as ``Iteration.safety_refusal``)
    last_refusal: str = ""
    #: what safety's status said over the run (published at its own rate, so counts vary run to run): its states
    #: seen, the limits it named, its last refusal, a protective stop's reason
    safety: dict = field(default_factory=dict)
    #: the speed limits the robot declared (MotionLimits as a dict)
    robot_limits: Optional[dict] = None
    #: ticks at which the robot node's lockstep wait for the pipeline ran out and the arm went on without its
    #: answer: a host too loaded for the wait (``lockstep.frame_timeout_s``); the run is then not a function of its
    #: scenario alone, and a rerun may differ
    lockstep_timeouts: int = 0
    #: how its stack ran: ``composed`` (the services in the runner's process, :mod:`services.composed`) or
    #: ``processes`` (each service a process of its own, as deployed)
    stack: str = ""

    def to_json(self) -> dict:
        return {
            "converged": self.converged, "iterations": self.iterations,
            "final_error_norm": self.final_error_norm, "status": self.status,
            "min_manipulability": self.min_manipulability,
            "max_joint_limit_violation_deg": self.max_joint_limit_violation_deg,
            "max_linear_speed_mps": self.max_linear_speed_mps, "trajectory_log": self.trajectory_log,
            "plots": self.plots, "law": self.law, "wall_time_s": self.wall_time_s,
            "servo_time_s": self.servo_time_s, "frames_answered": self.frames_answered,
            "frames_lost": self.frames_lost, "law_figures": self.law_figures, "detail": self.detail,
            "initial_error_norm": self.initial_error_norm, "max_error_norm": self.max_error_norm,
            "robot_limits_hit": self.robot_limits_hit, "min_zone_distance_m": self.min_zone_distance_m,
            "last_refusal": self.last_refusal, "safety": self.safety, "robot_limits": self.robot_limits,
            "lockstep_timeouts": self.lockstep_timeouts, "stack": self.stack,
        }


class _Watcher:
    """Collects what the runner needs from the bus: controller statuses, the commands, features, robot states."""

    def __init__(self, session, keys: Keys, joint_output: bool) -> None:
        #: guards everything below; each wait is on the condition of what it waits for, so that a message wakes
        #: only a runner waiting for its kind (the runner waits for statuses; ten other messages come per frame)
        self.lock = threading.RLock()
        self.new_status, self.new_state, self.new_answer, self.new_input = (
            threading.Condition(self.lock) for _ in range(4))
        self.statuses: list[m.ControllerStatus] = []
        self.features: dict[int, m.Features] = {}
        self.commands: dict[int, list] = {}
        self.state: Optional[m.RobotState] = None
        #: the robot's states by stamp, to log each iteration with the state of its frame's tick
        self.state_at: dict[int, m.RobotState] = {}
        self.latest_state_stamp = -1
        #: safety's answer to each frame's command, by the frame's stamp
        self.answers: dict[int, m.RobotCommand] = {}
        #: safety's statuses by state, its limits seen, its last refusal and what a latched stop said
        self.safety_states: dict[str, int] = {}
        self.safety_limits: dict[str, int] = {}
        self.safety_refusal = ""
        self.safety_stop = ""
        self.states: list[m.RobotState] = []
        self.joint_output = joint_output
        output_key = keys.desired_joint_velocity if joint_output else keys.desired_twist
        output_type = m.JointVelocity if joint_output else m.Twist
        self._subs = [
            session.declare_subscriber(keys.controller_status, self._typed(m.ControllerStatus, self._on_status)),
            session.declare_subscriber(keys.features, self._typed(m.Features, self._on_features)),
            session.declare_subscriber(output_key, self._typed(output_type, self._on_output)),
            session.declare_subscriber(keys.robot_state, self._typed(m.RobotState, self._on_state)),
            session.declare_subscriber(keys.safety_status, self._typed(m.SafetyStatus, self._on_safety)),
            session.declare_subscriber(keys.robot_command, self._typed(m.RobotCommand, self._on_command)),
        ]

    @staticmethod
    def _typed(message_type, handler):
        return lambda sample: handler(m.decode(sample.payload.to_bytes(), message_type))

    def _on_status(self, status):
        with self.lock:
            last = self.statuses[-1] if self.statuses else None
            if last is not None and (last.header.seq, last.header.source_stamp_ns) == (
                    status.header.seq, status.header.source_stamp_ns):
                return  # the controller's answer to a frame again (a lockstep retry): one record per frame
            self.statuses.append(status)
            self.new_status.notify_all()

    def _on_features(self, features):
        with self.lock:
            self.features[features.header.source_stamp_ns] = features
            self.new_input.notify_all()

    def _on_output(self, output):
        values = output.velocities if isinstance(output, m.JointVelocity) else [*output.linear, *output.rotational]
        with self.lock:
            self.commands[output.header.source_stamp_ns] = list(values)
            self.new_input.notify_all()

    def _on_state(self, state):
        with self.lock:
            self.state = state
            self.states.append(state)
            self.state_at[state.header.stamp_ns] = state
            self.latest_state_stamp = max(self.latest_state_stamp, state.header.stamp_ns)
            self.new_state.notify_all()

    def state_for_frame(self, stamp_ns: int, timeout_s: float = 1.0) -> Optional[m.RobotState]:
        """The state of the tick at which the frame ``stamp_ns`` was taken (in lockstep the robot publishes one
        with that stamp; it may reach us after the controller's answer, so wait for it), else the last state
        before it, else the newest. Call with :attr:`lock` held."""
        self.new_state.wait_for(lambda: self.latest_state_stamp >= stamp_ns, timeout=timeout_s)
        state = self.state_at.get(stamp_ns)
        if state is None:
            before = [s for s in self.state_at if s <= stamp_ns]
            state = self.state_at[max(before)] if before else self.state
        return state

    def _on_command(self, command):
        with self.lock:  # the first command derived from a frame is safety's answer to it (later ones resend it)
            self.answers.setdefault(command.header.source_stamp_ns, command)
            self.new_answer.notify_all()

    def answer_for_frame(self, stamp_ns: int, timeout_s: float) -> Optional[m.RobotCommand]:
        """Safety's answer to the command derived from frame ``stamp_ns`` (in lockstep there is exactly one, sent
        before the robot's next tick; wait for it). Call with :attr:`lock` held."""
        self.new_answer.wait_for(lambda: stamp_ns in self.answers, timeout=timeout_s)
        return self.answers.get(stamp_ns)

    def _on_safety(self, status):
        with self.lock:
            self.safety_states[status.state.value] = self.safety_states.get(status.state.value, 0) + 1
            for name in status.active_limits:
                self.safety_limits[name] = self.safety_limits.get(name, 0) + 1
            self.safety_refusal = status.last_refusal or self.safety_refusal
            if status.state is m.SafetyState.ESTOP and not self.safety_stop:
                self.safety_stop = status.last_refusal or "latched stop"

    def safety_summary(self) -> dict:
        with self.lock:
            return {"states": dict(self.safety_states), "limits": dict(self.safety_limits),
                    "last_refusal": self.safety_refusal, "protective_stop": self.safety_stop or None}

    def close(self) -> None:
        for sub in self._subs:
            sub.undeclare()


#: (service, counter) → the name ``ServoResult.frames_lost`` gives it
FRAME_LOSS_COUNTERS = {("robot_sim", "frames.dropped"): "camera.dropped", ("vision", "frames.skipped"): "vision.skipped",
                       ("vision", "frames.stale"): "vision.stale"}


#: the robot node's lockstep waits that ran out (wall time): the arm went on without the pipeline's answer
LOCKSTEP_TIMEOUT_COUNTERS = ("lockstep.timeouts.frame", "lockstep.timeouts.cycle",
                             "lockstep.timeouts.answerers")


def _frames_lost(session, keys: Keys) -> tuple[dict, int]:
    """Where frames were lost, from the services' health counters (every run starts a new stack: a counter is
    the run's; a service that does not answer is left out), and how many times the robot node's lockstep wait ran
    out."""
    health = query_health(session, keys)
    lost = {name: health[service].errors.get(counter, 0)
            for (service, counter), name in FRAME_LOSS_COUNTERS.items() if service in health}
    timeouts = sum(health[service].errors.get(counter, 0) for service in ROBOT_SERVICES
                   if service in health for counter in LOCKSTEP_TIMEOUT_COUNTERS)
    return lost, timeouts


def run(scenario: Scenario, out_dir: Optional[Path] = None, progress=None, profile: str = "sim",
        plots: bool = True, record: Optional[Path] = None, processes: bool = False, bus: str = "hub") -> ServoResult:
    """Run the scenario through a local stack; ``progress(iteration_record)`` is called per iteration. The gateway
    profile drives the simulated arm through robot_gateway and its RS-485 bus (the hub, robot_sim's actuators and
    the gateway as processes; ``bus="kinova_usb"``: robot_sim's emulated base through Kinova's USB comm layer instead
    of the hub), in the scenario's clock mode. With ``out_dir`` the trajectory log, the result and
    (unless ``plots`` is false) the figures are written there; with ``record`` every topic of the stack, from
    before the robot's first message, goes into that MCAP file (``mfvs record``'s).

    The sim profile in lockstep runs composed (:mod:`services.composed`: the services in this process, the same
    run byte for byte, faster) unless ``processes`` asks for every service in a process of its own, as deployed;
    anything else always runs as processes."""
    config = stack_config(scenario)
    config.profile, config.robot_bus = profile, bus
    stack_type = ComposedStack if composable(config) and not processes else LocalStack
    joint_output = config.controller.law in JOINT_LAWS
    arm = load_arm(scenario.robot.arm)
    kin = ArmKinematics(arm)
    lower, upper = arm.model_limits()
    records: list[Iteration] = []
    started = time.monotonic()
    status = "timeout"
    observer: dict = {}

    def watch(stack) -> None:  # before the robot's first message
        keys = Keys(config.robot.robot_id)
        observer["session"] = stack.open_session()
        observer["watcher"] = _Watcher(observer["session"], keys, joint_output)
        if record is not None:
            from services.observe.record import Recorder

            observer["recorder"] = Recorder(observer["session"], keys, record)
        # the stack comes up idle; the task starts before the robot's clock does, so lockstep stays exact
        started = start_task(observer["session"], keys, operator="mfvs servo", reason=f"{scenario.law} scenario")
        if started.state is not m.TaskState.RUNNING:
            raise RuntimeError(f"the controller did not start the task: {started.message}")

    try:
        stack_context = stack_type(config, before_robot=watch)
        stack = stack_context.__enter__()
    except BaseException:
        if observer:
            observer["watcher"].close()
            if "recorder" in observer:
                observer["recorder"].close()
            observer["session"].close()
        raise
    try:
        session, watcher = observer["session"], observer["watcher"]
        try:
            seen = 0
            initial_error = None
            lost_streak = 0
            # lockstep: safety answers each frame before the robot's next tick, so the answer always comes
            answer_timeout_s = 2.0 if scenario.clock is ClockMode.LOCKSTEP else 0.3
            refused_streak = 0
            while time.monotonic() - started < scenario.timeout_s:
                with watcher.lock:
                    watcher.new_status.wait_for(lambda n=seen: len(watcher.statuses) > n, timeout=1.0)
                    new = watcher.statuses[seen:]
                    seen = len(watcher.statuses)
                if not new:
                    if stack.robot_alive():
                        continue
                    status = "robot_stopped"
                    break
                done = False
                for st in new:
                    record = _record(st, watcher, kin, scenario.robot.dsp.zones, answer_timeout_s)
                    records.append(record)
                    if progress is not None:
                        progress(record)
                    if st.status is m.ControllerState.CONVERGED:
                        status, done = "converged", True
                    elif st.status is m.ControllerState.CONSTRAINT_ABORT:
                        status, done = "constraint_abort", True
                    lost_streak = lost_streak + 1 if st.status is m.ControllerState.TAG_LOST else 0
                    if st.status is m.ControllerState.CONVERGING:
                        initial_error = st.error_norm if initial_error is None else initial_error
                    refused_streak = refused_streak + 1 if record.safety_refusal else 0
                    if lost_streak >= scenario.tag_lost_iterations:
                        grew = initial_error is not None and max(
                            r.error_norm for r in records if r.status == "converging") > 2.0 * initial_error
                        status, done = ("diverged" if grew else "tag_lost"), True
                    elif refused_streak >= 30:
                        status, done = "refused", True
                    elif st.iteration >= scenario.convergence.max_iterations:
                        status, done = "max_iterations", True
                    if done:
                        break
                if done:
                    break
            states = list(watcher.states)
            with watcher.lock:  # features and commands may reach us after their status (each subscriber has
                # its own thread; the last ones may still be on their way): complete the log with what came later
                # (the controller answers every frame: zero when it does not act)
                watcher.new_input.wait_for(lambda: all(
                    r.stamp_ns in watcher.features and r.stamp_ns in watcher.commands for r in records), timeout=2.0)
                for record in records:
                    _fill_inputs(record, watcher)
            frames_lost, lockstep_timeouts = _frames_lost(session, Keys(config.robot.robot_id))
            safety = watcher.safety_summary()
        finally:
            watcher.close()
            if "recorder" in observer:
                observer["recorder"].close()
            session.close()
    finally:
        stack_context.__exit__(None, None, None)
    wall = time.monotonic() - started
    converging = [r for r in records if r.status in ("converging", "converged")]
    q_all = np.array([s.q for s in states]) if states else np.zeros((0, 7))
    violation = 0.0
    if len(q_all):
        limited = np.isfinite(lower)
        over = np.maximum(q_all[:, limited] - upper[limited], lower[limited] - q_all[:, limited])
        violation = max(0.0, float(np.degrees(over.max())))
    speeds = [kin.ee_speed(s.q, s.dq) for s in states]
    acted = [r for r in records if r.status == "converging"]
    answered = [r for r in records if acted and r.stamp_ns >= acted[0].stamp_ns]
    result = ServoResult(
        converged=status == "converged",
        iterations=max((r.iteration for r in records), default=0),
        final_error_norm=converging[-1].error_norm if converging else None,
        status=status,
        min_manipulability=min((r.manipulability for r in records if math.isfinite(r.manipulability)),
                               default=0.0),
        max_joint_limit_violation_deg=violation,
        max_linear_speed_mps=max(speeds, default=0.0),
        law=scenario.law,
        wall_time_s=round(wall, 3),
        servo_time_s=round((answered[-1].stamp_ns - answered[0].stamp_ns) * 1e-9, 3) if answered else 0.0,
        frames_answered=len(answered),
        frames_lost=frames_lost,
        lockstep_timeouts=lockstep_timeouts,
        law_figures=_law_figures(records),
        initial_error_norm=converging[0].error_norm if converging else None,
        max_error_norm=max(r.error_norm for r in converging) if converging else None,
        robot_limits_hit=_limits_hit(records),
        min_zone_distance_m=min((r.zone_distance_m for r in records if r.zone_distance_m is not None),
                                default=None),
        safety=safety,
        last_refusal=next((r.safety_refusal for r in reversed(records) if r.safety_refusal), ""),
        robot_limits=msgspec.to_builtins(states[-1].limits) if states and states[-1].limits is not None else None,
        stack="composed" if stack_type is ComposedStack else "processes",
    )
    result.detail = _why(result, converging)
    if out_dir is not None:
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        log = write_log(records, out / "trajectory.jsonl")
        result.trajectory_log = str(log)
        from services.plots import servo_plots

        result.plots = [] if not plots else [str(p) for p in servo_plots(
            records, out, law=scenario.law, arm=arm, goal=scenario.goal.features, camera=scenario.camera,
            threshold=scenario.convergence.error_norm, robot_limits=result.robot_limits)]
        (out / "result.json").write_text(json.dumps(result.to_json(), indent=2) + "\n")
    return result


def _limits_hit(records: list[Iteration]) -> dict:
    hits: dict[str, int] = {}
    for record in records:
        for name in record.robot_faults:
            hits[name] = hits.get(name, 0) + 1
    return hits


def _why(result: ServoResult, converging: list[Iteration]) -> str:
    """Why a run ended as it did, in words."""
    stop = result.safety.get("protective_stop")
    said = f"; safety latched a stop: {stop}" if stop else ""
    if result.status == "converged":
        return "" + said
    if not converging:
        return ("the tag was never seen: it is outside the camera's initial view, or too small or far to detect "
                "(check target.pose_in_camera and the camera)" + said)
    grew = f"‖e‖ from {result.initial_error_norm:.3g} up to {result.max_error_norm:.3g}"
    if result.status == "diverged":
        return f"the error grew ({grew}) and the tag left the image" + said
    if result.status == "tag_lost":
        return f"the tag left the image after {result.iterations} iterations ({grew})" + said
    if result.status == "refused":
        return f"safety refused the commands: {result.last_refusal}" + said
    if result.status == "max_iterations":
        return f"not converged after {result.iterations} iterations (‖e‖ = {result.final_error_norm:.3g})" + said
    if result.status == "constraint_abort":
        return "the law gave up: its constraints left no freedom for the task" + said
    if result.status == "robot_stopped":
        return "the robot stopped publishing its state" + said
    return f"the run ended as {result.status}" + said


def _law_figures(records: list[Iteration]) -> dict:
    figures: dict[str, float] = {}
    for record in records:
        for key, value in record.notes.items():
            figures[key] = max(figures.get(key, -math.inf), value)
    return figures


def _record(status: m.ControllerStatus, watcher: _Watcher, kin: ArmKinematics, zones: list,
            answer_timeout_s: float) -> Iteration:
    stamp = status.header.source_stamp_ns
    refusal = ""
    with watcher.lock:
        state = watcher.state_for_frame(stamp, answer_timeout_s)
        if status.status is m.ControllerState.CONVERGING:  # the law commanded: safety answers this frame
            answer = watcher.answer_for_frame(stamp, answer_timeout_s)
            if answer is not None and answer.mode in (m.CommandMode.STOP, m.CommandMode.EMERGENCY_STOP):
                refusal = answer.reason or answer.mode.value
    q = list(state.q) if state is not None else []
    manip, speed, angular_speed, zone_distance = math.nan, 0.0, 0.0, None
    if state is not None:
        _, p, J = kin.pose_and_jacobian(state.q)
        manip = manipulability(J)
        twist = J @ np.asarray(state.dq)
        speed, angular_speed = float(np.linalg.norm(twist[:3])), float(np.linalg.norm(twist[3:]))
        zone_distance = nearest_zone(zones, p)[1] if zones else None
    record = Iteration(
        iteration=status.iteration, t_s=stamp * 1e-9, stamp_ns=stamp, status=status.status.value,
        error_norm=status.error_norm,
        points=[], error=[], command=[], command_kind="", q=q,
        gain=status.gain, saturated=status.saturated,
        camera_twist=list(status.camera_twist) if status.camera_twist is not None else None,
        manipulability=manip, ee_speed_mps=speed, notes=dict(status.notes), ee_angular_speed_rps=angular_speed,
        robot_faults=list(state.faults) if state is not None else [], zone_distance_m=zone_distance,
        safety_refusal=refusal,
    )
    with watcher.lock:
        _fill_inputs(record, watcher)
    return record


def _fill_inputs(record: Iteration, watcher: _Watcher) -> None:
    """The iteration's features and command, by its frame's stamp (call with the watcher's lock held)."""
    features = watcher.features.get(record.stamp_ns)
    if features is not None:
        record.points = [list(p) for p in features.points]
        record.error = list(features.error)
    record.command = watcher.commands.get(record.stamp_ns, [])
    record.command_kind = "joint_velocity" if watcher.joint_output else "mixed_twist"
