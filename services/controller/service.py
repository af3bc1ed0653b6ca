"""The controller service: runs one control law on every features message.

Inputs: features (``…/vision/features``), robot state, camera info (for the camera-in-end-effector transform).
Outputs: the desired twist (mixed frame, the robot's angular convention) or desired joint velocities, carrying
the features' source stamp and trace, and a ControllerStatus per iteration.

Its rules are :class:`~services.controller.core.ControllerCore` (no zenoh, no locks, no clock): never the last
command (with no task running, the controller comes up idle, on tag loss, stale input, an ill-conditioned
interaction matrix or a constraint abort the output is zero and the status says why), and outputs saturated to the
limits the robot declares in its state. This service pairs each features message with its robot state, calls the
core and publishes.

Queryables ``…/controller/api/{start_task,stop_task,get_task}`` (TaskRequest, TaskRequest, nothing → TaskStatus).
"""
from __future__ import annotations

import threading
from typing import Optional

import msgspec
import numpy as np
import zenoh

from protocol.conventions import IMAGE_AGE_BUDGET_S, ClockMode, Frame
from protocol.messages import (
    CameraInfo,
    ControllerStatus,
    Features,
    Header,
    JointVelocity,
    ProtocolError,
    RobotState,
    SafetyStatus,
    TaskRequest,
    Twist,
    encode,
)
from protocol import messages
from protocol.keys import last_chunk
from services.model import frames
from services.model.arm import check_arm_name
from services.runtime.service import Service, ServiceConfig, query_argument
from services.runtime.state_history import StateHistory
from services.controller.core import ControllerCore
from services.controller.law import LawConfig, LawOutput
from services.controller.laws import LAW_NAMES
from services.controller.phases import GraspConfig, MoveConfig, ServoPhase
from services.runtime.ports import Port, Ports


class ControllerConfig(ServiceConfig):
    #: the arm it controls (services/model/arms/<arm>.yaml); null: the robot's, as its states declare it. Named,
    #: a robot that declares another arm gets nothing from this controller (status wrong_arm)
    arm: Optional[str] = None
    law: str = "adaptive-pd-mixed"
    control: LawConfig = msgspec.field(default_factory=LawConfig)
    #: the features' per-point RMS error (from their error and weights: services.model.point_features) below which
    #: the task has converged: 2.5e-5 is Sensors 2022's ‖e‖ < 5e-5 over its tag's four points (‖e‖/√4), and means
    #: the same whatever the number of points
    convergence_error_rms: float = 2.5e-5
    #: features whose image is older than this (to the controller's clock) are stale: zero output (the visual
    #: path's one budget; 0.15 s gave 1-41 stale frames of 114-124 a run through the gateway, 0.25 s 0-8)
    max_input_age_s: float = IMAGE_AGE_BUDGET_S
    #: the robot state used by the law must be this fresh
    state_budget_s: float = 0.15
    #: realtime: carry each frame's features from the arm's configuration when it was taken to its latest measured
    #: one (forward kinematics; a static target) before the law, so that the image pipeline's delay (30-90 ms on a
    #: loaded host) does not act as delay in the visual loop. Lockstep answers each frame at its own tick: nothing
    #: to carry. A departure from Sensors 2022, whose loop is stated without its latency
    latency_compensation: bool = True
    #: condition number of L̂ above which the law's output is not trusted
    max_condition_number: float = 1e5
    #: law-specific options (e.g. the smc or manipulability parameters)
    options: dict = msgspec.field(default_factory=dict)
    #: how a task's move phase moves (teach's depth probe, a grasp's approach and lift; services/controller/phases.py)
    move: MoveConfig = msgspec.field(default_factory=MoveConfig)
    #: how a grasp task reaches, grasps and lifts, and its grasp detector's thresholds
    grasp: GraspConfig = msgspec.field(default_factory=GraspConfig)

    def __post_init__(self) -> None:
        if self.law not in LAW_NAMES:
            raise ValueError(f"unknown law {self.law!r}; known: {', '.join(LAW_NAMES)}")
        if self.arm is not None:
            check_arm_name(self.arm)


