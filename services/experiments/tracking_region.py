"""Nelson 1995's experiment (``mfvs experiment tracking-region``): a target moving at 10 cm/s tracked on two
translational axes without the manipulability term, and on four with it; how far each tracked it before failing,
and why (joint limit, singularity, the tag beyond what vision can see)."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from services.experiments.figures import tracking_plots
from services.experiments.spec import Experiment, RunSpec, SINGULAR_MANIPULABILITY
from services.model.arm import load_arm
from services.robot_sim.scene import target_in_base
from services.servo.figures import with_points
from services.servo.result import ServoResult
from services.servo.scenario import Scenario, stack_config


# ------------------------------------------------------------------------------------------------ Nelson 1995
#: Nelson 1995: two-axis tracking without avoidance lost the target after 0.94 m; four axes with avoidance tracked
#: the whole 5 m of the lab ("an approximate ten fold increase")
TRACKING_PAPER = {"baseline_distance_m": 0.94, "full_distance_m": 5.0, "ratio": 10.0}


#: the window before a run's end in which its failure's cause is looked for (s)
FAILURE_WINDOW_S = 1.0


def _tracking_run(scenario: Scenario, result: ServoResult, records: list[dict]) -> dict:
    """How far the target travelled while it was tracked, why tracking ended, and how close the arm came to a
    singularity and to its joint limits."""
    speed = float(np.linalg.norm(scenario.target.velocity_mps))
    seen = [r for r in with_points(records) if r["status"] in ("converging", "converged")]
    start_ns = records[0]["stamp_ns"] if records else 0
    tracked_s = (seen[-1]["stamp_ns"] - start_ns) * 1e-9 if seen else 0.0
    end_ns = records[-1]["stamp_ns"] if records else 0
    window = [r for r in records if (end_ns - r["stamp_ns"]) * 1e-9 <= FAILURE_WINDOW_S]
    arm = load_arm(scenario.robot.arm)
    nearest = {id(r): float(arm.limit_margins_deg(r["q"]).min()) for r in records if r.get("q")}
    faults = {fault for r in window for fault in r.get("robot_faults", [])}
    if result.status == "max_iterations":
        failure = None  # the target's path ended with the target still tracked
    elif "joint_limit" in faults or any(nearest.get(id(r), math.inf) < 1.0 for r in window):
        failure = "joint_limit"
    elif "singularity" in faults or any(r["manipulability"] < SINGULAR_MANIPULABILITY for r in window):
        failure = "singularity"
    elif seen and beyond_vision(seen[-1]["points"], scenario.camera.fx):
        failure = "vision_range"  # too small or too oblique to detect: where Nelson 1995's own runs ended too
    else:
        failure = "tag_left_image" if result.status in ("target_lost", "diverged") else result.status
    w_primes = [r["notes"]["w_prime"] for r in records if "w_prime" in r.get("notes", {})]
    last_sides = _tag_sides_px(seen[-1]["points"], scenario.camera.fx) if seen else None
    return {"distance_m": round(speed * tracked_s, 3), "tracked_s": round(tracked_s, 2),
            "target_speed_mps": round(speed, 4), "failure": failure,
            "ended": "path_end" if failure is None else "failed",
            "min_w_prime": min(w_primes) if w_primes else None,
            "min_joint_margin_deg": round(min(nearest.values()), 2) if nearest else None,
            "last_tag_side_px": None if last_sides is None else round(float(last_sides.mean()), 1)}


#: a tag whose sides are shorter than this in the image, or foreshortened below this ratio (about 60° from
#: facing the camera), is at the edge of what vision detects reliably
VISION_MIN_SIDE_PX = 30.0


VISION_MIN_FORESHORTENING = 0.5


def _tag_sides_px(points, fx: float) -> np.ndarray:
    corners = np.asarray(points, dtype=float)
    return fx * np.linalg.norm(corners - np.roll(corners, -1, axis=0), axis=1)


def beyond_vision(points, fx: float) -> bool:
    sides = _tag_sides_px(points, fx)
    return bool(sides.mean() < VISION_MIN_SIDE_PX or sides.min() / sides.max() < VISION_MIN_FORESHORTENING)


def _tracking_summary(rows: dict, trajectories: dict) -> dict:
    baseline, full = rows["two-axis"], rows["four-axis-avoidance"]
    ratio = round(full["distance_m"] / baseline["distance_m"], 2) if baseline["distance_m"] > 0 else None
    return {
        "distance_ratio": ratio,
        "distance_m": {label: row["distance_m"] for label, row in rows.items()},
        "failure": {label: row["failure"] for label, row in rows.items()},
        "min_w_prime": {label: row["min_w_prime"] for label, row in rows.items()},
        "min_joint_margin_deg": {label: row["min_joint_margin_deg"] for label, row in rows.items()},
        "full_reached_path_end": full["failure"] is None,
        "paper": dict(TRACKING_PAPER),
    }


def _tracking_figures(trajectories: dict, rows: dict, out: Path, base: Scenario) -> list:
    arm = load_arm(base.robot.arm)
    start = target_in_base(stack_config(base).robot.scene, arm)[:3, 3]
    return tracking_plots(trajectories, out, arm=arm, target_start=start, target_velocity=base.target.velocity_mps,
                          failures={label: row["failure"] for label, row in rows.items()})


#: Nelson 1995's: the tracking region
EXPERIMENTS = (
    Experiment("tracking-region", "Nelson 1995: the tracking region grown by singularity and joint-limit avoidance",
               "two-axis tracking failed after 0.94 m (joint limit, singularity); four-axis tracking with the "
               "manipulability term followed the target over the lab's whole 5 m: about ten-fold",
               "tracking_region.yaml",
               [RunSpec("two-axis", "manipulability",
                        options={"tracking_axes": ["vx", "vy"], "avoidance_axes": [], "S": 0.0}),
                RunSpec("four-axis-avoidance", "manipulability",
                        options={"tracking_axes": ["vx", "vy", "wx", "wy"], "avoidance_axes": ["vx", "vy"]})],
               _tracking_summary, seed="004", keep_law_options=True, run_figures=_tracking_run,
               figures=_tracking_figures),
)
