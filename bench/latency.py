"""End-to-end latency: from image capture to the robot applying the command derived from it, and per hop,
read off the per-hop trace every robot command carries. The stack runs in realtime as separate processes
(`mfvs up`), on a free loopback port.

``python -m bench.latency [--json] [--seconds S] [--profiles sim,gateway] [--arm NAME] [--set SERVICE:KEY=VALUE]``
or ``mfvs bench latency``. ``--json`` prints the first profile's ``{"arm", "e2e_ms": {p50, p99, max, n}, "hops":
{name: {p50, p99, max, n}}, "start": {"e2e_ms": ...}, ...}`` and every profile's under ``"profiles"``; e2e counts each
frame once, at the first robot cycle that applies a command derived from it. ``start`` is the task's first second
(the services warm up before they say they are alive, so it should look like the rest); the measured window
follows it.
"""
from __future__ import annotations

import argparse
import json
import re
import time

import numpy as np

from protocol import messages as m
from protocol.keys import Keys
from services.runtime.service import query_health
from services.runtime.transport import ZenohConfig, open_session
from bench.stack import measured_arm, profile_on_arm, servoing_stack, unknown_arm, with_overrides
from services.cli.options import add_arm_option
from services.stack.launcher import load_profile
from services.model.arm import DEFAULT_ARM
from protocol.keys import ROBOT_SERVICES


def stats(values_ms: list[float]) -> dict:
    """p50, p99, max (ms, rounded to µs) and how many."""
    if not values_ms:
        return {"p50": None, "p99": None, "max": None, "n": 0}
    v = np.sort(values_ms)
    return {"p50": round(float(np.percentile(v, 50)), 3), "p99": round(float(np.percentile(v, 99)), 3),
            "max": round(float(v[-1]), 3), "n": len(v)}


#: the task's first second, reported on its own (``start``) and left out of the measured window
START_S = 1.0


def analyse(states: list[m.RobotState]) -> dict:
    """e2e and hop latencies from robot states whose applied command derives from an image."""
    first: dict[int, m.Header] = {}
    for state in states:
        applied = state.applied_command
        if applied is None or applied.source_stamp_ns == 0 or applied.source_stamp_ns in first:
            continue
        first[applied.source_stamp_ns] = applied
    e2e, hops = [], {}
    for capture, header in first.items():
        trace = header.trace
        names = [h.service for h in trace]
        if names[-1] not in ROBOT_SERVICES:
            continue
        e2e.append((trace[-1].pub_ns - capture) / 1e6)
        previous_name, previous_pub = "capture", capture
        for hop in trace:
            hops.setdefault(f"{previous_name}→{hop.service}", []).append((hop.recv_ns - previous_pub) / 1e6)
            hops.setdefault(hop.service, []).append((hop.pub_ns - hop.recv_ns) / 1e6)
            previous_name, previous_pub = hop.service, hop.pub_ns
    return {"e2e_ms": stats(e2e), "hops": {name: stats(values) for name, values in hops.items()}}


#: ``--target``: the tag (vision's tag front end), or a markerless object (its keypoint front end), taught where it is
TARGETS = ("tag", "plane", "cup")


