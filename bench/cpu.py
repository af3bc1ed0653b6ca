"""What each service costs per second of running: CPU (% of one core, user + system) and resident memory (MB) of
every process of a stack (with its children), per profile, while it servos onto the tag (`mfvs up`, realtime, on free ports).

``python -m bench.cpu [--json] [--seconds S] [--profiles sim,gateway] [--arm NAME] [--threads] [--maps]`` or
``mfvs bench cpu``. ``--json`` prints ``{"arm", "seconds", "profiles": {name: {"processes": {process: {"cpu_pct",
"rss_mb", "pss_mb", "threads": {name: cpu_pct}, "mappings": {name: rss_mb}}}, "total_cpu_pct", "total_rss_mb",
"total_pss_mb", "resident_mb"}}}``; ``--threads`` also prints each process's threads by their kernel names, ``--maps``
where each process's resident memory lies (each library, the heap, anonymous memory).

Three sums of a stack's memory: RSS counts each page once per process that maps it (NumPy, zenoh, libpython,
Pinocchio in every service); PSS divides a shared page among the processes that map it, outside the stack too; the
stack's resident memory counts every physical page its processes hold once (their page frames, from
``/proc/PID/pagemap``): what the machine gives the stack. That last needs the page frame numbers, which the kernel
shows only to a process with CAP_SYS_ADMIN (None without).
"""
from __future__ import annotations

import argparse
import json
import os
import re
import time
from collections import Counter
from typing import Optional

import numpy as np

from bench.stack import profile_on_arm, servoing_stack, unknown_arm
from services.cli.options import add_arm_option
from services.stack.launcher import read_stack
from services.model.arm import DEFAULT_ARM
from services.runtime.pacing import normal_priority, request_realtime

CLOCK_TICKS = os.sysconf("SC_CLK_TCK")
#: the reader's SCHED_FIFO priority, above every loop of a stack (robot loops 40-45)
READER_PRIORITY = 90


def children(pid: int) -> list[int]:
    """The processes ``pid``'s threads started that still run (none when it is gone)."""
    out = []
    try:
        for task in os.listdir(f"/proc/{pid}/task"):
            with open(f"/proc/{pid}/task/{task}/children") as f:
                out += [int(child) for child in f.read().split()]
    except OSError:
        pass
    return out


def process_tree(pid: int) -> list[int]:
    """``pid`` and its descendants (robot_sim's camera renders in a child process: it is robot_sim's cost)."""
    out, todo = [], [pid]
    while todo:
        current = todo.pop()
        out.append(current)
        todo += children(current)
    return out


def _stat_cpu(stat_path: str) -> tuple[str, float]:
    """The name and user + system CPU time (s) in a /proc ``stat`` file, a process's or a thread's (("", 0)
    when it ended meanwhile)."""
    try:
        with open(stat_path) as f:
            head, tail = f.read().rsplit(")", 1)
    except OSError:
        return "", 0.0
    fields = tail.split()
    return head.split("(", 1)[1], (int(fields[11]) + int(fields[12])) / CLOCK_TICKS


def _cpu_seconds_of(pid: int) -> float:
    return _stat_cpu(f"/proc/{pid}/stat")[1]


def _proc_mb(path: str, field: str) -> float:
    """A ``field: N kB`` line of a /proc file, in MB (0 when the process is gone)."""
    try:
        with open(path) as f:
            for line in f:
                if line.startswith(field):
                    return int(line.split()[1]) / 1024
    except OSError:
        pass
    return 0.0


def _rss_mb_of(pid: int) -> float:
    return _proc_mb(f"/proc/{pid}/status", "VmRSS:")


def cpu_seconds(pid: int) -> float:
    """User + system CPU time so far (s) of a process and its children, from /proc."""
    return sum(_cpu_seconds_of(p) for p in process_tree(pid))


def thread_cpu_seconds(pid: int) -> dict[str, float]:
    """User + system CPU time so far (s) per kernel thread name (``comm``) of a process and its children: the
    services name their loops (services/runtime/threads.py); zenoh's threads carry their own names."""
    out: dict[str, float] = {}
    for process in process_tree(pid):
        try:
            tasks = os.listdir(f"/proc/{process}/task")
        except OSError:
            continue
        for task in tasks:
            name, seconds = _stat_cpu(f"/proc/{process}/task/{task}/stat")
            if name:
                out[name] = out.get(name, 0.0) + seconds
    return out


