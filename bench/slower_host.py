"""Run a command on this machine made slower on purpose: a CPU cgroup that lets the command's whole process tree use
``--cpus`` of the machine's cores (CFS quota for normal threads; SCHED_FIFO ones get at most ``--realtime`` of each
core, by default as much as ``--cpus``, so the services' realtime work is bounded too and is not a way around it),
on a short period so that the slowdown is spread evenly rather than as long pauses.

    python -m bench.slower_host --cpus 0.8 -- .venv/bin/python -m pytest

``--cpus 0.8`` on this 2-core machine runs Table 3 (``mfvs experiment table3``) 2.5 times slower, about what a
2-core host whose 640×480 MuJoCo frame renders in 6-7 ms does (2.4 times); 0.6 runs it 3.6 times slower. This is
how the test suite's verdicts are checked against a slow host (issue 49): a test whose verdict moves with
``--cpus`` is a design bug.

What it does not do as a slower CPU would: a burst shorter than the quota runs at full speed (a 1.2 ms render
alone stays about 1.4 ms), and the stack's realtime threads share one realtime budget per core: once the threads of
every priority together used it up within a period, all of them wait for the next, the highest as long as the
lowest, where a slower CPU would run the highest first and only take longer. The default budget (``--cpus`` of each
core) keeps that wait under ``(1 - cpus)`` of a period (1 ms at 0.8) and rare, as a real slow host's realtime
threads, which run whenever they are ready, have it. A share per core of ``--cpus`` divided among the cores (0.4 of
each at 0.8, what this bench gave before) stalled every realtime thread up to 3 ms in 5: the gateway missed its
3.33 ms bus cycles (wake-up lag p99 3.44 ms), each missed cycle paused the actuators, and the emulated servo
catching up after a pause took the end effector 12-20 % over its speed limit, which safety stops (measured:
``--realtime`` 0.4 at ``--cpus 0.8`` with a hog, peak 1.12 and 1.20 of the limit; 0.8, peak 1.00). Pass a smaller
``--realtime`` to try a harsher host on purpose.

Needs root and a cgroup v1 ``cpu`` hierarchy or cgroup v2 with the ``cpu`` controller; ``--taskset`` also pins
the tree to the given cores, and ``--hogs N`` starts N CPU hogs inside the cgroup beside it (another program at
the services' normal priority)."""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

from bench.hogs import cpu_hogs

V1 = Path("/sys/fs/cgroup/cpu")
V2 = Path("/sys/fs/cgroup")
#: the quota's period: short, so that a throttled thread waits a few milliseconds, not a tenth of a second (the
#: kernel's default period, which would turn a slow host into one that stops for 60 ms at a time)
PERIOD_US = 5000


class CgroupUnavailable(RuntimeError):
    pass


def make_cgroup(name: str, cpus: float, realtime: float | None = None) -> Path:
    """A cpu cgroup limited to ``cpus`` cores' worth of time for its normal threads and ``realtime`` of each core
    (default: ``cpus``, at most 0.95, the kernel's own share) for its realtime ones; its directory."""
    if cpus <= 0:
        raise ValueError("--cpus must be positive")
    realtime = min(0.95, cpus) if realtime is None else realtime
    if not 0 < realtime <= 0.95:
        raise ValueError("--realtime must be within (0, 0.95] of a core")
    quota = max(1000, int(cpus * PERIOD_US))
    if (V1 / "cpu.cfs_quota_us").exists():
        # inside this process's own group: a limit within a slowed run (the overload test's) nests in it, as a
        # child's realtime budget must (the kernel refuses siblings whose budgets add up past their parent's)
        group = _own_v1_group() / name
        group.mkdir(exist_ok=True)
        (group / "cpu.cfs_period_us").write_text(str(PERIOD_US))
        (group / "cpu.cfs_quota_us").write_text(str(quota))
        if (group / "cpu.rt_runtime_us").exists():  # realtime bandwidth is per core
            (group / "cpu.rt_runtime_us").write_text("0")  # (a period may change only with no runtime granted)
            (group / "cpu.rt_period_us").write_text(str(PERIOD_US))
            _grant_realtime(group, max(100, int(realtime * PERIOD_US)), realtime)
        return group
    controllers = V2 / "cgroup.controllers"
    if controllers.exists() and "cpu" in controllers.read_text().split():
        if "cpu" not in (V2 / "cgroup.subtree_control").read_text().split():
            (V2 / "cgroup.subtree_control").write_text("+cpu")
        group = V2 / name
        group.mkdir(exist_ok=True)
        (group / "cpu.max").write_text(f"{quota} {PERIOD_US}")
        return group
    raise CgroupUnavailable("no cgroup cpu controller this process may write (root, cgroup v1 cpu or v2 +cpu)")


