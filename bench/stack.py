"""The running stack a benchmark measures: the named profile up in realtime, every service a process, in a run
directory of its own, with a servo task started (the stack comes up idle); taken down and the run directory
forgotten on the way out, whatever happened. Also what every benchmark on an arm shares: its ``--arm`` option
(checked as every command's is, before anything starts), the profile on that arm, and the arm a run measured."""
from __future__ import annotations

import argparse
import contextlib
import os
import re
import tempfile
from collections.abc import Iterable, Iterator
from typing import Optional

from protocol import messages as m
from services.cli.options import arm_or_exit
from services.stack.launcher import Profile, down, load_profile, stack_task, up, with_arm
from services.runtime.transport import free_loopback_port


def unknown_arm(parser: argparse.ArgumentParser, args: argparse.Namespace) -> bool:
    """Whether ``args.arm`` (services.cli.options.add_arm_option's ``--arm``) names no arm: then one line on stderr, as
    every command says it, and the benchmark exits 2 having started nothing."""
    return arm_or_exit(parser.prog.removeprefix("mfvs "), args.arm) is None


def profile_on_arm(name: str, arm: str) -> Profile:
    """The profile ``name`` (sim, gateway or a file) on free loopback ports, every service that runs on an arm set to
    ``arm``, as `mfvs up --profile NAME --arm ARM` runs it."""
    return with_arm(load_profile(name, free_loopback_port(), free_loopback_port()), arm)


def measured_arm(asked: str, declared: Iterable[str]) -> str:
    """The arm a run measured: the one its robot declared in its states (``declared``), which must be ``asked``
    (a robot on another arm would make every figure the wrong arm's)."""
    named = set(declared)
    if named and named != {asked}:
        raise RuntimeError(f"the robot declared the {', '.join(sorted(named))}, not the {asked} asked for")
    return asked


def detail_fields(detail: Optional[str]) -> dict[str, str]:
    """The ``name=value`` fields of a service's health detail (e.g. a robot node's ``bus_rate_hz=499.8``)."""
    return dict(re.findall(r"([\w.]+)=(\S+)", detail or ""))


@contextlib.contextmanager
def servoing_stack(profile: Profile, operator: str, start_task: bool = True) -> Iterator[str]:
    """Bring ``profile`` up in realtime, start its task as ``operator`` (unless not ``start_task``: the caller
    starts it, with :func:`services.stack.launcher.stack_task`), and yield the router's endpoint."""
    previous = os.environ.get("MFVS_RUN_DIR")
    with tempfile.TemporaryDirectory(prefix="mfvs-bench-") as directory:
        os.environ["MFVS_RUN_DIR"] = directory
        try:
            code, message = up(profile, "realtime")
            if code:
                raise RuntimeError(message)
            if start_task:
                stack_task(m.START_TASK, operator=operator)
            yield profile.endpoint()
        finally:
            down()
            if previous is None:
                os.environ.pop("MFVS_RUN_DIR", None)
            else:
                os.environ["MFVS_RUN_DIR"] = previous


def with_overrides(profile, assignments: list[str]):
    """The profile with ``SERVICE:KEY=VALUE`` assignments added to each named service's ``--set``."""
    for assignment in assignments:
        name, sep, setting = assignment.partition(":")
        services = [s for s in profile.services if s.name == name]
        if not sep or "=" not in setting or not services:
            known = ", ".join(s.name for s in profile.services)
            raise ValueError(f"--set {assignment!r}: give SERVICE:KEY=VALUE with a service of the profile ({known})")
        for service in services:
            service.set.append(setting)
    return profile
