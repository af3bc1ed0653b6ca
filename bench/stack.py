"""The running stack a benchmark measures: the named profile up in realtime, every service a process, in a run
directory of its own, with a servo task started (the stack comes up idle); taken down and the run directory
forgotten on the way out, whatever happened."""
from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator

from protocol import messages as m
from services.launcher import Profile, down, stack_task, up


@contextlib.contextmanager
def servoing_stack(profile: Profile, operator: str) -> Iterator[str]:
    """Bring ``profile`` up in realtime, start its task as ``operator``, and yield the router's endpoint."""
    previous = os.environ.get("MFVS_RUN_DIR")
    with tempfile.TemporaryDirectory(prefix="mfvs-bench-") as directory:
        os.environ["MFVS_RUN_DIR"] = directory
        try:
            code, message = up(profile, "realtime")
            if code:
                raise RuntimeError(message)
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
