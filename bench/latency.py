"""End-to-end latency: from image capture to the robot applying the command derived from it, and per hop,
read off the per-hop trace every robot command carries. The stack runs in realtime as separate processes
(`mfvs up`), on a free loopback port.

``python -m bench.latency [--json] [--seconds S] [--profile sim|gateway]`` or ``mfvs bench latency``. ``--json`` prints
``{"e2e_ms": {p50, p99, max, n}, "hops": {name: {p50, p99, max, n}}}``; e2e counts each frame once, at the
first robot cycle that applies a command derived from it.
"""
from __future__ import annotations

import argparse
import json
import os
import tempfile
import time

import numpy as np

from protocol import messages as m
from protocol.keys import Keys
from services.runtime.transport import ZenohConfig, free_loopback_port, open_session
from services.launcher import down, load_profile, stack_task, up


def _stats(values_ms: list[float]) -> dict:
    if not values_ms:
        return {"p50": None, "p99": None, "max": None, "n": 0}
    v = np.sort(values_ms)
    return {"p50": round(float(np.percentile(v, 50)), 3), "p99": round(float(np.percentile(v, 99)), 3),
            "max": round(float(v[-1]), 3), "n": len(v)}


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
        if names[-1] != "robot_sim" and names[-1] != "robot_gateway":
            continue
        e2e.append((trace[-1].pub_ns - capture) / 1e6)
        previous_name, previous_pub = "capture", capture
        for hop in trace:
            hops.setdefault(f"{previous_name}→{hop.service}", []).append((hop.recv_ns - previous_pub) / 1e6)
            hops.setdefault(hop.service, []).append((hop.pub_ns - hop.recv_ns) / 1e6)
            previous_name, previous_pub = hop.service, hop.pub_ns
    return {"e2e_ms": _stats(e2e), "hops": {name: _stats(values) for name, values in hops.items()}}


def run(seconds: float = 10.0, profile: str = "sim") -> dict:
    previous = os.environ.get("MFVS_RUN_DIR")
    with tempfile.TemporaryDirectory(prefix="mfvs-latency-") as directory:
        os.environ["MFVS_RUN_DIR"] = directory
        port = free_loopback_port()
        try:
            code, message = up(load_profile(profile, port, free_loopback_port()), "realtime")
            if code:
                raise RuntimeError(message)
            stack_task(m.START_TASK, operator="bench latency")  # the stack comes up idle
            session = open_session(ZenohConfig(connect=[f"tcp/127.0.0.1:{port}"]))
            states: list[m.RobotState] = []
            session.declare_subscriber(Keys().robot_state,
                                       lambda s: states.append(m.decode(s.payload.to_bytes(), m.RobotState)))
            time.sleep(2.0)  # warm-up
            start = len(states)
            time.sleep(seconds)
            window = states[start:]
            session.close()
        finally:
            down()
            if previous is None:
                os.environ.pop("MFVS_RUN_DIR", None)
            else:
                os.environ["MFVS_RUN_DIR"] = previous
    result = analyse(window)
    result["seconds"] = seconds
    result["profile"] = profile
    return result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="mfvs bench latency", description=__doc__.split("\n\n")[0])
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--seconds", type=float, default=10.0, help="measurement window (s)")
    parser.add_argument("--profile", choices=["sim", "gateway"], default="sim",
                        help="sim: robot_sim's DSP; gateway: robot_gateway over the RS-485 bus hub")
    args = parser.parse_args(argv)
    result = run(args.seconds, args.profile)
    if args.json:
        print(json.dumps(result))
    else:
        e = result["e2e_ms"]
        print(f"end to end (capture → applied): p50 {e['p50']} ms, p99 {e['p99']} ms, max {e['max']} ms "
              f"({e['n']} frames)")
        for name, h in result["hops"].items():
            print(f"  {name:24s} p50 {h['p50']:8.3f} ms  p99 {h['p99']:8.3f} ms  max {h['max']:8.3f} ms")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