def rss_mb(pid: int) -> float:
    """Resident memory (MB) of a process and its children."""
    return sum(_rss_mb_of(p) for p in process_tree(pid))


def peak_rss_mb(pid: int) -> float:
    """The most a process has held resident since it started (MB; VmHWM)."""
    return _proc_mb(f"/proc/{pid}/status", "VmHWM:")


def _pss_mb_of(pid: int) -> float:
    return _proc_mb(f"/proc/{pid}/smaps_rollup", "Pss:")


def pss_mb(pid: int) -> float:
    """Proportional resident memory (MB) of a process and its children: each shared page divided among the
    processes that map it, so that a stack's sum counts the libraries every service maps (numpy, zenoh, MuJoCo,
    pinocchio) once, where the sum of RSS counts them once per process."""
    return sum(_pss_mb_of(p) for p in process_tree(pid))


PAGE_BYTES = os.sysconf("SC_PAGE_SIZE")
_PAGE_PRESENT = np.uint64(1 << 63)
_PAGE_FRAME = np.uint64((1 << 55) - 1)
#: pagemap entries read at once (8 MB)
_PAGEMAP_SLICE = 1 << 20
_MAPPING_LINE = re.compile(r"^([0-9a-f]+)-([0-9a-f]+) \S+ \S+ \S+ \S+\s*(.*)$")


def resident_mappings(pid: int) -> list[tuple[int, int, str, int]]:
    """A process's mappings that hold resident memory: (start, end, name, RSS in kB), from /proc/PID/smaps (the
    name is the mapped file's path, or ``[heap]``, ``[stack]``, '' for anonymous memory); [] when it is gone."""
    out, current = [], None
    try:
        with open(f"/proc/{pid}/smaps") as f:
            for line in f:
                header = _MAPPING_LINE.match(line)
                if header:
                    current = (int(header[1], 16), int(header[2], 16), header[3].strip())
                elif line.startswith("Rss:") and current is not None:
                    kb = int(line.split()[1])
                    if kb:
                        out.append((*current, kb))
    except OSError:
        return []
    return out


