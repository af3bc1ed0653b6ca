"""The JACO thesis's chapter-5 controllers, each a law of :mod:`~services.controller.torque_laws` with its reference and
gains, as a stateful object with no zenoh, no clock and no threads: :meth:`TorqueController.begin` at the start
(the arm's joints and its own Cartesian report), then :meth:`TorqueController.step` once per low-level state, at
the state's own time. The process that runs one against the robot is :mod:`services.torque_controller`.

==================  ==========================================================================================
jt-pid              (a) Jacobian-transpose PID, eq. 4.3, Table 5.2, tracking eq. 5.1 from X0 to Xf (eq. 5.2)
null-space          (b) position first, orientation in its null space, eq. 4.9-4.13 with W = I
null-space-mass     (c) the same with W = M̂(q), the dynamically consistent inverse
joint-pd            (d) joint-space PD with the dynamic model, eq. 4.16-4.19, Table 5.3, on eq. 5.3's sinusoid
joint-velocity      (e) joint-velocity control with the task-space reference and a null-space term,
                    eq. 4.20-4.23, Tables 5.4-5.5
computed-torque     eq. 4.16-4.18 with the feed-forward and Ĉ the thesis leaves out, on eq. 5.1 in joint space
                    (a well-modelled baseline of the low-level API, not one of the thesis's runs)
==================  ==========================================================================================

Every controller returns the whole torque, gravity included where its law has it: the thesis switched the arm's
own gravity compensation off (Table 5.1), so the commands go out with ``gravity_compensation: false``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal, Optional

import msgspec
import numpy as np

from services.controller import torque_laws as laws
from services.model.arm import ArmDescription
from services.model.frames import rotation_log
from services.runtime.config import ConfigStruct

#: the thesis's arm: its final pose is eq. 5.2's Xf itself; on another arm Xf is its own X0 moved as eq. 5.2 moves
THESIS_ARM = "j2n6s300"
TASK_CONTROLLERS = ("jt-pid", "null-space", "null-space-mass", "joint-velocity")
JOINT_CONTROLLERS = ("joint-pd", "computed-torque")
CONTROLLERS = (*TASK_CONTROLLERS[:3], "joint-pd", "joint-velocity", "computed-torque")
#: the thesis's controllers (a)-(e), in its order
THESIS_CONTROLLERS = ("jt-pid", "null-space", "null-space-mass", "joint-pd", "joint-velocity")


class ControllerOptions(ConfigStruct):
    """What a run of one controller may set; the defaults are the thesis's experiment."""

    #: eq. 5.1's tf (s) and how much of eq. 5.2's motion to make (1: all of it; a shorter test takes less)
    tf_s: float = laws.THESIS_TF_S
    displacement_scale: float = 1.0
    #: Xf: ``thesis`` eq. 5.2's final pose itself, ``displacement`` X0 moved as eq. 5.2 moves it; null: the thesis's
    #: pose on the thesis's arm, the displacement on another
    target: Optional[Literal["thesis", "displacement"]] = None
    #: controllers a-c add the model's gravity ĝ(q) to their torque (the thesis does not say; docs/torque.md)
    task_gravity: bool = True
    #: the model knows the motors' rotor inertia (the description's armature) and the viscous friction; the
    #: thesis's CAD model knew neither
    rotor_inertia: bool = False
    friction: bool = False
    #: eq. 5.3 (joint-pd)
    amplitude_deg: float = math.degrees(laws.SINUSOID_AMPLITUDE_RAD)
    period_s: float = laws.SINUSOID_PERIOD_S
    #: joint-pd's gains per joint (null: Table 5.3's, mapped onto the arm by torque_laws.per_joint_gains)
    kp: Optional[list[float]] = None
    kd: Optional[list[float]] = None
    #: the joint cubic of computed-torque (deg per joint; null: 10° on every joint)
    joint_displacement_deg: Optional[list[float]] = None
    #: eq. 4.6-4.7's threshold (rad)
    orientation_threshold_rad: float = laws.ORIENTATION_THRESHOLD_RAD
    #: the controller gives up (stops commanding: the arm holds) beyond these errors
    abort_position_m: float = 0.25
    abort_orientation_deg: float = 90.0
    abort_joint_deg: float = 45.0

    def __post_init__(self) -> None:
        if not (self.tf_s > 0 and 0 < self.displacement_scale <= 1.0 and self.period_s > 0
                and 0 <= self.amplitude_deg <= 45.0):
            raise ValueError("options need tf_s > 0, 0 < displacement_scale <= 1, period_s > 0 and "
                             "0 <= amplitude_deg <= 45")
        for gains in (self.kp, self.kd):
            if gains is not None and not all(math.isfinite(g) and g >= 0 for g in gains):
                raise ValueError("kp and kd are non-negative gains, one per joint")
        if not (self.abort_position_m > 0 and self.abort_orientation_deg > 0 and self.abort_joint_deg > 0):
            raise ValueError("the abort thresholds must be positive")
        if not 0 <= self.orientation_threshold_rad < 0.5:
            raise ValueError("orientation_threshold_rad must be within [0, 0.5)")


