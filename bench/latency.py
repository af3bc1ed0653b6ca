"""End-to-end latency: from image capture to the robot applying the command derived from it, and per hop,
read off the per-hop trace every robot command carries. The stack runs in realtime as separate processes
(`mfvs up`), on a free loopback port.

``python -m bench.latency [--json] [--seconds S] [--profiles sim,gateway] [--arm NAME] [--set SERVICE:KEY=VALUE]
[--source servo|jog]`` (jog: a person's stick's path from its request, and the arm's stop times after a release and
after the stream stops)
or ``mfvs bench latency``. ``--json`` prints the first profile's ``{"arm", "e2e_ms": {p50, p99, max, n}, "hops":
{name: {p50, p99, max, n}}, "start": {"e2e_ms": ...}, ...}`` and every profile's under ``"profiles"``; e2e counts each
frame once, at the first robot cycle that applies a command derived from it. ``start`` is the task's first second
(the services warm up before they say they are alive, so it should look like the rest); the measured window
follows it.
"""
from __future__ import annotations

import argparse
import json
import math
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


def analyse(states: list[m.RobotState], origin: str = "capture") -> dict:
    """e2e and hop latencies from robot states whose applied command derives from an image (``origin`` capture), or
    from a person's stick (``request``: a jog's source stamp is when its device was last heard, each request's own
    time when the device is read at every slot)."""
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
        previous_name, previous_pub = origin, capture
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


#: the stick's to-and-fro during the jog window: along the base's Y at the slowest level, the dead-man held
JOG_SWEEP_S = 2.0


def run_jog(seconds: float = 10.0, profile: str = "sim", overrides: list[str] | None = None,
            arm: str = DEFAULT_ARM) -> dict:
    """The person's path: a scripted stick (services/jog) streamed at 50 Hz to the stack with no task, from its request
    to the robot applying it; then how long the arm takes to come to rest after a release and after the stream
    stops (``stops``: s, each from the request that ended it to the first state at rest)."""
    import threading

    from services.jog.client import run_stick
    from services.jog.config import JogConfig
    from services.jog.script import script_from_mapping
    from services.jog.sender import script_reader

    stack = with_overrides(profile_on_arm(profile, arm), list(overrides or []))
    sweep = [{"for_s": JOG_SWEEP_S / 2, "mode": "translation", "axes": [0, 1, 0], "deadman": True},
             {"for_s": JOG_SWEEP_S / 2, "axes": [0, -1, 0], "deadman": True}]
    n = max(1, math.ceil((START_S + seconds) / JOG_SWEEP_S))
    steps = sweep * n + [{"for_s": 1.0, "deadman": False}] + sweep[:1] + [
        {"for_s": 1.0, "axes": [0, -1, 0], "deadman": True, "device": "silent"}]
    script = script_from_mapping({"rate_hz": 50, "speed_level": 1, "steps": steps})
    with servoing_stack(stack, "bench latency", start_task=False) as endpoint:
        session = open_session(ZenohConfig(connect=[endpoint]))
        states: list[m.RobotState] = []
        jogs: list[m.Jog] = []
        session.declare_subscriber(Keys().robot_state,
                                   lambda s: states.append(m.decode(s.payload.to_bytes(), m.RobotState)))
        session.declare_subscriber(Keys().desired_jog, lambda s: jogs.append(m.decode(s.payload.to_bytes(), m.Jog)))
        time.sleep(0.5)
        sender = threading.Thread(target=run_stick, args=(session, Keys(), JogConfig(), script_reader(script), 50.0))
        sender.start()
        sender.join(timeout=script.duration_s + 30)
        time.sleep(1.0)
        session.close()
    t0 = jogs[0].header.stamp_ns
    released = next(j for j in jogs if not j.deadman)  # the sweeps hold the dead-man throughout
    window_start, window_end = t0 + int(START_S * 1e9), released.header.stamp_ns
    applied_in = [s for s in states if window_start <= s.header.stamp_ns <= window_end]
    result = analyse(applied_in, origin="request")
    result["start"] = analyse([s for s in states if t0 <= s.header.stamp_ns < window_start], origin="request")
    last_before_silence = max((j for j in jogs if j.deadman and j.header.stamp_ns > released.header.stamp_ns),
                              key=lambda j: j.header.stamp_ns)
    result["stops"] = {"released_s": _rest_after(states, released.header.stamp_ns),
                       "stale_s": _rest_after(states, last_before_silence.header.stamp_ns)}
    result["direction"] = _direction_errors([j for j in jogs if j.header.stamp_ns < window_end], states)
    result.update(seconds=seconds, profile=profile, target="jog", camera_trigger=None,
                  arm=measured_arm(arm, {state.arm for state in states}))
    return result


#: s: a sweep's motion is judged from this long after its first request (the spasm filter's ramp and the arm's
#: acceleration) to its last
JOG_SETTLE_S = 0.5


