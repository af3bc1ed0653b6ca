"""``mfvs experiment torque-control``: the JACO thesis's chapter 5 on the emulated arm, over the robot's 500 Hz
low-level torque API, every controller a process of its own (``python -m services.torque_controller``) talking to the
robot as a real client would.

For each run: a zenoh router, a fresh robot (robot_sim in api mode, or the gateway profile: robot_sim's actuators
on the emulated RS-485 bus behind robot_gateway) with the arm at its home (the thesis started every run from
HOME), the controller process for the run, its log, the robot stopped. The runs:

=======================  =========================================================================================
(a) jt-pid               Jacobian-transpose PID (eq. 4.3, Table 5.2) on eq. 5.1's spline from X0 to Xf, tf 16 s
(b) null-space           the same gains, orientation in the position task's null space, W = I (eq. 4.13)
(c) null-space-mass      the same with W = M̂(q) (eq. 4.11)
(d) joint-pd             computed-torque joint PD (eq. 4.17-4.18, Table 5.3) on eq. 5.3's ±20°, 8 s sinusoid
(e) joint-velocity       joint-velocity control with the task reference and a null-space term (Tables 5.4-5.5)
jt-pid-no-gravity        (a) as the thesis prints it, without ĝ(q): what the integral alone holds up
joint-pd-last-low        (d) with the last joint at the first joint's gains: does it need its far higher gain?
joint-pd-last-low-rotors the same with the motors' rotor inertia in the model: why it does
null-space-mass-rotors   (c) with the rotor inertia in M̂: why W = M̂ changes what it changes
=======================  =========================================================================================

Each controller makes the thesis's Table 5.1 torque-mode setup through the arm's Kinova API before its first torque
(safety factor 1, damping 0, gravity OPTIMAL with every optimal-Z parameter 0, gain 0: the arm adds no gravity, so
the controllers add their ĝ(q)); its log records the calls. X0 is the arm's own Cartesian report at HOME
(GetCartesianPosition); Xf is eq. 5.2's on the thesis's j2n6s300 and
X0 moved as eq. 5.2 moves it on another arm (whether it can be reached is computed and reported). ``quick`` runs
the five controllers on a 3 s reference (3/16 of the motion: the thesis's speeds) for a look, or a test.
"""
from __future__ import annotations

import json
import math
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional

import msgspec
import numpy as np

from services.controller import torque_laws as laws
from services.controller.torque_controllers import (JOINT_CONTROLLERS, THESIS_ARM, ControllerOptions,
                                                    make_controller)
from services.model.arm import ArmDescription, load_arm
from services.model.frames import rotation_log
from services.robot.hardware import CYCLE_S
from services.torque_controller.core import load_log

NAME = "torque-control"
TITLE = "The JACO thesis, chapter 5: torque control of the JACO-2 over the 500 Hz low-level API"
PAPER = ("the null space improves the primary (position) task over the Jacobian transpose; W = M(q) barely changes "
         "it; joint 6 needs a far higher gain; orientation couples into position around 10 s in (a)")
#: seconds the task runs hold Xf after tf (the thesis's plots run to about 20 s, L2669)
HOLD_S = 4.0
#: the joint PD's run: two periods of eq. 5.3 (the thesis gives no run length)
JOINT_PERIODS = 2
#: quick runs: a 3 s reference over 3/16 of the motion (the same speeds), held 1 s; the joint PD for 4 s
QUICK_TF_S = 3.0
QUICK_HOLD_S = 1.0
QUICK_JOINT_S = 4.0
#: a position disturbance smaller than this is not one (the steady tracking error of these runs is a few tenths)
DISTURBANCE_MM = 0.5
#: a run whose controller missed more than this fraction of the 500 Hz cycles (late, superseded or unseen) measured
#: the host, not the controller: its loop ran with a delay the thesis's did not have. Our choice: on the 2-core
#: machine the quick runs miss 0.05-2.5 % of their cycles; a host slowed to 0.8 of a core (bench.slower_host)
#: 17-63 %, where the joint-velocity law's high-gain velocity loop (Table 5.4 through M̂) saturates its torques
#: 3× over and the others do not
MAX_MISSED_FRACTION = 0.10


@dataclass(frozen=True)
class TorqueRunSpec:
    label: str
    controller: str
    #: the thesis's letter, or '' for a run that checks one of its observations
    letter: str
    what: str
    options: dict = field(default_factory=dict)


def last_joint_at_first_gains(arm: ArmDescription) -> dict:
    """Table 5.3 mapped onto the arm, with the last joint at the first joint's gains."""
    kp = laws.per_joint_gains(laws.TABLE_5_3_KP, arm.n_joints)
    kd = laws.per_joint_gains(laws.TABLE_5_3_KD, arm.n_joints)
    kp[-1], kd[-1] = kp[0], kd[0]
    return {"kp": kp.tolist(), "kd": kd.tolist()}


