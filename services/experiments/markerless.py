"""``mfvs experiment markerless``: a person shows the arm their own object once, and it goes back to that view from
starts nobody tuned, with no marker (Sensors 2022's own future work).

For each start (the random-start generator of Table 3's, :mod:`.starts`, the tag replaced by the object, its whole
outline in view):

1. **teach** at the goal: the arm placed where the camera is in Table 2's goal pose before the object (squarely in
   front of it at 0.2888 m; inverse kinematics from the start), the region a person would draw around the object,
   and the whole teach as `mfvs teach` runs it (vision's first view, the controller's 3-cm probe and its return,
   the triangulated depths: services/vision/teach_client.py) through the real services in lockstep;
2. **servo** from the start to the taught view (adaptive-pd-mixed, the keypoint front end), with the perturbations
   asked for: ``lighting`` (the servo lit otherwise than the teach: ±50 % intensity, the light's direction turned
   30°), ``occlusion`` (a plate 30 % of the object's width crossing in front of it during the servo), ``swap`` (the
   object replaced by another of another print 1 s into the servo: the arm must hold and not move toward it);
3. **the tag on the same start**: the tag in the object's place, its goal the same camera pose, the same law and the
   same convergence threshold (the per-point RMS the markerless runs are held to), for the iterations.

Each run's errors are MuJoCo's: the camera frame MuJoCo renders from at the end against the one it rendered the
taught view from, the object fixed between them.
"""
from __future__ import annotations

import json
import math
import random
import tempfile
from pathlib import Path
from typing import Callable, Optional

import msgspec
import numpy as np

from protocol.conventions import LOCKSTEP_EPOCH_NS
from protocol.keys import Keys
from services.experiments.pool import RunTask, run_tasks
from services.experiments.report import cell, write_results
from services.experiments.spec import failure
from services.experiments.starts import TABLE2_LIKE, quartiles, random_start
from services.model import frames
from services.model.arm import load_arm
from services.model.frames import PoseConfig
from services.model.kinematics import ArmKinematics, inverse_kinematics
from services.paths import SCENARIOS
from services.robot_sim.imaging import ImagingConfig
from services.robot_sim.scene import (LightConfig, SceneObject, TargetKind, camera_in_ee, target_in_base,
                                      target_outline)
from services.servo.result import error_rms, read_log
from services.servo.scenario import Scenario, load_scenario, on_arm, stack_config
from services.safety.checks import SafetyLimits
from services.vision.service import GoalConfig
from services.vision.teach import TeachConfig

PERTURBATIONS = ("lighting", "occlusion", "swap", "clutter", "webcam")
OBJECTS = ("plane", "cup")
BASE_SCENARIO = SCENARIOS / "markerless.yaml"

#: Table 2's goal: the camera squarely in front of the target at 0.2888 m (the pose the tag experiments' goal square
#: is seen from)
GOAL_IN_CAMERA = PoseConfig(xyz=(0.0, 0.0, 0.2888), rpy_deg=(180.0, 0.0, 0.0))
#: the region a person draws around the object at the teach: its outline's box grown by this (px)
REGION_MARGIN_PX = 12.0
#: lighting: the servo's light, by start (even: brighter, odd: dimmer), its direction turned this far from the teach's
LIGHT_INTENSITIES = (1.5, 0.5)
LIGHT_TURN_DEG = 30.0
#: occlusion: a plate this share of the object's width, this far in front of it, crossing it in this long from this
#: time into the servo (s)
OCCLUDER_SHARE = 0.3
OCCLUDER_OFFSET_M = 0.05
OCCLUSION_START_S, OCCLUSION_CROSSING_S = 0.8, 1.6
#: clutter: two objects of the same kind and a print of the same style (other seeds) beside the object, at the teach
#: and the servo: this far from it on each side (m, the object's frame), turned this much (deg)
CLUTTER_OFFSET_M, CLUTTER_TURN_DEG = 0.2, 20.0
CLUTTER_SEEDS = (101, 102)
#: swap: the object replaced by another (another print) this long into the servo (s)
SWAP_AT_S = 1.0
#: the other object's print
SWAP_TEXTURE_SEED = 4242


