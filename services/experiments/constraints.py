"""Muñoz 2018's experiment (``mfvs experiment constraints``): one task in which every constraint type binds,
with exact gradients and with 30 % gradient error (eq. 49), run by the sliding-mode law; the figures of each run
(max φ against the chattering band, time active)."""
from __future__ import annotations

import hashlib
import json
import statistics
from pathlib import Path

from services.experiments.figures import constraint_plots
from services.experiments.spec import Experiment, RunSpec
from services.servo.result import ServoResult
from services.servo.scenario import Scenario


# ------------------------------------------------------------------------------------------------ Muñoz 2018
#: Muñoz 2018 eq. 49's error in the robustness runs
GRADIENT_ERROR = 0.3


def constraint_figures(records: list[dict]) -> dict:
    """Per constraint type, from the sliding-mode law's notes of every iteration: the largest φ and the band
    T_s·u⁺ (eq. 43) it is held to (the median over the run; T_s is the frame period), whether every iteration's
    φ stayed within that iteration's band, the largest σ (the constraint itself, exact under gradient error) and
    the time the type was active (s)."""
    notes = [r["notes"] for r in records if r.get("notes")]
    kinds = sorted({key.split(".", 1)[1] for n in notes for key in n if key.startswith("max_phi.")})
    out = {}
    for kind in kinds:
        steps = [n for n in notes if f"max_phi.{kind}" in n]
        phis = [n[f"max_phi.{kind}"] for n in steps]
        bands = [n[f"band.{kind}"] for n in steps]
        out[kind] = {
            "max_phi": round(max(phis), 6), "band": round(statistics.median(bands), 6),
            "held": all(phi <= band for phi, band in zip(phis, bands)),
            "max_sigma": round(max(n[f"max_sigma.{kind}"] for n in steps), 6),
            "active_s": round(sum(n.get("Ts", 0.0) for n in steps if n.get(f"active.{kind}", 0) > 0), 3),
        }
    return out


def _constraints_run(scenario: Scenario, result: ServoResult, records: list[dict]) -> dict:
    periods = [r["notes"]["Ts"] for r in records if r.get("notes", {}).get("Ts")]
    return {"constraints": constraint_figures(records),
            "gradient_error": scenario.law_options.get("gradient_error", 0.0),
            "law_rate_hz": round(1.0 / statistics.median(periods), 2) if periods else None}


def _trajectory_digest(records: list[dict]) -> str:
    """A fingerprint of a run's joint trajectory (two runs differ when theirs do)."""
    return hashlib.sha1(json.dumps([r["q"] for r in records]).encode()).hexdigest()[:16]


def _constraints_summary(rows: dict, trajectories: dict) -> dict:
    exact, erroneous = rows["exact-gradients"], rows["gradient-error-30"]
    kinds = sorted(set(exact["constraints"]) | set(erroneous["constraints"]))

    def every(row, test):
        return all(k in row["constraints"] and test(row["constraints"][k]) for k in kinds)

    return {
        "held": every(exact, lambda c: c["held"]) and every(erroneous, lambda c: c["held"]),
        "held_by_run": {label: {k: c["held"] for k, c in row["constraints"].items()} for label, row in rows.items()},
        "sigma_within_band": {label: every(row, lambda c: c["max_sigma"] <= c["band"]) for label, row in rows.items()},
        "every_type_active": {label: every(row, lambda c: c["active_s"] > 0) for label, row in rows.items()},
        "never_active": {label: [k for k in kinds if row["constraints"].get(k, {}).get("active_s", 0) == 0]
                         for label, row in rows.items()},
        "completed": {label: row["converged"] for label, row in rows.items()},
        "runs_differ": _trajectory_digest(trajectories["exact-gradients"])
        != _trajectory_digest(trajectories["gradient-error-30"]),
        "law_rate_hz": exact["law_rate_hz"],
        "paper": "every constraint fulfilled (max φ ≤ 0 up to the chattering band T_s·u⁺), also with 30 % "
                 "gradient error; up to three constraints active at a time",
    }


def _constraints_figures(trajectories: dict, rows: dict, out: Path, base: Scenario) -> list:
    return constraint_plots(trajectories, out, law_options=base.law_options, camera=base.camera,
                            goal=base.goal.features)


#: Muñoz 2018's: every constraint type in one task
EXPERIMENTS = (
    Experiment("constraints", "Muñoz 2018: every constraint type held by the sliding-mode law, with and without "
               "gradient error",
               "all the constraints fulfilled (max φ ≤ 0 up to the chattering band), also with 30 % gradient "
               "error (eq. 49)", "constraints.yaml",
               [RunSpec("exact-gradients", "smc", options={"gradient_error": 0.0}),
                RunSpec("gradient-error-30", "smc", options={"gradient_error": GRADIENT_ERROR})],
               _constraints_summary, seed="002", keep_law_options=True, run_figures=_constraints_run,
               figures=_constraints_figures),
)
