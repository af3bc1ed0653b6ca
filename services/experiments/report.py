"""An experiment's output on disk: its JSON and ``report.md`` (the runs' table beside what the paper reports)."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Callable

from services.experiments.mixed_frame import TABLE3_PAPER
from services.experiments.tracking_region import TRACKING_PAPER


def write_results(output: dict, out: Path, markdown: Callable[[dict, Path], str]) -> None:
    """An experiment's ``report.md`` (``markdown(output, out)``) and ``result.json`` in ``out``, beside its figures;
    ``output["report"]`` names the report."""
    report = out / "report.md"
    report.write_text(markdown(output, out))
    output["report"] = str(report)
    (out / "result.json").write_text(json.dumps(output, indent=2) + "\n")


# ------------------------------------------------------------------------------------------------ the report
def cell(value) -> str:
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
             "same run every time).", "", f"**Seed {output['seed']} reports:** {output['paper']}.", ""]
    if not output["repeatable"]:
        lines += ["**Not repeatable:** the arm went on without the pipeline's answer at some ticks (lockstep "
                  "timeouts: the host was too loaded); a rerun may differ.", ""]
    if name == "table3":
        summary = output["summary"]
        lines += ["| law | gains | iterations | paper | ratio to paper |", "|---|---|---|---|---|"]
        for row in output["runs"]:
            law = row["law"]
            gains = {k: v for k, v in row["gains"].items()
                     if (k == "lambda") == (law == "p-joint") and not (k == "kd" and v == 0.0)}
            lines.append(f"| {law} | {cell(gains)} | {cell(summary['iterations'][law])} | "
                         f"{TABLE3_PAPER[law]} | {cell(summary['relative_to_paper'][law])} |")
        lines += ["", f"adaptive-pd-mixed took **{cell(summary['improvement_pct'])} %** fewer iterations than "
                      f"adaptive-pd-joint (paper: {summary['paper_improvement_pct']} %); in the paper's order: "
                      f"{cell(summary['in_paper_order'])}.", ""]
    if name == "constraints":
        lines += ["| run | constraint | max φ | band T_s·u⁺ | held | max σ | active (s) |", "|---|---|---|---|---|---|---|"]
        for row in output["runs"]:
            for kind, c in row["constraints"].items():
                lines.append(f"| {row['label']} | {kind} | {cell(c['max_phi'])} | {cell(c['band'])} | "
                             f"{cell(c['held'])} | {cell(c['max_sigma'])} | {cell(c['active_s'])} |")
        summary = output["summary"]
        lines += ["", f"Held in both runs: **{cell(summary['held'])}**; every type active: "
                      f"{cell(summary['every_type_active'])}; the two runs differ: {cell(summary['runs_differ'])}; "
                      f"the law ran at {cell(summary['law_rate_hz'])} Hz.", ""]
    if name == "tracking-region":
        lines += ["| run | distance tracked (m) | failure | min w'(q) | min joint-limit margin (deg) |",
                  "|---|---|---|---|---|"]
        for row in output["runs"]:
            lines.append(f"| {row['label']} | {cell(row['distance_m'])} | {row['failure'] or 'none (path end)'} | "
                         f"{cell(row['min_w_prime'])} | {cell(row['min_joint_margin_deg'])} |")
        lines += ["", f"Ratio of distances: **{cell(output['summary']['distance_ratio'])}** (paper: about "
                      f"{TRACKING_PAPER['ratio']:g}, 0.94 m against the lab's whole 5 m).", ""]
    columns = ("label", "converged", "iterations", "status", "final_error_norm", "error_growth", "failure",
               "limits_met", "min_manipulability", "min_zone_distance_m", "straightness")
    lines += ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    for row in output["runs"]:
        lines.append("| " + " | ".join(cell(row[c]) for c in columns) + " |")
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