def run(seconds: float = 10.0, profile: str = "sim", overrides: list[str] | None = None,
        arm: str = DEFAULT_ARM, target: str = "tag") -> dict:
    overrides = list(overrides or [])
    if target != "tag":  # the object where the tag would be; the view taught there, then the task started on it
        overrides.append(f"robot_sim:scene.target.kind={target}")
    stack = with_overrides(profile_on_arm(profile, arm), overrides)
    with servoing_stack(stack, "bench latency", start_task=target == "tag") as endpoint:
        session = open_session(ZenohConfig(connect=[endpoint]))
        if target != "tag":
            from services.stack.launcher import stack_task
            from services.vision.teach_client import teach

            teach(session, Keys(), "bench", "bench latency")
            stack_task(m.START_TASK, operator="bench latency")
        states: list[m.RobotState] = []
        session.declare_subscriber(Keys().robot_state,
                                   lambda s: states.append(m.decode(s.payload.to_bytes(), m.RobotState)))
        time.sleep(START_S)
        start = len(states)
        time.sleep(seconds)
        window = states[start:]
        first_second = states[:start]
        robot_sim = query_health(session, Keys()).get("robot_sim")
        session.close()
    result = analyse(window)
    result["start"] = analyse(first_second)
    result["seconds"] = seconds
    trigger = re.search(r"camera_trigger_ms=\S+ \([^)]*\)", robot_sim.detail) if robot_sim is not None else None
    result["camera_trigger"] = trigger.group(0) if trigger else None
    result["profile"] = profile
    result["target"] = target
    result["arm"] = measured_arm(arm, {state.arm for state in states})
    return result


def run_profiles(seconds: float, profiles: list[str], overrides: list[str], arm: str = DEFAULT_ARM,
                 target: str = "tag") -> dict:
    """The first profile's figures at the top (the format of one), each profile's under ``profiles``. An override
    goes to the profiles that have its service."""
    names = {profile: {s.name for s in load_profile(profile, 0, 0).services} for profile in profiles}
    for override in overrides:
        if not any(override.partition(":")[0] in each for each in names.values()):
            raise ValueError(f"--set {override!r}: no service of {', '.join(profiles)} is called that "
                             f"({', '.join(sorted(set().union(*names.values())))})")
    results = {}
    for profile in profiles:
        results[profile] = run(seconds, profile, [o for o in overrides if o.partition(":")[0] in names[profile]],
                               arm, target)
    return {**results[profiles[0]], "profiles": results}


def print_result(result: dict) -> None:
    e = result["e2e_ms"]
    print(f"{result['profile']} ({result['arm']}, {result.get('target', 'tag')}): end to end (capture → applied): "
          f"p50 {e['p50']} ms, p99 {e['p99']} ms, "
          f"max {e['max']} ms ({e['n']} frames)")
    for name, h in result["hops"].items():
        print(f"  {name:24s} p50 {h['p50']:8.3f} ms  p99 {h['p99']:8.3f} ms  max {h['max']:8.3f} ms")
    print(f"  at the end: {result['camera_trigger']}")
    s = result["start"]["e2e_ms"]
    print(f"  the task's first second: p50 {s['p50']} ms, p99 {s['p99']} ms, max {s['max']} ms ({s['n']} frames)")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="mfvs bench latency", description=__doc__.split("\n\n")[0])
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--seconds", type=float, default=10.0, help="measurement window (s)")
    parser.add_argument("--profiles", default="sim,gateway",
                        help="comma-separated, each measured in turn (default sim,gateway); sim: robot_sim's DSP; "
                             "gateway: robot_gateway over the RS-485 bus hub")
    parser.add_argument("--set", action="append", default=[], metavar="SERVICE:KEY=VALUE",
                        help="a config override for one service, e.g. robot_sim:scene.camera.trigger_offset_ms=4")
    parser.add_argument("--target", default="tag", choices=TARGETS,
                        help="tag (default), or a markerless object (plane, cup) taught where it stands and servoed "
                             "to with the keypoint front end")
    add_arm_option(parser)
    args = parser.parse_args(argv)
    if unknown_arm(parser, args):
        return 2
    profiles = [p.strip() for p in args.profiles.split(",") if p.strip()]
    unknown = [p for p in profiles if p not in ("sim", "gateway")]
    if unknown or not profiles:
        parser.error(f"--profiles takes sim and/or gateway, not {', '.join(unknown) or 'nothing'}")
    try:
        result = run_profiles(args.seconds, profiles, args.set, args.arm, args.target)
    except ValueError as exc:
        parser.error(str(exc))
    if args.json:
        print(json.dumps(result))
    else:
        for each in result["profiles"].values():
            print_result(each)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
