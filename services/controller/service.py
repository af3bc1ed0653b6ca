"""The controller service: runs one control law on every features message.

Inputs: features (``…/vision/features``), robot state, camera info (for the camera-in-end-effector transform).
Outputs: the desired twist (mixed frame, the robot's angular convention) or desired joint velocities, carrying
the features' source stamp and trace, and a ControllerStatus per iteration.

Never the last command: with no task running (the controller comes up idle: :mod:`services.controller.task`),
on tag loss, stale input, an ill-conditioned interaction matrix or a constraint abort the output is zero and the
status says why. Outputs are saturated to the configured limits (``saturated``).

Queryables ``…/controller/api/{start_task,stop_task,get_task}`` (TaskRequest, TaskRequest, nothing → TaskStatus).
"""
from __future__ import annotations

import threading
from typing import Optional

import msgspec
import numpy as np
import zenoh

from protocol.conventions import ClockMode, Frame
from protocol.messages import (
    USABLE_FEATURE_STATUSES,
    CameraInfo,
    ControllerState,
    ControllerStatus,
    Features,
    FeatureStatus,
    Header,
    JointVelocity,
    ProtocolError,
    RobotState,
    TaskRequest,
    Twist,
    encode,
)
from protocol import messages
from services.model import frames, jaco2
from services.runtime.config import ConfigStruct
from services.runtime.service import Service, ServiceConfig, query_argument
from services.runtime.state_history import StateHistory
from services.controller import ibvs
from services.controller.law import ConstraintAbort, LawConfig, LawOutput, ServoInput
from services.controller.laws import JOINT_LAWS, LAW_NAMES, make_law
from services.controller.task import Task


class OutputLimits(ConfigStruct):
    max_linear_speed_mps: float = 0.15
    max_angular_speed_rps: float = 0.8
    joint_speed_scale: float = 0.8


class ControllerConfig(ServiceConfig):
    law: str = "adaptive-pd-mixed"
    control: LawConfig = msgspec.field(default_factory=LawConfig)
    #: ‖e‖ below this is converged (seed 000: 5e-5)
    convergence_error_norm: float = 5e-5
    #: features whose image is older than this (to the controller's clock) are stale
    max_input_age_s: float = 0.15
    #: the robot state used by the law must be this fresh
    state_budget_s: float = 0.15
    #: condition number of L̂ above which the law's output is not trusted
    max_condition_number: float = 1e5
    limits: OutputLimits = msgspec.field(default_factory=OutputLimits)
    #: law-specific options (e.g. the smc or manipulability parameters)
    options: dict = msgspec.field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.law not in LAW_NAMES:
            raise ValueError(f"unknown law {self.law!r}; known: {', '.join(LAW_NAMES)}")


