"""The command line of :mod:`services.observe`: ``mfvs echo``, ``hz``, ``keys``, ``record``, ``replay``, ``view``."""
from __future__ import annotations

import json
import sys
import time

from protocol.keys import Keys
from protocol.topics import UnknownTopic, matching


def add_parsers(sub, add_connection_options, operator_session, stack_connection, service_graph=None) -> None:
    """``stack_connection(args)`` fills in the router and the robot id from the running stack where the command
    line did not; ``operator_session(args)`` opens a session to that router; ``service_graph()`` gives the lines of
    the stack as its services declare it (``mfvs keys --graph``)."""
    def command(name: str, help: str, func):
        parser = sub.add_parser(name, help=help)
        add_connection_options(parser)
        parser.set_defaults(func=_guarded(func), operator_session=operator_session,
                            stack_connection=stack_connection)
        return parser

    echo = command("echo", "print each message on a key, decoded (a line each, or --json)", _cmd_echo)
    echo.add_argument("key", help="a topic, whole (mfvs/jaco/robot/state) or below the robot (robot/state), or a "
                                  "pattern (vision/*, **)")
    echo.add_argument("--json", action="store_true", help="each message as one JSON line (bytes as their length)")
    echo.add_argument("--count", type=int, default=None, help="stop after this many messages")
    echo.add_argument("--seconds", type=float, default=None, help="stop after this long")

    hz = command("hz", "rate and jitter of a key's messages, every second", _cmd_hz)
    hz.add_argument("key", help="a topic or a pattern, as for echo")
    hz.add_argument("--seconds", type=float, default=None, help="stop after this long (default: Ctrl-C)")
    hz.add_argument("--window", type=int, default=1000, help="messages the statistics are over")
    hz.add_argument("--json", action="store_true", help="a JSON line per key and report")

    keys = command("keys", "what the stack publishes now: key, type, rate, size; and the services alive", _cmd_keys)
    keys.add_argument("--seconds", type=float, default=2.0, help="how long to listen")
    keys.add_argument("--json", action="store_true", help="one JSON object")
    keys.add_argument("--graph", action="store_true",
                      help="the service graph as the services declare it (who publishes each topic, who subscribes; "
                           "no stack needed)")
    keys.set_defaults(service_graph=service_graph)

    record = command("record", "record a running stack into an MCAP file: the payloads byte for byte, and the "
                               "viewer's channels in Foxglove's schemas", _cmd_record)
    record.add_argument("--out", required=True, metavar="FILE.mcap")
    record.add_argument("--keys", nargs="+", default=["**"], metavar="PATTERN",
                        help="topics to record (default: all)")
    record.add_argument("--seconds", type=float, default=None, help="stop after this long (default: Ctrl-C)")
    record.add_argument("--raw-only", action="store_true", help="only the payloads (no viewer channels: less CPU)")
    record.add_argument("--json", action="store_true", help="print the report as one JSON object")

    replay = command("replay", "publish a recording back onto zenoh (never commands: it moves no arm)", _cmd_replay)
    replay.add_argument("file", metavar="FILE.mcap")
    replay.add_argument("--keys", nargs="+", default=None, metavar="PATTERN",
                        help="topics to replay (default: all but commands)")
    replay.add_argument("--rate", type=float, default=1.0, help="speed against the recording's timing")
    replay.add_argument("--lockstep", action="store_true",
                        help="as fast as the consumers answer: each camera frame waits for the answers to the last")
    replay.add_argument("--answers", nargs="+", default=["vision/features"], metavar="KEY",
                        help="--lockstep: the keys that answer each frame (default vision/features; add "
                             "controller/twist when a controller runs)")
    replay.add_argument("--json", action="store_true", help="print the report as one JSON object")

    view = command("view", "a live Foxglove WebSocket server for the running stack (layout: "
                           "deploy/foxglove/mfvs.json)", _cmd_view)
    view.add_argument("--port", type=int, default=8765)
    view.add_argument("--host", default="127.0.0.1", help="where to listen (0.0.0.0: every interface)")
    view.add_argument("--seconds", type=float, default=None, help="stop after this long (default: Ctrl-C)")


