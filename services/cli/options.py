"""The options several commands share with the benchmarks (``--arm``, ``--jobs``, ``--processes``, the connection
to a running stack), each defined once."""
from __future__ import annotations

import argparse
import sys
from typing import Optional


def arm_or_exit(command: str, name: str):
    """The arm description ``name``, or (None, after one line on stderr: ``mfvs <command>: ...``) when there is none
    of that name: every command's ``--arm``, the benchmarks' too, checked before anything starts."""
    from services.model.arm import ArmError, load_arm

    try:
        return load_arm(name)
    except ArmError as exc:
        print(f"mfvs {command}: {exc}", file=sys.stderr)
        return None


def add_arm_option(parser, default: Optional[str] = "default", what: str = "") -> None:
    """``--arm NAME``: the arm description a command runs with (one setting for a whole stack); ``default``: the
    default arm unless given (None: what the command's input says, ``what``)."""
    from services.model.arm import DEFAULT_ARM, arm_names

    default = DEFAULT_ARM if default == "default" else default
    parser.add_argument("--arm", default=default, metavar="NAME",
                        help=f"the arm: {', '.join(arm_names())} (default {default or what})")


def add_processes_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--processes", action="store_true",
                        help="in lockstep with the sim profile, every service a process of its own with a router, as "
                             "deployed (the same numbers, slower); by default they run composed in the runner's "
                             "process, on one zenoh session")


def add_jobs_option(parser: argparse.ArgumentParser) -> None:
    from services.experiments.pool import default_jobs

    parser.add_argument("--jobs", type=int, default=default_jobs(), metavar="N",
                        help=f"lockstep runs side by side, each on a stack and a core of its own (default: the "
                             f"cores, {default_jobs()} here); every run gives the same numbers however many run "
                             "beside it (torque-control runs in realtime, one controller at a time, and takes none)")


def jobs_or_exit(command: str, jobs: int) -> bool:
    from services.experiments.pool import check_jobs

    try:
        check_jobs(jobs)
    except ValueError as exc:
        print(f"mfvs {command}: {exc}", file=sys.stderr)
        return False
    return True


def add_connection_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--connect", default=None, help="zenoh router endpoint (default: the running stack's)")
    parser.add_argument("--zenoh-config", default=None, help="zenoh client config (credentials, certificates)")
    parser.add_argument("--robot-id", default=None, help="robot id (keys under mfvs/<robot_id>/; default: the "
                        "running stack's)")
    parser.add_argument("--timeout", type=float, default=5.0, help="seconds to wait for confirmation")
