"""Run a command on this machine made slower on purpose: a CPU cgroup that lets the command's whole process tree use
``--cpus`` of the machine's cores (CFS quota for normal threads, the same share of realtime bandwidth for SCHED_FIFO
ones, so the services' realtime loops slow down too and are not a way around it), on a short period so that the
slowdown is spread evenly rather than as long pauses.

    python -m bench.slower_host --cpus 0.8 -- .venv/bin/python -m pytest

``--cpus 0.8`` on this 2-core machine runs Table 3 (``mfvs experiment table3``) 2.5 times slower, about what a
2-core host whose 640×480 MuJoCo frame renders in 6-7 ms does (2.4 times); 0.6 runs it 3.6 times slower. This is
how the test suite's verdicts are checked against a slow host (issue 49): a test whose verdict moves with
``--cpus`` is a design bug.

What it does not do as a slower CPU would: a burst shorter than the quota runs at full speed (a 1.2 ms render
alone stays about 1.4 ms), and the stack's realtime threads share one realtime budget, so at a small ``--cpus`` a
high-priority thread can hold back a lower one for longer than a slow CPU would (at 0.6 safety's e-stop waited
behind robot_sim's realtime process).

Needs root and a cgroup v1 ``cpu`` hierarchy or cgroup v2 with the ``cpu`` controller; ``--taskset`` also pins
the tree to the given cores, and ``--hogs N`` starts N CPU hogs inside the cgroup beside it (another program at
the services' normal priority)."""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
from pathlib import Path

from bench.hogs import cpu_hogs

V1 = Path("/sys/fs/cgroup/cpu")
V2 = Path("/sys/fs/cgroup")
#: the quota's period: short, so that a throttled thread waits a few milliseconds, not a tenth of a second (the
#: kernel's default period, which would turn a slow host into one that stops for 60 ms at a time)
PERIOD_US = 5000


class CgroupUnavailable(RuntimeError):
    pass


def make_cgroup(name: str, cpus: float) -> Path:
    """A cpu cgroup limited to ``cpus`` cores' worth of time (normal and realtime threads); its directory."""
    if cpus <= 0:
        raise ValueError("--cpus must be positive")
    quota = max(1000, int(cpus * PERIOD_US))
    if (V1 / "cpu.cfs_quota_us").exists():
        group = V1 / name
        group.mkdir(exist_ok=True)
        (group / "cpu.cfs_period_us").write_text(str(PERIOD_US))
        (group / "cpu.cfs_quota_us").write_text(str(quota))
        if (group / "cpu.rt_runtime_us").exists():  # realtime bandwidth is per core: the per-core share
            cores = os.cpu_count() or 1
            (group / "cpu.rt_period_us").write_text(str(PERIOD_US))
            (group / "cpu.rt_runtime_us").write_text(str(max(100, int(min(0.95, cpus / cores) * PERIOD_US))))
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


def remove_cgroup(group: Path) -> None:
    try:
        group.rmdir()
    except OSError:
        pass  # a process is still in it (a service left behind): the next run reuses it


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.slower_host", description=__doc__.split("\n\n")[0])
    parser.add_argument("--cpus", type=float, default=0.8, help="cores' worth of CPU time for the command's tree")
    parser.add_argument("--taskset", help="also pin the tree to these cores (taskset's list, e.g. 0)")
    parser.add_argument("--hogs", type=int, default=0, help="CPU hogs started inside the cgroup beside the command")
    parser.add_argument("--name", default="mfvs-slower-host", help="the cgroup's name")
    parser.add_argument("command", nargs=argparse.REMAINDER, help="-- then the command")
    args = parser.parse_args(argv)
    command = args.command[1:] if args.command[:1] == ["--"] else args.command
    if not command:
        parser.error("give the command to run after --")
    try:
        group = make_cgroup(args.name, args.cpus)
    except (CgroupUnavailable, OSError) as exc:
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
