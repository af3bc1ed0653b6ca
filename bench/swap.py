"""The swap, measured: servo scenarios through robot_sim's own DSP and through robot_gateway on the RS-485 bus,
several runs each, with the iterations to converge, the final error, the peak measured end-effector speed
(J(q)·dq of every robot state), the wall time of every run, the servo time and frames answered (a profile whose
loop moves alike but sees fewer frames converges in the same time with fewer iterations), and where the frames
that became no iteration were lost.

Profiles: ``sim-lockstep`` and ``gateway-lockstep`` (deterministic: one run each, and they must agree exactly),
``sim-realtime`` and ``gateway-realtime`` (the gateway's iterations should be within 10 % of the sim's).

``python -m bench.swap [--json] [--runs N] [--scenario FILE ...] [--random-starts N [--seed S] [--base FILE]]
[--arm NAME]`` or ``mfvs bench swap``; without ``--scenario`` or ``--random-starts`` every file in
``examples/scenarios``. Each scenario runs on its own arm (``robot.arm``), as `mfvs servo` runs it; ``--arm NAME``
runs them on that arm (as `mfvs servo --arm`): of the shipped scenarios, those that start another arm at joint
angles of its own are left out (and named); a ``--scenario`` that does is refused.
``--random-starts N`` makes N scenarios no one has seen from ``--base`` (table2 by default): the tag placed at random
in front of the camera as for Table 3 over random starts (:mod:`services.experiments.starts`), each written next to the
results so a start can be run again.

Realtime against lockstep: a lockstep run repeats itself exactly, but its iteration count is one draw from a wide
spread. The last iterations are spent creeping under the arm's velocity dead-band toward a threshold near the
detection's noise floor (Sensors 2022's 5e-5), where the step on which the error first dips under it depends on the
start to a fraction of a millimetre: table2 from a random start took 140 iterations in lockstep, and 143, 145, 156,
163 and 179 with the tag 0.2-1 mm nearer or farther. Realtime's timing jitter is such a perturbation too. So each
lockstep profile also runs ``--nudges`` starts with the tag moved by :data:`NUDGE_M` (each exactly repeatable), and
realtime is compared with the median of that spread; and for every run the iterations until the error first fell
below :data:`APPROACH_FACTOR` times the threshold (``approach``: the motion itself, before the creep), where
the host's delay would show.
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
from pathlib import Path
from typing import Optional

import msgspec

from bench.stack import unknown_arm
from protocol.conventions import ClockMode
from services.paths import SCENARIOS
from services.runtime.config import ConfigError
from services.runtime.progress import ProgressLine
from services.robot_sim.scene import default_target_in_camera
from services.cli.options import add_arm_option
from services.servo.result import error_rms
from services.servo.run import run
from services.servo.scenario import load_scenario, on_arm
from services.experiments.starts import write_starts

#: how far a nudged lockstep start moves the tag (m): about what the arm covers at its top speed in a millisecond
#: of realtime's timing jitter
NUDGE_M = 5e-4
#: ``approach``: iterations until the error first fell below this many times the convergence threshold
APPROACH_FACTOR = 10.0
#: realtime's median iterations within this fraction of lockstep's (issue 17)
REALTIME_TOLERANCE = 0.10
PROFILES = {"sim-lockstep": ("sim", ClockMode.LOCKSTEP), "gateway-lockstep": ("gateway", ClockMode.LOCKSTEP),
            "sim-realtime": ("sim", ClockMode.REALTIME), "gateway-realtime": ("gateway", ClockMode.REALTIME)}


def nudge_offsets(count: int) -> list[tuple[float, float, float]]:
    """``count`` offsets of the tag's start, :data:`NUDGE_M` along ±x, ±y, ±z of its pose's frame in turn, then
    twice as far, and so on: the same every time."""
    offsets = []
    for k in range(count):
        axis, sign, scale = (k // 2) % 3, (1.0 if k % 2 == 0 else -1.0), 1 + k // 6
        offset = [0.0, 0.0, 0.0]
        offset[axis] = sign * scale * NUDGE_M
        offsets.append(tuple(offset))
    return offsets


def nudged(scenario, offset: tuple[float, float, float]):
    """The scenario with the tag's start moved by ``offset`` (m) in the frame its pose is given in (the camera's
    when it gives none: robot_sim's default pose)."""
    target = scenario.target
    field = "pose_in_base" if target.pose_in_base is not None else "pose_in_camera"
    pose = getattr(target, field) or default_target_in_camera()
    moved = msgspec.structs.replace(pose, xyz=tuple(float(a + b) for a, b in zip(pose.xyz, offset)))
    return msgspec.structs.replace(scenario, target=msgspec.structs.replace(target, **{field: moved}))