@dataclass
class Step:
    """One step's answer: the torque to send (N·m, model sign, gravity included where the law has it), what was
    tracked (task: [p; XYZ Euler] measured and desired; joint: q_d), and why the controller gave up, if it did."""

    tau: np.ndarray
    x: Optional[np.ndarray] = None
    x_d: Optional[np.ndarray] = None
    q_d: Optional[np.ndarray] = None
    position_error_m: float = 0.0
    orientation_error_deg: float = 0.0
    joint_error_deg: float = 0.0
    abort: str = ""


@dataclass
class Start:
    """Where a run starts and goes: the joints at t = 0, and for task controllers X0 (the arm's report) and Xf."""

    q0: np.ndarray
    x0: Optional[np.ndarray] = None
    xf: Optional[np.ndarray] = None
    target: str = ""


class TorqueController:
    name = ""

    def __init__(self, arm: ArmDescription, options: ControllerOptions) -> None:
        self.arm, self.options = arm, options
        self.model = laws.DynamicsModel(arm, rotor_inertia=options.rotor_inertia, friction=options.friction)
        self.start: Optional[Start] = None

    def begin(self, q0, x0_reported=None) -> Start:
        raise NotImplementedError

    def step(self, t: float, dt: float, q, dq) -> Step:
        raise NotImplementedError

    @property
    def duration_s(self) -> float:
        """How long the reference moves (the run holds its end after this)."""
        raise NotImplementedError


class _TaskController(TorqueController):
    """A controller tracking eq. 5.1 from the arm's X0 to Xf on [p; XYZ Euler]."""

    def begin(self, q0, x0_reported=None) -> Start:
        o = self.options
        q0 = np.asarray(q0, dtype=float)
        kin = self.model.kinematics(q0)
        x0 = laws.pose_vector(kin.R, kin.p) if x0_reported is None else np.asarray(x0_reported, dtype=float)
        target = o.target or ("thesis" if self.arm.name == THESIS_ARM else "displacement")
        goal = laws.THESIS_XF if target == "thesis" else x0 + laws.THESIS_DISPLACEMENT
        xf = x0 + o.displacement_scale * (goal - x0)
        self.start = Start(q0=q0, x0=x0, xf=xf, target=target)
        self.pid = laws.TaskPID(self._gains(), o.orientation_threshold_rad)
        return self.start

    @property
    def duration_s(self) -> float:
        return self.options.tf_s

    def _gains(self) -> laws.TaskGains:
        return laws.TABLE_5_2

    def reference(self, t: float) -> laws.PoseReference:
        return laws.pose_reference(self.start.x0, self.start.xf, self.options.tf_s, t)

    def step(self, t: float, dt: float, q, dq) -> Step:
        q, dq = np.asarray(q, dtype=float), np.asarray(dq, dtype=float)
        kin = self.model.kinematics(q)
        ref = self.reference(t)
        f, mu = self.pid.step(kin, dq, ref, dt)
        tau = self.torque(q, dq, kin, ref, f, mu, dt)
        position_error = float(np.linalg.norm(ref.p - kin.p))
        orientation_error = math.degrees(float(np.linalg.norm(rotation_log(kin.R.T @ ref.R))))
        abort = ""
        if position_error > self.options.abort_position_m:
            abort = f"position error {position_error:.3f} m > {self.options.abort_position_m} m"
        elif orientation_error > self.options.abort_orientation_deg:
            abort = f"orientation error {orientation_error:.1f}° > {self.options.abort_orientation_deg}°"
        return Step(tau=tau, x=laws.pose_vector(kin.R, kin.p), x_d=ref.x, position_error_m=position_error,
                    orientation_error_deg=orientation_error, abort=abort)

    def torque(self, q, dq, kin, ref, f, mu, dt) -> np.ndarray:
        raise NotImplementedError

    def _gravity(self, q) -> np.ndarray:
        return self.model.gravity(q) if self.options.task_gravity else np.zeros(self.arm.n_joints)


class JacobianTransposePID(_TaskController):
    """(a) eq. 4.3 with Table 5.2's gains (+ ĝ(q) with ``task_gravity``)."""

    name = "jt-pid"

    def torque(self, q, dq, kin, ref, f, mu, dt) -> np.ndarray:
        return laws.jacobian_transpose(kin, f, mu) + self._gravity(q)


class NullSpace(_TaskController):
    """(b), (c) eq. 4.13 with Table 5.2's gains, W = I or M̂(q) (+ ĝ(q) with ``task_gravity``)."""

    def __init__(self, arm: ArmDescription, options: ControllerOptions, weight: str) -> None:
        super().__init__(arm, options)
        self.weight = weight
        self.name = "null-space" if weight == "identity" else "null-space-mass"

    def torque(self, q, dq, kin, ref, f, mu, dt) -> np.ndarray:
        W = self.model.mass(q) if self.weight == "mass" else None
        return laws.null_space_torque(kin, f, mu, W) + self._gravity(q)