def runs_for(arm: ArmDescription, quick: bool = False) -> list[TorqueRunSpec]:
    thesis = [
        TorqueRunSpec("jt-pid", "jt-pid", "a", "Jacobian-transpose PID, Table 5.2"),
        TorqueRunSpec("null-space", "null-space", "b", "orientation in the null space, W = I"),
        TorqueRunSpec("null-space-mass", "null-space-mass", "c", "orientation in the null space, W = M̂(q)"),
        TorqueRunSpec("joint-pd", "joint-pd", "d", "joint PD with the dynamic model, Table 5.3, eq. 5.3"),
        TorqueRunSpec("joint-velocity", "joint-velocity", "e", "joint-velocity control, Tables 5.4-5.5"),
    ]
    if quick:
        return thesis
    low = last_joint_at_first_gains(arm)
    return thesis + [
        TorqueRunSpec("jt-pid-no-gravity", "jt-pid", "", "(a) without ĝ(q): the law as printed",
                      {"task_gravity": False}),
        TorqueRunSpec("joint-pd-last-low", "joint-pd", "", "(d), the last joint at the first joint's gains", low),
        TorqueRunSpec("joint-pd-last-low-rotors", "joint-pd", "",
                      "(d), the last joint at the first joint's gains, the rotors' inertia in M̂",
                      {**low, "rotor_inertia": True}),
        TorqueRunSpec("null-space-mass-rotors", "null-space-mass", "", "(c) with the rotors' inertia in M̂",
                      {"rotor_inertia": True}),
    ]


def run_options(spec: TorqueRunSpec, quick: bool) -> tuple[ControllerOptions, float]:
    """The controller's options and the run's duration (s)."""
    options = dict(spec.options)
    if spec.controller in JOINT_CONTROLLERS:
        duration = QUICK_JOINT_S if quick else JOINT_PERIODS * laws.SINUSOID_PERIOD_S
    elif quick:
        options.update(tf_s=QUICK_TF_S, displacement_scale=QUICK_TF_S / laws.THESIS_TF_S)
        duration = QUICK_TF_S + QUICK_HOLD_S
    else:
        duration = laws.THESIS_TF_S + HOLD_S
    return msgspec.convert(options, ControllerOptions), duration


# ------------------------------------------------------------------------------------------------ one run


def run_one(spec: TorqueRunSpec, arm: ArmDescription, log: Path, profile: str, quick: bool, router) -> dict:
    """A fresh robot with the arm at home, the controller's process for the run, the robot stopped; the log's
    (meta, arrays), or a failure."""
    from services.robot_gateway.service import GatewayConfig
    from services.robot_sim.scene import CameraConfig, SceneConfig
    from services.robot_sim.service import RobotSimConfig
    from services.stack.local import RobotProcesses

    options, duration = run_options(spec, quick)
    robot = RobotSimConfig(arm=arm.name, scene=SceneConfig(camera=CameraConfig(enabled=False)))
    command = [sys.executable, "-m", "services.torque_controller", "--controller", spec.controller,
               "--arm", arm.name, "--duration", repr(duration), "--log", str(log), "--connect", router.endpoint]
    for key, value in msgspec.to_builtins(options).items():
        if key in spec.options or key in ("tf_s", "displacement_scale"):
            command += ["--set", f"options.{key}={json.dumps(value)}"]
    log.parent.mkdir(parents=True, exist_ok=True)
    started = time.monotonic()
    with RobotProcesses(router.client_config(), robot=robot, gateway=GatewayConfig(arm=arm.name),
                        profile=profile) as processes:
        output = log.with_suffix(".log")
        with output.open("w") as out:
            process = subprocess.run(command, stdout=out, stderr=subprocess.STDOUT, timeout=duration + 120)
        alive = processes.alive()
    if not log.is_file():
        tail = output.read_text()[-400:] if output.is_file() else ""
        return {"failure": f"the controller wrote no log (exit {process.returncode}): {tail}"}
    meta, arrays = load_log(log)
    meta["exit_code"] = process.returncode
    meta["wall_time_s"] = round(time.monotonic() - started, 1)
    meta["robot_alive"] = alive
    return {"meta": meta, "arrays": arrays}


# ------------------------------------------------------------------------------------------------ metrics


def _stats(values: np.ndarray) -> dict:
    if not len(values):
        return {"rms": None, "max": None, "final": None}
    return {"rms": round(float(np.sqrt(np.mean(values**2))), 3), "max": round(float(values.max()), 3),
            "final": round(float(values[-1]), 3)}


def _durations(t: np.ndarray) -> np.ndarray:
    """How long each sample stood (to the next; the last one a bus cycle)."""
    return np.append(np.diff(t), CYCLE_S) if len(t) else t


def task_errors(arm: ArmDescription, arrays: dict) -> tuple[np.ndarray, np.ndarray]:
    """Position (mm) and orientation (deg) error of each sample: for a task run as logged, for a joint run the end
    effector's against where q_d would put it."""
    if np.isfinite(arrays["x_d"]).all() and len(arrays["x_d"]):
        return arrays["position_error_m"] * 1e3, arrays["orientation_error_deg"]
    model = laws.DynamicsModel(arm)
    position, orientation = [], []
    for q, q_d in zip(arrays["q"], arrays["q_d"]):
        kin, kin_d = model.kinematics(q), model.kinematics(q_d)
        position.append(np.linalg.norm(kin.p - kin_d.p) * 1e3)
        orientation.append(math.degrees(float(np.linalg.norm(rotation_log(kin.R.T @ kin_d.R)))))
    return np.array(position), np.array(orientation)


def emulated_arm_missed(robot_counters: Optional[dict]) -> int:
    """How many of its own 2 ms cycles the emulated arm missed in a run (its ``cycles.missed``)."""
    return (robot_counters or {}).get("cycles.missed") or 0


def kept_time(timing: dict, robot_counters: Optional[dict] = None) -> bool:
    """Whether a run's controller answered its cycles as a 500 Hz loop must (MAX_MISSED_FRACTION), and the emulated
    arm kept its own 2 ms cycles (none missed: a real arm's loop never stalls, the emulation's does on a starved host,
    and a stall of 0.1 s then made the joint-velocity law's high-gain loop command 2.3 times its peak torque for
    0.41 s when the arm came back; stalls of 10-40 ms, each its arm's cycles late but none missed, did not saturate
    it): otherwise its figures are the host's lateness as much as the controller's."""
    return (timing["missed"] <= MAX_MISSED_FRACTION * max(1, timing["received"])
            and emulated_arm_missed(robot_counters) == 0)