def first_below(errors: list[float], threshold: float) -> Optional[int]:
    """The 1-based iteration at which the error first fell below ``threshold`` (None if it never did)."""
    return next((i + 1 for i, error in enumerate(errors) if error < threshold), None)


def summarize(rows: list[dict]) -> dict:
    """A profile's runs: how many converged, the median, least and most iterations of those that did, the median
    approach, the peak speed against the robot's limit."""
    converged = [row["iterations"] for row in rows if row["converged"]]
    approaches = [row["approach"] for row in rows if row["approach"] is not None]
    return {
        "runs": rows, "converged": f"{len(converged)}/{len(rows)}",
        "iterations_median": statistics.median(converged) if converged else None,
        "iterations_min": min(converged, default=None), "iterations_max": max(converged, default=None),
        "approach_median": statistics.median(approaches) if approaches else None,
        "peak_speed_mps": max(row["peak_speed_mps"] for row in rows),
        "speed_limit_mps": min((row["speed_limit_mps"] for row in rows if row["speed_limit_mps"]), default=None),
    }


def realtime_against_lockstep(lockstep: dict, realtime: dict) -> Optional[dict]:
    """Realtime's iterations over lockstep's (medians, and realtime's run farthest from lockstep's median), its
    approach over lockstep's, and lockstep's own spread over its nudged starts (least and most over its median):
    ``within`` when every realtime run converged and realtime's median is within :data:`REALTIME_TOLERANCE` of
    lockstep's."""
    if not (lockstep["iterations_median"] and realtime["iterations_median"]):
        return None
    base = lockstep["iterations_median"]
    ratios = [row["iterations"] / base for row in realtime["runs"] if row["converged"]]
    median = realtime["iterations_median"] / base
    approach = (realtime["approach_median"] / lockstep["approach_median"]
                if realtime["approach_median"] and lockstep["approach_median"] else None)
    return {"median": round(median, 3), "worst": round(max(ratios, key=lambda r: abs(r - 1.0)), 3),
            "approach": round(approach, 3) if approach is not None else None,
            "lockstep_spread": [round(lockstep["iterations_min"] / base, 3), round(lockstep["iterations_max"] / base, 3)],
            "within": abs(median - 1.0) <= REALTIME_TOLERANCE and len(ratios) == len(realtime["runs"])}


def scenario_on(path: Path, arm: Optional[str]):
    """The scenario at ``path`` on ``arm`` (None: its own); ValueError when it starts another arm at angles of its
    own (services.servo.on_arm)."""
    return on_arm(load_scenario(path), arm, str(path))


def shipped_for(arm: Optional[str]) -> tuple[list[Path], list[Path]]:
    """The shipped scenarios that run on ``arm`` (all of them for None), and those left out (they start another
    arm at joint angles of its own)."""
    fit, left = [], []
    for path in sorted(SCENARIOS.glob("*.yaml")):
        try:
            scenario_on(path, arm)
            fit.append(path)
        except ValueError:
            left.append(path)
    return fit, left


