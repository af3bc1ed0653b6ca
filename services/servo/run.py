"""``mfvs servo``: run one servo task described by a scenario file through the real services and report.

The scenario (YAML; every field has the default shown in :class:`Scenario`) says where the arm starts, where the
target is (and how it moves), the goal, the law and its gains, when to stop, and the camera. The runner starts a
router and the services (robot_sim, vision, controller, safety; lockstep by default), watches the controller's
iterations, stops the services, and returns :class:`ServoResult` (docs/contracts.md). With an output directory it
writes the trajectory log (one JSON line per iteration) and plots.
"""
from __future__ import annotations

import contextlib
import json
import math
import time
from pathlib import Path
from typing import Optional

import msgspec
import numpy as np

from protocol import messages as m
from protocol.conventions import ClockMode
from protocol.keys import Keys
from services.controller.laws import JOINT_LAWS
from services.controller.task_client import start_task
from services.model.arm import load_arm
from services.model.kinematics import ArmKinematics, manipulability
from services.model.zones import nearest_zone
from services.servo.result import Iteration, ServoResult, write_log
from services.servo.scenario import Scenario, stack_config
from services.servo.termination import TerminationRule
from services.servo.watcher import Watcher, frames_lost
from services.stack.composed import ComposedStack, composable
from services.stack.local import LocalStack


def run(scenario: Scenario, out_dir: Optional[Path] = None, progress=None, profile: str = "sim",
        plots: bool = True, record: Optional[Path] = None, processes: bool = False, bus: str = "hub") -> ServoResult:
    """Run the scenario through a local stack; ``progress(iteration_record)`` is called per iteration. The gateway
    profile drives the simulated arm through robot_gateway and its RS-485 bus (the hub, robot_sim's actuators and
    the gateway as processes; ``bus="kinova_usb"``: robot_sim's emulated base through Kinova's USB comm layer instead
    of the hub), in the scenario's clock mode. With ``out_dir`` the trajectory log, the result and
    (unless ``plots`` is false) the figures are written there; with ``record`` every topic of the stack, from
    before the robot's first message, goes into that MCAP file (``mfvs record``'s).

    The sim profile in lockstep runs composed (:mod:`services.stack.composed`: the services in this process, the same
    run byte for byte, faster) unless ``processes`` asks for every service in a process of its own, as deployed;
    anything else always runs as processes."""
    config = stack_config(scenario)
    config.profile, config.robot_bus = profile, bus
    stack_type = ComposedStack if composable(config) and not processes else LocalStack
    keys = Keys(config.robot.robot_id)
    arm = load_arm(scenario.robot.arm)
    started = time.monotonic()
    # what watches the stack opens before the robot's first message, inside the stack's start, and closes before
    # the stack stops (also when the stack fails to come up after it was opened)
    observers = contextlib.ExitStack()
    watching: dict = {}

    def watch(stack) -> None:
        session = stack.open_session()
        observers.callback(session.close)
        if record is not None:
            from services.observe.record import Recorder

            observers.callback(Recorder(session, keys, record).close)
        watcher = Watcher(session, keys, config.controller.law in JOINT_LAWS)
        observers.callback(watcher.close)
        watching.update(session=session, watcher=watcher)
        # the stack comes up idle; the task starts before the robot's clock does, so lockstep stays exact
        task = start_task(session, keys, operator="mfvs servo", reason=f"{scenario.law} scenario")
        if task.state is not m.TaskState.RUNNING:
            raise RuntimeError(f"the controller did not start the task: {task.message}")

    try:
        with stack_type(config, before_robot=watch) as stack, observers:
            watcher = watching["watcher"]
            records, status = _follow(scenario, stack, watcher, ArmKinematics(arm), started, progress)
            states = list(watcher.states)
            with watcher.lock:  # features and commands may reach us after their status (each subscriber has
                # its own thread; the last ones may still be on their way): complete the log with what came later
                # (the controller answers every frame: zero when it does not act)
                watcher.new_input.wait_for(lambda: all(
                    r.stamp_ns in watcher.features and r.stamp_ns in watcher.commands for r in records), timeout=2.0)
                for iteration_record in records:
                    _fill_inputs(iteration_record, watcher)
            lost, lockstep_timeouts = frames_lost(watching["session"], keys)
            safety = watcher.safety_summary()
            front_end = front_end_figures(list(watcher.features.values()))
    finally:
        observers.close()
    result = _result(scenario, arm, records, states, status, lost, lockstep_timeouts, safety,
                     wall_s=time.monotonic() - started, composed=stack_type is ComposedStack)
    result.front_end = front_end
    if out_dir is not None:
        _write(result, records, scenario, arm, Path(out_dir), plots)
    return result