class ControllerService(Service):
    name = "controller"

    def __init__(self, config: ControllerConfig | None = None, **kw) -> None:
        config = config or ControllerConfig()
        super().__init__(config, **kw)
        self.config: ControllerConfig = config
        self.law = make_law(config.law, config.control, **config.options)
        self.joint_output = config.law in JOINT_LAWS
        self.lock = threading.Lock()
        self.robot_state: Optional[RobotState] = None
        self.lockstep = ClockMode(config.clock) is ClockMode.LOCKSTEP
        self.states: StateHistory[RobotState] = StateHistory()
        #: lockstep: features whose frame's robot state has not arrived yet, with their receive time
        self._waiting: list[tuple[Features, int]] = []
        #: one iteration at a time: features are handled on zenoh's threads (and deferred ones on the state's),
        #: and the law's kinematics are not thread-safe
        self._iteration_lock = threading.Lock()
        self.camera_in_ee: Optional[np.ndarray] = None
        self.iteration = 0
        self.last_status: Optional[ControllerStatus] = None
        #: idle until started; changed under the iteration lock, so a start or stop falls between iterations
        self.task = Task()
        #: the last features answered (realtime: a stopped task answers them again with zero at once)
        self._last_features: Optional[tuple[Features, int]] = None

    def on_start(self) -> None:
        keys = self.keys
        self.output_pub = self.publisher(keys.desired_joint_velocity if self.joint_output else keys.desired_twist,
                                         "output")
        self.status_pub = self.publisher(keys.controller_status, "status")
        self.subscribe(keys.robot_state, RobotState, self._on_state, "robot_state", sim_stamped=True)
        self.subscribe(keys.camera_info, CameraInfo, self._on_camera_info, "camera_info")
        self.subscribe(keys.features, Features, self._on_features, "features")
        for function in messages.TASK_FUNCTIONS:
            self.queryable(keys.controller_api(function), self._on_task_query)

    def check_health(self) -> tuple[bool, str]:
        status = self.last_status
        task = f"task={self.task.state.value}" + (f"({self.task.count} by {self.task.by})" if self.task.by else "")
        return True, f"{task} law={self.config.law} iteration={self.iteration} " + (
            f"status={status.status.value} error_norm={status.error_norm:.3g}" if status else "no features yet")

    # ------------------------------------------------------------------ the task
    def start_task(self, request: TaskRequest) -> messages.TaskStatus:
        with self._iteration_lock:
            was_running = self.task.running
            reply = self.task.start(request, self.clock.now_ns())
            if not was_running:  # a new task: the law's memory and the iteration count start afresh
                self.law.reset()
                self.iteration = 0
        self.log.info("task: %s (%s%s)", reply.message, request.operator, f": {request.reason}" if request.reason else "")
        return reply

    def stop_task(self, request: TaskRequest) -> messages.TaskStatus:
        with self._iteration_lock:
            was_running = self.task.running
            reply = self.task.stop(request)
            self.law.reset()
            last = self._last_features
            if was_running and last is not None and not self.lockstep and self.session is not None:
                # realtime: answer the last frame again, now with zero, so the arm starts braking at once
                # rather than a frame and the pipeline later (lockstep answers the next tick's frame with zero)
                features, _ = last
                status, _ = self.compute(features)
                self._publish(features, self.clock.now_ns(), status, None)
        self.log.info("task: %s (%s%s)", reply.message, request.operator, f": {request.reason}" if request.reason else "")
        return reply

    def _on_task_query(self, query: zenoh.Query) -> None:
        function = str(query.key_expr).rsplit("/", 1)[-1]
        try:
            if function == messages.START_TASK:
                reply = self.start_task(query_argument(query, function, TaskRequest))
            elif function == messages.STOP_TASK:
                reply = self.stop_task(query_argument(query, function, TaskRequest))
            else:
                query_argument(query, function, None)
                with self._iteration_lock:
                    reply = self.task.status()
        except ProtocolError as exc:
            self.refuse("task", str(exc))
            with self._iteration_lock:
                reply = self.task.status(False, str(exc))
        query.reply(query.key_expr, encode(reply))

    # ------------------------------------------------------------------ inputs
    def _on_state(self, state: RobotState, _recv_ns: int) -> None:
        with self.lock:
            self.robot_state = state
            self.states.add(state.header.stamp_ns, state)
            waiting, self._waiting = self._waiting, []
        for features, recv_ns in waiting:
            self._on_features(features, recv_ns)

    def _on_camera_info(self, info: CameraInfo, _recv_ns: int) -> None:
        T = frames.homogeneous(frames.quat_wxyz_to_matrix(info.camera_in_ee.quat_wxyz), info.camera_in_ee.xyz)
        with self.lock:
            self.camera_in_ee = T

    def _on_features(self, features: Features, recv_ns: int) -> None:
        state = None
        if self.lockstep:  # the law uses the arm as it was when the frame was taken
            with self.lock:
                state, ready = self.states.for_input(features.header.source_stamp_ns)
                if not ready:
                    self._waiting.append((features, recv_ns))
                    return
        with self._iteration_lock:
            status, output = self.compute(features, state)
            self._publish(features, recv_ns, status, output)
            self._last_features = (features, recv_ns)

    # ------------------------------------------------------------------ one iteration
    def compute(self, features: Features, state: Optional[RobotState] = None) -> tuple[ControllerStatus,
                                                                                       Optional[LawOutput]]:
        """The law's output for one features message, or None (zero output) with the reason in the status.
        ``state``: the robot state to use (default: the latest)."""
        cfg = self.config
        header = features.header
        with self.lock:
            camera_in_ee = self.camera_in_ee
            if state is None:
                state = self.robot_state

        def status(kind: ControllerState, detail: str = "", **kw) -> ControllerStatus:
            return ControllerStatus(header=self.header("status", source=header), law=cfg.law, status=kind,
                                    iteration=self.iteration, error_norm=features.error_norm, detail=detail[:256], **kw)

        if not self.task.running:
            return status(ControllerState.IDLE, "no task running (mfvs task start)"), None

        if features.status not in USABLE_FEATURE_STATUSES:
            self.law.reset()
            kind = ControllerState.STALE_INPUT if features.status is FeatureStatus.STALE else ControllerState.TAG_LOST
            return status(kind, f"features {features.status.value}: {features.detail}"), None
        now = self.clock.now_ns()
        age = (now - header.source_stamp_ns) * 1e-9
        if age > cfg.max_input_age_s:
            self.law.reset()
            return status(ControllerState.STALE_INPUT, f"image is {age * 1e3:.0f} ms old"), None
        if state is None or (now - state.header.stamp_ns) * 1e-9 > cfg.state_budget_s:
            return status(ControllerState.STALE_INPUT, "no fresh robot state"), None
        if camera_in_ee is None:
            return status(ControllerState.STALE_INPUT, "no camera info (camera-in-end-effector transform)"), None
        if state.angular_convention is not cfg.control.robot_convention and not self.joint_output:
            return status(ControllerState.STALE_INPUT, f"the robot reads '{state.angular_convention.value}', the "
                          f"controller is configured for '{cfg.control.robot_convention.value}'"), None

        self.iteration += 1
        if features.error_norm < cfg.convergence_error_norm:
            return status(ControllerState.CONVERGED), None
        inp = ServoInput(t_s=header.source_stamp_ns * 1e-9, points=np.array(features.points),
                         depths=np.array(features.depths), goal_points=np.array(features.goal_points),
                         goal_depths=np.array(features.goal_depths), q=np.array(state.q), camera_in_ee=camera_in_ee)
        # the L̂ the law will invert, with the configured depth source
        L = ibvs.approximate_interaction_matrix(inp.points, inp.depths, inp.goal_points, inp.goal_depths,
                                                cfg.control.depth)
        if np.linalg.cond(L) > cfg.max_condition_number:
            self.law.reset()
            return status(ControllerState.ILL_CONDITIONED, f"cond(L) = {np.linalg.cond(L):.3g}"), None
        try:
            output = self.law.step(inp)
        except frames.EulerSingularityError as exc:
            self.law.reset()
            return status(ControllerState.ILL_CONDITIONED, str(exc)), None
        except ConstraintAbort as exc:
            self.law.reset()
            return status(ControllerState.CONSTRAINT_ABORT, str(exc)), None
        values = output.joint_velocities if self.joint_output else output.twist
        if values is None or not np.all(np.isfinite(values)):
            self.law.reset()
            return status(ControllerState.ILL_CONDITIONED, "the law produced a non-finite output"), None
        saturated = self._saturate(output)
        camera_twist = tuple(output.camera_twist) if output.camera_twist is not None else None
        notes = {k: float(v) for k, v in output.notes.items() if np.isfinite(v)}
        return status(ControllerState.CONVERGING, gain=output.gain, saturated=saturated,
                      camera_twist=camera_twist, notes=notes), output

    def _saturate(self, output: LawOutput) -> bool:
        lim = self.config.limits
        if self.joint_output:
            ratio = float(np.max(np.abs(output.joint_velocities) / (jaco2.MAX_SPEED * lim.joint_speed_scale)))
            if ratio > 1.0:
                output.joint_velocities = output.joint_velocities / ratio
                return True
            return False
        saturated = False
        for part, vmax in ((slice(0, 3), lim.max_linear_speed_mps), (slice(3, 6), lim.max_angular_speed_rps)):
            speed = float(np.linalg.norm(output.twist[part]))
            if speed > vmax:
                output.twist[part] *= vmax / speed
                saturated = True
        return saturated

    def _publish(self, features: Features, recv_ns: int, status: ControllerStatus,
                 output: Optional[LawOutput]) -> None:
        header: Header = self.header("output", source=features.header, recv_ns=recv_ns)
        if self.joint_output:
            dq = output.joint_velocities if output is not None else np.zeros(jaco2.N_JOINTS)
            self.output_pub.put(JointVelocity(header=header, velocities=dq.tolist()))
        else:
            twist = output.twist if output is not None else np.zeros(6)
            self.output_pub.put(Twist(header=header, frame=Frame.MIXED, angular=self.config.control.robot_convention,
                                      linear=tuple(twist[:3]), rotational=tuple(twist[3:])))
        self.status_pub.put(status)
        self.last_status = status