def measure_scenario(scenario_path: Path, runs: int, profiles: list[str], quiet: bool = False,
                     nudges: int = 0, arm: Optional[str] = None) -> dict:
    """Each profile's runs of one scenario (a lockstep profile: the start as written, then ``nudges`` nudged
    starts), on ``arm`` (None: the scenario's own); on a terminal (unless ``quiet``) a progress line during each
    run."""
    results = {}
    for name in profiles:
        profile, clock = PROFILES[name]
        # lockstep repeats itself exactly: its spread comes from nudged starts, realtime's from the host
        starts = ([(0.0, 0.0, 0.0)] + nudge_offsets(nudges) if clock is ClockMode.LOCKSTEP
                  else [(0.0, 0.0, 0.0)] * runs)
        rows = []
        for offset in starts:
            scenario = scenario_on(scenario_path, arm)
            scenario.clock = clock
            if any(offset):
                scenario = nudged(scenario, offset)
            line = ProgressLine(f"{scenario_path.stem} {name}", scenario.convergence.rms,
                                scenario.convergence.max_iterations, enabled=not quiet)
            errors = []

            def progress(record, line=line, errors=errors):
                errors.append(error_rms(record))
                line.update(record.iteration, errors[-1])

            result = run(scenario, progress=progress, profile=profile)
            line.done()
            rows.append({"converged": result.converged, "status": result.status, "iterations": result.iterations,
                         "nudge_mm": [round(v * 1e3, 3) for v in offset],
                         "approach": first_below(errors, APPROACH_FACTOR * scenario.convergence.rms),
                         "final_error_norm": result.final_error_norm,
                         "peak_speed_mps": round(result.max_linear_speed_mps, 4),
                         # the limit the robot declared in its states, to compare the measured peak with
                         "speed_limit_mps": (result.robot_limits or {}).get("linear_speed_mps"),
                         "wall_time_s": result.wall_time_s, "servo_time_s": result.servo_time_s,
                         "frames_answered": result.frames_answered, "frames_lost": result.frames_lost})
        results[name] = summarize(rows)
    comparison = {}
    for clock in ("lockstep", "realtime"):
        sim, gateway = results.get(f"sim-{clock}"), results.get(f"gateway-{clock}")
        if sim and gateway and sim["iterations_median"] and gateway["iterations_median"]:
            ratios = [row["iterations"] / sim["iterations_median"] for row in gateway["runs"] if row["converged"]]
            comparison[clock] = {"gateway_over_sim": round(gateway["iterations_median"] / sim["iterations_median"], 3),
                                 # the run farthest from the sim's median, either way
                                 "worst_gateway_over_sim": round(max(ratios, key=lambda r: abs(r - 1.0)), 3)}
            if clock == "lockstep":  # start by start, the two must agree to the iteration
                comparison[clock]["identical"] = ([row["iterations"] for row in sim["runs"]]
                                                  == [row["iterations"] for row in gateway["runs"]])
    # what the host's timing costs: realtime against the lockstep runs of the same profile (issue 17: within 10 %)
    realtime_over_lockstep = {}
    for profile in ("sim", "gateway"):
        lockstep, realtime = results.get(f"{profile}-lockstep"), results.get(f"{profile}-realtime")
        if lockstep and realtime:
            compared = realtime_against_lockstep(lockstep, realtime)
            if compared is not None:
                realtime_over_lockstep[profile] = compared
    return {"scenario": str(scenario_path), "arm": scenario_on(scenario_path, arm).robot.arm, "profiles": results,
            "comparison": comparison,
            "realtime_over_lockstep": realtime_over_lockstep}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="mfvs bench swap", description=__doc__.split("\n\n")[0])
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--runs", type=int, default=5, help="runs per realtime profile (default 5)")
    parser.add_argument("--nudges", type=int, default=6,
                        help=f"lockstep runs from starts with the tag moved {NUDGE_M * 1e3:g} mm, beside the start "
                             "as written (default 6: ±x, ±y, ±z; 0: that start alone)")
    parser.add_argument("--scenario", type=Path, action="append",
                        help="scenario YAML, repeatable (default: every file in examples/scenarios)")
    parser.add_argument("--profiles", default=",".join(PROFILES),
                        help=f"comma-separated subset of {', '.join(PROFILES)}")
    parser.add_argument("--random-starts", type=int, default=0, metavar="N",
                        help="N scenarios from random starts (the tag placed at random) instead of the shipped ones")
    parser.add_argument("--seed", type=int, default=1, help="the random starts' draws (default 1)")
    parser.add_argument("--base", type=Path, default=SCENARIOS / "table2.yaml",
                        help="the scenario the random starts vary (default examples/scenarios/table2.yaml)")
    parser.add_argument("--keep", type=Path, metavar="DIR",
                        help="write the random starts' scenario files here (default: a temporary directory)")
    add_arm_option(parser, default=None, what="each scenario's robot.arm")
    args = parser.parse_args(argv)
    if args.arm is not None and unknown_arm(parser, args):
        return 2
    profiles = [p for p in args.profiles.split(",") if p]
    unknown = [p for p in profiles if p not in PROFILES]
    if unknown or args.runs < 1 or args.nudges < 0:
        parser.error(f"unknown profiles {unknown}" if unknown
                     else "--runs must be at least 1" if args.runs < 1 else "--nudges must be at least 0")
    if args.random_starts < 0:
        parser.error("--random-starts must be at least 0")
    try:  # every scenario named, and the random starts' base, on the arm before anything runs
        for path in [*(args.scenario or []), *([args.base] if args.random_starts else [])]:
            scenario_on(path, args.arm)
    except (ConfigError, ValueError) as exc:
        print(f"{parser.prog}: {exc}", file=sys.stderr)
        return 2
    starts_dir = (args.keep or Path(tempfile.mkdtemp(prefix="mfvs-starts-"))) if args.random_starts else None
    scenarios = (args.scenario or []) + ([start.scenario for start in write_starts(
        args.base, args.random_starts, args.seed, starts_dir, command="mfvs bench swap --random-starts",
        arm=args.arm)] if args.random_starts else [])
    if not scenarios:
        scenarios, left_out = shipped_for(args.arm)
        if left_out and not args.json:
            print(f"on the {args.arm}, leaving out {', '.join(p.name for p in left_out)} (they start another arm at "
                  f"joint angles of its own)")
    results = []
    for path in scenarios:
        result = measure_scenario(path, args.runs, profiles, quiet=args.json, nudges=args.nudges, arm=args.arm)
        results.append(result)
        if args.json:
            continue
        print(f"scenario {result['scenario']} on the {result['arm']}")
        if args.random_starts and Path(result["scenario"]).parent == starts_dir:
            print(f"  start: tag at {load_scenario(Path(result['scenario'])).target.pose_in_camera} in the camera")
        for name, r in result["profiles"].items():
            runs = ", ".join(f"{row['iterations']}{'' if row['converged'] else ' (' + row['status'] + ')'}"
                             for row in r["runs"])
            print(f"  {name:17s} converged {r['converged']}, iterations median {r['iterations_median']} "
                  f"(runs: {runs}), peak speed {r['peak_speed_mps']:.3f} m/s (the robot's limit "
                  f"{r['speed_limit_mps']} m/s)",
                  flush=True)
            timing = ", ".join(f"{row['servo_time_s']:.2f} s/{row['frames_answered']}" for row in r["runs"])
            print(f"  {'':17s} servo time / frames answered: {timing}", flush=True)
            lost = "; ".join(", ".join(f"{k} {v}" for k, v in row["frames_lost"].items()) or "-" for row in r["runs"])
            print(f"  {'':17s} frames lost: {lost}", flush=True)
        for clock, c in result["comparison"].items():
            same = {True: ", start by start identical", False: ", NOT identical start by start"}.get(c.get("identical"), "")
            print(f"  {clock}: gateway/sim iterations {c['gateway_over_sim']} (worst run {c['worst_gateway_over_sim']}"
                  f"{same})", flush=True)
        for profile, c in result["realtime_over_lockstep"].items():
            low, high = c["lockstep_spread"]
            print(f"  {profile}: realtime/lockstep iterations {c['median']} (medians; realtime's worst run "
                  f"{c['worst']}; lockstep's own starts {low}-{high}), approach {c['approach']}", flush=True)
    if not args.json:
        outside = [f"{Path(r['scenario']).stem} {profile} {c['median']}" for r in results
                   for profile, c in r["realtime_over_lockstep"].items() if not c["within"]]
        print(f"realtime within {REALTIME_TOLERANCE:.0%} of lockstep (medians) in every scenario: "
              f"{'yes' if not outside else 'no: ' + ', '.join(outside)}")
    if args.json:
        print(json.dumps({"arm": args.arm, "scenarios": results}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