def _grant_realtime(group: Path, runtime_us: int, realtime: float) -> None:
    """Write the group's realtime budget; the kernel refuses one that does not fit beside its siblings' within
    their parent's, and a sibling just removed frees its budget only a moment later: tried again for a second."""
    deadline = time.monotonic() + 1.0
    while True:
        try:
            (group / "cpu.rt_runtime_us").write_text(str(runtime_us))
            return
        except OSError as exc:
            if time.monotonic() < deadline:
                time.sleep(0.05)
                continue
            others = [p.name for p in group.parent.iterdir() if p.is_dir() and p != group]
            remove_cgroup(group)
            raise CgroupUnavailable(f"realtime budget of {realtime:g} of a core refused ({exc}): the groups beside "
                                    f"it ({', '.join(others) or 'none'}) may hold the rest of {group.parent}'s") from exc


def _own_v1_group() -> Path:
    """This process's group in the cgroup v1 ``cpu`` hierarchy (the root where it is in none)."""
    for line in Path("/proc/self/cgroup").read_text().splitlines():
        _, controllers, path = line.split(":", 2)
        if "cpu" in controllers.split(","):
            return V1 / path.lstrip("/")
    return V1


def remove_cgroup(group: Path) -> None:
    try:
        group.rmdir()
    except OSError:
        pass  # a process is still in it (a service left behind): the next run reuses it


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.slower_host", description=__doc__.split("\n\n")[0])
    parser.add_argument("--cpus", type=float, default=0.8, help="cores' worth of CPU time for the command's tree")
    parser.add_argument("--realtime", type=float, default=None,
                        help="fraction of each core its realtime threads may use (default: --cpus, at most 0.95)")
    parser.add_argument("--taskset", help="also pin the tree to these cores (taskset's list, e.g. 0)")
    parser.add_argument("--hogs", type=int, default=0, help="CPU hogs started inside the cgroup beside the command")
    parser.add_argument("--name", default="mfvs-slower-host", help="the cgroup's name")
    parser.add_argument("command", nargs=argparse.REMAINDER, help="-- then the command")
    args = parser.parse_args(argv)
    command = args.command[1:] if args.command[:1] == ["--"] else args.command
    if not command:
        parser.error("give the command to run after --")
    try:
        group = make_cgroup(args.name, args.cpus, args.realtime)
    except (CgroupUnavailable, OSError, ValueError) as exc:
        print(f"slower_host: {exc}", file=sys.stderr)
        return 2
    (group / "cgroup.procs").write_text(str(os.getpid()))  # the hogs and the command inherit it
    if args.taskset:
        os.sched_setaffinity(0, {int(c) for c in args.taskset.split(",")})
    print(f"slower_host: {args.cpus:g} cores' worth of CPU ({group})"
          + (f", cores {args.taskset}" if args.taskset else "") + (f", {args.hogs} hogs" if args.hogs else ""),
          file=sys.stderr)
    try:
        if args.hogs:
            with cpu_hogs(args.hogs):
                return subprocess.call(command)
        return subprocess.call(command)
    finally:
        parent = group.parent / "cgroup.procs"
        try:
            parent.write_text(str(os.getpid()))
        except OSError:
            pass
        remove_cgroup(group)


if __name__ == "__main__":
    sys.exit(main())
