"""``mfvs experiment NAME``: seed 000's experiments, each a comparison of laws from one start, run through the real
services in lockstep (so every run, and every rerun, is the same to the bit), reported beside the paper.

=========  ================================================================================================
table3     Table 3: the four laws with the paper's gains; iterations to ‖e‖ < 5e-5, beside 446/189/114/79
part-a     Part A: the end-effector twist sent as if it were mixed (the conventional mistake) diverges; the
           mixed law converges
part-b     Part B: an outstretched start near the workspace's boundary: the joint law against the mixed law
part-c     Part C: a start whose straight-line motion would pass through the base's protection zone
part-d     Part D: the mixed twist realised in joint space through Jm⁺ (eq. 26); iterations, straightness
=========  ================================================================================================

Each experiment has a default start (``examples/scenarios/``); ``--scenario`` runs the same comparison from a
user's start and goal, with each run's law and gains the experiment's own. The result is one JSON shape for every
experiment (:func:`run_experiment`); with an output directory each run's log and figures go in a folder of their
own, and the comparison's figures and a ``report.md`` beside them.
"""
from __future__ import annotations

import json
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Optional

import msgspec
import numpy as np

from protocol.conventions import ClockMode
from services.controller.law import Gains
from services.plots import comparison_plots
from services.servo import Scenario, ServoResult, load_scenario, run

SCENARIOS = Path(__file__).resolve().parent.parent / "examples" / "scenarios"

#: seed 000 Table 3: the gains of each law and the iterations it took to converge on the real JACO-2
TABLE3_GAINS = {
    "p-joint": Gains(lambda_=1.2),
    "adaptive-p-joint": Gains(lambda0=2.0, lambda_inf=0.2, slope0=30.0, kd=0.0),
    "adaptive-pd-joint": Gains(lambda0=2.8, lambda_inf=0.3, slope0=30.0, kd=0.25),
    "adaptive-pd-mixed": Gains(lambda0=4.5, lambda_inf=0.5, slope0=30.0, kd=0.55),
}
TABLE3_PAPER = {"p-joint": 446, "adaptive-p-joint": 189, "adaptive-pd-joint": 114, "adaptive-pd-mixed": 79}
PROPOSED = TABLE3_GAINS["adaptive-pd-mixed"]
#: manipulability below which a run counts as having met a singularity
SINGULAR_MANIPULABILITY = 0.01


@dataclass
class RunSpec:
    label: str
    law: str
    gains: Gains


@dataclass
class Experiment:
    name: str
    title: str
    #: what the paper reports, in a sentence (the report prints it above the table)
    paper: str
    scenario: str
    runs: list[RunSpec]
    #: the summary of the runs (label → run row): what the paper reports, as figures
    summarize: Callable[[dict], dict]
    zone_distance: bool = False


def improvement_pct(better: Optional[int], baseline: Optional[int]) -> Optional[float]:
    """How many fewer iterations ``better`` took than ``baseline``, in % of the baseline."""
    if not better or not baseline:
        return None
    return round(100.0 * (baseline - better) / baseline, 1)


def straightness(records: list[dict]) -> Optional[float]:
    """How far from straight the features' image trajectories are: the largest, over the four points, of the path
    length over the distance from start to end (1.0: a straight line)."""
    points = np.array([r["points"] for r in records if len(r["points"]) == 4])
    if len(points) < 2:
        return None
    ratios = []
    for i in range(4):
        path = points[:, i, :]
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
    return result.status  # tag_lost, diverged, max_iterations, ...


def _row(spec: RunSpec, result: ServoResult, records: list[dict]) -> dict:
    return {
        "label": spec.label, "law": spec.law, "converged": result.converged,
        "iterations": result.iterations, "status": result.status, "final_error_norm": result.final_error_norm,
        "detail": result.detail, "initial_error_norm": result.initial_error_norm,
        "max_error_norm": result.max_error_norm,
        "error_growth": (round(result.max_error_norm / result.initial_error_norm, 3)
                         if result.initial_error_norm else None),
        "failure": failure(result), "limits_met": limits_met(result),
        "min_manipulability": round(result.min_manipulability, 5),
        "min_zone_distance_m": (None if result.min_zone_distance_m is None
                                else round(result.min_zone_distance_m, 4)),
        "max_linear_speed_mps": round(result.max_linear_speed_mps, 4),
        "straightness": straightness(records),
        "servo_time_s": result.servo_time_s,
        "gains": msgspec.to_builtins(spec.gains),
    }


