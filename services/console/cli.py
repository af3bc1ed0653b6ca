"""``mfvs console``: the operator's page for a running stack, served by the stack's own machine.

    mfvs console                       # http://127.0.0.1:8080/ on this machine
    mfvs console --listen 0.0.0.0 --token-file /etc/mfvs/console-token   # a tablet on the same network

It reaches the stack as `mfvs task` and `mfvs estop` do (the running stack's router and robot id, and behind
authority the operator's zenoh config), so what the page does is what the operator identity may do. Where the
deployment's certificates include the console's (``mfvs authority init --tls``), it serves HTTPS with them.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Optional

DEFAULT_PORT = 8080


def add_parser(sub, add_connection_options, stack_connection) -> None:
    console = sub.add_parser("console", help="the operator's page in a browser: the arm's camera, start and stop "
                                             "the task, the e-stop, each service's health")
    console.add_argument("--port", type=int, default=DEFAULT_PORT, help=f"port (default {DEFAULT_PORT}; 0: a free "
                                                                         "one, printed)")
    console.add_argument("--listen", default="127.0.0.1",
                         help="address to listen on (default 127.0.0.1: this machine only); any other needs "
                              "--token or --token-file")
    console.add_argument("--token", default=None, help="the token (or password) the page asks for; every action "
                                                       "needs it (prefer --token-file: a command line is visible)")
    console.add_argument("--token-file", default=None, help="a file holding the token (its first line)")
    console.add_argument("--tls-cert", default=None, help="serve HTTPS with this certificate (PEM) ...")
    console.add_argument("--tls-key", default=None, help="... and its private key (default: the deployment's "
                                                         "certs/console.pem and .key next to the operator's config)")
    console.add_argument("--http", action="store_true", help="plain HTTP even where the deployment has a "
                                                             "certificate for the console")
    console.add_argument("--goals-dir", default="~/.local/share/mfvs/goals",
                         help="where the goals taught from the page are kept (default ~/.local/share/mfvs/goals)")
    console.add_argument("--jog-zenoh-config", default=None, metavar="FILE",
                         help="the jog identity's zenoh client config: the page's stick and gamepad send jog requests "
                              "as it (behind authority the operator may not; without authority the console's own "
                              "session sends them and this is not needed)")
    add_connection_options(console)
    console.set_defaults(func=lambda args: run(args, stack_connection))


def _fail(message: str) -> int:
    print(f"mfvs console: {message}", file=sys.stderr)
    return 2


def read_token(token: Optional[str], token_file: Optional[str]) -> Optional[str]:
    """The token from the command line or its file (first line, without its newline); ValueError when both, or
    the file cannot be read or is empty."""
    if token is not None and token_file is not None:
        raise ValueError("give --token or --token-file, not both")
    if token_file is None:
        return token
    try:
        lines = Path(token_file).read_text().splitlines()
    except OSError as exc:
        raise ValueError(f"cannot read the token file: {exc}") from None
    if not lines or not lines[0].strip():
        raise ValueError(f"the token file {token_file} is empty")
    return lines[0].strip()


def deployment_certificate(zenoh_config: Optional[str]) -> Optional[tuple[str, str]]:
    """The console's certificate and key of the deployment whose client config this is (``mfvs authority init
    --tls`` writes DIR/clients/<identity>.json5 and DIR/certs/console.pem), if there is one."""
    if not zenoh_config:
        return None
    certs = Path(zenoh_config).resolve().parent.parent / "certs"
    cert, key = certs / "console.pem", certs / "console.key"
    return (str(cert), str(key)) if cert.is_file() and key.is_file() else None


def run(args: argparse.Namespace, stack_connection) -> int:
    import asyncio

    from services.console.core import Access
    from services.console.service import ConsoleConfig, ConsoleService
    from services.console.web import serve, tls_context
    from services.runtime.config import ConfigError
    from services.runtime.logs import setup_logging
    from services.runtime.transport import ZenohConfig

    stack_connection(args)
    try:
        access = Access(listen=args.listen, token=read_token(args.token, args.token_file))
    except ValueError as exc:
        return _fail(str(exc))
    if (args.tls_cert is None) != (args.tls_key is None):
        return _fail("give both --tls-cert and --tls-key")
    certificate = (args.tls_cert, args.tls_key) if args.tls_cert else (
        None if args.http else deployment_certificate(args.zenoh_config))
    try:
        ssl_context = tls_context(*certificate) if certificate else None
    except (OSError, ValueError) as exc:
        return _fail(f"cannot use the certificate {certificate[0]}: {exc}")
    setup_logging("info")
    from services.console.jog import ConsoleJogConfig

    config = ConsoleConfig(robot_id=args.robot_id, action_timeout_s=args.timeout, goals_dir=args.goals_dir,
                           zenoh=ZenohConfig(connect=[args.connect], config_file=args.zenoh_config),
                           jog=ConsoleJogConfig(zenoh_config=args.jog_zenoh_config))
    try:
        service = ConsoleService(config).start()
    except ConfigError as exc:
        return _fail(str(exc))
    except Exception as exc:
        if type(exc).__name__ != "ZError":
            raise
        return _fail(f"cannot reach the stack's router at {args.connect} (is the stack up? `mfvs up`, or --connect): "
                     f"{str(exc).split('  at ')[0]}")

    def ready(console) -> None:
        print(json.dumps({"console": console.url(args.listen), "robot_id": args.robot_id, "router": args.connect,
                          "token_required": access.token_required, "tls": ssl_context is not None}), flush=True)

    try:
        asyncio.run(serve(service, access, args.listen, args.port, ssl_context, on_ready=ready))
    except OSError as exc:
        print(f"mfvs console: cannot listen on {args.listen}:{args.port}: {exc.strerror or exc}", file=sys.stderr)
        return 1
    finally:
        service.stop()
    return 0