def run_row(spec: TorqueRunSpec, result: dict, arm: ArmDescription, quick: bool) -> dict:
    """One run's figures: tracking errors, saturation, timing, the robot's counters."""
    options, duration = run_options(spec, quick)
    row = {"label": spec.label, "law": spec.controller, "letter": spec.letter, "what": spec.what,
           "options": {k: v for k, v in msgspec.to_builtins(options).items() if k in spec.options}}
    if "failure" in result:
        return {**row, "status": "failed", "converged": False, "iterations": 0, "final_error_norm": None,
                "failure": result["failure"]}
    meta, a = result["meta"], result["arrays"]
    t = a["t"]
    position_mm, orientation_deg = task_errors(arm, a)
    limits = np.asarray(meta["torque_limits_nm"])
    durations = _durations(t)
    over_command = np.any(np.abs(a["tau_command"]) > limits, axis=1) if len(t) else np.zeros(0, bool)
    timing, robot = meta["timing"], meta.get("robot", {})
    robot_counters = robot.get("counters", {})
    failure = meta.get("failure") or ""
    status = "completed" if not failure else ("aborted" if failure.startswith("gave up") else "failed")
    reference_s = meta["reference_s"]
    end_of_motion = int(np.searchsorted(t, min(reference_s, t[-1] if len(t) else 0.0)))
    row.update({
        "status": status, "failure": failure or None,
        "converged": status == "completed",
        "iterations": int(len(t)), "duration_s": round(float(t[-1]), 3) if len(t) else 0.0,
        "final_error_norm": None if not len(t) else round(float(position_mm[-1]) / 1e3, 6),
        "position_mm": _stats(position_mm), "orientation_deg": _stats(orientation_deg),
        "at_end_of_motion": None if not len(t) else {
            "t_s": round(float(t[min(end_of_motion, len(t) - 1)]), 3),
            "position_mm": round(float(position_mm[min(end_of_motion, len(t) - 1)]), 3),
            "orientation_deg": round(float(orientation_deg[min(end_of_motion, len(t) - 1)]), 3)},
        "saturation_s": round(float(durations[over_command].sum()), 3),
        # the actuators' own count (robot_sim's: physics steps of 1 ms in which some motor gave less than asked,
        # at its peak or its torque-speed line); the measured torques carry the sensors' noise and bias
        "saturation_robot_s": None if robot_counters.get("torque.limited_ms") is None else
        round(robot_counters["torque.limited_ms"] / 1e3, 3),
        "saturated_joints": [i + 1 for i in range(len(limits)) if len(t) and
                             np.any(np.abs(a["tau_command"][:, i]) > limits[i])],
        "peak_torque_fraction": None if not len(t) else
        [round(float(v), 3) for v in (np.abs(a["tau_command"]).max(axis=0) / limits)],
        "missed_cycles": timing["missed"], "timing": timing, "faults": meta.get("faults", {}),
        "host_kept_time": kept_time(timing, robot_counters),
        "robot_watchdog": robot_counters.get("lowlevel.watchdog"),
        "safety_stops": robot_counters.get("lowlevel.safety_stops"),
        "torque_setup": meta.get("torque_setup") or None,
        "robot_counters": robot_counters, "robot_bus_hz": robot.get("bus_cycle_hz"),
        "torque_mode_fraction": round(float(np.mean(a["torque_mode"])), 4) if len(t) else 0.0,
        "x0": meta.get("x0"), "xf": meta.get("xf"), "target": meta.get("target"),
        "wall_time_s": meta.get("wall_time_s"),
    })
    if spec.controller in JOINT_CONTROLLERS and len(t):
        errors = np.degrees(np.abs(a["q_d"] - a["q"]))
        row["joint_error_deg"] = {"rms": [round(float(v), 3) for v in np.sqrt(np.mean(errors**2, axis=0))],
                                  "max": [round(float(v), 3) for v in errors.max(axis=0)]}
    return row


# ------------------------------------------------------------------------------------------------ the thesis beside
def _window_max(arrays: dict, values: np.ndarray, start: float, end: float) -> Optional[float]:
    t = arrays["t"]
    inside = (t >= start) & (t <= end)
    return round(float(values[inside].max()), 3) if inside.any() else None


def _observation(key: str, thesis: str, measured: str, verdict: str) -> dict:
    return {"id": key, "thesis": thesis, "measured": measured, "verdict": verdict}


def _ran(rows: dict, label: str) -> bool:
    """Whether the run ``label`` was made and did not fail (its figures can be judged)."""
    return label in rows and rows[label]["status"] != "failed"


def _position_rms(rows: dict, label: str) -> float:
    return rows[label]["position_mm"]["rms"]


def observations(rows: dict, arrays: dict, arm: ArmDescription, quick: bool) -> list[dict]:
    """The thesis's observations, each beside what was measured: agrees, does not, or cannot tell."""
    return (_null_space_observations(rows) + [_last_joint_observation(rows, arm.n_joints)]
            + _coupling_observations(rows, arrays, arm, quick) + _joint_velocity_observations(rows, arrays, arm, quick)
            + _joint_pd_observations(rows))


