"""The gateway path, measured, with and without another program keeping every core busy: the router, the CAN hub,
robot_sim's emulated actuators and robot_gateway as processes (as deployed), and a stand-in for safety's resend
loop (bench/command_source.py, at realtime priority as safety runs) commanding a constant mixed-frame twist.

Per run: how well the arm tracked the commanded end-effector velocity (the mean velocity over the commanded
motion, from the poses, against the commanded one; and the largest instantaneous deviation), the measured peak
speed against the commanded peak and the arm's limit, and how the bus kept time (late and missed cycles per
second, the gateway's loop work and exchange times, the arm's lock to the host).

``python -m bench.gateway [--json] [--load N] [--seconds S] [--runs R] [--arm NAME]`` or ``mfvs bench gateway``.
``--load``: how many spinning processes (default: a run without and a run with one per core). ``--json`` prints
``{"arm", "runs": [...]}``.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

import numpy as np

from protocol import messages as m
from protocol.keys import Keys
from services.model.kinematics import ArmKinematics
from services.paths import REPO
from services.runtime.transport import open_session
from bench.hogs import cpu_hogs
from bench.stack import measured_arm, unknown_arm
from services.cli.options import add_arm_option
from services.model.arm import DEFAULT_ARM, load_arm
from services.model.limits import arm_limits
from services.robot_sim.service import RobotSimConfig
from services.stack.local import RobotProcesses, RouterProcess

LINEAR = np.array([0.04, -0.03, 0.03])
ROTATIONAL = np.array([0.0, 0.0, 0.2])


def _command_source(endpoint: str, seconds: float) -> subprocess.Popen:
    """The commanded twist: constant, resent every 5 ms from a process at realtime priority (safety's shape)."""
    return subprocess.Popen([sys.executable, "-m", "bench.command_source", "--connect", endpoint, "--linear",
                             *map(str, LINEAR), "--rotational", *map(str, ROTATIONAL), "--seconds", str(seconds)],
                            cwd=REPO)


def _health(client, keys: Keys, name: str):
    for reply in client.get(keys.health(name), timeout=2.0):
        if reply.ok is not None:
            return m.decode(reply.ok.payload.to_bytes(), m.ServiceHealth)
    return None


def run_once(load: int, seconds: float, arm: str = DEFAULT_ARM) -> dict:
    keys = Keys()
    kin = None
    with RouterProcess() as router, RobotProcesses(router.client_config(), RobotSimConfig(arm=arm)):
        client = open_session(router.client_config())
        states: list[m.RobotState] = []
        client.declare_subscriber(keys.robot_state, lambda s: states.append(
            m.decode(s.payload.to_bytes(), m.RobotState)))
        deadline = time.monotonic() + 30
        while len(states) < 20 and time.monotonic() < deadline:
            time.sleep(0.05)
        description = load_arm(measured_arm(arm, {s.arm for s in states}))  # the robot's, as its states declare it
        kin, limit = ArmKinematics(description), arm_limits(description).linear_speed_mps
        with cpu_hogs(load):
            time.sleep(0.3)
            source = _command_source(router.endpoint, seconds)
            source.wait(timeout=seconds + 30)
            time.sleep(0.1)
            gateway, actuators = _health(client, keys, "robot_gateway"), _health(client, keys, "robot_sim")
        snapshot = list(states)
        client.close()
    moving = [s for s in snapshot if s.applied_command is not None]
    steady = moving[int(0.4 * len(moving)):]  # past the acceleration ramp (0.64 m/s²)
    if len(steady) < 10:
        raise RuntimeError(f"too few commanded states ({len(steady)})")
    p0 = np.array([steady[0].pose.X, steady[0].pose.Y, steady[0].pose.Z])
    p1 = np.array([steady[-1].pose.X, steady[-1].pose.Y, steady[-1].pose.Z])
    dt = (steady[-1].header.stamp_ns - steady[0].header.stamp_ns) * 1e-9
    mean_velocity = (p1 - p0) / dt
    instant = np.array([kin.ee_velocity(s.q, s.dq) for s in steady])
    speeds = np.array([kin.ee_speed(s.q, s.dq) for s in snapshot])
    return {
        "arm": arm, "load": load,
        "mean_velocity_error_pct": round(100 * float(np.linalg.norm(mean_velocity - LINEAR) / np.linalg.norm(LINEAR)),
                                         2),
        "max_instant_error_pct": round(100 * float(np.max(np.linalg.norm(instant - LINEAR, axis=1))
                                                   / np.linalg.norm(LINEAR)), 1),
        "peak_speed_mps": round(float(speeds.max()), 4), "commanded_speed_mps": round(float(np.linalg.norm(LINEAR)), 4),
        "speed_limit_mps": limit,
        "late_per_s": round(float(np.mean([s.timing.late_per_s for s in steady])), 2),
        "missed_per_s": round(float(np.mean([s.timing.missed_per_s for s in steady])), 2),
        "gateway": gateway.detail if gateway else None, "gateway_degraded": list(gateway.degraded) if gateway else None,
        "actuators": actuators.detail if actuators else None,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="mfvs bench gateway", description=__doc__.split("\n\n")[0])
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--load", type=int, default=None,
                        help="spinning processes beside the stack (default: 0, then one per core)")
    parser.add_argument("--seconds", type=float, default=3.0, help="commanded motion per run (default 3)")
    parser.add_argument("--runs", type=int, default=3, help="runs per load (default 3)")
    add_arm_option(parser)
    args = parser.parse_args(argv)
    if unknown_arm(parser, args):
        return 2
    loads = [args.load] if args.load is not None else [0, os.cpu_count() or 1]
    runs = [run_once(load, args.seconds, args.arm) for load in loads for _ in range(args.runs)]
    if args.json:
        print(json.dumps({"arm": args.arm, "runs": runs}))
        return 0
    print(f"the gateway profile's robot on the {args.arm}")
    for r in runs:
        print(f"load {r['load']}: mean velocity {r['mean_velocity_error_pct']:.2f} % off (worst instant "
              f"{r['max_instant_error_pct']:.0f} %), peak {r['peak_speed_mps']:.3f} m/s (commanded "
              f"{r['commanded_speed_mps']:.3f}, limit {r['speed_limit_mps']:.3f}), late {r['late_per_s']:.1f}/s, "
              f"missed {r['missed_per_s']:.1f}/s")
        print(f"    gateway:   {r['gateway']}")
        print(f"    actuators: {r['actuators']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