def wilson_interval(successes: int, n: int, z: float = 1.959964) -> tuple[Optional[float], Optional[float]]:
    """The Wilson score interval of a success rate (95 % by default): (low, high), or (None, None) for no runs."""
    if n == 0:
        return None, None
    p = successes / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z / (1 + z * z / n) * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n))
    return max(0.0, centre - half), min(1.0, centre + half)


# ------------------------------------------------------------------------------------------------ the starts
def base_scenario(kind: str, texture: Optional[str], arm: Optional[str], scenario: Optional[Path] = None) -> Scenario:
    path = Path(scenario) if scenario is not None else BASE_SCENARIO
    base = on_arm(load_scenario(path), arm, str(path))
    base.target = msgspec.structs.replace(base.target, kind=TargetKind(kind),
                                          texture=texture if texture is not None else base.target.texture)
    return base


def goal_joints(base: Scenario, pose_in_camera: PoseConfig) -> tuple[Optional[np.ndarray], str]:
    """The arm's joints (model, rad) that put the camera in the goal pose before the object placed at
    ``pose_in_camera`` (the camera's frame at the start), or (None, why not)."""
    arm = load_arm(base.robot.arm)
    kin = ArmKinematics(arm)
    scene = stack_config(base).robot.scene
    scene.target = msgspec.structs.replace(scene.target, pose_in_camera=pose_in_camera, pose_in_base=None)
    T_bt = target_in_base(scene, arm)
    goal_camera = T_bt @ np.linalg.inv(GOAL_IN_CAMERA.matrix())
    q0 = arm.physical_deg_to_model(scene.start_deg(arm))
    q, ok = inverse_kinematics(kin, q0, goal_camera[:3, :3], goal_camera[:3, 3], tool=camera_in_ee(scene))
    if not ok:
        return None, "the goal pose is out of the arm's reach"
    # a teach there makes the probe: its far end, too, must be where safety lets the arm go (its joints inside
    # safety's margin of their limits; a goal 2° from joint 6's limit was reached, and the probe never moved)
    probe = np.asarray(TeachConfig().probe_m)
    far = goal_camera.copy()
    far[:3, 3] += goal_camera[:3, :3] @ probe
    q_far, ok = inverse_kinematics(kin, q, far[:3, :3], far[:3, 3], tool=camera_in_ee(scene))
    margin = SafetyLimits().joint_limit_margin_deg
    for name, joints in (("the goal pose", q), ("the teach's probe", q_far)):
        if not ok or not arm.within_limits(joints) or np.min(arm.limit_margins_deg(joints), initial=np.inf) < margin:
            return None, f"{name} is within {margin:g}° of a joint limit (safety's margin)"
    return q, ""


def draw_starts(base: Scenario, count: int, seed: int) -> list[dict]:
    """``count`` starts from ``seed``: the object's pose in the camera at the start, and the arm's joints at the
    goal (a start whose goal is out of reach is drawn again, and counted)."""
    rng = random.Random(seed)
    outline = target_outline(base.target)
    starts, redrawn = [], 0
    while len(starts) < count:
        pose = random_start(rng, TABLE2_LIKE, outline, base.camera)
        q, why = goal_joints(base, pose)
        if q is None:
            redrawn += 1
            if redrawn > 10 * count:
                raise ValueError(f"no reachable goal in {redrawn} draws: {why}")
            continue
        starts.append({"index": len(starts), "seed": seed, "pose_in_camera": {"xyz": list(pose.xyz),
                                                                               "rpy_deg": list(pose.rpy_deg)},
                       "goal_joints": [float(v) for v in q], "redrawn_before": redrawn})
    return starts