def _null_space_observations(rows: dict) -> list[dict]:
    """(b) against (a), and (c) against (b): what the null space, and its weighting, do to the position task."""
    found = []
    if _ran(rows, "jt-pid") and _ran(rows, "null-space"):
        a, b = _position_rms(rows, "jt-pid"), _position_rms(rows, "null-space")
        found.append(_observation(
            "null_space_improves_position", "the null space improves the primary (position) task over the "
            "transpose (L2455-2457)", f"position RMS {a:.2f} mm (a) against {b:.2f} mm (b)",
            "agrees" if b < a else "does not"))
    if _ran(rows, "null-space") and _ran(rows, "null-space-mass"):
        b, c = _position_rms(rows, "null-space"), _position_rms(rows, "null-space-mass")
        change = (c - b) / b if b else float("inf")
        line = f"position RMS {b:.2f} mm (W = I) against {c:.2f} mm (W = M̂), {100 * change:+.0f} %"
        if _ran(rows, "null-space-mass-rotors"):
            line += f"; with the rotors in M̂ {_position_rms(rows, 'null-space-mass-rotors'):.2f} mm"
        found.append(_observation(
            "mass_weight_barely_changes", "W = M(q) performs \"practically the same\" as W = I (L2482-2488)", line,
            "agrees" if abs(change) <= 0.25 or abs(c - b) < 0.5 else "does not"))
    return found


def _last_joint_observation(rows: dict, n: int) -> dict:
    """(d)'s last joint at Table 5.3's gain against at joint 1's, on an arm of ``n`` joints."""
    thesis = "joint 6 needs a considerably higher proportional gain (L2572-2577)"
    if not (_ran(rows, "joint-pd") and _ran(rows, "joint-pd-last-low")):
        return _observation("last_joint_needs_high_gain", thesis, "not run (quick)", "cannot tell")
    table, low = rows["joint-pd"]["joint_error_deg"]["rms"], rows["joint-pd-last-low"]["joint_error_deg"]["rms"]
    others = max(table[:-1])
    line = (f"joint {n} RMS error {table[-1]:.2f}° with Table 5.3's gain "
            f"({laws.per_joint_gains(laws.TABLE_5_3_KP, n)[-1]:g}), {low[-1]:.2f}° at joint 1's "
            f"({laws.TABLE_5_3_KP[0]:g}); the other joints' worst {others:.2f}°")
    if _ran(rows, "joint-pd-last-low-rotors"):
        line += (f"; with the rotors' inertia in M̂ joint 1's gain gives joint {n} "
                 f"{rows['joint-pd-last-low-rotors']['joint_error_deg']['rms'][-1]:.2f}°")
    return _observation("last_joint_needs_high_gain", thesis, line,
                        "agrees" if low[-1] > 1.5 * table[-1] and low[-1] > others else "does not")


def _coupling_observations(rows: dict, arrays: dict, arm: ArmDescription, quick: bool) -> list[dict]:
    """(a)'s orientation displacing its position, when, and its oscillation, against (b) (the whole runs only)."""
    if not (_ran(rows, "jt-pid") and _ran(rows, "null-space") and not quick):
        return [_observation(key, thesis, "not run (quick)" if quick else "a run failed", "cannot tell")
                for key, thesis in (
                    ("orientation_couples_into_position", "in (a) the orientation displaces the position"),
                    ("coupling_near_10s", "that displacement comes at around 10 s"),
                    ("oscillation_2_5_to_7_5s", "(a) oscillates in orientation over [2.5, 7.5] s"))]
    a_t, a_e = arrays["jt-pid"]["t"], task_errors(arm, arrays["jt-pid"])[0]
    b_e = task_errors(arm, arrays["null-space"])[0]
    moving = a_t <= laws.THESIS_TF_S
    coupling = a_e[moving] - np.interp(a_t[moving], arrays["null-space"]["t"], b_e)
    coupling_t = float(a_t[moving][np.argmax(coupling)])
    b_max = float(b_e[arrays["null-space"]["t"] <= laws.THESIS_TF_S].max())
    gamma = _orientation_component_error(arrays["jt-pid"], 2)
    early, later = _ripple(arrays["jt-pid"]["t"], gamma, 2.5, 7.5), _ripple(arrays["jt-pid"]["t"], gamma, 7.5, 16.0)
    return [
        _observation("orientation_couples_into_position", "in (a) the orientation's adjustment displaces the "
                     "position: force coupling between the two controllers (L2401-2409)",
                     f"(a)'s position error reaches {a_e[moving].max():.2f} mm, (b)'s, with the orientation filtered "
                     f"into the null space, {b_max:.2f} mm", "agrees" if a_e[moving].max() > 3 * b_max else "does not"),
        _observation("coupling_near_10s", "that displacement comes at around 10 s (L2405-2409)",
                     f"(a)'s excess over (b) is largest at {coupling_t:.1f} s",
                     "agrees" if 8.5 <= coupling_t <= 11.5 else "does not"),
        _observation("oscillation_2_5_to_7_5s", "(a) oscillates in orientation (Fig. 5.1f) over [2.5, 7.5] s "
                     "(L2411-2413)", f"ripple of the γ (Z) error about its 0.5 s mean: {early:.3f}° in [2.5, 7.5] s, "
                     f"{later:.3f}° in [7.5, 16] s", "agrees" if early > 2 * later and early > 0.1 else "does not"),
    ]