def _guarded(func):
    """A bad key or file is one line on stderr and exit 2, not a traceback (no router: services.cli.main)."""
    def run(args) -> int:
        args.stack_connection(args)
        try:
            return func(args)
        except (UnknownTopic, ValueError, OSError) as exc:
            print(f"mfvs {args.command}: {exc}", file=sys.stderr)
            return 2
    return run


def _session(args, patterns=()):
    """A session to the stack, once the keys ``patterns`` name are known to be topics."""
    keys = Keys(args.robot_id)
    for pattern in patterns:
        matching(pattern, keys)
    return args.operator_session(args), keys


def _cmd_echo(args) -> int:
    from services.observe.introspect import echo

    session, keys = _session(args, [args.key])
    try:
        return echo(session, keys, args.key, as_json_lines=args.json, count=args.count, seconds=args.seconds)
    finally:
        session.close()


def _cmd_hz(args) -> int:
    from services.observe.introspect import hz

    session, keys = _session(args, [args.key])
    try:
        reports = hz(session, keys, args.key, seconds=args.seconds, window=args.window, as_json_lines=args.json)
    finally:
        session.close()
    return 0 if any(r is not None for r in reports.values()) else 1


def _cmd_keys(args) -> int:
    from services.observe.introspect import discover, keys_table
    from services.runtime.service import alive_services

    if args.graph:
        print("\n".join(args.service_graph()))
        return 0
    session, keys = _session(args)
    try:
        services = alive_services(session, keys)
        rows = discover(session, keys, args.seconds)
    finally:
        session.close()
    if args.json:
        print(json.dumps({"services": services, "keys": rows}))
    else:
        print(keys_table(rows, services, args.seconds))
    return 0 if rows else 1


def _wait(seconds) -> None:
    start = time.monotonic()
    try:
        while seconds is None or time.monotonic() - start < seconds:
            time.sleep(0.1)
    except KeyboardInterrupt:
        pass


def _cmd_record(args) -> int:
    from services.observe.record import Recorder

    session, keys = _session(args, args.keys)
    try:
        with Recorder(session, keys, args.out, args.keys, view=not args.raw_only) as recorder:
            if not args.json:
                print(f"recording {len(recorder.topics)} topics into {args.out} (Ctrl-C ends)", file=sys.stderr)
            _wait(args.seconds)
    finally:
        session.close()
    report = recorder.report()
    if args.json:
        print(json.dumps(report))
    else:
        total = sum(report["messages"].values())
        print(f"{args.out}: {total} messages, {report['bytes'] / 1e6:.1f} MB")
        for key, n in report["messages"].items():
            print(f"  {key}: {n}")
    return 0 if report["messages"] else 1


def _cmd_replay(args) -> int:
    from services.observe.replay import replay

    def progress(report) -> None:
        if not args.json and sys.stderr.isatty():
            print(f"\r  {report.frames} frames replayed", end="", file=sys.stderr, flush=True)

    from services.observe.replay import read_recording

    next(iter(read_recording(args.file, args.keys, Keys(args.robot_id))), None)  # a file that is no recording
    session, keys = _session(args, [*(args.keys or []), *(args.answers if args.lockstep else [])])
    try:
        report = replay(session, args.file, keys, args.keys, rate=args.rate, lockstep=args.lockstep,
                        answer_patterns=args.answers, progress=progress)
    finally:
        session.close()
    out = {"published": report.published, "frames": report.frames, "unanswered_frames": report.unanswered,
           "frames_sent_again": report.retries, "not_replayed": report.not_replayed, "seconds": round(report.seconds, 3)}
    if args.json:
        print(json.dumps(out))
    else:
        if sys.stderr.isatty():
            print(file=sys.stderr)
        print(f"replayed {sum(report.published.values())} messages ({report.frames} frames) in "
              f"{report.seconds:.1f} s; {report.not_replayed} commands and health messages not replayed"
              + (f"; {report.unanswered} frames unanswered, {report.retries} sent again" if args.lockstep else ""))
    return 0 if report.unanswered == 0 else 1


def _cmd_view(args) -> int:
    from services.observe.view import Viewer

    session, keys = _session(args)
    try:
        with Viewer(session, keys, args.host, args.port) as viewer:
            print(f"Foxglove: open a connection to ws://{args.host}:{viewer.port} (layout deploy/foxglove/mfvs.json); "
                  f"Ctrl-C ends", flush=True)
            _wait(args.seconds)
    finally:
        session.close()
    return 0
