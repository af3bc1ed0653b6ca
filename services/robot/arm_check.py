"""The commissioning check's rules, without zenoh, locks or clocks: does the arm description agree with the arm?

The robot node runs it (:class:`ArmCheckRun`) on the arm it drives: each joint in turn moves by a few degrees at a
low speed and back, and at rest before and after each move the node takes a sample: the joints' angles as the arm
reports them and the end effector's pose as the arm itself reports it (its own kinematics: Kinova's DSP through the
SDK, the simulator's physics). :func:`analyse` then compares both with the description's forward kinematics of the
same angles:

* **joint directions**: the end effector's motion while joint j moved (its displacement and turn, in the base
  frame) against the description's prediction for that change of angle and for the joint turning the other way.
  The base-frame motion does not depend on how the end-effector frame is attached, so a frame difference cannot
  pass for a reversed joint or hide one;
* **zero offsets and the end-effector frame**: at the start, the arm's pose against the description's. A constant
  turn of the end-effector frame (the arm's frame in the description's: Kinova's URDFs put a turn of π about z
  there) is named as such with its axis and angle.

The check passes when every joint moved as the description predicts (within ``motion_tolerance``) and the poses
agree at the start (within ``static_tolerance``). Kinova's URDFs have had sign errors, and the JACO-2's joint 1 is
turned one way by ``../shared/reference/kinova.md`` and the other by kinova-ros (docs/robot.md): this is what
settles it on the first connection.
"""
from __future__ import annotations

import enum
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Optional

import numpy as np

from protocol.messages import ArmCheckReply, ArmCheckState, JointCheck
from services.model import frames
from services.model.arm import ArmDescription
from services.runtime.config import ConfigStruct

#: the end effector's motion may differ from the description's by this much (mm, deg) for a joint to pass
MOTION_TOLERANCE = (2.0, 0.5)
#: the poses may differ by this much at the start (mm, deg)
STATIC_TOLERANCE = (3.0, 0.5)


@dataclass(frozen=True)
class ArmCheckPlan:
    #: which joints (1-based); empty: every joint of the arm
    joints: tuple[int, ...] = ()
    step_deg: float = 5.0
    speed_dps: float = 5.0
    #: at rest this long (joint speeds below ``rest_dps``) before a sample is taken
    settle_s: float = 0.4
    rest_dps: float = 0.2
    #: a target is reached within this (deg)
    reach_deg: float = 0.15
    #: keep this far from a joint limit (deg): a step that would come closer goes the other way
    limit_margin_deg: float = 3.0


@dataclass
class Sample:
    label: str
    #: the joint that moved before this sample (0 for the start)
    joint: int
    q: np.ndarray
    arm_pose: np.ndarray


class Phase(enum.Enum):
    SETTLE = "settle"
    MOVE = "move"
    DONE = "done"


class ArmCheckRun:
    """The check's motion, one DSP tick at a time: :meth:`step` takes the time, the joints and the arm's own pose
    and says which joint velocities to command (model rad/s), or None when the check is over (:attr:`samples`,
    :attr:`failure`)."""

    def __init__(self, plan: ArmCheckPlan, arm: ArmDescription, q_start: np.ndarray, t_s: float) -> None:
        self.plan = plan
        self.q_start = np.asarray(q_start, dtype=float).copy()
        joints = plan.joints or tuple(range(1, arm.n_joints + 1))
        if any(not 1 <= j <= arm.n_joints for j in joints):
            raise ValueError(f"the {arm.name} has joints 1 to {arm.n_joints}, not {list(joints)}")
        self.samples: list[Sample] = []
        self.failure = ""
        #: the moves: (joint, target), each joint out and back
        self.moves: list[tuple[int, np.ndarray]] = []
        lower, upper = arm.model_limits()
        margin = math.radians(plan.limit_margin_deg)
        step = math.radians(plan.step_deg)
        for joint in joints:
            i = joint - 1
            out = self.q_start.copy()
            out[i] += step if self.q_start[i] + step <= upper[i] - margin else -step
            if not lower[i] + margin <= out[i] <= upper[i] - margin:
                raise ValueError(f"joint {joint} is too close to its limits to move {plan.step_deg}° either way")
            self.moves += [(joint, out), (joint, self.q_start.copy())]
        self._move = -1  # the start: settle and sample first
        self._phase = Phase.SETTLE
        self._since = t_s
        self._rest_since: Optional[float] = None

    @property
    def done(self) -> bool:
        return self._phase is Phase.DONE

    def abort(self, reason: str) -> None:
        self.failure = self.failure or reason
        self._phase = Phase.DONE

    def step(self, t_s: float, q: np.ndarray, dq: np.ndarray, arm_pose: Optional[np.ndarray]) -> Optional[np.ndarray]:
        plan = self.plan
        if self._phase is Phase.DONE:
            return None
        if arm_pose is None:
            self.abort("the arm gives no Cartesian report of its own (an RS-485 gateway computes its pose from the "
                       "description itself): nothing to compare with; use the kinova_sdk backend")
            return None
        zero = np.zeros(len(self.q_start))
        if self._phase is Phase.SETTLE:
            if np.degrees(np.abs(dq)).max() < plan.rest_dps:
                self._rest_since = t_s if self._rest_since is None else self._rest_since
                if t_s - self._rest_since >= plan.settle_s:
                    joint = self.moves[self._move][0] if self._move >= 0 else 0
                    label = "start" if self._move < 0 else f"joint {joint} {'out' if self._move % 2 == 0 else 'back'}"
                    self.samples.append(Sample(label, joint, np.asarray(q, float).copy(),
                                               np.asarray(arm_pose, float).copy()))
                    self._move += 1
                    if self._move >= len(self.moves):
                        self._phase = Phase.DONE
                        return None
                    self._phase, self._since = Phase.MOVE, t_s
            else:
                self._rest_since = None
            if t_s - self._since > 10.0:
                self.abort("the arm did not come to rest within 10 s")
                return None
            return zero
        joint, target = self.moves[self._move]
        i = joint - 1
        error = target[i] - q[i]
        if abs(math.degrees(error)) < plan.reach_deg:
            self._phase, self._since, self._rest_since = Phase.SETTLE, t_s, None
            return zero
        if t_s - self._since > 3.0 * plan.step_deg / plan.speed_dps + 3.0:
            self.abort(f"joint {joint} did not reach its target (it is {math.degrees(error):+.2f}° away): is it "
                       "blocked, or does the arm refuse the motion?")
            return None
        velocity = zero.copy()
        speed = math.radians(plan.speed_dps)
        velocity[i] = max(-speed, min(speed, 2.0 * error))  # slow down into the target
        return velocity