def _joint_velocity_observations(rows: dict, arrays: dict, arm: ArmDescription, quick: bool) -> list[dict]:
    """(e): the position reached at tf, the orientation early on against (b)'s, the disturbance after tf."""
    if not _ran(rows, "joint-velocity"):
        return []
    end = rows["joint-velocity"]["at_end_of_motion"]
    found = [_observation("velocity_position_reached_at_tf", "(e) the desired position is practically achieved "
                          "around 16 s (L2659-2663)",
                          f"position error {end['position_mm']:.2f} mm at {end['t_s']:.1f} s",
                          "agrees" if end["position_mm"] < 5.0 else "does not")]
    if _ran(rows, "null-space"):
        t_e = arrays["joint-velocity"]["t"]
        first = (t_e <= 0.5 * (QUICK_TF_S if quick else laws.THESIS_TF_S))
        e_o = task_errors(arm, arrays["joint-velocity"])[1]
        b_o = task_errors(arm, arrays["null-space"])[1]
        t_b = arrays["null-space"]["t"]
        e_rms = float(np.sqrt(np.mean(e_o[first] ** 2)))
        b_rms = float(np.sqrt(np.mean(b_o[t_b <= t_e[first][-1]] ** 2)))
        found.append(_observation(
            "velocity_orientation_poor_early", "(e) orientation tracking \"lefts much to be desired in the first "
            "stages\" (L2680-2682)", f"orientation RMS over the first half of the motion {e_rms:.2f}° (e) "
            f"against {b_rms:.2f}° (b)", "agrees" if e_rms > 2 * b_rms else "does not"))
    if not quick:
        position = task_errors(arm, arrays["joint-velocity"])[0]
        late = _window_max(arrays["joint-velocity"], position, 15.0, 20.0)
        before = _window_max(arrays["joint-velocity"], position, 11.0, 15.0)
        found.append(_observation(
            "velocity_disturbance_15_to_20s", "(e) small disturbances of the position around [15, 20] s as the "
            "orientation is readjusted (L2667-2677)", f"max position error {late} mm in [15, 20] s, {before} mm "
            "in [11, 15] s", "agrees" if late is not None and before is not None and
            late > max(1.5 * before, DISTURBANCE_MM) else "does not"))
    return found


def _joint_pd_observations(rows: dict) -> list[dict]:
    """(d)'s tracking as the thesis describes it, in words: shown, not judged."""
    if not _ran(rows, "joint-pd"):
        return []
    rms_all = rows["joint-pd"]["joint_error_deg"]["rms"]
    return [_observation("joint_pd_good_tracking", "(d) the joints follow with \"relatively good tracking\", "
                         "stable, little coupling (L2543-2558)",
                         f"joint RMS errors {', '.join(f'{v:.1f}' for v in rms_all)}° on a ±20° sinusoid (no "
                         "feed-forward in eq. 4.18: the PD lags); stable, no abort", "cannot tell")]


def _orientation_component_error(arrays: dict, k: int) -> np.ndarray:
    """One XYZ Euler angle's error (deg), measured less desired, unwrapped."""
    measured = np.unwrap(arrays["x"][:, 3 + k])
    return np.degrees(measured - arrays["x_d"][:, 3 + k])


def _ripple(t: np.ndarray, values: np.ndarray, start: float, end: float) -> float:
    """RMS of ``values`` about their 0.5 s moving mean within [start, end] (an oscillation's size)."""
    window = max(1, int(round(0.5 / CYCLE_S)))
    kernel = np.ones(window) / window
    smooth = np.convolve(values, kernel, mode="same")
    inside = (t >= start) & (t <= end)
    return float(np.sqrt(np.mean((values - smooth)[inside] ** 2))) if inside.any() else 0.0


# ------------------------------------------------------------------------------------------------ the experiment


def run_torque_control(arm_name: Optional[str] = None, out_dir: Optional[str | Path] = None, profile: str = "sim",
                       quick: bool = False, progress: Optional[Callable[[dict], None]] = None,
                       labels: Optional[list[str]] = None) -> dict:
    """Run the experiment on ``arm_name`` (None: the thesis's j2n6s300); ``progress(row)`` after each run. Returns
    ``{"experiment", "title", "paper", "arm", "profile", "runs": [...], "summary": {...}, "report", "plots"}``."""
    from services.stack.local import RouterProcess

    if profile not in ("sim", "gateway"):
        raise ValueError(f"unknown profile {profile!r}: sim or gateway")
    arm = load_arm(arm_name or THESIS_ARM)
    specs = [s for s in runs_for(arm, quick) if labels is None or s.label in labels]
    target = reference_target(arm, quick)
    rows: dict[str, dict] = {}
    arrays: dict[str, dict] = {}
    metas: dict[str, dict] = {}
    with tempfile.TemporaryDirectory(prefix="mfvs-torque-") as scratch:
        root = Path(out_dir) if out_dir is not None else Path(scratch)
        with RouterProcess() as router:
            for spec in specs:
                result = run_one(spec, arm, root / spec.label / "log.npz", profile, quick, router)
                rows[spec.label] = run_row(spec, result, arm, quick)
                if "arrays" in result:
                    arrays[spec.label], metas[spec.label] = result["arrays"], result["meta"]
                if progress is not None:
                    progress(rows[spec.label])
        summary = {"target": target, "observations": observations(rows, arrays, arm, quick),
                   "timing": _timing_summary(rows), "choices": CHOICES,
                   "model": model_error(arm, profile)}
        output = {"experiment": NAME, "seed": "003", "title": TITLE, "paper": PAPER, "arm": arm.name,
                  "profile": profile, "quick": quick, "runs": list(rows.values()), "summary": summary,
                  "report": None, "plots": [],
                  # realtime: a rerun differs by the host's timing (the counts of late cycles say how much)
                  "repeatable": False}
        if out_dir is not None:
            from services.experiments.report import write_results
            from services.experiments.figures import torque_comparison_plots, torque_run_plots

            out = Path(out_dir)
            for label, run_arrays in arrays.items():
                rows[label]["plots"] = [str(p) for p in torque_run_plots(
                    run_arrays, metas[label], out / label, arm=arm, label=label)]
            output["plots"] = [str(p) for p in torque_comparison_plots(arrays, metas, out, arm=arm)]
            write_results(output, out, report_markdown)
    return output


