"""The ``mfvs`` command line (ARCHITECTURE.md lists its stable commands; each lands with the issue that builds it)."""
from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
from importlib.metadata import PackageNotFoundError, version


def _version() -> str:
    try:
        return version("mfvs")
    except PackageNotFoundError:
        return "unknown (not installed)"


def _cmd_router(args: argparse.Namespace) -> int:
    from services.common.transport import Router

    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    with Router(port=args.port, host=args.host, config_file=args.config) as router:
        print(json.dumps({"router": router.endpoint, "zid": router.zid}), flush=True)
        stop.wait()
    return 0


def _cmd_model(args: argparse.Namespace) -> int:
    import numpy as np

    from services.common import frames, jaco2

    if args.what == "urdf":
        sys.stdout.write(jaco2.urdf() + "\n")
        return 0
    lower, upper = jaco2.model_limits()
    T = jaco2.dh_forward_kinematics(jaco2.HOME)
    info = {
        "robot": "j2s7s300",
        "joints": [
            {
                "name": j.name,
                "continuous": j.continuous,
                "limits_physical_deg": None if j.continuous else [j.lower_deg, j.upper_deg],
                "max_speed_dps": j.max_speed_dps,
                "max_torque_nm": j.max_torque_nm,
            }
            for j in jaco2.JOINTS
        ],
        "home_physical_deg": jaco2.HOME_DEG.tolist(),
        "home_ee_xyz_m": np.round(T[:3, 3], 4).tolist(),
        "home_ee_euler_xyz_deg": np.round(np.degrees(frames.matrix_to_euler_xyz(T[:3, :3])), 2).tolist(),
        "straight_reach_m": round(jaco2.STRAIGHT_REACH, 4),
    }
    print(json.dumps(info, indent=2))
    return 0


BENCHMARKS = {"loops": "bench.loops", "vision": "bench.vision"}


def _cmd_bench(args: argparse.Namespace) -> int:
    import importlib

    module = importlib.import_module(BENCHMARKS[args.name])
    return module.main((["--json"] if args.json else []) + args.options)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="mfvs",
        description="Mixed-frame visual servoing for assistive robot arms (Kinova JACO-2) over Eclipse Zenoh.",
    )
    parser.add_argument("--version", action="version", version=f"mfvs {_version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    router = sub.add_parser("router", help="run a zenoh router in the foreground until SIGTERM/SIGINT")
    router.add_argument("--port", type=int, default=7447, help="TCP port to listen on (0: a free one; default 7447)")
    router.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1)")
    router.add_argument("--config", default=None, help="zenoh JSON5 config file (access control, TLS)")
    router.set_defaults(func=_cmd_router)

    model = sub.add_parser("model", help="the JACO-2 j2s7s300 description")
    model.add_argument("what", choices=["urdf", "info"], help="urdf: print the URDF; info: limits, home pose")
    model.set_defaults(func=_cmd_model)

    bench = sub.add_parser("bench", help="run a benchmark and print its figures")
    bench.add_argument("name", choices=sorted(BENCHMARKS),
                       help="loops: robot_sim loop rate, jitter, lockstep speed; vision: detection time per frame")
    bench.add_argument("--json", action="store_true", help="print one JSON object")
    bench.add_argument("options", nargs=argparse.REMAINDER, help="options of the benchmark itself (see --help)")
    bench.set_defaults(func=_cmd_bench)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