def resident_frames(pid: int) -> Optional[np.ndarray]:
    """The physical page frames a process holds resident (its mappings' present pages, /proc/PID/pagemap), or None
    when the kernel hides them (without CAP_SYS_ADMIN it reports frame 0 for every page)."""
    frames = []
    try:
        with open(f"/proc/{pid}/pagemap", "rb") as pagemap:
            for start, end, _name, _kb in resident_mappings(pid):
                # a large reservation with a few pages resident is read a slice at a time (8 bytes a page)
                for first in range(start // PAGE_BYTES, end // PAGE_BYTES, _PAGEMAP_SLICE):
                    pagemap.seek(first * 8)
                    count = min(_PAGEMAP_SLICE, end // PAGE_BYTES - first)
                    entries = np.frombuffer(pagemap.read(count * 8), dtype=np.uint64)
                    frames.append(entries[(entries & _PAGE_PRESENT) != 0] & _PAGE_FRAME)
    except OSError:
        return np.empty(0, dtype=np.uint64)  # gone meanwhile: it holds nothing
    held = np.concatenate(frames) if frames else np.empty(0, dtype=np.uint64)
    return None if held.size and not held.any() else held


def resident_mb(pids) -> Optional[float]:
    """The memory the processes ``pids`` (and their children) hold resident, each physical page once however many
    of them map it (MB); None when page frames cannot be read."""
    held = []
    for pid in pids:
        for process in process_tree(pid):
            frames = resident_frames(process)
            if frames is None:
                return None
            held.append(frames)
    return np.unique(np.concatenate(held)).size * PAGE_BYTES / 2**20 if held else 0.0


def mapping_name(path: str) -> str:
    """A mapping as the breakdown names it: a library by its file (a package's by the package: ``numpy``,
    ``cv2``, ``zenoh``), the heap, anonymous memory."""
    if not path:
        return "anonymous"
    if path.startswith("["):
        return path
    if path.startswith("/dev/shm/") and path.endswith(".zenoh"):
        return "zenoh's shared memory"
    package = re.search(r"/site-packages/([^/]+)/", path)
    if package:
        # wheels' bundled libraries: numpy.libs, opencv_python_headless.libs; cmeel.prefix holds Pinocchio's C++
        # libraries and their own (coal, eigenpy, Boost, urdfdom)
        return {"cmeel.prefix": "pinocchio's libraries (cmeel.prefix)"}.get(package[1], package[1])
    return re.sub(r"\.so[.0-9]*$", "", os.path.basename(path))


def mappings_mb(pid: int) -> dict[str, float]:
    """Where a process's (and its children's) resident memory lies: MB per :func:`mapping_name`, largest first."""
    total: Counter = Counter()
    for process in process_tree(pid):
        for _start, _end, name, kb in resident_mappings(process):
            total[mapping_name(name)] += kb / 1024
    return {name: round(mb, 1) for name, mb in total.most_common()}


def measure(profile_name: str, seconds: float, settle_s: float = 3.0, arm: str = DEFAULT_ARM) -> dict:
    with servoing_stack(profile_on_arm(profile_name, arm), "bench cpu"):
        try:
            time.sleep(settle_s)  # past start-up (imports, first frames)
            processes = {p["name"]: p["pid"] for p in read_stack()["processes"]}
            # readings above the stack's realtime loops (after `up`: its processes must not inherit this), each
            # with its own clock: a reader that waits between one process and the next would count the wait as CPU
            request_realtime(READER_PRIORITY, "bench cpu's reader")
            before = {name: (time.monotonic(), cpu_seconds(pid), thread_cpu_seconds(pid))
                      for name, pid in processes.items()}
            time.sleep(seconds)
            result = {}
            for name, pid in processes.items():
                start, cpu_before, threads_before = before[name]
                cpu_after, threads_after = cpu_seconds(pid), thread_cpu_seconds(pid)
                elapsed = time.monotonic() - start
                threads = {thread: round(100.0 * (cpu - threads_before.get(thread, 0.0)) / elapsed, 1)
                           for thread, cpu in threads_after.items()}
                result[name] = {"cpu_pct": round(100.0 * (cpu_after - cpu_before) / elapsed, 1),
                                "rss_mb": round(rss_mb(pid), 1), "pss_mb": round(pss_mb(pid), 1),
                                "threads": dict(sorted(threads.items(), key=lambda kv: -kv[1])),
                                "mappings": mappings_mb(pid)}
            resident = resident_mb(processes.values())
        finally:
            normal_priority()
    return {"processes": result, "total_cpu_pct": round(sum(r["cpu_pct"] for r in result.values()), 1),
            "total_rss_mb": round(sum(r["rss_mb"] for r in result.values()), 1),
            "total_pss_mb": round(sum(r["pss_mb"] for r in result.values()), 1),
            "resident_mb": None if resident is None else round(resident, 1)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="mfvs bench cpu", description=__doc__.split("\n\n")[0])
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--seconds", type=float, default=8.0, help="measured time per profile (default 8)")
    parser.add_argument("--profiles", default="sim,gateway", help="comma-separated profiles (default sim,gateway)")
    parser.add_argument("--threads", action="store_true",
                        help="also each process's threads (by kernel name) costing 1 %% of a core or more")
    parser.add_argument("--maps", action="store_true",
                        help="also where each process's resident memory lies (libraries, heap, anonymous), 1 MB or more")
    add_arm_option(parser)
    args = parser.parse_args(argv)
    if unknown_arm(parser, args):
        return 2
    results = {name: measure(name, args.seconds, arm=args.arm) for name in args.profiles.split(",") if name}
    if args.json:
        print(json.dumps({"arm": args.arm, "seconds": args.seconds, "profiles": results}))
        return 0
    for name, r in results.items():
        resident = "unknown (page frames need CAP_SYS_ADMIN)" if r["resident_mb"] is None else \
            f"{r['resident_mb']:.0f} MB"
        print(f"{name} ({args.arm}): {r['total_cpu_pct']:.0f} % of a core; resident {resident} (every page once), "
              f"{r['total_rss_mb']:.0f} MB summed RSS (a shared page once per process), {r['total_pss_mb']:.0f} MB "
              f"summed PSS (a shared page divided among its processes)")
        for process, figures in sorted(r["processes"].items(), key=lambda kv: -kv[1]["cpu_pct"]):
            print(f"  {process:14s} {figures['cpu_pct']:5.1f} %  {figures['rss_mb']:6.0f} MB  "
                  f"PSS {figures['pss_mb']:4.0f} MB")
            if args.threads:
                for thread, pct in figures["threads"].items():
                    if pct >= 1.0:
                        print(f"      {thread:16s} {pct:5.1f} %")
            if args.maps:
                print("      " + ", ".join(f"{mapping} {mb:.0f}" for mapping, mb in figures["mappings"].items()
                                          if mb >= 1.0) + " (MB)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
