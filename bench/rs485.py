"""RS-485 actuator bus benchmark (robot_sim's actuators answering a host, in realtime):

* the actuators' 500 Hz cycle: achieved rate and period jitter (|period − 2 ms|) while the host commands them;
* request → reply latency of one full exchange: a 0x14 to each of the seven actuators until all 21 replies
  (0x15, 0x16, 0x17 each) are back, and of a single position query;
* the host's bus period (``--period``: 2, 2.5, 3.33 or 5 ms, the gateway's ``bus.period_ms``): the exchanges are
  paced on it, and the share of them whose replies were all back within it says whether the bus sustains it.

Transports: ``virtual`` (python-can's in-process bus, the actuators in a thread of this process) or ``hub`` (the
deploy shape of the gateway profile: the actuators in a robot_sim process, frames through the mfvs CAN hub).

``python -m bench.rs485 [--json] [--seconds S] [--period MS] [--transport virtual|hub] [--arm NAME]`` or
``mfvs bench rs485``.
"""
from __future__ import annotations

import argparse
import json
import time

import numpy as np

from services.runtime.metrics import LoopTimer
from services.robot.hardware import DEFAULT_TIMING, BusTiming
from services.robot.rs485_bus import BusConfig, RS485Bus
from bench.stack import detail_fields, unknown_arm
from services.cli.options import add_arm_option
from services.model.arm import DEFAULT_ARM, load_arm
from services.robot_gateway.link import ActuatorLink
from services.stack.local import simulated_link


def _stats(ms: list[float]) -> dict:
    v = np.sort(ms)
    return {"p50": round(float(np.percentile(v, 50)), 3), "p99": round(float(np.percentile(v, 99)), 3),
            "max": round(float(v[-1]), 3), "n": len(v)}


def _measure(link: ActuatorLink, seconds: float, timing: BusTiming = DEFAULT_TIMING) -> tuple[list[float],
                                                                                              list[float]]:
    """Exchanges paced on ``timing``'s period, a position query after each (within the same period)."""
    positions = link.positions_deg()
    exchange_ms, query_ms = [], []
    start = time.monotonic()
    end, k = start + seconds, 0
    while time.monotonic() < end:
        t = time.perf_counter()
        link.command(positions)
        exchange_ms.append((time.perf_counter() - t) * 1e3)
        t = time.perf_counter()
        link.positions_deg()
        query_ms.append((time.perf_counter() - t) * 1e3)
        k += 1
        time.sleep(max(0.0, start + k * timing.period_s - time.monotonic()))
        k = max(k, int((time.monotonic() - start) / timing.period_s))  # woke a period or more late: this slot
    return exchange_ms, query_ms


def _period_fields(timing: BusTiming, exchange_ms: list[float]) -> dict:
    return {"host_period_ms": timing.period_ms,
            "exchanges_within_period": round(float(np.mean(np.asarray(exchange_ms) <= timing.period_s * 1e3)), 4)}