def _motion(T_before: np.ndarray, T_after: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The end effector's displacement (m) and turn (rad, a rotation vector), both in the base frame."""
    return T_after[:3, 3] - T_before[:3, 3], frames.rotation_log(T_after[:3, :3] @ T_before[:3, :3].T)


def _difference(a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray]) -> tuple[float, float]:
    return float(np.linalg.norm(a[0] - b[0]) * 1e3), float(np.degrees(np.linalg.norm(a[1] - b[1])))


def _within(error: tuple[float, float], tolerance: tuple[float, float]) -> bool:
    return error[0] <= tolerance[0] and error[1] <= tolerance[1]


#: a fitted zero offset beyond this (deg) is named
ZERO_TOLERANCE_DEG = 0.5


def zero_offsets(samples: list[Sample], fk: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
    """The joint offsets (model rad) that best explain the arm's positions at the samples (damped Gauss-Newton on
    the end effector's position; joint 7 turns the end effector about its own axis and cannot be told from the
    end-effector frame by positions, so it stays at zero)."""
    n = len(samples[0].q)
    offsets = np.zeros(n)
    free = list(range(n - 1))
    h = 1e-6
    for _ in range(20):
        residual, jacobian = [], []
        for sample in samples:
            base = fk(sample.q + offsets)[:3, 3]
            residual.append(sample.arm_pose[:3, 3] - base)
            columns = []
            for i in free:
                nudged = offsets.copy()
                nudged[i] += h
                columns.append((fk(sample.q + nudged)[:3, 3] - base) / h)
            jacobian.append(np.array(columns).T)
        r, J = np.concatenate(residual), np.vstack(jacobian)
        step = np.linalg.solve(J.T @ J + 1e-8 * np.eye(len(free)), J.T @ r)
        offsets[free] += step
        if np.abs(step).max() < 1e-9:
            break
    return offsets


def analyse(samples: list[Sample], fk: Callable[[np.ndarray], np.ndarray], failure: str = "") -> ArmCheckReply:
    """The verdict on a run's samples against the description's forward kinematics ``fk``: each joint's direction,
    and the poses at the start."""
    if failure or not samples:
        return ArmCheckReply(ok=False, state=ArmCheckState.FAILED, message=(failure or "no samples")[:512])
    start = samples[0]
    T_start = fk(start.q)
    static = (float(np.linalg.norm(T_start[:3, 3] - start.arm_pose[:3, 3]) * 1e3),
              float(np.degrees(np.linalg.norm(frames.rotation_log(T_start[:3, :3].T @ start.arm_pose[:3, :3])))))
    turn = frames.rotation_log(T_start[:3, :3].T @ start.arm_pose[:3, :3])
    angle = float(np.degrees(np.linalg.norm(turn)))
    axis = tuple(float(v) for v in (turn / np.linalg.norm(turn) if angle > 1e-9 else np.array([0.0, 0.0, 1.0])))
    joints = []
    previous = start
    for sample in samples[1:]:
        if not sample.label.endswith("out"):
            previous = sample
            continue
        i = sample.joint - 1
        change = sample.q - previous.q
        reversed_q = previous.q.copy()
        reversed_q[i] -= change[i]
        arm = _motion(previous.arm_pose, sample.arm_pose)
        predicted = _motion(fk(previous.q), fk(sample.q))
        if_reversed = _motion(fk(previous.q), fk(reversed_q))
        error = _difference(arm, predicted)
        error_reversed = _difference(arm, if_reversed)
        if _within(error, MOTION_TOLERANCE):
            direction, detail = "ok", ""
        elif _within(error_reversed, MOTION_TOLERANCE):
            direction = "reversed"
            detail = (f"joint {sample.joint} turns the other way from the arm description: the arm moved as the "
                      f"description predicts for {-math.degrees(change[i]):+.1f}°, not {math.degrees(change[i]):+.1f}°")
        else:
            direction = "disagrees"
            detail = (f"joint {sample.joint}: the end effector moved {error[0]:.1f} mm and {error[1]:.2f}° off the "
                      "description's prediction either way (a wrong axis, link length or gear ratio?)")
        joints.append(JointCheck(joint=sample.joint, moved_deg=float(math.degrees(change[i])), direction=direction,
                                 motion_error_mm=error[0], motion_error_deg=error[1], passed=direction == "ok",
                                 detail=detail[:256]))
        previous = sample
    static_ok = _within(static, STATIC_TOLERANCE)
    problems = [j.detail for j in joints if not j.passed]
    if not static_ok and static[0] > STATIC_TOLERANCE[0] and all(j.passed for j in joints):
        # the joints turn the right way but the poses disagree at rest: whose zero is off?
        offsets = zero_offsets(samples, fk)
        for k, check in enumerate(joints):
            offset = float(np.degrees(offsets[check.joint - 1]))
            if abs(offset) > ZERO_TOLERANCE_DEG:
                joints[k] = JointCheck(**{**{f: getattr(check, f) for f in check.__struct_fields__},
                                          "zero_offset_deg": offset, "passed": False,
                                          "detail": f"joint {check.joint}'s zero is {offset:+.2f}° from the "
                                                    "description's"})
                problems.append(joints[k].detail)
    passed = static_ok and all(j.passed for j in joints)
    if not static_ok:
        problems.append(f"at the start the arm reports its end effector {static[0]:.1f} mm and {static[1]:.2f}° from "
                        f"the description's pose" + (f" (its frame turned {angle:.1f}° about "
                                                     f"[{axis[0]:.2f}, {axis[1]:.2f}, {axis[2]:.2f}])"
                                                     if angle > STATIC_TOLERANCE[1] else ""))
    message = "the arm agrees with its description" if passed else "; ".join(problems)
    return ArmCheckReply(ok=True, passed=passed, state=ArmCheckState.PASSED if passed else ArmCheckState.FAILED,
                         message=message[:512], joints=joints, static_error_mm=static[0], static_error_deg=static[1],
                         ee_frame_rotation_deg=angle, ee_frame_axis=axis)


# ------------------------------------------------------------------------------------------ the verdict, kept


class ArmCheckConfig(ConfigStruct):
    """The robot node's commissioning check: where its verdict is kept, and whether it is waived."""

    #: not checked, by a setting: the controller then starts tasks on this arm unchecked. For a simulated arm (which
    #: is its description) and for an arm the check cannot see (an RS-485 bus carries no Cartesian report)
    waived: bool = False
    #: a file that keeps the verdict across restarts (null: this run only); a verdict for another arm description
    #: is not taken
    record: Optional[str] = None


def description_fingerprint(arm: ArmDescription) -> str:
    """What identifies the arm description a verdict was reached with (its name and file, hashed)."""
    return f"{arm.name}:{arm.digest}"


def load_verdict(config: ArmCheckConfig, arm: ArmDescription) -> tuple[ArmCheckState, str]:
    """The state to start with: waived, the recorded verdict for this description, or never."""
    if config.waived:
        return ArmCheckState.WAIVED, "waived by the robot's config (arm_check.waived)"
    if not config.record:
        return ArmCheckState.NEVER, "the arm has not been checked (mfvs check arm)"
    try:
        record = json.loads(Path(config.record).read_text())
    except FileNotFoundError:
        return ArmCheckState.NEVER, "the arm has not been checked (mfvs check arm)"
    except (OSError, ValueError) as exc:
        return ArmCheckState.NEVER, f"the check's record {config.record} cannot be read ({exc}): check again"
    if record.get("description") != description_fingerprint(arm):
        return ArmCheckState.NEVER, "the arm description changed since the last check: check again"
    state = ArmCheckState.PASSED if record.get("passed") is True else ArmCheckState.FAILED
    return state, str(record.get("message", ""))[:256]


def save_verdict(config: ArmCheckConfig, arm: ArmDescription, reply: ArmCheckReply, when: str) -> None:
    if config.record:
        Path(config.record).write_text(json.dumps({
            "passed": reply.passed, "message": reply.message, "when": when, "description": description_fingerprint(arm),
            "joints": [{"joint": j.joint, "direction": j.direction, "zero_offset_deg": j.zero_offset_deg}
                       for j in reply.joints]}, indent=2))