# ------------------------------------------------------------------------------------------------ summaries
def _table3_summary(rows: dict) -> dict:
    iterations = {law: rows[law]["iterations"] if rows[law]["converged"] else None for law in TABLE3_PAPER}
    ordered = [iterations[law] for law in TABLE3_PAPER]
    in_order = all(v is not None for v in ordered) and all(a > b for a, b in zip(ordered, ordered[1:]))
    return {
        "iterations": iterations,
        "paper_iterations": dict(TABLE3_PAPER),
        "improvement_pct": improvement_pct(iterations["adaptive-pd-mixed"], iterations["adaptive-pd-joint"]),
        "paper_improvement_pct": improvement_pct(TABLE3_PAPER["adaptive-pd-mixed"],
                                                 TABLE3_PAPER["adaptive-pd-joint"]),
        "in_paper_order": in_order,
        "relative_to_paper": {law: (round(v / TABLE3_PAPER[law], 3) if v else None)
                              for law, v in iterations.items()},
    }


def _part_a_summary(rows: dict) -> dict:
    ee, mixed = rows["ee-frame"], rows["adaptive-pd-mixed"]
    ee_failed = not ee["converged"]
    return {
        "ee_frame_failed": ee_failed, "ee_frame_status": ee["status"], "ee_frame_error_growth": ee["error_growth"],
        "ee_frame_tag_left_image": ee["status"] in ("tag_lost", "diverged"),
        "ee_frame_iterations_before_failure": ee["iterations"],
        "mixed_converged": mixed["converged"], "mixed_iterations": mixed["iterations"],
        "as_in_paper": ee_failed and mixed["converged"],
    }


def _joint_vs_mixed_summary(rows: dict) -> dict:
    joint, mixed = rows["adaptive-pd-joint"], rows["adaptive-pd-mixed"]
    return {
        "joint_converged": joint["converged"], "joint_iterations": joint["iterations"],
        "joint_failure": joint["failure"],
        "joint_limits_met": joint["limits_met"],
        "mixed_converged": mixed["converged"], "mixed_iterations": mixed["iterations"],
        "mixed_failure": mixed["failure"],
        "mixed_limits_met": mixed["limits_met"],
        "min_zone_distance_m": {label: row["min_zone_distance_m"] for label, row in rows.items()},
        "as_in_paper": mixed["converged"] and not joint["converged"],
    }


def _part_d_summary(rows: dict) -> dict:
    d, mixed = rows["mixed-jacobian-joint"], rows["adaptive-pd-mixed"]
    return {
        "converged": d["converged"], "iterations": d["iterations"], "paper_iterations": 154,
        "straightness": d["straightness"], "mixed_straightness": mixed["straightness"],
        "mixed_iterations": mixed["iterations"], "paper_mixed_iterations": 79,
        "slower_than_mixed": bool(d["converged"] and mixed["converged"] and d["iterations"] > mixed["iterations"]),
    }


def _joint_and_mixed(gains: Gains = TABLE3_GAINS["adaptive-pd-joint"]) -> list[RunSpec]:
    return [RunSpec("adaptive-pd-joint", "adaptive-pd-joint", gains),
            RunSpec("adaptive-pd-mixed", "adaptive-pd-mixed", PROPOSED)]


EXPERIMENTS: dict[str, Experiment] = {e.name: e for e in (
    Experiment("table3", "Table 3: effect of the adaptive gain on convergence",
               "446, 189, 114 and 79 iterations; the mixed law 31 % fewer than the joint PD law",
               "table2.yaml", [RunSpec(law, law, gains) for law, gains in TABLE3_GAINS.items()], _table3_summary),
    Experiment("part-a", "Part A: the need for the mixed frame",
               "the end-effector-frame twist diverges and the features leave the image; the mixed law converges "
               "(47 iterations)", "table2.yaml",
               [RunSpec("ee-frame", "ee-frame", PROPOSED), RunSpec("adaptive-pd-mixed", "adaptive-pd-mixed", PROPOSED)],
               _part_a_summary),
    Experiment("part-b", "Part B: the arm outstretched, near the workspace's boundary",
               "the joint law fails near the 25th iteration (joint limits, singularity: abrupt joint velocities); the "
               "mixed law converges smoothly", "part_b.yaml", _joint_and_mixed(), _joint_vs_mixed_summary),
    Experiment("part-c", "Part C: near the base, where the straight path crosses the protection zone",
               "the mixed law converges, gliding over the base's safety zone (the features take a curved route)",
               "part_c.yaml", _joint_and_mixed(), _joint_vs_mixed_summary, zone_distance=True),
    Experiment("part-d", "Part D: the mixed twist realised in joint space (eq. 26)",
               "converges in 154 iterations with a wavy image trajectory (the mixed Cartesian law: 79)",
               "table2.yaml", [RunSpec("mixed-jacobian-joint", "mixed-jacobian-joint", PROPOSED),
                               RunSpec("adaptive-pd-mixed", "adaptive-pd-mixed", PROPOSED)], _part_d_summary),
)}


def _copy(scenario: Scenario) -> Scenario:
    return msgspec.convert(msgspec.to_builtins(scenario), Scenario)