def _pose(start: dict) -> PoseConfig:
    return PoseConfig(xyz=tuple(start["pose_in_camera"]["xyz"]), rpy_deg=tuple(start["pose_in_camera"]["rpy_deg"]))


def _placed(base: Scenario, start: dict) -> Scenario:
    """The base scenario with the object where the start puts it, fixed in the base frame (so that the teach, at
    another configuration of the arm, sees it where the servo will)."""
    scenario = msgspec.convert(msgspec.to_builtins(base), Scenario)
    arm = load_arm(base.robot.arm)
    scene = stack_config(base).robot.scene
    scene.target = msgspec.structs.replace(scene.target, pose_in_camera=_pose(start), pose_in_base=None)
    T_bt = target_in_base(scene, arm)
    scenario.target = msgspec.structs.replace(base.target, pose_in_camera=None, pose_in_base=PoseConfig(
        xyz=tuple(T_bt[:3, 3]), rpy_deg=tuple(np.degrees(frames.matrix_to_euler_xyz(T_bt[:3, :3])))))
    return scenario


def _clutter(scenario: Scenario) -> list[SceneObject]:
    """Objects like the target (its kind, a print of the same style from other seeds) to each side of it."""
    target = scenario.target
    T_bt = target.pose_in_base.matrix()
    out = []
    for side, seed in zip((-1.0, 1.0), CLUTTER_SEEDS):
        T = T_bt @ frames.homogeneous(frames.rot_y(math.radians(side * CLUTTER_TURN_DEG)),
                                      [side * CLUTTER_OFFSET_M, 0.0, -0.03])
        out.append(SceneObject(name=f"clutter{seed}", kind=target.kind.value, size_m=(*target.plane_m, 0.01),
                               cup=target.cup, texture_seed=seed, pose_in_base=PoseConfig(
                                   xyz=tuple(float(v) for v in T[:3, 3]),
                                   rpy_deg=tuple(float(v) for v in np.degrees(frames.matrix_to_euler_xyz(T[:3, :3]))))))
    return out


def _perturbed_scene(scenario: Scenario, perturb: tuple[str, ...]) -> Scenario:
    """What a teach and its servo share: clutter beside the object, the webcam's imaging."""
    if "clutter" in perturb:
        scenario.objects = [*scenario.objects, *_clutter(scenario)]
    if "webcam" in perturb:
        scenario.camera = msgspec.structs.replace(scenario.camera, imaging=ImagingConfig())
    return scenario


def teach_scenario(base: Scenario, start: dict, perturb: tuple[str, ...] = ()) -> Scenario:
    scenario = _perturbed_scene(_placed(base, start), perturb)
    arm = load_arm(base.robot.arm)
    scenario.robot = msgspec.structs.replace(scenario.robot, initial_joints_deg=[
        float(v) for v in arm.model_to_physical_deg(np.asarray(start["goal_joints"]))])
    return scenario


def teach_region(base: Scenario) -> list[tuple[float, float]]:
    """The region a person draws around the object at the goal: its outline's box, grown by REGION_MARGIN_PX."""
    T = GOAL_IN_CAMERA.matrix()
    P = target_outline(base.target) @ T[:3, :3].T + T[:3, 3]
    K = base.camera.matrix()
    px = np.column_stack([K[0, 0] * P[:, 0] / P[:, 2] + K[0, 2], K[1, 1] * P[:, 1] / P[:, 2] + K[1, 2]])
    lo = np.maximum(px.min(axis=0) - REGION_MARGIN_PX, 0.0)
    hi = np.minimum(px.max(axis=0) + REGION_MARGIN_PX, [base.camera.width - 1, base.camera.height - 1])
    return [(float(lo[0]), float(lo[1])), (float(hi[0]), float(lo[1])), (float(hi[0]), float(hi[1])),
            (float(lo[0]), float(hi[1]))]


