"""RS-485 actuator bus benchmark (robot_sim's actuators on a python-can virtual bus, in realtime):

* the actuators' 500 Hz cycle: achieved rate and period jitter (|period − 2 ms|) while the host commands them;
* request → reply latency of one full exchange: a 0x14 to each of the seven actuators until all 21 replies
  (0x15, 0x16, 0x17 each) are back, and of a single position query.

``python -m bench.rs485 [--json] [--seconds S]`` or ``mfvs bench rs485``.
"""
from __future__ import annotations

import argparse
import json
import time

import numpy as np

from services.common.metrics import LoopTimer
from services.common.rs485_bus import BusConfig, RS485Bus
from services.robot_gateway.link import ActuatorLink
from services.robot_sim.bus_runner import BusRunner
from services.robot_sim.sim import Simulation


def _stats(ms: list[float]) -> dict:
    v = np.sort(ms)
    return {"p50": round(float(np.percentile(v, 50)), 3), "p99": round(float(np.percentile(v, 99)), 3),
            "max": round(float(v[-1]), 3), "n": len(v)}


def run(seconds: float = 5.0) -> dict:
    channel = f"bench-rs485-{time.monotonic_ns()}"
    runner = BusRunner(Simulation(render=False), BusConfig(channel=channel)).start()
    host = RS485Bus(BusConfig(channel=channel))
    link = ActuatorLink(host, timeout_s=0.1)
    try:
        time.sleep(0.5)
        runner.loop_timer = LoopTimer(0.002)
        positions = link.positions_deg()
        exchange_ms, query_ms = [], []
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            t = time.perf_counter()
            link.command(positions)
            exchange_ms.append((time.perf_counter() - t) * 1e3)
            t = time.perf_counter()
            link.positions_deg()
            query_ms.append((time.perf_counter() - t) * 1e3)
            time.sleep(0.002)
        loop = runner.loop_timer.stats()
    finally:
        host.close()
        runner.stop()
    return {"cycle_rate_hz": round(loop["rate_hz"], 2), "cycle_jitter_ms_p50": round(loop["jitter_ms_p50"], 3),
            "cycle_jitter_ms_p99": round(loop["jitter_ms_p99"], 3),
            "cycle_jitter_ms_max": round(loop["jitter_ms_max"], 3),
            "exchange_ms": _stats(exchange_ms), "position_query_ms": _stats(query_ms), "seconds": seconds}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="mfvs bench rs485", description=__doc__.split("\n\n")[0])
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--seconds", type=float, default=5.0, help="measurement window (s)")
    args = parser.parse_args(argv)
    result = run(args.seconds)
    if args.json:
        print(json.dumps(result))
    else:
        print(f"actuator cycle: {result['cycle_rate_hz']:.2f} Hz (nominal 500), period jitter p50 "
              f"{result['cycle_jitter_ms_p50']:.3f} ms, p99 {result['cycle_jitter_ms_p99']:.3f} ms, max "
              f"{result['cycle_jitter_ms_max']:.3f} ms")
        for name in ("exchange_ms", "position_query_ms"):
            s = result[name]
            label = "0x14 ×7 → 21 replies" if name == "exchange_ms" else "position query ×7 → 7 replies"
            print(f"{label}: p50 {s['p50']:.3f} ms, p99 {s['p99']:.3f} ms, max {s['max']:.3f} ms ({s['n']})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