class JointVelocity(_TaskController):
    """(e) eq. 4.20-4.23: Table 5.5's outer PID makes the task velocities, the null-space resolution makes q̇_d, and
    Table 5.4's per-joint gain through M̂(q) tracks it (+ ĝ(q), eq. 4.17). q_d, the integral of q̇_d (L2166-2168),
    is kept for the log."""

    name = "joint-velocity"

    def begin(self, q0, x0_reported=None) -> Start:
        start = super().begin(q0, x0_reported)
        self.kv = laws.per_joint_gains(laws.TABLE_5_4_KV, self.arm.n_joints)
        self.q_d = np.asarray(q0, dtype=float).copy()
        return start

    def _gains(self) -> laws.TaskGains:
        return laws.TABLE_5_5

    def torque(self, q, dq, kin, ref, f, mu, dt) -> np.ndarray:
        dq_d = laws.joint_velocity_reference(kin, f, mu)  # f, μ of Table 5.5: a velocity (m/s) and a rate (rad/s)
        self.q_d = self.q_d + dq_d * dt
        return laws.velocity_torque(self.model.mass(q), self.model.gravity(q), dq, dq_d, self.kv)


class JointPD(TorqueController):
    """(d) eq. 4.17-4.18 with Table 5.3's gains on eq. 5.3's sinusoid about the starting posture."""

    name = "joint-pd"

    def begin(self, q0, x0_reported=None) -> Start:
        n = self.arm.n_joints
        self.start = Start(q0=np.asarray(q0, dtype=float))
        o = self.options
        self.kp = laws.per_joint_gains(laws.TABLE_5_3_KP if o.kp is None else o.kp, n)
        self.kd = laws.per_joint_gains(laws.TABLE_5_3_KD if o.kd is None else o.kd, n)
        return self.start

    @property
    def duration_s(self) -> float:
        return 2 * self.options.period_s

    def reference(self, t: float):
        return laws.sinusoid(self.start.q0, math.radians(self.options.amplitude_deg), self.options.period_s, t)

    def step(self, t: float, dt: float, q, dq) -> Step:
        q_d, dq_d, ddq_d = self.reference(t)
        tau = self.torque(q, dq, q_d, dq_d, ddq_d)
        error = float(np.degrees(np.abs(q_d - np.asarray(q, dtype=float))).max())
        abort = f"joint error {error:.1f}° > {self.options.abort_joint_deg}°" if error > self.options.abort_joint_deg \
            else ""
        return Step(tau=tau, q_d=q_d, joint_error_deg=error, abort=abort)

    def torque(self, q, dq, q_d, dq_d, ddq_d) -> np.ndarray:
        return laws.computed_torque(self.model.mass(q), self.model.gravity(q), q, dq, q_d, self.kp, self.kd)


class ComputedTorque(JointPD):
    """Eq. 4.16-4.18 with the feed-forward (q̈_d, q̇_d), Ĉ and friction on eq. 5.1 between two joint configurations:
    the low-level API's well-modelled baseline (the rotors' inertia and the viscous friction known; gains the
    options' kp and kd, else 100 and 20 on every joint)."""

    name = "computed-torque"

    def __init__(self, arm: ArmDescription, options: ControllerOptions) -> None:
        options = msgspec.structs.replace(options, rotor_inertia=True, friction=True)
        super().__init__(arm, options)

    def begin(self, q0, x0_reported=None) -> Start:
        n = self.arm.n_joints
        o = self.options
        self.start = Start(q0=np.asarray(q0, dtype=float))
        self.kp = np.full(n, 100.0) if o.kp is None else laws.per_joint_gains(o.kp, n)
        self.kd = np.full(n, 20.0) if o.kd is None else laws.per_joint_gains(o.kd, n)
        displacement = self.options.joint_displacement_deg or [10.0] * n
        if len(displacement) != n:
            raise ValueError(f"joint_displacement_deg has {len(displacement)} angles for {n} joints")
        self.qf = self.start.q0 + np.radians(displacement)
        return self.start

    @property
    def duration_s(self) -> float:
        return self.options.tf_s

    def reference(self, t: float):
        return laws.cubic(self.start.q0, self.qf, self.options.tf_s, t)

    def torque(self, q, dq, q_d, dq_d, ddq_d) -> np.ndarray:
        m = self.model
        return laws.computed_torque(m.mass(q), m.gravity(q), q, dq, q_d, self.kp, self.kd, dq_d=dq_d, ddq_d=ddq_d,
                                    coriolis=m.coriolis(q, dq) + m.friction * np.asarray(dq, dtype=float))


def make_controller(name: str, arm: ArmDescription, options: ControllerOptions | None = None) -> TorqueController:
    """A controller by name (:data:`CONTROLLERS`); ValueError naming the known ones."""
    options = options or ControllerOptions()
    if name == "jt-pid":
        return JacobianTransposePID(arm, options)
    if name == "null-space":
        return NullSpace(arm, options, "identity")
    if name == "null-space-mass":
        return NullSpace(arm, options, "mass")
    if name == "joint-pd":
        return JointPD(arm, options)
    if name == "joint-velocity":
        return JointVelocity(arm, options)
    if name == "computed-torque":
        return ComputedTorque(arm, options)
    raise ValueError(f"unknown controller {name!r}; known: {', '.join(CONTROLLERS)}")