def _direction_errors(jogs: list[m.Jog], states: list[m.RobotState]) -> dict:
    """How far the hand's measured base-frame velocity points from what each held sweep asked (the distance between
    the unit directions: 0.05 is about 2.9°), in each sweep's steady part; and the hand's turning meanwhile."""
    from services.model.arm import load_arm
    from services.model.kinematics import ArmKinematics

    sweeps: list[list[m.Jog]] = []
    for jog in jogs:
        if not jog.deadman or not any(jog.linear):
            continue
        if sweeps and np.sign(sweeps[-1][-1].linear).tolist() == np.sign(jog.linear).tolist():
            sweeps[-1].append(jog)
        else:
            sweeps.append([jog])
    errors, turning, kin = [], [], None
    for sweep in sweeps:
        asked = np.array(sweep[0].linear) / np.linalg.norm(sweep[0].linear)
        begin, end = sweep[0].header.stamp_ns + int(JOG_SETTLE_S * 1e9), sweep[-1].header.stamp_ns
        for state in states:
            if begin <= state.header.stamp_ns <= end:
                kin = kin or ArmKinematics(load_arm(state.arm))
                R, _, J = kin.pose_and_jacobian(np.array(state.q))
                twist = J @ np.array(state.dq)
                if np.linalg.norm(twist[:3]) > 0.0:
                    errors.append(float(np.linalg.norm(twist[:3] / np.linalg.norm(twist[:3]) - asked)))
                    turning.append(float(np.linalg.norm(twist[3:])))
    if not errors:
        return {"states": 0}
    return {"states": len(errors), "sweeps": len(sweeps), "p50": round(float(np.median(errors)), 4),
            "max": round(max(errors), 4), "turning_max_rps": round(max(turning), 4)}


def _rest_after(states: list[m.RobotState], from_ns: int) -> float | None:
    """Seconds from ``from_ns`` to the first state at rest (the hand under 2 mm/s) after it."""
    from services.model.arm import load_arm
    from services.model.kinematics import ArmKinematics

    kin = None
    for state in states:
        if state.header.stamp_ns < from_ns:
            continue
        kin = kin or ArmKinematics(load_arm(state.arm))
        if kin.ee_speed(state.q, state.dq) < 2e-3:
            return round((state.header.stamp_ns - from_ns) * 1e-9, 4)
    return None


def run_profiles(seconds: float, profiles: list[str], overrides: list[str], arm: str = DEFAULT_ARM,
                 target: str = "tag", source: str = "servo") -> dict:
    """The first profile's figures at the top (the format of one), each profile's under ``profiles``. An override
    goes to the profiles that have its service."""
    names = {profile: {s.name for s in load_profile(profile, 0, 0).services} for profile in profiles}
    for override in overrides:
        if not any(override.partition(":")[0] in each for each in names.values()):
            raise ValueError(f"--set {override!r}: no service of {', '.join(profiles)} is called that "
                             f"({', '.join(sorted(set().union(*names.values())))})")
    results = {}
    for profile in profiles:
        mine = [o for o in overrides if o.partition(":")[0] in names[profile]]
        results[profile] = run_jog(seconds, profile, mine, arm) if source == "jog" else run(seconds, profile, mine,
                                                                                             arm, target)
    return {**results[profiles[0]], "profiles": results}


def print_result(result: dict) -> None:
    e = result["e2e_ms"]
    path = "request → applied" if result.get("target") == "jog" else "capture → applied"
    print(f"{result['profile']} ({result['arm']}, {result.get('target', 'tag')}): end to end ({path}): "
          f"p50 {e['p50']} ms, p99 {e['p99']} ms, "
          f"max {e['max']} ms ({e['n']} frames)")
    for name, h in result["hops"].items():
        print(f"  {name:24s} p50 {h['p50']:8.3f} ms  p99 {h['p99']:8.3f} ms  max {h['max']:8.3f} ms")
    if result.get("direction", {}).get("states"):
        d = result["direction"]
        print(f"  the hand's direction against the stick's ({d['sweeps']} sweeps, {d['states']} states in their steady "
              f"parts): p50 {d['p50']}, max {d['max']} (0.05 ≈ 2.9°); turning at most {d['turning_max_rps']} rad/s")
    if result.get("stops"):
        stops = result["stops"]
        print(f"  at rest after the dead-man's release: {stops['released_s']} s; after the stream stopped: "
              f"{stops['stale_s']} s")
    else:
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
    parser.add_argument("--source", default="servo", choices=("servo", "jog"),
                        help="servo (default): the visual servo's path from the image; jog: a person's stick's, from "
                             "its request (a scripted stick, no task), and its stop times")
    add_arm_option(parser)
    args = parser.parse_args(argv)
    if unknown_arm(parser, args):
        return 2
    profiles = [p.strip() for p in args.profiles.split(",") if p.strip()]
    unknown = [p for p in profiles if p not in ("sim", "gateway")]
    if unknown or not profiles:
        parser.error(f"--profiles takes sim and/or gateway, not {', '.join(unknown) or 'nothing'}")
    try:
        result = run_profiles(args.seconds, profiles, args.set, args.arm, args.target, args.source)
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
