"""The controller's rules, with no zenoh, no locks and no clock: for one features message, the robot state and the
camera mount, at a given time, what the law outputs, or why the output is zero.

Never the last command: with no task running, on the target lost, stale input, an ill-conditioned interaction matrix, a
law that gives up (a constraint abort, an Euler singularity, a non-finite output) the output is zero and the step
says why. The law's output is saturated to the limits the robot declares in its state (``saturated``).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from protocol.conventions import AngularConvention
from protocol.messages import (
    USABLE_FEATURE_STATUSES,
    ArmCheckState,
    GraspVerdict,
    TaskPlan,
    ControllerState,
    Features,
    FeatureStatus,
    MotionLimits,
    RobotState,
    SERVO_SOURCE,
    TaskRequest,
    TaskStatus,
    declared_source,
)
from services.controller import ibvs
from services.controller.law import ConstraintAbort, LawOutput, ServoInput
from services.controller.laws import JOINT_LAWS, make_law
from services.controller.phases import (HandPhase, MovePhase, ServoPhase, phases_for, release_phases,
                                       twist_from_move)
from services.controller.task import Task
from services.model import frames, saturation
from services.model.point_features import per_point_rms
from services.model.arm import ArmDescription, declared_arm, load_arm
from services.model.kinematics import ArmKinematics
from services.model.limits import declared as declared_limits


@dataclass
class Step:
    """One features message answered: the state, why (when not converging), the law's output (None: zero), the
    iteration it counts as, and whether the output was scaled down to the limits."""

    kind: ControllerState
    iteration: int
    detail: str = ""
    output: Optional[LawOutput] = None
    saturated: bool = False
    #: the features' per-point RMS error (0 when they were not usable)
    error_rms: float = 0.0
    #: the task's phase this step ran ("" when none)
    phase: str = ""


#: the commissioning check's states in which the controller moves the arm
ARM_CHECK_OK = frozenset({ArmCheckState.PASSED, ArmCheckState.WAIVED})


def arm_not_checked(state: RobotState) -> str:
    return (f"the arm's commissioning check is {state.arm_check.value}: the arm description may not match the arm "
            "(run `mfvs check arm`; a simulated arm waives it: arm_check.waived)")


class ControllerCore:
    def __init__(self, config) -> None:
        """``config``: the service's :class:`~services.controller.service.ControllerConfig` (the arm, the law, its
        options, the convergence threshold, the input budgets, the conditioning bound and the output limits). The
        law is made for the robot's arm once a state declares it (:meth:`step`)."""
        self.config = config
        #: the arm the law runs on, and the law (None until known: the configured arm, or the robot's first state)
        self.arm: Optional[ArmDescription] = None
        self.law = None
        self.joint_output = config.law in JOINT_LAWS
        self.task = Task()
        self.iteration = 0
        if config.arm is not None:
            self._make_law(load_arm(config.arm))

    def take_arm(self, state: RobotState) -> str:
        """Run on the arm ``state`` declares (the law is made for it the first time): "" or why not."""
        arm, why = declared_arm(state.arm, state.arm_digest, len(state.q), self.config.arm, self.arm)
        if arm is not None and self.law is None:
            self._make_law(arm)
        return why

    def _make_law(self, arm: ArmDescription) -> None:
        self.arm = arm
        self.law = make_law(self.config.law, self.config.control, ArmKinematics(arm), **self.config.options)

    # ------------------------------------------------------------------ the task
    def start_task(self, request: TaskRequest, now_ns: int, state: Optional[RobotState] = None) -> TaskStatus:
        """Start a task, unless the arm (by its latest ``state``) has failed or never passed its commissioning
        check and is not waived."""
        if state is not None and state.arm_check not in ARM_CHECK_OK:
            return self.task.status(False, arm_not_checked(state))
        if state is not None:
            wrong = self.take_arm(state)
            if wrong:
                return self.task.status(False, wrong)
        was_running = self.task.running
        if was_running and request.plan is TaskPlan.RELEASE:
            return self._release(request)
        if not was_running:
            try:
                phases = phases_for(request, self.config.move, self.config.grasp,
                                    self.arm.hand if self.arm is not None else None)
            except ValueError as exc:
                return self.task.status(False, str(exc))
        reply = self.task.start(request, now_ns, phases if not was_running else None)
        if not was_running:  # a new task: the law's memory and the iteration count start afresh
            self._reset_law()
            self.iteration = 0
        return reply

    def _release(self, request: TaskRequest) -> TaskStatus:
        """A release while a task runs: what is left of it becomes the hand opening (a grasp task's hold ends so)."""
        if self.arm is None or self.arm.hand is None:
            return self.task.status(False, "a release needs a hand, and the arm carries none")
        self.task.replace_rest(release_phases(self.arm.hand, self.config.grasp), request)
        return self.task.status(True, f"task {self.task.count}: releasing")

    def stop_task(self, request: TaskRequest) -> TaskStatus:
        reply = self.task.stop(request)
        self._reset_law()
        return reply

    def resume_task(self, request: TaskRequest) -> TaskStatus:
        reply = self.task.resume(request)
        if reply.ok:
            self._reset_law()
        return reply

    def observe_control(self, in_control: str) -> Optional[str]:
        """Safety says who is in control (``SafetyStatus.in_control``): another source than this controller (the
        person's stick) pauses a running task. Why it paused, or None."""
        if not in_control or declared_source(in_control) == declared_source(SERVO_SOURCE):
            return None
        why = f"{in_control} took control"
        if not self.task.pause(why):
            return None
        self._reset_law()
        return why

    def _reset_law(self) -> None:
        if self.law is not None:
            self.law.reset()

    # ------------------------------------------------------------------ one iteration
    def step(self, features: Features, state: Optional[RobotState], camera_in_ee: Optional[np.ndarray],
             now_ns: int, capture_state: Optional[RobotState] = None) -> Step:
        """``state``: the arm's state the law uses (realtime: the latest; lockstep: the frame's tick's).
        ``capture_state``: the state when the frame was taken, when it is older than ``state`` (realtime); with
        ``latency_compensation`` the features are carried from that configuration to ``state``'s."""
        cfg = self.config
        header = features.header

        def zero(kind: ControllerState, detail: str = "", reset: bool = False) -> Step:
            if reset:
                self._reset_law()
            return Step(kind, self.iteration, detail)

        if state is not None:
            wrong = self.take_arm(state)
            if wrong:
                return zero(ControllerState.WRONG_ARM, wrong, reset=True)
        if self.task.paused:
            return zero(ControllerState.PAUSED, f"task {self.task.count} paused: {self.task.reason} "
                                                "(mfvs task resume)")
        if not self.task.running:
            return zero(ControllerState.IDLE, "no task running (mfvs task start)")
        phase = self.task.phase
        if isinstance(phase, MovePhase):
            return self._move(phase, features, state, camera_in_ee, now_ns)
        if isinstance(phase, HandPhase):
            return self._hand(phase, features, state, camera_in_ee, now_ns)
        if features.status not in USABLE_FEATURE_STATUSES:
            kind = ControllerState.STALE_INPUT if features.status is FeatureStatus.STALE else ControllerState.TARGET_LOST
            return zero(kind, f"features {features.status.value}: {features.detail}", reset=True)
        problem = self._inputs_problem(header, state, camera_in_ee, now_ns)
        if problem is not None:
            return zero(*problem)

        self.iteration += 1
        rms = per_point_rms(features.error, features.point_weights())
        threshold = getattr(phase, "error_rms", None) or cfg.convergence_error_rms
        if rms < threshold:
            detail = ""
            if getattr(phase, "until_converged", False):  # a grasp's reach: on to the approach
                self._reset_law()
                detail = "task done" if self.task.advance() else "phase done: converged"
            return Step(ControllerState.CONVERGED, self.iteration, detail, error_rms=rms, phase=ServoPhase.name)
        points, depths = np.array(features.points), np.array(features.depths)
        if cfg.latency_compensation and capture_state is not None and capture_state is not state:
            points, depths = self.features_now(points, depths, capture_state.q, state.q, camera_in_ee)
        inp = ServoInput(t_s=header.source_stamp_ns * 1e-9, points=points,
                         depths=depths, goal_points=np.array(features.goal_points),
                         goal_depths=np.array(features.goal_depths), q=np.array(state.q), camera_in_ee=camera_in_ee,
                         dq=np.array(state.dq), ids=np.array(features.point_ids()),
                         weights=np.array(features.point_weights()))
        # the D·L̂ the law will invert, with the configured depth source
        L = ibvs.approximate_interaction_matrix(inp.points, inp.depths, inp.goal_points, inp.goal_depths,
                                                cfg.control.depth)
        if inp.row_weights is not None:
            L = inp.row_weights[:, None] * L
        if np.linalg.cond(L) > cfg.max_condition_number:
            return zero(ControllerState.ILL_CONDITIONED, f"cond(L) = {np.linalg.cond(L):.3g}", reset=True)
        try:
            output = self.law.step(inp)
        except frames.EulerSingularityError as exc:
            return zero(ControllerState.ILL_CONDITIONED, str(exc), reset=True)
        except ConstraintAbort as exc:
            return zero(ControllerState.CONSTRAINT_ABORT, str(exc), reset=True)
        values = output.joint_velocities if self.joint_output else output.twist
        if values is None or not np.all(np.isfinite(values)):
            return zero(ControllerState.ILL_CONDITIONED, "the law produced a non-finite output", reset=True)
        saturated = saturate(output, declared_limits(state, self.arm), self.joint_output, state,
                             cfg.control.robot_convention)
        return Step(ControllerState.CONVERGING, self.iteration, output=output, saturated=saturated, error_rms=rms,
                    phase=ServoPhase.name)

    def _inputs_problem(self, header, state: Optional[RobotState], camera_in_ee: Optional[np.ndarray],
                        now_ns: int) -> Optional[tuple[ControllerState, str, bool]]:
        """Why a phase may not act on this frame (its image too old, no fresh state, an arm not checked, no camera
        mount, a convention the robot does not read): (state, why, whether the law's memory goes), or None."""
        cfg = self.config
        age = (now_ns - header.source_stamp_ns) * 1e-9
        if age > cfg.max_input_age_s:
            return ControllerState.STALE_INPUT, f"image is {age * 1e3:.0f} ms old", True
        if state is None or (now_ns - state.header.stamp_ns) * 1e-9 > cfg.state_budget_s:
            return ControllerState.STALE_INPUT, "no fresh robot state", False
        if state.arm_check not in ARM_CHECK_OK:
            return ControllerState.ARM_NOT_CHECKED, arm_not_checked(state), True
        if camera_in_ee is None:
            return ControllerState.STALE_INPUT, "no camera info (camera-in-end-effector transform)", False
        if state.angular_convention is not cfg.control.robot_convention and not self.joint_output:
            return ControllerState.STALE_INPUT, (f"the robot reads '{state.angular_convention.value}', the "
                                                 f"controller is configured for '{cfg.control.robot_convention.value}'"), False
        return None

    def _move(self, phase: MovePhase, features: Features, state: Optional[RobotState],
              camera_in_ee: Optional[np.ndarray], now_ns: int) -> Step:
        """A frame of a move phase: driven by the arm's state (the features only pace it and date its command:
        a move stops as a servo does when the image path stops)."""
        cfg = self.config

        def zero(kind: ControllerState, detail: str = "") -> Step:
            return Step(kind, self.iteration, detail, phase=phase.name)

        held = self._paced_problem(phase, features, state, camera_in_ee, now_ns)
        if held is not None:
            return held
        if phase.detector is not None:  # the hand watched as the arm moves it (a lift)
            slipping = self._watch_hand(phase.detector, state)
            if slipping:
                return self._failed(phase, slipping)
        self.iteration += 1
        kin = self.law.kin
        q = np.asarray(state.q, dtype=float)
        R_be, p, J_base = kin.pose_and_jacobian(q)
        t_s = now_ns * 1e-9
        if phase.target_p is None:
            phase.begin(R_be, p, camera_in_ee, t_s)
        elif phase.started_s is None:  # resumed after a pause: the rest of the way from here
            phase.resume_at(p, t_s)
        move = phase.step(R_be, p, float(np.linalg.norm((J_base @ np.asarray(state.dq))[:3])), t_s)
        if move.failure:
            return self._failed(phase, move.failure)
        if move.done:
            detail = "task done" if self.task.advance() else "phase done"
            return zero(ControllerState.IDLE if not self.task.running else ControllerState.CONVERGING,
                        f"{detail}: moved {np.linalg.norm(phase.displacement) * 1e3:.1f} mm in the {phase.frame.value} frame")
        twist_ee, twist_base = twist_from_move(move, kin, q)
        if self.joint_output:
            output = LawOutput(joint_velocities=np.linalg.pinv(J_base) @ twist_base)
        else:
            output = LawOutput(twist=frames.mixed_from_ee_twist(twist_ee, R_be, cfg.control.robot_convention))
        saturated = saturate(output, declared_limits(state, self.arm), self.joint_output, state,
                             cfg.control.robot_convention)
        return Step(ControllerState.CONVERGING, self.iteration, f"{move.remaining_m * 1e3:.1f} mm to go",
                    output=output, saturated=saturated, phase=phase.name)

    def _paced_problem(self, phase, features: Features, state: Optional[RobotState],
                       camera_in_ee: Optional[np.ndarray], now_ns: int) -> Optional[Step]:
        """The zero step of a phase paced by the frames but driven by the arm's state (a move, a hand phase) when
        this frame may not drive it (stale features, the inputs' problems), or None."""
        if features.status is FeatureStatus.STALE:
            return Step(ControllerState.STALE_INPUT, self.iteration, f"features stale: {features.detail}",
                        phase=phase.name)
        problem = self._inputs_problem(features.header, state, camera_in_ee, now_ns)
        if problem is not None:
            kind, detail, _ = problem
            return Step(kind, self.iteration, detail, phase=phase.name)
        return None

    def _failed(self, phase, why: str) -> Step:
        """The task ends here, saying why (the zero step: no motion, no finger part)."""
        self.task.fail(why)
        return Step(ControllerState.IDLE, self.iteration, f"task failed: {why}", phase=phase.name)

    def _watch_hand(self, detector, state: RobotState) -> str:
        """The grasp detector fed this state's fingers; why the task cannot go on (the object slipping), or ""."""
        if state.fingers is None:
            return "the robot reports no fingers"
        verdict = detector.observe(state.header.stamp_ns * 1e-9, state.fingers)
        self.task.grasp = verdict
        if verdict is GraspVerdict.SLIPPING:
            return "the object is slipping out of the hand"
        return ""

    def _hand(self, phase: HandPhase, features: Features, state: Optional[RobotState],
              camera_in_ee: Optional[np.ndarray], now_ns: int) -> Step:
        """A frame of a hand phase: the arm still, the fingers as the phase asks, judged on the robot's fingers
        (the features only pace it and date its command, as a move's)."""
        held = self._paced_problem(phase, features, state, camera_in_ee, now_ns)
        if held is not None:
            return held
        if phase.started_s is None and phase.fresh_detector:
            phase.detector.reset()
        why = self._watch_hand(phase.detector, state)
        if why:
            return self._failed(phase, why)
        self.iteration += 1
        hand_step = phase.step(state.header.stamp_ns * 1e-9)
        if hand_step.failure:
            return self._failed(phase, hand_step.failure)
        detail = hand_step.detail
        if hand_step.done:
            detail = f"{'task done' if self.task.advance() else 'phase done'}: {hand_step.detail}"
        if self.joint_output:
            output = LawOutput(joint_velocities=np.zeros(self.arm.n_joints), fingers=hand_step.fingers)
        else:
            output = LawOutput(twist=np.zeros(6), fingers=hand_step.fingers)
        return Step(ControllerState.CONVERGING, self.iteration, detail, output=output, phase=phase.name)

    def features_now(self, points: np.ndarray, depths: np.ndarray, q_capture, q_now, camera_in_ee: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray]:
        """The frame's features carried from the arm's configuration when it was taken to the latest one: the
        camera's motion in between, by forward kinematics, applied to the points at their depths (a static target).
        What the image pipeline took (capture, detection, transport) then does not act as delay in the loop."""
        kin = self.law.kin
        camera_then = frames.homogeneous(*kin.pose(q_capture)) @ camera_in_ee
        camera_now = frames.homogeneous(*kin.pose(q_now)) @ camera_in_ee
        return ibvs.features_after_camera_motion(points, depths, np.linalg.inv(camera_then) @ camera_now)


def saturate(output: LawOutput, robot: MotionLimits, joint_output: bool, state: RobotState,
             convention: AngularConvention) -> bool:
    """Scale the law's output down to the robot's limits (in place) by one factor, so it keeps the direction the law
    asked for: joint velocities to the joints' speeds; a twist so that its linear speed and the end effector's
    angular speed (its rates in the robot's convention turned into ω, the way the robot measures it) are both
    within their limits. Whether anything was scaled."""
    if joint_output:
        output.joint_velocities, ratio = saturation.limit_uniformly(output.joint_velocities, robot.joint_speed_rps)
        return ratio > 1.0
    twist = output.twist
    pose = state.pose
    R = frames.euler_xyz_to_matrix((pose.ThetaX, pose.ThetaY, pose.ThetaZ))
    motion = np.concatenate([twist[:3], frames.omega_ee_from_angular(twist[3:], R, convention)])
    output.twist, ratio = saturation.limit_twist(twist, robot.linear_speed_mps, robot.angular_speed_rps,
                                                 judged_on=motion)
    return ratio.over > 1.0