def servo_scenario(base: Scenario, start: dict, goal_file: Path, perturb: tuple[str, ...]) -> Scenario:
    scenario = _perturbed_scene(_placed(base, start), perturb)
    scenario.goal = GoalConfig(features=None, taught=str(goal_file))
    target = scenario.target
    objects: list[SceneObject] = []
    T_bt = target.pose_in_base.matrix()
    if "lighting" in perturb:
        index = start["index"]
        turn = frames.rot_x(math.radians(LIGHT_TURN_DEG if index % 2 == 0 else -LIGHT_TURN_DEG))
        direction = turn @ np.array(LightConfig().direction)
        scenario_light = LightConfig(intensity=LIGHT_INTENSITIES[index % 2], direction=tuple(float(v) for v in direction))
    else:
        scenario_light = None
    if "occlusion" in perturb:
        width = target.plane_m[0] if target.kind == TargetKind.PLANE else 2 * target.cup.radius_m
        height = target.plane_m[1] if target.kind == TargetKind.PLANE else target.cup.height_m
        front = OCCLUDER_OFFSET_M + (0.0 if target.kind == TargetKind.PLANE else target.cup.radius_m)
        speed = (width + OCCLUDER_SHARE * width) / OCCLUSION_CROSSING_S
        begin = T_bt @ frames.homogeneous(np.eye(3), [-(width + OCCLUDER_SHARE * width) / 2 - speed * OCCLUSION_START_S,
                                                     0.0, front])
        objects.append(SceneObject(
            name="occluder", kind="box", size_m=(OCCLUDER_SHARE * width, 1.5 * height, 0.004),
            pose_in_base=PoseConfig(xyz=tuple(begin[:3, 3]),
                                    rpy_deg=tuple(np.degrees(frames.matrix_to_euler_xyz(begin[:3, :3])))),
            velocity_mps=tuple(float(v) for v in T_bt[:3, :3] @ np.array([speed, 0.0, 0.0])),
            arrives_at_s=OCCLUSION_START_S, leaves_at_s=OCCLUSION_START_S + OCCLUSION_CROSSING_S))
        # the arm holds while the plate hides too much of the object: the run goes on for as long as it crosses,
        # and ends as target_lost only as long after it cleared as any run
        scenario.target_lost_iterations += math.ceil(OCCLUSION_CROSSING_S * scenario.camera.rate_hz)
    if "swap" in perturb:
        scenario.target = target = msgspec.structs.replace(target, leaves_at_s=SWAP_AT_S)
        objects.append(SceneObject(name="swapped", kind=target.kind.value, size_m=(*target.plane_m, 0.01),
                                   cup=target.cup, texture_seed=SWAP_TEXTURE_SEED, pose_in_base=target.pose_in_base,
                                   arrives_at_s=SWAP_AT_S))
    scenario.objects = [*scenario.objects, *objects]
    if scenario_light is not None:
        scenario.light = scenario_light
    return scenario


def tag_scenario(base: Scenario, start: dict) -> Scenario:
    """The same start with the tag in the object's place, its goal the same camera pose, held to the same threshold."""
    scenario = _placed(base, start)
    scenario.target = msgspec.structs.replace(scenario.target, kind=TargetKind.TAG)
    camera_in_tag = np.linalg.inv(GOAL_IN_CAMERA.matrix())
    scenario.goal = GoalConfig(features=None, camera_in_tag=PoseConfig(
        xyz=tuple(float(v) for v in camera_in_tag[:3, 3]),
        rpy_deg=tuple(float(v) for v in np.degrees(frames.matrix_to_euler_xyz(camera_in_tag[:3, :3])))))
    return scenario


# ------------------------------------------------------------------------------------------------ one start
def truth_camera(scenario: Scenario, q) -> np.ndarray:
    """The camera frame MuJoCo renders from with the arm at ``q`` (model rad), in the base frame."""
    from services.robot_sim.sim import Simulation

    config = stack_config(scenario).robot
    sim = Simulation(config.scene, arm=load_arm(scenario.robot.arm), render=False)
    try:
        sim.reset(sim.arm.model_to_physical_deg(np.asarray(q)))
        return sim.camera_pose()
    finally:
        sim.close()