def run_experiment(name: str, scenario_path: Optional[str | Path] = None, out_dir: Optional[str | Path] = None,
                   progress: Optional[Callable[[str, ServoResult], None]] = None, profile: str = "sim") -> dict:
    """Run experiment ``name`` from its start (or ``scenario_path``'s start and goal); ``progress(label, result)``
    after each run. Returns ``{"experiment", "title", "paper", "scenario", "runs": [...], "summary": {...},
    "report", "plots"}``."""
    if name not in EXPERIMENTS:
        raise KeyError(f"unknown experiment {name!r}; known: {', '.join(EXPERIMENTS)}")
    experiment = EXPERIMENTS[name]
    path = Path(scenario_path) if scenario_path is not None else SCENARIOS / experiment.scenario
    base = load_scenario(path)
    base.clock = ClockMode.LOCKSTEP  # every experiment is a function of its scenario
    base.law_options = {}
    rows: dict[str, dict] = {}
    trajectories: dict[str, list[dict]] = {}
    with tempfile.TemporaryDirectory(prefix=f"mfvs-{name}-") as scratch:
        root = Path(out_dir) if out_dir is not None else Path(scratch)
        for spec in experiment.runs:
            scenario = _copy(base)
            scenario.law, scenario.gains = spec.law, spec.gains
            result = run(scenario, root / spec.label, profile=profile, plots=out_dir is not None)
            records = [json.loads(line) for line in Path(result.trajectory_log).read_text().splitlines()]
            trajectories[spec.label] = records
            rows[spec.label] = _row(spec, result, records)
            rows[spec.label]["plots"] = result.plots if out_dir is not None else []
            if progress is not None:
                progress(spec.label, result)
        output = {"experiment": name, "title": experiment.title, "paper": experiment.paper, "scenario": str(path),
                  "profile": profile, "runs": list(rows.values()), "summary": experiment.summarize(rows),
                  "report": None, "plots": []}
        if out_dir is not None:
            out = Path(out_dir)
            plots = comparison_plots(trajectories, out, title=experiment.title,
                                     threshold=base.convergence.error_norm, zone_distance=experiment.zone_distance,
                                     goal=base.goal.features, camera=base.camera)
            output["plots"] = [str(p) for p in plots]
            report = out / "report.md"
            report.write_text(report_markdown(output, out))
            output["report"] = str(report)
            (out / "result.json").write_text(json.dumps(output, indent=2) + "\n")
    return output


# ------------------------------------------------------------------------------------------------ the report
def _cell(value) -> str:
    if value is None:
        return "–"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        return f"{value:.3g}" if (abs(value) < 1e-3 or abs(value) >= 1e4) and value != 0 else f"{value:.4g}"
    if isinstance(value, dict):
        return ", ".join(f"{k} {v}" for k, v in value.items()) or "–"
    return str(value)


def report_markdown(output: dict, out_dir: Path) -> str:
    """The experiment's report: what the paper reports, the table of runs, the summary, the figures."""
    name = output["experiment"]
    lines = [f"# {output['title']}", "",
             f"`mfvs experiment {name}` from `{output['scenario']}` ({output['profile']} profile, lockstep: the "
             "same run every time).", "", f"**Seed 000 reports:** {output['paper']}.", ""]
    if name == "table3":
        summary = output["summary"]
        lines += ["| law | gains | iterations | paper | ratio to paper |", "|---|---|---|---|---|"]
        for row in output["runs"]:
            law = row["law"]
            gains = {k: v for k, v in row["gains"].items()
                     if (k == "lambda") == (law == "p-joint") and not (k == "kd" and v == 0.0)}
            lines.append(f"| {law} | {_cell(gains)} | {_cell(summary['iterations'][law])} | "
                         f"{TABLE3_PAPER[law]} | {_cell(summary['relative_to_paper'][law])} |")
        lines += ["", f"adaptive-pd-mixed took **{_cell(summary['improvement_pct'])} %** fewer iterations than "
                      f"adaptive-pd-joint (paper: {summary['paper_improvement_pct']} %); in the paper's order: "
                      f"{_cell(summary['in_paper_order'])}.", ""]
    columns = ("label", "converged", "iterations", "status", "final_error_norm", "error_growth", "failure",
               "limits_met", "min_manipulability", "min_zone_distance_m", "straightness")
    lines += ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    for row in output["runs"]:
        lines.append("| " + " | ".join(_cell(row[c]) for c in columns) + " |")
    lines += ["", "Why each run ended:", ""]
    lines += [f"- **{row['label']}**: {row['status']}" + (f": {row['detail']}" if row["detail"] else "")
              for row in output["runs"]]
    lines += ["", "## Summary", "", "```json", json.dumps(output["summary"], indent=2), "```", "", "## Figures", ""]
    for plot in output["plots"]:
        rel = Path(plot).relative_to(out_dir)
        lines.append(f"![{rel.stem}]({rel.as_posix()})")
    for row in output["runs"]:
        if row["plots"]:
            lines += ["", f"### {row['label']}", ""]
            lines += [f"![{row['label']} {Path(p).stem}]({Path(p).relative_to(out_dir).as_posix()})"
                      for p in row["plots"]]
    lines.append("")
    return "\n".join(lines)