class ControllerService(Service):
    name = "controller"
    PORTS = Ports(consumes=(Port("robot_state", RobotState), Port("camera_info", CameraInfo),
                            Port("features", Features), Port("safety_status", SafetyStatus)),
                  produces=(Port("desired_twist", Twist), Port("desired_joint_velocity", JointVelocity),
                            Port("controller_status", ControllerStatus)),
                  answers=(Port("controller_api"),))
    clock_from_inputs = True  # the robot states (features are answered at their frame's state)

    def __init__(self, config: ControllerConfig | None = None, **kw) -> None:
        config = config or ControllerConfig()
        super().__init__(config, **kw)
        self.config: ControllerConfig = config
        self.core = ControllerCore(config)
        self.lock = threading.Lock()
        self.robot_state: Optional[RobotState] = None
        self.lockstep = ClockMode(config.clock) is ClockMode.LOCKSTEP
        self.states: StateHistory[RobotState] = StateHistory()
        #: lockstep: features whose frame's robot state has not arrived yet, with their receive time
        self._waiting: list[tuple[Features, int]] = []
        #: one iteration at a time: features are handled on zenoh's threads (and deferred ones on the state's),
        #: the law's kinematics are not thread-safe, and a task's start or stop falls between iterations
        self._iteration_lock = threading.Lock()
        self.camera_in_ee: Optional[np.ndarray] = None
        self.last_status: Optional[ControllerStatus] = None
        #: the last features answered (realtime: a stopped task answers them again with zero at once)
        self._last_features: Optional[Features] = None
        #: the frame (capture stamp) last answered and what was published for it: the same features again (a frame
        #: robot_sim's lockstep retry delivered twice) get that answer again, with no second step of the law
        self._last_answer: Optional[tuple[int, object, ControllerStatus]] = None

    def on_start(self) -> None:
        keys = self.keys
        self.output_pub = self.publisher(keys.desired_joint_velocity if self.core.joint_output else keys.desired_twist,
                                         "output")
        self.status_pub = self.publisher(keys.controller_status, "status")
        self.subscribe(keys.robot_state, RobotState, self._on_state, "robot_state", sim_stamped=True)
        self.subscribe(keys.camera_info, CameraInfo, self._on_camera_info, "camera_info")
        self.subscribe(keys.features, Features, self._on_features, "features")
        self.subscribe(keys.safety_status, SafetyStatus, self._on_safety_status, "safety_status")
        for function in messages.TASK_FUNCTIONS:
            self.queryable(keys.controller_api(function), self._on_task_query)

    def check_health(self) -> tuple[bool, str]:
        status, task = self.last_status, self.core.task
        state = f"task={task.state.value}" + (f"({task.count} by {task.by})" if task.by else "")
        arm = self.core.arm.name if self.core.arm is not None else "(the robot's, not heard yet)"
        return True, f"{state} arm={arm} law={self.config.law} iteration={self.core.iteration} " + (
            f"status={status.status.value} error_norm={status.error_norm:.3g}" if status else "no features yet")

    # ------------------------------------------------------------------ the task
    def start_task(self, request: TaskRequest) -> messages.TaskStatus:
        with self.lock:
            state = self.robot_state
        with self._iteration_lock:
            reply = self.core.start_task(request, self.clock.now_ns(), state)
        self._log_task(reply, request)
        return reply

    def stop_task(self, request: TaskRequest) -> messages.TaskStatus:
        with self._iteration_lock:
            was_running = self.core.task.running
            reply = self.core.stop_task(request)
            last = self._last_features
            if was_running and last is not None and not self.lockstep and self.session is not None:
                # realtime: answer the last frame again, now with zero, so the arm starts braking at once
                # rather than a frame and the pipeline later (lockstep answers the next tick's frame with zero)
                status, _ = self.compute(last)
                self._publish(last, self.clock.now_ns(), status, None)
        self._log_task(reply, request)
        return reply

    def resume_task(self, request: TaskRequest) -> messages.TaskStatus:
        with self._iteration_lock:
            reply = self.core.resume_task(request)
        self._log_task(reply, request)
        return reply

    def _on_safety_status(self, status: SafetyStatus, _recv_ns: int) -> None:
        with self._iteration_lock:
            why = self.core.observe_control(status.in_control)
        if why is not None:
            self.counters.inc("task.paused")
            self.log.warning("task %d paused: %s (mfvs task resume goes on with it)", self.core.task.count, why)

    def _log_task(self, reply: messages.TaskStatus, request: TaskRequest) -> None:
        why = f": {request.reason}" if request.reason else ""
        self.log.info("task: %s (%s%s)", reply.message, request.operator, why)

    def _on_task_query(self, query: zenoh.Query) -> None:
        function = last_chunk(query.key_expr)
        try:
            if function == messages.START_TASK:
                reply = self.start_task(query_argument(query, function, TaskRequest))
            elif function == messages.STOP_TASK:
                reply = self.stop_task(query_argument(query, function, TaskRequest))
            elif function == messages.RESUME_TASK:
                reply = self.resume_task(query_argument(query, function, TaskRequest))
            else:
                query_argument(query, function, None)
                with self._iteration_lock:
                    reply = self.core.task.status()
        except ProtocolError as exc:
            self.refuse("task", str(exc))
            with self._iteration_lock:
                reply = self.core.task.status(False, str(exc))
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
        state = capture_state = None
        if self.lockstep:  # the law uses the arm as it was when the frame was taken
            with self.lock:
                state, ready = self.states.for_input(features.header.source_stamp_ns)
                if not ready:
                    self._waiting.append((features, recv_ns))
                    return
        else:
            with self.lock:
                capture_state = self.states.at_capture(features.header.source_stamp_ns)
        with self._iteration_lock:
            answered = self._last_answer
            if answered is not None and answered[0] == features.header.source_stamp_ns:
                self.counters.inc("features.repeated")
                if answered[1] is not None:
                    self.output_pub.put(answered[1])
                self.status_pub.put(answered[2])
                return
            status, output = self.compute(features, state, capture_state)
            self._publish(features, recv_ns, status, output)
            self._last_features = features

    # ------------------------------------------------------------------ one iteration
    def compute(self, features: Features, state: Optional[RobotState] = None,
                capture_state: Optional[RobotState] = None) -> tuple[ControllerStatus, Optional[LawOutput]]:
        """The law's output for one features message, or None (zero output) with the reason in the status.
        ``state``: the robot state to use (default: the latest); ``capture_state``: the one when the frame was
        taken (realtime)."""
        with self.lock:
            camera_in_ee = self.camera_in_ee
            if state is None:
                state = self.robot_state
        step = self.core.step(features, state, camera_in_ee, self.clock.now_ns(), capture_state)
        output = step.output
        figures = {}
        if output is not None:
            figures = dict(gain=output.gain, saturated=step.saturated,
                           camera_twist=tuple(output.camera_twist) if output.camera_twist is not None else None,
                           notes={k: float(v) for k, v in output.notes.items() if np.isfinite(v)})
        status = ControllerStatus(header=self.header("status", source=features.header), law=self.config.law,
                                  status=step.kind, iteration=step.iteration, error_norm=features.error_norm,
                                  error_rms=step.error_rms, phase=step.phase,
                                  detail=step.detail[:256], **figures)
        return status, output

    @staticmethod
    def _source(status: ControllerStatus) -> str:
        """The command source its output names to safety: the controller, doing its phase (servo when idle)."""
        return f"controller/{status.phase or ServoPhase.name}"

    def _publish(self, features: Features, recv_ns: int, status: ControllerStatus,
                 output: Optional[LawOutput]) -> None:
        header: Header = self.header("output", source=features.header, recv_ns=recv_ns)
        message = None
        if self.core.joint_output:
            if output is not None or self.core.arm is not None:  # a zero needs the arm's joints (none: no output)
                dq = output.joint_velocities if output is not None else np.zeros(self.core.arm.n_joints)
                message = JointVelocity(header=header, velocities=dq.tolist(), source=self._source(status),
                                        fingers=output.fingers if output is not None else None)
        else:
            twist = output.twist if output is not None else np.zeros(6)
            message = Twist(header=header, frame=Frame.MIXED, angular=self.config.control.robot_convention,
                            linear=tuple(twist[:3]), rotational=tuple(twist[3:]), source=self._source(status),
                            fingers=output.fingers if output is not None else None)
        if message is not None:
            self.output_pub.put(message)
        self.status_pub.put(status)
        self.last_status = status
        self._last_answer = (features.header.source_stamp_ns, message, status)