def run_hub(seconds: float = 5.0, arm: str = DEFAULT_ARM, timing: BusTiming = DEFAULT_TIMING) -> dict:
    """``arm``'s actuators in a robot_sim process (actuator_bus mode), this process the host, the hub between."""
    import subprocess
    import sys

    from services.tools.can_hub import CanHub
    from services.runtime.transport import Router
    from services.stack.launcher import status
    from services.paths import REPO

    with Router(port=0) as router, CanHub() as hub:
        config = BusConfig(interface="mfvs_hub", channel=hub.channel)
        sim = subprocess.Popen([sys.executable, "-m", "services.robot_sim", "--connect", router.endpoint,
                                "--set", f"arm={arm}", "--set", "mode=actuator_bus", "--set", "bus.interface=mfvs_hub",
                                "--set", f"bus.channel={hub.channel}", "--set", f"bus.period_ms={timing.period_ms}"],
                               cwd=REPO,
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        host = RS485Bus(config)
        try:
            link = ActuatorLink(host, load_arm(arm).bus_addresses, timeout_s=0.1)
            deadline = time.monotonic() + 60.0
            while True:  # until the actuators answer (the process loads MuJoCo first)
                try:
                    link.positions_deg()
                    break
                except Exception:
                    if time.monotonic() > deadline or sim.poll() is not None:
                        raise RuntimeError("robot_sim's actuators did not answer on the hub") from None
                    time.sleep(0.2)
            time.sleep(1.0)
            exchange_ms, query_ms = _measure(link, seconds, timing)
            health = status(router.endpoint).get("robot_sim")
            detail = detail_fields(health.detail if health else None)
        finally:
            host.close()
            sim.terminate()
            sim.wait(timeout=20)
    return {"transport": "hub", "arm": arm, "actuators": len(link.addresses),
            "cycle_rate_hz": float(detail.get("bus_cycle_rate_hz", "nan")),
            "cycle_jitter_ms_p99": float(detail.get("jitter_ms_p99", "nan")),
            "exchange_ms": _stats(exchange_ms), "position_query_ms": _stats(query_ms), "seconds": seconds,
            **_period_fields(timing, exchange_ms)}


def run(seconds: float = 5.0, arm: str = DEFAULT_ARM, timing: BusTiming = DEFAULT_TIMING) -> dict:
    with simulated_link(timeout_s=0.1, settle_s=0.5, arm=load_arm(arm)) as (runner, link):
        runner.loop_timer = LoopTimer(0.002)
        runner.set_host_period(timing.period_s)
        exchange_ms, query_ms = _measure(link, seconds, timing)
        loop = runner.loop_timer.stats()
    return {"transport": "virtual", "arm": arm, "actuators": len(link.addresses),
            "cycle_rate_hz": round(loop["rate_hz"], 2),
            "cycle_jitter_ms_p50": round(loop["jitter_ms_p50"], 3),
            "cycle_jitter_ms_p99": round(loop["jitter_ms_p99"], 3),
            "cycle_jitter_ms_max": round(loop["jitter_ms_max"], 3),
            "exchange_ms": _stats(exchange_ms), "position_query_ms": _stats(query_ms), "seconds": seconds,
            **_period_fields(timing, exchange_ms)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="mfvs bench rs485", description=__doc__.split("\n\n")[0])
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--seconds", type=float, default=5.0, help="measurement window (s)")
    parser.add_argument("--transport", choices=["virtual", "hub"], default="virtual",
                        help="virtual: one process; hub: robot_sim's actuators in their own process, via the hub")
    parser.add_argument("--period", type=float, default=DEFAULT_TIMING.period_ms,
                        help="the host's bus period (ms): 2, 2.5, 3.33 or 5 (the gateway's bus.period_ms)")
    add_arm_option(parser)
    args = parser.parse_args(argv)
    if unknown_arm(parser, args):
        return 2
    try:
        timing = BusTiming.from_period_ms(args.period)
    except ValueError as exc:
        parser.error(str(exc))
    result = (run(args.seconds, args.arm, timing) if args.transport == "virtual"
              else run_hub(args.seconds, args.arm, timing))
    if args.json:
        print(json.dumps(result))
    else:
        if result["transport"] == "virtual":
            print(f"{result['arm']}'s {result['actuators']} actuators: cycle {result['cycle_rate_hz']:.2f} Hz (nominal 500), "
                  f"period jitter p50 "
                  f"{result['cycle_jitter_ms_p50']:.3f} ms, p99 {result['cycle_jitter_ms_p99']:.3f} ms, max "
                  f"{result['cycle_jitter_ms_max']:.3f} ms")
        else:
            print(f"{result['arm']}'s {result['actuators']} actuators (robot_sim process, via the CAN hub): cycle "
                  f"{result['cycle_rate_hz']:.2f} Hz (nominal "
                  f"500), period jitter p99 {result['cycle_jitter_ms_p99']:.3f} ms")
        for name in ("exchange_ms", "position_query_ms"):
            s = result[name]
            n = result["actuators"]
            label = f"0x14 ×{n} → {3 * n} replies" if name == "exchange_ms" else f"position query ×{n} → {n} replies"
            print(f"{label}: p50 {s['p50']:.3f} ms, p99 {s['p99']:.3f} ms, max {s['max']:.3f} ms ({s['n']})")
        print(f"host bus period {result['host_period_ms']:g} ms: {100 * result['exchanges_within_period']:.1f} % of "
              f"the exchanges had every reply back within it")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