def reference_target(arm: ArmDescription, quick: bool) -> dict:
    """X0 at the arm's home (the model's; each run reads the arm's own report), Xf, and whether Xf is reachable."""
    spec = runs_for(arm, quick)[0]
    options, _ = run_options(spec, quick)
    controller = make_controller("jt-pid", arm, options)
    start = controller.begin(arm.home)
    nearest = laws.nearest_pose(arm, start.xf, arm.home)
    return {"kind": start.target, "x0": [round(v, 6) for v in start.x0.tolist()],
            "xf": [round(v, 6) for v in start.xf.tolist()],
            "reachable": nearest.reachable,
            "nearest": {"position_mm": round(nearest.position_error_m * 1e3, 2),
                        "orientation_deg": round(nearest.orientation_error_deg, 3),
                        "joints_deg": [round(v, 1) for v in arm.model_to_physical_deg(nearest.q).tolist()],
                        "sigma_min_J": round(nearest.sigma_min, 4),
                        "sigma_min_Jv": round(nearest.sigma_min_position, 4),
                        "weighting": f"1 rad counted as {laws.ORIENTATION_WEIGHT_M} m"}}


def model_error(arm: ArmDescription, profile: str = "sim") -> dict:
    """How the controllers' model (the links alone, as the thesis's CAD model) differs from the emulated arm, at
    home: the diagonal of M̂ against the arm's (robot_sim's MuJoCo model: the rotors' inertia, the heavier hand),
    the friction it does not know, and the gravity the arm's hand adds beyond the model's."""
    import mujoco

    from services.robot_sim.scene import CameraConfig, SceneConfig, build_model

    true_model = build_model(SceneConfig(camera=CameraConfig(enabled=False)), arm)
    data = mujoco.MjData(true_model)
    n = arm.n_joints
    data.qpos[:n] = arm.home
    mujoco.mj_forward(true_model, data)
    full = np.zeros((true_model.nv, true_model.nv))
    mujoco.mj_fullM(true_model, data, full)
    cad = laws.DynamicsModel(arm)
    m_cad, m_arm = np.diag(cad.mass(arm.home)), np.diag(full)[:n]
    return {"mass_diagonal_model": [round(float(v), 4) for v in m_cad],
            "mass_diagonal_arm": [round(float(v), 4) for v in m_arm],
            "model_over_arm": [round(float(v), 3) for v in m_cad / m_arm],
            "rotor_inertia_kg_m2": arm.armature.tolist(), "viscous_friction_nm_s_per_rad": arm.damping.tolist(),
            "coulomb_friction_nm": [round(float(v), 3) for v in arm.true_friction_nm],
            "link_mass_scale": arm.true_link_mass_scale.tolist(),
            "gravity_model_nm": [round(float(v), 3) for v in cad.gravity(arm.home)],
            "gravity_arm_nm": [round(float(v), 3) for v in data.qfrc_bias[:n]],
            "torque_limits_nm": arm.max_torque.tolist(),
            "gravity": GRAVITY_FACED[profile]}


#: what gravity the controllers face after Table 5.1, by profile (services/robot/lowlevel.py)
GRAVITY_FACED = {
    "sim": ("The controllers face the arm's true gravity: with Table 5.1's gravity off, robot_sim's actuators add "
            "none, so the hand's extra weight, which their ĝ(q) does not know, is theirs to hold (as a real arm "
            "with its compensation off leaves a CAD model's error to the client)"),
    "gateway": ("The controllers face the arm's true gravity, as in the sim profile: over the RS-485 bus the "
                "emulated actuators add none (the base's DSP is bypassed, as on a real arm), and with Table 5.1's "
                "gravity off the robot node sends none of its own either, so the hand's extra weight, which their "
                "ĝ(q) does not know, is theirs to hold"),
}


def _timing_summary(rows: dict) -> dict:
    done = [r for r in rows.values() if r["status"] != "failed"]
    if not done:
        return {}
    return {"cycle_rate_hz": [r["timing"]["cycle_rate_hz"] for r in done],
            "latency_p99_ms": max(r["timing"]["latency_ms"]["p99"] or 0.0 for r in done),
            "arrival_jitter_p99_ms": max(r["timing"]["arrival_jitter_ms"]["p99"] or 0.0 for r in done),
            "missed_cycles": sum(r["missed_cycles"] for r in done),
            "answered": sum(r["timing"]["answered"] for r in done),
            "robot_watchdog": sum(r["robot_watchdog"] or 0 for r in done),
            "safety_stops": sum(r["safety_stops"] or 0 for r in done)}


#: the choices where the thesis is silent (docs/torque.md says why)
CHOICES = [
    "Table 5.1 made by each controller through the Kinova API before its first torque (the arm adds no gravity); "
    "the thesis's calibration (SetTorqueZero at [*, 180, 180, 0, 0, 180]°, SetJointZero) is not: no controller "
    "reads a torque sensor, and the emulated position sensors never slip",
    "(a)-(c) add the model's gravity ĝ(q) (not stated by the thesis); the literal law runs as jt-pid-no-gravity",
    "D terms on the error's rate (reference velocity less J·q̇), not on −J·q̇ alone",
    "integrals weighed by each step's duration (the thesis's fixed 10 ms step has none)",
    "eq. 4.8 leaves the integral unchanged when θ is below the 0.03 rad threshold",
    "q̇ is the actuators' own (the low-level state); the thesis differenced 100 Hz positions",
    "(e): Ẋ_d, Ẋ_ω are Table 5.5's PID outputs; J_ω⁻¹ is the Moore-Penrose pseudo-inverse",
    "(d): q_d = q_home + 20°·sin(2πt/8) on every joint, from HOME, for two periods",
    "the controllers' model: the links alone (no rotor inertia, no friction), as the thesis's CAD model",
    "X0: the arm's report at HOME; Xf: eq. 5.2's on the j2n6s300, X0 + eq. 5.2's displacement elsewhere",
    "the 7-DoF takes joint 3's gain for its extra joint (3 of 7) and the wrist's for joints 5-7",
]


