"""What an experiment is (:class:`Experiment`: its runs, :class:`RunSpec`, the scenario they start from, how its
rows are summarised) and the row every run gives (:func:`run_row`: iterations, failure, limits met, straightness)."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional

import msgspec
import numpy as np

from services.controller.law import Gains
from services.servo.figures import point_tracks, with_points
from services.servo.result import ServoResult
from services.servo.scenario import Scenario


#: manipulability below which a run counts as having met a singularity
SINGULAR_MANIPULABILITY = 0.01


@dataclass
class RunSpec:
    label: str
    law: str
    gains: Gains = field(default_factory=Gains)
    #: law options set over the scenario's (or over none, for an experiment that replaces them)
    options: dict = field(default_factory=dict)


@dataclass
class Experiment:
    name: str
    title: str
    #: what the paper reports, in a sentence (the report prints it above the table)
    paper: str
    scenario: str
    runs: list[RunSpec]
    #: the summary of the runs (label → run row, label → trajectory records): what the paper reports, as figures
    summarize: Callable[[dict, dict], dict]
    zone_distance: bool = False
    seed: str = "000"
    #: the scenario's law options are the case (its constraints, its tuning): runs set theirs over them
    keep_law_options: bool = False
    #: figures of one run beyond the common row (scenario as run, result, trajectory records) → row fields
    run_figures: Optional[Callable[[Scenario, ServoResult, list], dict]] = None
    #: the experiment's own figures (trajectories, rows, out dir, base scenario) → paths
    figures: Optional[Callable[[dict, dict, Path, Scenario], list]] = None
    #: it also runs over random starts (``--random-starts N``): the law it proposes and the one it improves on
    random_starts: Optional[tuple[str, str]] = None


def improvement_pct(better: Optional[int], baseline: Optional[int]) -> Optional[float]:
    """How many fewer iterations ``better`` took than ``baseline``, in % of the baseline."""
    if not better or not baseline:
        return None
    return round(100.0 * (baseline - better) / baseline, 1)


def straightness(records: list[dict]) -> Optional[float]:
    """How far from straight the features' image trajectories are: the largest, over the points (by id) measured
    at two frames at least, of the path length over the distance from start to end (1.0: a straight line)."""
    ratios = []
    for path in point_tracks(with_points(records)).values():
        if len(path) < 2:
            continue
        length = float(np.sum(np.linalg.norm(np.diff(path, axis=0), axis=1)))
        chord = float(np.linalg.norm(path[-1] - path[0]))
        if chord > 1e-9:
            ratios.append(length / chord)
    return round(max(ratios), 4) if ratios else None


def limits_met(result: ServoResult) -> dict:
    """What the arm's limits did in a run, by cause (joint_limit, singularity, zone, speed, acceleration,
    dead_band): at how many iterations' ticks each shaped the motion. (Safety's refusals are in the run's status
    and ``last_refusal``, frame by frame; its status messages come at their own rate and are not counted here.)"""
    met: dict[str, int] = {}
    for name, count in result.robot_limits_hit.items():
        cause = "zone" if name.startswith("zone:") else name
        met[cause] = met.get(cause, 0) + count
    return met


def failure(result: ServoResult) -> Optional[str]:
    """Why a run failed, by cause (protective stop, zone, joint limit, singularity, tag lost, not converged), or
    None when it converged."""
    if result.converged:
        return None
    if result.safety.get("protective_stop"):
        return "protective_stop"
    refusal = result.last_refusal if result.status == "refused" else ""
    met = limits_met(result)
    if "zone" in refusal:
        return "zone"
    if "joint_limit" in refusal or "joint_limit" in met:
        return "joint_limit"
    if "singularity" in met or result.min_manipulability < SINGULAR_MANIPULABILITY:
        return "singularity"
    return result.status  # target_lost, diverged, max_iterations, ...


def run_row(spec: RunSpec, result: ServoResult, records: list[dict], scenario_arm: str) -> dict:
    return {
        "label": spec.label, "law": spec.law, "converged": result.converged,
        "iterations": result.iterations, "status": result.status, "final_error_norm": result.final_error_norm,
        "detail": result.detail, "initial_error_norm": result.initial_error_norm,
        "max_error_norm": result.max_error_norm,
        "error_growth": (round(result.max_error_norm / result.initial_error_norm, 3)
                         if result.initial_error_norm else None),
        "failure": failure(result), "limits_met": limits_met(result),
        # iterations whose law output the controller scaled down to the arm's speed limits
        "saturated_iterations": sum(1 for r in records if r.get("saturated")),
        "min_manipulability": round(result.min_manipulability, 5),
        "min_zone_distance_m": (None if result.min_zone_distance_m is None
                                else round(result.min_zone_distance_m, 4)),
        "max_linear_speed_mps": round(result.max_linear_speed_mps, 4),
        "straightness": straightness(records),
        "servo_time_s": result.servo_time_s,
        "lockstep_timeouts": result.lockstep_timeouts,
        "gains": msgspec.to_builtins(spec.gains),
        "arm": scenario_arm,
        "options": dict(spec.options),
    }