def _follow(scenario: Scenario, stack, watcher: Watcher, kin: ArmKinematics, started: float,
            progress) -> tuple[list[Iteration], str]:
    """The controller's iterations as they come, each recorded (and given to ``progress``) until the task ends
    (:class:`~services.servo.termination.TerminationRule`), the robot stops, or the scenario's time is up; the
    records and how it ended."""
    rule = TerminationRule(scenario.target_lost_iterations, scenario.convergence.max_iterations)
    # lockstep: safety answers each frame before the robot's next tick, so the answer always comes
    answer_timeout_s = 2.0 if scenario.clock is ClockMode.LOCKSTEP else 0.3
    records: list[Iteration] = []
    seen = 0
    while time.monotonic() - started < scenario.timeout_s:
        with watcher.lock:
            watcher.new_status.wait_for(lambda n=seen: len(watcher.statuses) > n, timeout=1.0)
            new = watcher.statuses[seen:]
            seen = len(watcher.statuses)
        if not new and not stack.robot_alive():
            return records, "robot_stopped"
        for status in new:
            iteration_record = _record(status, watcher, kin, scenario.robot.dsp.zones, answer_timeout_s)
            records.append(iteration_record)
            if progress is not None:
                progress(iteration_record)
            outcome = rule.observe(status.status, status.error_norm, status.iteration,
                                   refused=bool(iteration_record.safety_refusal))
            if outcome is not None:
                return records, outcome
    return records, "timeout"


def _result(scenario: Scenario, arm, records: list[Iteration], states: list, status: str, lost: dict,
            lockstep_timeouts: int, safety: dict, wall_s: float, composed: bool) -> ServoResult:
    kin = ArmKinematics(arm)
    lower, upper = arm.model_limits()
    converging = [r for r in records if r.status in ("converging", "converged")]
    q_all = np.array([s.q for s in states]) if states else np.zeros((0, arm.n_joints))
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
        wall_time_s=round(wall_s, 3),
        servo_time_s=round((answered[-1].stamp_ns - answered[0].stamp_ns) * 1e-9, 3) if answered else 0.0,
        frames_answered=len(answered),
        frames_lost=lost,
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
        stack="composed" if composed else "processes",
    )
    result.detail = _why(result, converging)
    return result


def _write(result: ServoResult, records: list[Iteration], scenario: Scenario, arm, out: Path, plots: bool) -> None:
    """The trajectory log, the figures (unless ``plots`` is false) and the result, in ``out``."""
    from services.servo.figures import servo_plots  # (matplotlib: only when figures are drawn)

    out.mkdir(parents=True, exist_ok=True)
    result.trajectory_log = str(write_log(records, out / "trajectory.jsonl"))
    result.plots = [] if not plots else [str(p) for p in servo_plots(
        records, out, law=scenario.law, arm=arm, goal=scenario.goal.features, camera=scenario.camera,
        threshold=scenario.convergence.rms, robot_limits=result.robot_limits)]
    (out / "result.json").write_text(json.dumps(result.to_json(), indent=2) + "\n")


def front_end_figures(features: list) -> Optional[dict]:
    """A keypoint target's front end over the run (its wall time a frame, how often it detected), or None."""
    views = [f.keypoints for f in features if f.keypoints is not None]
    if not views:
        return None
    took = np.array([v.took_ms for v in views])
    return {"ms_per_frame": {"p50": round(float(np.median(took)), 2), "p95": round(float(np.percentile(took, 95)), 2),
                             "max": round(float(took.max()), 2), "n": len(took)},
            "detected_share": round(sum(v.search == "detect" for v in views) / len(views), 3)}


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
        return ("the target was never seen: it is outside the camera's initial view, or too small or far to detect "
                "(check target.pose_in_camera and the camera)" + said)
    grew = f"‖e‖ from {result.initial_error_norm:.3g} up to {result.max_error_norm:.3g}"
    if result.status == "diverged":
        return f"the error grew ({grew}) and the target was lost" + said
    if result.status == "target_lost":
        return f"the target was lost after {result.iterations} iterations ({grew})" + said
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


def _record(status: m.ControllerStatus, watcher: Watcher, kin: ArmKinematics, zones: list,
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


def _fill_inputs(record: Iteration, watcher: Watcher) -> None:
    """The iteration's features and command, by its frame's stamp (call with the watcher's lock held)."""
    features = watcher.features.get(record.stamp_ns)
    if features is not None:
        record.points = [list(p) for p in features.points]
        record.error = list(features.error)
        view = features.keypoints
        if view is not None:  # a keypoint target's figures (a tag's log lines stay as they were)
            record.keypoints = {"ids": list(features.ids), "weights": [round(w, 4) for w in features.weights],
                                "error_rms": features.error_rms, "inliers": view.inliers,
                                "candidates": view.candidates, "median_error_px": round(view.median_error_px, 4),
                                "search": view.search}
    record.command = watcher.commands.get(record.stamp_ns, [])
    record.command_kind = "joint_velocity" if watcher.joint_output else "mixed_twist"