# ------------------------------------------------------------------------------------------------ the report


def _f(value, digits: int = 2) -> str:
    if value is None:
        return "–"
    if isinstance(value, float):
        return f"{value:.{digits}f}"
    return str(value)


def report_markdown(output: dict, out_dir: Path) -> str:
    summary = output["summary"]
    lines = (_reference_section(output) + _model_section(summary["model"]) + _torque_setup_section(output["runs"])
             + _other_arm_section(output) + _runs_section(output["runs"], summary["observations"])
             + _observations_section(summary["observations"]) + _loop_section(summary["timing"]))
    lines += ["", "## Choices where the thesis is silent", ""] + [f"- {c}" for c in summary["choices"]]
    return "\n".join(lines + _figures_section(output, out_dir))


def _reference_section(output: dict) -> list[str]:
    """The title, how the runs were made, what the thesis reports, and the reference (is Xf reachable?)."""
    target = output["summary"]["target"]
    nearest = target["nearest"]
    return [f"# {output['title']}", "",
            f"`mfvs experiment torque-control --arm {output['arm']}` ({output['profile']} profile, realtime at "
            "500 Hz: each controller a process talking to the robot's low-level API; a rerun differs by the host's "
            "timing)." + (" Quick runs: a 3 s reference over 3/16 of the motion." if output["quick"] else ""), "",
            f"**The JACO thesis reports:** {output['paper']}. It gives no numbers: its figures are described in "
            "words.", "",
            "## The reference", "",
            f"X0 = {target['x0']} (the arm's home), Xf = {target['xf']} ({target['kind']}). "
            + ("Xf is reachable." if target["reachable"] else
               f"**Xf is not reachable**: the nearest pose the arm reaches within its joint limits is "
               f"{nearest['position_mm']} mm and {nearest['orientation_deg']}° away ({nearest['weighting']}), at "
               f"joints {nearest['joints_deg']}° where σ_min(J) = {nearest['sigma_min_J']} and σ_min(J_v) = "
               f"{nearest['sigma_min_Jv']}: every task controller's final error has that floor."), ""]


def _model_section(model: dict) -> list[str]:
    """The controllers' model against the emulated arm, joint by joint (:func:`model_error`)."""
    return ["## The model against the arm", "",
            "The controllers' M̂(q) is the links' alone (the description's masses, centres, inertias: the thesis's "
            "eq. 3.35 from its CAD model); the emulated arm also has the motors' rotor inertia reflected through "
            "the gears, a hand heavier than described, viscous and Coulomb friction and its actuators' peak "
            "torques, which the thesis's model did not have either.", "",
            "| joint | " + " | ".join(str(i + 1) for i in range(len(model["mass_diagonal_model"]))) + " |",
            "|---|" + "---|" * len(model["mass_diagonal_model"]),
            "| M̂ii, model (kg m²) | " + " | ".join(f"{v:.4f}" for v in model["mass_diagonal_model"]) + " |",
            "| Mii, arm | " + " | ".join(f"{v:.4f}" for v in model["mass_diagonal_arm"]) + " |",
            "| model / arm | " + " | ".join(f"{v:.2f}" for v in model["model_over_arm"]) + " |",
            "| Coulomb friction in torque mode (N·m) | " + " | ".join(f"{v:g}" for v in model["coulomb_friction_nm"])
            + " |",
            "| gravity at home, model (N·m) | " + " | ".join(f"{v:.2f}" for v in model["gravity_model_nm"]) + " |",
            "| gravity at home, arm (N·m) | " + " | ".join(f"{v:.2f}" for v in model["gravity_arm_nm"]) + " |",
            "| torque limit (N·m) | " + " | ".join(f"{v:g}" for v in model["torque_limits_nm"]) + " |", "",
            f"{model['gravity']}.", ""]


def _torque_setup_section(runs: list[dict]) -> list[str]:
    """Table 5.1's setup as the first run that logged it made it (none: no section)."""
    setup = next((row["torque_setup"] for row in runs if row.get("torque_setup")), None)
    if not setup:
        return []
    return ["## The torque-mode setup", "",
            f"Each controller made {setup['table']} through the arm's Kinova API before its first torque: "
            + ", ".join(f"{a['function']}({a['argument']})" for a in setup["applied"]) + ". Not made: "
            + "; ".join(f"{f}: {why}" for f, why in setup["not_applied"].items()) + ".", ""]


def _other_arm_section(output: dict) -> list[str]:
    """What differs on an arm other than the thesis's (none on the thesis's)."""
    if output["arm"] == THESIS_ARM:
        return []
    target = output["summary"]["target"]
    nearest = target["nearest"]
    n = len(output["summary"]["model"]["torque_limits_nm"])
    kp = laws.per_joint_gains(laws.TABLE_5_3_KP, n)
    return [f"## What differs on the {output['arm']}", "",
            f"- {n} joints: J_v is 3×{n} and J 6×{n}. (a)'s Jᵀ law leaves J's {n - 6}-dimensional null space "
            "to itself (only the joints' friction damps a self-motion); (b) and (c) filter the orientation's "
            f"torque into a {n - 3}-dimensional null space of the position task; (e) resolves the velocities "
            "with pseudo-inverses (the least joint motion: no self-motion is commanded).",
            f"- Table 5.3-5.4's per-joint gains mapped onto {n} joints (Kp {', '.join(f'{v:g}' for v in kp)}): "
            "see torque_laws.per_joint_gains.",
            f"- Xf is X0 moved as eq. 5.2 moves the thesis's arm ({target['kind']}); "
            + ("it is reachable." if target["reachable"] else
               f"it is not reachable: the nearest pose is {nearest['position_mm']} mm and "
               f"{nearest['orientation_deg']}° away."), ""]


