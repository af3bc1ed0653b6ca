"""The robot's 100 Hz loop under load: the sim profile up in realtime with a task running (640×480 frames at 30 Hz
through vision), first as it is, then while another process floods an unrelated key through the same router at
``--rate`` messages a second (small payloads, received by a subscriber of its own, so the router routes every one).

For each phase it prints the robot loop's period (p50, p99, max of the states' own stamps: when the loop ran), the
period at which a separate subscriber receives them (what every service sees) and how long after the loop's tick,
the robot loop's own account (bus cycles per second, late and missed cycles per second, from RobotState.timing)
and, under flood, the rate the flood achieved.

``python -m bench.load [--json] [--seconds S] [--rate N] [--arm NAME]`` or ``mfvs bench load``.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time

import numpy as np

from protocol import messages as m
from protocol.keys import Keys
from bench.latency import stats
from bench.stack import measured_arm, profile_on_arm, servoing_stack, unknown_arm
from services.cli.options import add_arm_option
from services.paths import REPO
from services.model.arm import DEFAULT_ARM
from services.runtime.transport import ZenohConfig, open_session

#: where the flood goes: outside the stack's keys, so no service decodes it
FLOOD_KEY = "bench/flood/payload"

#: run as its own process: publish ``rate`` messages a second for ``seconds`` (in bursts every millisecond) and
#: receive them in a second session; print how many went out and came back
FLOOD = """
import sys, time, zenoh
from services.runtime.transport import ZenohConfig, open_session
endpoint, key, rate, seconds = sys.argv[1], sys.argv[2], float(sys.argv[3]), float(sys.argv[4])
received = [0]
sink = open_session(ZenohConfig(connect=[endpoint]))
sink.declare_subscriber(key, lambda s: received.__setitem__(0, received[0] + 1))
source = open_session(ZenohConfig(connect=[endpoint]))
publisher = source.declare_publisher(key)
payload = bytes(64)
start = time.monotonic()
sent = 0
while (now := time.monotonic()) < start + seconds:
    due = int((now - start) * rate)
    while sent < due:
        publisher.put(payload)
        sent += 1
    time.sleep(0.001)
elapsed = time.monotonic() - start
time.sleep(0.5)
print(sent / elapsed, received[0] / elapsed)
source.close()
sink.close()
"""


def _periods_ms(stamps_ns: list[int]) -> list[float]:
    return list(np.diff(np.asarray(stamps_ns, dtype=np.int64)) / 1e6)


def _phase(states: list[tuple[int, m.RobotState]]) -> dict:
    timing = [s.timing for _, s in states if s.timing is not None]
    return {
        "state_period_ms": stats(_periods_ms([t for t, _ in states])),
        "loop_period_ms": stats(_periods_ms([s.header.stamp_ns for _, s in states])),
        "heard_after_ms": stats([(t - s.header.stamp_ns) / 1e6 for t, s in states]),
        "loop_rate_hz": round(float(np.mean([t.rate_hz for t in timing])), 1) if timing else None,
        "late_per_s": round(float(np.mean([t.late_per_s for t in timing])), 2) if timing else None,
        "missed_per_s": round(float(np.mean([t.missed_per_s for t in timing])), 2) if timing else None,
    }


def run(seconds: float = 10.0, rate: float = 10_000.0, arm: str = DEFAULT_ARM) -> dict:
    with servoing_stack(profile_on_arm("sim", arm), "bench load") as endpoint:
        session = open_session(ZenohConfig(connect=[endpoint]))
        states: list[tuple[int, m.RobotState]] = []
        session.declare_subscriber(Keys().robot_state, lambda s: states.append(
            (time.time_ns(), m.decode(s.payload.to_bytes(), m.RobotState))))
        time.sleep(1.0)  # the task's first second
        mark = len(states)
        time.sleep(seconds)
        quiet = states[mark:]
        mark = len(states)
        flood = subprocess.run([sys.executable, "-c", FLOOD, endpoint, FLOOD_KEY, str(rate), str(seconds)],
                               capture_output=True, text=True, cwd=REPO, timeout=seconds + 60)
        flooded = states[mark:]
        session.close()
    if flood.returncode != 0:
        raise RuntimeError(f"the flood failed: {flood.stderr.strip()[-300:]}")
    sent, received = (float(x) for x in flood.stdout.split())
    return {"arm": measured_arm(arm, {state.arm for _, state in states}), "seconds": seconds, "quiet": _phase(quiet),
            "flood": {**_phase(flooded), "asked_msg_s": rate, "sent_msg_s": round(sent), "received_msg_s":
                      round(received)}}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="mfvs bench load", description=__doc__.split("\n\n")[0])
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--seconds", type=float, default=10.0, help="each phase's length (s)")
    parser.add_argument("--rate", type=float, default=10_000.0, help="flood messages per second")
    add_arm_option(parser)
    args = parser.parse_args(argv)
    if unknown_arm(parser, args):
        return 2
    result = run(args.seconds, args.rate, args.arm)
    if args.json:
        print(json.dumps(result))
        return 0
    print(f"the sim stack on the {result['arm']}, {result['seconds']:g} s a phase")
    for name in ("quiet", "flood"):
        r = result[name]
        loop, heard = r["loop_period_ms"], r["state_period_ms"]
        extra = (f"; flood {r['sent_msg_s']} msg/s sent, {r['received_msg_s']} received" if name == "flood" else "")
        after = r["heard_after_ms"]
        print(f"{name:6s} robot loop period p50 {loop['p50']} ms, p99 {loop['p99']} ms, max {loop['max']} ms; "
              f"states heard every p50 {heard['p50']} ms, p99 {heard['p99']} ms, max {heard['max']} ms "
              f"({heard['n']}), {after['p50']}/{after['p99']} ms after the loop's tick; bus {r['loop_rate_hz']} "
              f"cycles/s, late {r['late_per_s']}/s, missed {r['missed_per_s']}/s{extra}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