def pose_error(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """(mm, deg) between two poses."""
    d = np.linalg.inv(a) @ b
    angle = math.degrees(math.acos(max(-1.0, min(1.0, (np.trace(d[:3, :3]) - 1.0) / 2.0))))
    return float(np.linalg.norm(d[:3, 3]) * 1e3), angle


def teach_at(scenario: Scenario, region, name: str) -> dict:
    """The whole teach through a lockstep stack (the real services, composed), as `mfvs teach` runs it."""
    from services.stack.composed import ComposedStack
    from services.vision.teach_client import TeachFailed, teach

    config = stack_config(scenario)
    with ComposedStack(config) as stack:
        session = stack.open_session()
        try:
            result = teach(session, Keys(config.robot.robot_id), name, "markerless experiment", region_px=region)
        except TeachFailed as exc:
            return {"ok": False, "failure": str(exc)}
        finally:
            session.close()
    return {"ok": True, "file": result.file, "goal": result.goal, "digest": result.digest,
            "keypoints": result.keypoints, "planar": result.planar,
            "triangulation_error_px": round(result.triangulation_error_px, 4),
            "probe_mm": [round(v * 1e3, 2) for v in result.probe_m]}


def command_steps(records: list[dict]) -> Optional[float]:
    """The largest change of the commanded linear velocity from one frame to the next while the law acted on both
    (m/s): a point set that changes size (occlusion, fading) must not make the command jump. A frame without the
    target in between is a restart from rest, as at the start (safety's acceleration limit shapes both)."""
    def acting(r: dict) -> bool:
        return r["status"] == "converging" and bool(r["command"])
    steps = [float(np.linalg.norm(np.subtract(b["command"][:3], a["command"][:3])))
             for a, b in zip(records, records[1:]) if acting(a) and acting(b)]
    return round(max(steps), 5) if steps else None


def _kept_points_error(records: list[dict]) -> Optional[float]:
    last = [r for r in records if r.get("keypoints")]
    return last[-1]["keypoints"]["median_error_px"] if last else None


def _swap_figures(records: list[dict], scenario: Scenario) -> dict:
    """After the swap: how many frames the arm went on being commanded, and how far the end effector travelled."""
    kin = ArmKinematics(load_arm(scenario.robot.arm))
    swap_stamp_s = (LOCKSTEP_EPOCH_NS * 1e-9) + SWAP_AT_S  # the scene's time is the arm's, its stamps from the epoch
    after = [r for r in records if r["t_s"] >= swap_stamp_s - 1e-9]
    acting = 0
    for r in after:
        if r["status"] != "converging":
            break
        acting += 1
    path = [kin.pose(np.asarray(r["q"]))[1] for r in after if r.get("q")]
    travel = float(sum(np.linalg.norm(b - a) for a, b in zip(path, path[1:]))) if len(path) > 1 else 0.0
    return {"frames_commanded_after_swap": acting, "travel_after_swap_mm": round(travel * 1e3, 2),
            "held": acting <= 1}


def run_start(task: RunTask, each=None) -> dict:
    """One start's teach, servo and tag runs (in a pool worker or here): its row."""
    from services.servo.run import run

    args = task.args
    base = msgspec.convert(args["base"], Scenario)
    start, perturb, out = args["start"], tuple(args["perturb"]), Path(task.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    row = {"label": task.label, "start": start, "object": base.target.kind.value, "arm": base.robot.arm,
           "perturb": list(perturb)}
    taught_scenario = teach_scenario(base, start, perturb)
    taught = teach_at(taught_scenario, teach_region(base), f"start{start['index']}")
    if not taught["ok"]:
        return {**row, "converged": False, "iterations": 0, "status": "teach_failed", "failure": taught["failure"],
                "teach": taught}
    goal_file = out / "goal.mfvsgoal"
    goal_file.write_bytes(taught.pop("file"))
    row["teach"] = taught
    servo = servo_scenario(base, start, goal_file, perturb)
    result = run(servo, out / "markerless", each, plots=False)
    records = read_log(result.trajectory_log)
    from services.vision.taught import read_goal

    goal, _ = read_goal(goal_file)
    taught_camera = truth_camera(taught_scenario, goal.file.joints)
    final_q = next((r["q"] for r in reversed(records) if r.get("q")), None)
    mm, deg = pose_error(taught_camera, truth_camera(servo, final_q)) if final_q else (None, None)
    row.update({"converged": result.converged, "iterations": result.iterations, "status": result.status,
                "failure": failure(result), "detail": result.detail,
                "final_position_error_mm": None if mm is None else round(mm, 3),
                "final_rotation_error_deg": None if deg is None else round(deg, 3),
                "median_inlier_error_px": _kept_points_error(records),
                "final_error_rms": error_rms(records[-1]) if records else None,
                "inliers": [r["keypoints"]["inliers"] if r.get("keypoints") else 0 for r in records],
                "max_command_step_mps": command_steps(records),
                "front_end": result.front_end, "max_linear_speed_mps": round(result.max_linear_speed_mps, 4),
                "safety": result.safety, "lockstep_timeouts": result.lockstep_timeouts,
                "wall_time_s": result.wall_time_s})
    if "swap" in perturb:
        row.update(_swap_figures(records, servo))
    tag = run(tag_scenario(base, start), out / "tag", None, plots=False)
    row["tag"] = {"converged": tag.converged, "iterations": tag.iterations, "status": tag.status}
    return row


# ------------------------------------------------------------------------------------------------ the experiment
def succeeded(row: dict) -> bool:
    """A run that did what it was to: converged (a swap run: held before the other object, never servoed to it)."""
    if "swap" in row["perturb"]:
        return bool(row.get("held"))
    return bool(row["converged"])


def summarize(rows: list[dict]) -> dict:
    n = len(rows)
    wins = sum(succeeded(r) for r in rows)
    low, high = wilson_interval(wins, n)
    both = [r for r in rows if r["converged"] and r.get("tag", {}).get("converged")]
    ratios = [r["iterations"] / r["tag"]["iterations"] for r in both if r["tag"]["iterations"]]
    converged = [r for r in rows if r["converged"]]
    failures: dict[str, int] = {}
    for r in rows:
        if not succeeded(r):
            failures[r.get("failure") or r["status"]] = failures.get(r.get("failure") or r["status"], 0) + 1
    ms = [r["front_end"]["ms_per_frame"]["p50"] for r in rows if r.get("front_end")]
    summary = {
        "starts": n, "succeeded": wins, "success_rate": round(wins / n, 3) if n else None,
        "wilson_95": [None if low is None else round(low, 3), None if high is None else round(high, 3)],
        "failures": failures,
        "iterations": quartiles([r["iterations"] for r in converged]),
        "tag_iterations": quartiles([r["tag"]["iterations"] for r in both]),
        "iterations_over_tag": quartiles(ratios),
        "final_position_error_mm": quartiles([r["final_position_error_mm"] for r in converged]),
        "final_rotation_error_deg": quartiles([r["final_rotation_error_deg"] for r in converged]),
        "median_inlier_error_px": quartiles([r["median_inlier_error_px"] for r in converged
                                             if r["median_inlier_error_px"] is not None]),
        "front_end_ms_per_frame_p50": quartiles(ms),
        "within_1mm_0.5deg": sum(1 for r in converged if r["final_position_error_mm"] <= 1.0
                                 and r["final_rotation_error_deg"] <= 0.5),
        # what safety did with the commands (its status, sampled at 10 Hz): runs it refused a command in, or stopped
        "safety_refused_runs": sum(1 for r in rows if (r.get("safety") or {}).get("last_refusal")),
        "protective_stops": sum(1 for r in rows if (r.get("safety") or {}).get("protective_stop")),
        "max_linear_speed_mps": max((r.get("max_linear_speed_mps") or 0.0 for r in rows), default=None),
        "max_command_step_mps": quartiles([r["max_command_step_mps"] for r in rows
                                           if r.get("max_command_step_mps") is not None]),
    }
    if any("swap" in r["perturb"] for r in rows):
        summary["held_on_swap"] = sum(bool(r.get("held")) for r in rows)
        summary["travel_after_swap_mm"] = quartiles([r["travel_after_swap_mm"] for r in rows
                                                     if r.get("travel_after_swap_mm") is not None])
    return summary


def run_markerless(kind: str = "plane", texture: Optional[str] = None, count: int = 20, seed: int = 1,
                   arm: Optional[str] = None, perturb: tuple[str, ...] = (), out_dir: Optional[str | Path] = None,
                   jobs: int = 1, progress: Optional[Callable[[str, dict], None]] = None,
                   scenario: Optional[Path] = None) -> dict:
    """The experiment (module doc); its output in the shape every experiment's has (``runs``, ``summary``)."""
    if kind not in OBJECTS:
        raise ValueError(f"--object must be one of {', '.join(OBJECTS)}, not {kind!r}")
    unknown = [p for p in perturb if p not in PERTURBATIONS]
    if unknown:
        raise ValueError(f"unknown perturbation {unknown[0]!r}; known: {', '.join(PERTURBATIONS)}")
    if count < 1:
        raise ValueError("the number of random starts must be at least 1")
    base = base_scenario(kind, texture, arm, scenario)
    stack_config(base)  # a bad texture or scene is refused here, before anything runs
    from services.robot_sim.textures import texture_image

    texture_image(base.target.texture, base.target.texture_seed)
    starts = draw_starts(base, count, seed)
    with tempfile.TemporaryDirectory(prefix="mfvs-markerless-") as scratch:
        root = Path(out_dir) if out_dir is not None else Path(scratch)
        tasks = [RunTask(f"start{s['index']}", base, root / f"start{s['index']}", runner=f"{__name__}:run_start",
                         args={"base": msgspec.to_builtins(base), "start": s, "perturb": list(perturb)})
                 for s in starts]
        done = (lambda task, row: progress(task.label, row)) if progress is not None else None
        rows = run_tasks(tasks, jobs, None, done)
    output = {"experiment": "markerless", "seed": "000",
              "title": f"Markerless teach-by-showing: a {kind}, {count} random starts"
                       + (f", perturbed by {', '.join(perturb)}" if perturb else ""),
              "paper": "Sensors 2022 leaves markerless visual servoing in unstructured environments as future work; "
                       "CNS's classic front end reports success with a 95 % interval over 150 episodes",
              "scenario": str(scenario or BASE_SCENARIO), "object": kind, "texture": texture, "arm": base.robot.arm,
              "random_starts": {"count": count, "seed": seed, "ranges": {
                  "ahead_m": list(TABLE2_LIKE.ahead_m), "off_centre_m": TABLE2_LIKE.off_centre_m,
                  "roll_deg": TABLE2_LIKE.roll_deg, "pitch_deg": TABLE2_LIKE.pitch_deg,
                  "yaw_deg": TABLE2_LIKE.yaw_deg}},
              "perturb": list(perturb), "runs": rows, "summary": summarize(rows),
              "repeatable": all(r.get("lockstep_timeouts", 0) == 0 for r in rows), "report": None, "plots": []}
    if out_dir is not None:
        out = Path(out_dir)
        output["plots"] = [str(p) for p in markerless_plots(rows, out)]
        write_results(output, out, markerless_report)
    return output


def markerless_plots(rows: list[dict], out: Path) -> list[Path]:
    from services.servo.figures import pyplot, save

    plt = pyplot()
    paths: list[Path] = []
    fig, (left, right) = plt.subplots(1, 2, figsize=(11.0, 4.2))
    for row in rows:
        if row.get("inliers"):
            left.plot(row["inliers"], lw=0.8, alpha=0.7)
    left.set_xlabel("iteration")
    left.set_ylabel("inliers")
    left.set_title("the keypoints the front end kept, start by start", fontsize=10)
    left.grid(alpha=0.3)
    both = [r for r in rows if r["converged"] and r.get("tag", {}).get("converged")]
    if both:
        right.scatter([r["tag"]["iterations"] for r in both], [r["iterations"] for r in both], s=14)
        top = max(max(r["tag"]["iterations"], r["iterations"]) for r in both)
        right.plot([0, top], [0, top], ":", color="0.5", label="as many")
        right.plot([0, top], [0, 1.5 * top], "--", color="tab:red", lw=0.8, label="1.5 times")
        right.legend(fontsize=8)
    right.set_xlabel("iterations, the tag on the same start")
    right.set_ylabel("iterations, markerless")
    right.set_title("markerless against the tag", fontsize=10)
    right.grid(alpha=0.3)
    save(fig, out / "markerless.png", paths)
    return paths


def markerless_report(output: dict, out_dir: Path) -> str:
    s = output["summary"]
    rs = output["random_starts"]
    lines = [f"# {output['title']}", "",
             f"`mfvs experiment markerless --object {output['object']} --random-starts {rs['count']} --seed "
             f"{rs['seed']}` on the {output['arm']}" + (f", the print from `{output['texture']}`" if output["texture"]
                                                       else ", the procedural print") + ".", "",
             f"**Succeeded on {s['succeeded']} of {s['starts']}** ({cell(s['success_rate'])}; Wilson 95 % "
             f"{cell(s['wilson_95'])}); failures {cell(s['failures'])}. Final error against MuJoCo's truth "
             f"(median, q3): {cell(s['final_position_error_mm']['median'])} / {cell(s['final_position_error_mm']['q3'])} mm, "
             f"{cell(s['final_rotation_error_deg']['median'])} / {cell(s['final_rotation_error_deg']['q3'])} deg; "
             f"{s['within_1mm_0.5deg']} within 1 mm and 0.5°. Iterations against the tag on the same starts "
             f"(median ratio) {cell(s['iterations_over_tag']['median'])}, largest {cell(s['iterations_over_tag']['max'])}. "
             f"The front end's wall time a frame (median over the runs' medians): "
             f"{cell(s['front_end_ms_per_frame_p50']['median'])} ms.", ""]
    if "held_on_swap" in s:
        lines += [f"Object swapped {SWAP_AT_S:g} s into the servo: held on {s['held_on_swap']} of {s['starts']}, "
                  f"travel after the swap {cell(s['travel_after_swap_mm'])} mm.", ""]
    lines += ["| start | object in the camera (xyz m, rpy deg) | status | iterations | tag | mm | deg | inlier px |",
              "|---|---|---|---|---|---|---|---|"]
    for r in output["runs"]:
        pose = r["start"]["pose_in_camera"]
        lines.append(f"| {r['start']['index']} | {pose['xyz']}, {pose['rpy_deg']} | {r['status']} | "
                     f"{r['iterations']} | {cell(r.get('tag', {}).get('iterations'))} | "
                     f"{cell(r.get('final_position_error_mm'))} | {cell(r.get('final_rotation_error_deg'))} | "
                     f"{cell(r.get('median_inlier_error_px'))} |")
    lines += ["", "## Summary", "", "```json", json.dumps(s, indent=2), "```", "", "## Figures", ""]
    lines += [f"![{Path(p).stem}]({Path(p).relative_to(out_dir).as_posix()})" for p in output["plots"]]
    return "\n".join(lines) + "\n"