def _runs_section(runs: list[dict], observations: list[dict]) -> list[str]:
    lines = ["## The runs", ""]
    for row in runs:
        lines += _run_section(row, [obs for obs in observations if _observation_run(obs["id"]) == row["label"]])
    return lines


def _run_section(row: dict, mine: list[dict]) -> list[str]:
    """One run: its figures, whether the host kept its time, the robot's faults, and the observations it judges."""
    head = f"### {'(' + row['letter'] + ') ' if row['letter'] else ''}{row['label']}: {row['what']}"
    lines = [head, ""]
    if row["status"] == "failed":
        return lines + [f"Failed: {row['failure']}", ""]
    p, o = row["position_mm"], row["orientation_deg"]
    lines += ["| position RMS / max / final (mm) | orientation RMS / max / final (deg) | saturation (s, commanded "
              "/ actuators) | missed cycles (late+superseded+unseen) | robot watchdog | safety stops | status |",
              "|---|---|---|---|---|---|---|",
              f"| {_f(p['rms'])} / {_f(p['max'])} / {_f(p['final'])} | {_f(o['rms'])} / {_f(o['max'])} / "
              f"{_f(o['final'])} | {_f(row['saturation_s'])} / {_f(row['saturation_robot_s'])} | "
              f"{row['missed_cycles']} ({row['timing']['late']}+{row['timing']['superseded']}+"
              f"{row['timing']['unseen']}) of {row['timing']['answered']} | {_f(row['robot_watchdog'])} | "
              f"{_f(row['safety_stops'])} | {row['status']}{': ' + row['failure'] if row['failure'] else ''} |", ""]
    if not row["host_kept_time"]:
        lines += [f"**This host did not keep the loop's time**: the controller missed {row['missed_cycles']} of "
                  f"{row['timing']['received']} cycles (at most {MAX_MISSED_FRACTION:.0%} keep it), the emulated "
                  f"arm {emulated_arm_missed(row.get('robot_counters'))} of its own (none keep it): these figures are the host's lateness as much as "
                  "the controller's (run it with fewer processes beside it)", ""]
    if row.get("faults"):
        lines += ["The robot reported: " + "; ".join(f"{fault} ({count} states)"
                                                     for fault, count in row["faults"].items()), ""]
    if "joint_error_deg" in row:
        je = row["joint_error_deg"]
        lines += ["joint error RMS (deg): " + ", ".join(f"{v:.2f}" for v in je["rms"]) + "; max: " +
                  ", ".join(f"{v:.2f}" for v in je["max"]), ""]
    if mine:
        lines += ["| the thesis | measured | |", "|---|---|---|"]
        lines += [f"| {obs['thesis']} | {obs['measured']} | **{obs['verdict']}** |" for obs in mine]
        lines.append("")
    return lines


def _observations_section(observations: list[dict]) -> list[str]:
    return (["## The thesis beside the measurements", "", "| observation | measured | |", "|---|---|---|"]
            + [f"| {obs['thesis']} | {obs['measured']} | **{obs['verdict']}** |" for obs in observations])


def _loop_section(timing: dict) -> list[str]:
    """The low-level loop over all runs (:func:`_timing_summary`; none when every run failed)."""
    if not timing:
        return []
    return ["", "## The low-level loop", "",
            f"Cycle rate per run {timing['cycle_rate_hz']} Hz; the controller's answer, from the state's stamp to "
            f"its command sent: p99 {timing['latency_p99_ms']} ms; arrival jitter p99 "
            f"{timing['arrival_jitter_p99_ms']} ms; missed low-level cycles {timing['missed_cycles']} of "
            f"{timing['answered']} answered; the robot applied no fresh command (its 5 ms watchdog) on "
            f"{timing['robot_watchdog']} cycles."]


def _figures_section(output: dict, out_dir: Path) -> list[str]:
    """The comparison's figures, then each run's, as links relative to the report."""
    lines = ["", "## Figures", ""]
    for plot in output["plots"]:
        lines.append(f"![{Path(plot).stem}]({Path(plot).relative_to(out_dir).as_posix()})")
    for row in output["runs"]:
        for plot in row.get("plots", []):
            lines.append(f"![{row['label']} {Path(plot).stem}]({Path(plot).relative_to(out_dir).as_posix()})")
    lines.append("")
    return lines


def _observation_run(key: str) -> str:
    """The run an observation belongs to (its table in the report)."""
    return {"null_space_improves_position": "null-space", "mass_weight_barely_changes": "null-space-mass",
            "last_joint_needs_high_gain": "joint-pd", "coupling_near_10s": "jt-pid",
            "orientation_couples_into_position": "jt-pid",
            "oscillation_2_5_to_7_5s": "jt-pid", "velocity_position_reached_at_tf": "joint-velocity",
            "velocity_orientation_poor_early": "joint-velocity", "velocity_disturbance_15_to_20s": "joint-velocity",
            "joint_pd_good_tracking": "joint-pd"}.get(key, "")
