"""The swap, measured: one servo scenario through robot_sim's own DSP and through robot_gateway on the RS-485
bus, several runs each, with the iterations to converge, the final error and the wall time of every run.

Profiles: ``sim-lockstep`` (deterministic, the reference count), ``sim-realtime`` and ``gateway-realtime``
(the gateway is realtime only, so the fair comparison is with the sim profile in realtime).

``python -m bench.swap [--json] [--runs N] [--scenario FILE]`` or ``mfvs bench swap``.
"""
from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path

from protocol.conventions import ClockMode
from services.servo import load_scenario, run

DEFAULT_SCENARIO = Path(__file__).resolve().parents[1] / "examples" / "scenarios" / "table2.yaml"
PROFILES = {"sim-lockstep": ("sim", ClockMode.LOCKSTEP), "sim-realtime": ("sim", ClockMode.REALTIME),
            "gateway-realtime": ("gateway", ClockMode.REALTIME)}


def measure(scenario_path: Path, runs: int, profiles: list[str]) -> dict:
    results = {}
    for name in profiles:
        profile, clock = PROFILES[name]
        rows = []
        for _ in range(1 if clock is ClockMode.LOCKSTEP else runs):  # lockstep repeats itself exactly
            scenario = load_scenario(scenario_path)
            scenario.clock = clock
            result = run(scenario, profile=profile)
            rows.append({"converged": result.converged, "iterations": result.iterations,
                         "final_error_norm": result.final_error_norm, "wall_time_s": result.wall_time_s})
        converged = [row["iterations"] for row in rows if row["converged"]]
        results[name] = {
            "runs": rows, "converged": f"{len(converged)}/{len(rows)}",
            "iterations_median": statistics.median(converged) if converged else None,
            "iterations_min": min(converged, default=None), "iterations_max": max(converged, default=None),
        }
    return {"scenario": str(scenario_path), "profiles": results}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="mfvs bench swap", description=__doc__.split("\n\n")[0])
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--runs", type=int, default=3, help="runs per realtime profile (default 3)")
    parser.add_argument("--scenario", type=Path, default=DEFAULT_SCENARIO, help="scenario YAML (default table2)")
    parser.add_argument("--profiles", default=",".join(PROFILES),
                        help=f"comma-separated subset of {', '.join(PROFILES)}")
    args = parser.parse_args(argv)
    profiles = [p for p in args.profiles.split(",") if p]
    unknown = [p for p in profiles if p not in PROFILES]
    if unknown or args.runs < 1:
        parser.error(f"unknown profiles {unknown}" if unknown else "--runs must be at least 1")
    result = measure(args.scenario, args.runs, profiles)
    if args.json:
        print(json.dumps(result))
        return 0
    print(f"scenario {result['scenario']}")
    for name, r in result["profiles"].items():
        runs = ", ".join(f"{row['iterations']}{'' if row['converged'] else ' (not converged)'}"
                         for row in r["runs"])
        print(f"  {name:17s} converged {r['converged']}, iterations median {r['iterations_median']} "
              f"(runs: {runs})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
