"""Where a lockstep iteration's wall time goes, and the check that speeding it up changed nothing it computes.

``mfvs bench lockstep [--scenario FILE] [--law NAME] [--arm NAME] [--hogs N] [--json]``: one lockstep run through
the real services (sim profile; by default Table 3's p-joint run from examples/scenarios/table2.yaml, 640×480), every
process timing its part of each iteration (:mod:`services.runtime.iteration_profile`), and per iteration the wall
time split by where it goes: the robot's loop (physics, the emulated actuators and bus, the robot node, the state
out), rendering, the waits for the pipeline and what filled them (detection, the law, safety, messages, and the
hand-offs between processes), with the CPU each process spent, every service a process of its own as deployed
(``--processes``); then the same run composed, as experiments run it (:mod:`services.stack.composed`: the services in
one process on one zenoh session), split the same way with every service's functions timed in that one process (the
rows then overlap: a service's thread may run while the loop thread waits for the interpreter lock inside one of
its own rows), and its wall time and CPU per iteration. The machine's load (``uptime``) is printed with
the figures: on a shared 2-core host they mean nothing without it.

``mfvs bench lockstep --identity [--base REV] [--hogs N]``: runs Table 3 from table2.yaml (its four laws),
part_b.yaml and part_b_j2n6s300.yaml (the 6-DoF arm) on the code of ``REV`` (default: where this branch left main)
and on this tree, and compares every trajectory log byte for byte and each run's iterations, status and final
error. Exit 1 when anything differs. ``--hogs N`` runs N CPU hogs beside both (lockstep must not change under
load). The base's logs are kept per commit and reused (``--fresh`` runs it again), the four most recently used.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from bench.cpu import children, cpu_seconds, peak_rss_mb, process_tree
from bench.hogs import cpu_hogs
from bench.stack import unknown_arm
from services.cli.options import add_arm_option
from services.controller.laws import LAW_NAMES
from services.experiments.mixed_frame import TABLE3_GAINS
from services.paths import REPO, SCENARIOS
from services.runtime import iteration_profile as ip
from services.servo.run import run
from services.servo.scenario import load_scenario, on_arm

LOOP = ip.LOOP_THREAD

#: the runs the identity check compares: (name, the mfvs command's arguments)
IDENTITY_RUNS = (
    ("table3", ["experiment", "table3", "--json", "--scenario", str(SCENARIOS / "table2.yaml")]),
    ("part_b", ["servo", "--json", "--scenario", str(SCENARIOS / "part_b.yaml")]),
    ("part_b_j2n6s300", ["servo", "--json", "--scenario", str(SCENARIOS / "part_b_j2n6s300.yaml")]),
)


# ------------------------------------------------------------------------------------------------ load
def load() -> str:
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


# ------------------------------------------------------------------------------------------------ the profile
def profile_run(scenario, hogs: int = 0) -> dict:
    """Run ``scenario`` with every process of its stack timing itself; the figures (see :func:`split`)."""
    window: dict = {}

    def progress(record) -> None:
        now = time.monotonic()
        if "first" not in window:  # the stack is up and the loop runs: CPU from here on is the loop's
            # each process of the stack with its children (robot_sim's renderer)
            window["cpu"] = {pid: cpu_seconds(pid) for pid in process_tree(os.getpid())[1:]}
            window["runner_cpu"] = time.process_time()
            window["first"] = (record.iteration, now)
        window["last"] = (record.iteration, now)

    previous = os.environ.get(ip.PROFILE_DIR_ENV)
    with tempfile.TemporaryDirectory(prefix="mfvs-profile-") as directory, cpu_hogs(hogs):
        os.environ[ip.PROFILE_DIR_ENV] = directory
        try:
            load_before = load()
            # every service a process of its own: each times its part (the composed run is composed_run's)
            result = run(scenario, None, progress, plots=False, processes=True)
            load_after = load()
        finally:
            if previous is None:
                os.environ.pop(ip.PROFILE_DIR_ENV, None)
            else:
                os.environ[ip.PROFILE_DIR_ENV] = previous
        runner_cpu = time.process_time() - window.get("runner_cpu", 0.0)
        profiles = ip.read_profiles(Path(directory))
    figures = split(profiles)
    (first_it, first_t), (last_it, last_t) = window["first"], window["last"]
    cpu = {}
    for profile in profiles.values():
        before = window["cpu"].get(profile["pid"], 0.0)
        cpu[profile["process"]] = profile["cpu_s"] + profile["children_cpu_s"] - before
    cpu["runner"] = runner_cpu
    frames = figures["frames"]
    return {
        "scenario": scenario.law, "iterations": result.iterations, "status": result.status,
        "final_error_norm": result.final_error_norm, "wall_time_s": result.wall_time_s,
        "lockstep_timeouts": result.lockstep_timeouts, "load_before": load_before, "load_after": load_after,
        "hogs": hogs,
        # the runner's view: iterations as the controller reported them, from the first to the last
        "iteration_ms": round(1e3 * (last_t - first_t) / max(1, last_it - first_it), 3),
        "loop_s": round(figures["loop_ms"] / 1e3, 3),
        "frames": frames,
        "per_iteration_ms": figures["rows"],
        "cpu_per_iteration_ms": {name: round(1e3 * s / frames, 3) for name, s in sorted(cpu.items())},
    }


def composed_run(scenario, hogs: int = 0) -> dict:
    """Run ``scenario`` composed (:mod:`services.stack.composed`, as experiments run it) twice: as it is, for wall time
    and CPU per iteration from the first iteration the runner saw to the last (the CPU is this process's: the
    services, their renderer and the runner; and its children's that the run started, none in lockstep, where
    robot_sim renders in its loop's thread) and the process's peak memory; then with every service's functions
    timed in this process where they run, for the same split as :func:`profile_run`'s. The timers cost time of
    their own (Python around every timed call, on the loop's thread and on the services'): the split's run is
    slower, and says by how much (``profiled_iteration_ms``)."""
    _reset_peak_rss()  # the peak is then the composed run's, not the profiled run's runner's before it
    figures = _timed_composed_run(scenario, hogs, profiled=False)
    figures["peak_rss_mb"] = round(peak_rss_mb(os.getpid()), 1)  # the stack's and the runner's, in this process
    split_run = _timed_composed_run(scenario, hogs, profiled=True)
    figures.update({"profiled_iteration_ms": split_run["iteration_ms"], "loop_s": split_run["loop_s"],
                    "frames": split_run["frames"], "per_iteration_ms": split_run["per_iteration_ms"]})
    return figures


class _RunChildren:
    """The CPU of the processes a run starts, from /proc, sampled on a thread of its own every ``period_s`` from
    :meth:`start` (the run's first iteration) to :meth:`stop`: a process started and ended between two samples,
    and a child's last ``period_s`` before it ends, go uncounted. (``os.times``' children's figure would count
    every child this process reaps meanwhile: what ran before in it, the processes' run of ``mfvs bench
    lockstep`` or an earlier test, was once reaped inside a composed run's window and counted as its.)"""

    def __init__(self, older: set[int], period_s: float = 0.1) -> None:
        self.older, self.period_s = older, period_s
        self.first: dict[int, float] = {}
        self.last: dict[int, float] = {}
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def sample(self) -> None:
        for pid in children(os.getpid()):
            if pid not in self.older:
                seconds = cpu_seconds(pid)
                self.first.setdefault(pid, seconds if self._thread is None else 0.0)  # (started since)
                self.last[pid] = seconds

    def start(self) -> None:
        self.sample()
        self._thread = threading.Thread(target=self._run, name="bench-run-children", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(self.period_s):
            self.sample()

    def stop(self) -> float:
        """The CPU (s) the run's processes spent since :meth:`start`."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        return sum(self.last[pid] - self.first[pid] for pid in self.last)


def _timed_composed_run(scenario, hogs: int, profiled: bool) -> dict:
    window: dict = {}

    def progress(record) -> None:
        now = time.monotonic()
        if "first" not in window:
            run_children.start()
            window["cpu"] = time.process_time()
            window["first"] = (record.iteration, now)
        window["last"] = (record.iteration, now)

    if profiled:
        ip.install_composed()
    try:
        with cpu_hogs(hogs):
            run_children = _RunChildren(older=set(process_tree(os.getpid())))  # (the warm server is older)
            load_before = load()
            try:
                result = run(scenario, None, progress, plots=False)
            finally:
                children_s = run_children.stop()
            load_after = load()
        profile = ip.profile_now("composed") if profiled else None
    finally:
        if profiled:
            ip.uninstall()
    (first_it, first_t), (last_it, last_t) = window["first"], window["last"]
    iterations = max(1, last_it - first_it)
    services = time.process_time() - window["cpu"]
    figures = {"iterations": result.iterations, "status": result.status, "final_error_norm": result.final_error_norm,
               "wall_time_s": result.wall_time_s, "lockstep_timeouts": result.lockstep_timeouts,
               "stack": result.stack, "load_before": load_before, "load_after": load_after,
               "iteration_ms": round(1e3 * (last_t - first_t) / iterations, 3),
               "cpu_per_iteration_ms": {"the process": round(1e3 * services / iterations, 3),
                                        "its children": round(1e3 * children_s / iterations, 3)}}
    if profile is not None:
        split_figures = split({process: profile for process in ip.COMPOSED}, composed=True)
        figures.update({"loop_s": round(split_figures["loop_ms"] / 1e3, 3), "frames": split_figures["frames"],
                        "per_iteration_ms": split_figures["rows"]})
    return figures


def _reset_peak_rss() -> None:
    """VmHWM of this process back to what it holds now (``/proc/self/clear_refs``, Linux 4.0)."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
    except OSError:
        pass


def print_composed(figures: dict) -> None:
    error = figures["final_error_norm"]
    error = "none" if error is None else f"{error:.6e}"
    cpu = figures["cpu_per_iteration_ms"]
    print(f"\ncomposed (the services in one process, as experiments run): {figures['status']}, {figures['iterations']} "
          f"iterations, final ‖e‖ {error}, lockstep timeouts {figures['lockstep_timeouts']}; load "
          f"{figures['load_before']} before, {figures['load_after']} after")
    print(f"wall: run {figures['wall_time_s']:.2f} s; {figures['iteration_ms']:.2f} ms per iteration as the runner saw "
          f"them")
    print("CPU per iteration (ms), from the loop's first iteration to the stack's stop: "
          + ", ".join(f"{name} {ms:.2f}" for name, ms in cpu.items())
          + f"; total {sum(cpu.values()):.2f}; the process's peak resident memory {figures['peak_rss_mb']:.0f} MB")
    print(f"\nthe same run again with every service's functions timed: {figures['profiled_iteration_ms']:.2f} ms per "
          f"iteration (the timers' own cost); loop {figures['loop_s']:.2f} s for {figures['frames']} frames")
    # one interpreter: a service's work on its own thread may run while the loop thread is inside one of its own rows
    # (waiting for the interpreter lock), so the rows overlap and the rest can come out below zero
    print_rows(figures["per_iteration_ms"], "the rest (below 0: the rows overlapped under one lock)")


#: the rows of the split: (key, what it is); indented keys are parts of the row above
ROWS = (
    ("robot_loop", "robot_sim's loop (its own work)"),
    ("  physics", "MuJoCo's steps"),
    ("  actuators", "the emulated actuators' torques, every physics step"),
    ("  bus", "the emulated bus cycle (commands, values, readings)"),
    ("  node", "the robot node (DSP, core, bookkeeping)"),
    ("  state", "robot state built (kinematics)"),
    ("  publish", "its messages encoded and put"),
    ("  frame_snapshot", "the camera's snapshot of the world"),
    ("rendering", "rendering the frame"),
    ("waits", "robot_sim's loop waiting, for"),
    ("  render_process", "the frame rendered in the render process (with the pipe)"),
    ("  detection", "detection (vision)"),
    ("  law", "the law (controller)"),
    ("  safety", "safety's checks"),
    ("  services", "the services' own handling"),
    ("  messages", "messages encoded, put and decoded in the services"),
    ("  handoffs", "zenoh hops, wake-ups, scheduling (the rest)"),
)


def split(profiles: dict[str, dict], composed: bool = False) -> dict:
    """Per iteration (a frame rendered), in ms: where robot_sim's loop thread spent its time, and what filled its
    waits. The rows add up to the loop's time per frame. ``composed``: every process's name maps to the one profile
    of the process they all ran in."""
    robot = profiles["robot_sim"]
    frames = max(1, ip.calls(robot, ip.FRAMES_LABEL, returned=True))

    def loop(label: str) -> float:
        return ip.exclusive_ms(robot, label, LOOP)

    def other(process: str, label: str, thread=None) -> float:
        return ip.exclusive_ms(profiles[process], label, thread) if process in profiles else 0.0

    rendering_in_loop = loop("render")
    render_elsewhere = ip.exclusive_ms(robot, "render") - rendering_in_loop
    waiting = loop("frame_wait") + loop("answer_wait")
    rows = {
        "  physics": loop("physics"), "  actuators": loop("actuators"), "  bus": loop("bus"), "  node": loop("node"),
        "  state": loop("state"), "  publish": loop("publish"), "  frame_snapshot": loop("frame_snapshot"),
        "rendering": rendering_in_loop,
        "  render_process": render_elsewhere,
        "  detection": other("vision", "detection"),
        "  law": other("controller", "law"),
        "  safety": other("safety", "safety"),
        "  services": other("vision", "vision") + other("controller", "controller"),
        # the loop's own puts are its rows'; composed, every other thread's puts and every decode are the services'
        "  messages": (ip.exclusive_ms(robot, "decode") + ip.exclusive_ms(robot, "publish") - loop("publish")
                       if composed else ip.exclusive_ms(robot, "decode") + sum(
                           other(p, label) for p in ("vision", "controller", "safety") for label in ("publish", "decode"))),
    }
    rows["robot_loop"] = sum(rows[k] for k in ("  physics", "  actuators", "  bus", "  node", "  state", "  publish",
                                                "  frame_snapshot"))
    accounted = sum(rows[k] for k in ("  render_process", "  detection", "  law", "  safety", "  services",
                                      "  messages"))
    rows["  handoffs"] = waiting - accounted
    rows["waits"] = waiting
    total = rows["robot_loop"] + rows["rendering"] + rows["waits"]
    out = {key: round(rows[key] / frames, 3) for key, _ in ROWS}
    out["total"] = round(total / frames, 3)
    return {"frames": frames, "loop_ms": total, "rows": out}


def print_rows(rows: dict, handoffs: str = "") -> None:
    """The split, a row a line (``handoffs``: what the rest is, where it is not :data:`ROWS`' words)."""
    print("\nper iteration (ms of wall time)")
    for key, what in ROWS:
        indent = "  " if key.startswith("  ") else ""
        what = handoffs if key == "  handoffs" and handoffs else what
        print(f"  {indent}{what:<{58 - len(indent)}} {rows[key]:7.3f}")
    print(f"  {'total (robot_sim loop time per frame)':<58} {rows['total']:7.3f}")


def print_profile(figures: dict, label: str) -> None:
    print(f"mfvs bench lockstep: {label}")
    print(f"load (uptime) {figures['load_before']} before, {figures['load_after']} after"
          + (f"; {figures['hogs']} CPU hogs beside" if figures["hogs"] else ""))
    error = figures["final_error_norm"]
    error = "none" if error is None else f"{error:.6e}"
    print(f"{figures['status']}: {figures['iterations']} iterations, final ‖e‖ {error}, lockstep timeouts "
          f"{figures['lockstep_timeouts']}")
    print(f"wall: run {figures['wall_time_s']:.2f} s (start-up and stop included); loop {figures['loop_s']:.2f} s for "
          f"{figures['frames']} frames; {figures['iteration_ms']:.2f} ms per iteration as the runner saw them")
    print_rows(figures["per_iteration_ms"])
    cpu = figures["cpu_per_iteration_ms"]
    print("\nCPU per iteration (ms), from the loop's first iteration to the stack's stop: "
          + ", ".join(f"{name} {ms:.2f}" for name, ms in cpu.items())
          + f"; total {sum(cpu.values()):.2f} (on 2 cores the wall time is at least half of it)")


# ------------------------------------------------------------------------------------------------ identity
def _git(*args: str) -> str:
    return subprocess.run(["git", "-C", str(REPO), *args], check=True, capture_output=True, text=True).stdout.strip()


def export(rev: str, directory: Path) -> None:
    """The tree of ``rev`` into ``directory`` (no .git: only its files)."""
    directory.mkdir(parents=True)
    archive = subprocess.Popen(["git", "-C", str(REPO), "archive", rev], stdout=subprocess.PIPE)
    subprocess.run(["tar", "-x", "-C", str(directory)], stdin=archive.stdout, check=True)
    if archive.wait():
        raise RuntimeError(f"git archive {rev} failed")


def snapshot(directory: Path) -> None:
    """This tree's files as they are now (committed or not; git's ignored files left out) into ``directory``: the
    runs then use what was there when the check began, whatever is edited meanwhile."""
    listed = subprocess.run(["git", "-C", str(REPO), "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
                            check=True, capture_output=True).stdout.decode().split("\0")
    for name in filter(None, listed):
        source = REPO / name
        if source.is_file():
            target = directory / name
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(source, target)


def run_identity_set(tree: Path, out: Path) -> dict:
    """The identity runs on the code in ``tree`` (this interpreter, its packages; the tree first on the path), their
    logs under ``out``; each run's JSON output and wall time by name."""
    env = dict(os.environ, PYTHONPATH=str(tree))
    env.pop(ip.PROFILE_DIR_ENV, None)
    results = {}
    for name, args in IDENTITY_RUNS:
        started = time.monotonic()
        done = subprocess.run([sys.executable, "-m", "services.cli", *args, "--out", str(out / name)], cwd=tree,
                              env=env, capture_output=True, text=True)
        try:
            output = json.loads(done.stdout.strip().splitlines()[-1])
        except (ValueError, IndexError):
            raise RuntimeError(f"{name} on {tree} printed no result (exit {done.returncode}): "
                               f"{done.stderr[-2000:]}") from None
        runs = output["runs"] if "runs" in output else [dict(output, label=name)]
        results[name] = {"wall_s": round(time.monotonic() - started, 2),
                         "runs": [{k: r.get(k) for k in ("label", "iterations", "status", "final_error_norm",
                                                           "lockstep_timeouts")} for r in runs]}
    (out / "identity.json").write_text(json.dumps(results, indent=1))
    return results


def compare(base: Path, mine: Path) -> list[str]:
    """What differs between two identity sets' outputs (empty: identical)."""
    problems = []
    base_logs = {p.relative_to(base) for p in base.rglob("trajectory.jsonl")}
    mine_logs = {p.relative_to(mine) for p in mine.rglob("trajectory.jsonl")}
    for missing in sorted(base_logs ^ mine_logs):
        problems.append(f"{missing}: only in {'the base' if missing in base_logs else 'this tree'}")
    for log in sorted(base_logs & mine_logs):
        a, b = (base / log).read_bytes(), (mine / log).read_bytes()
        if a != b:
            lines_a, lines_b = a.splitlines(), b.splitlines()
            first = next((i for i, (x, y) in enumerate(zip(lines_a, lines_b)) if x != y), min(len(lines_a),
                                                                                               len(lines_b)))
            problems.append(f"{log}: differs from line {first + 1} ({len(lines_a)} lines in the base, "
                            f"{len(lines_b)} here)")
    results_a = json.loads((base / "identity.json").read_text())
    results_b = json.loads((mine / "identity.json").read_text())
    for name in results_a:
        if results_a[name]["runs"] != results_b.get(name, {}).get("runs"):
            problems.append(f"{name}: results differ: {results_a[name]['runs']} against "
                            f"{results_b.get(name, {}).get('runs')}")
    return problems


#: how many bases' logs the identity check keeps for reuse (a few MB each), the most recently used
BASES_KEPT = 4
BASE_PREFIX = "mfvs-identity-base-"


def prune_bases(root: Path, kept: int = BASES_KEPT) -> list[Path]:
    """Remove the bases' logs under ``root`` beyond the ``kept`` most recently used (nothing else expires them);
    the ones removed."""
    bases = sorted(root.glob(BASE_PREFIX + "*"), key=lambda path: path.stat().st_mtime, reverse=True)
    for old in bases[kept:]:
        shutil.rmtree(old, ignore_errors=True)
    return bases[kept:]


@contextlib.contextmanager
def _terminated_as_exit():
    """A SIGTERM ends the check through its ``finally`` (its tree copies removed), as Ctrl-C does."""
    def leave(signum, _frame):
        raise SystemExit(128 + signum)

    if threading.current_thread() is not threading.main_thread():  # (only the main thread takes signals)
        yield
        return
    previous = signal.signal(signal.SIGTERM, leave)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def identity(rev: str, hogs: int, fresh: bool, keep: Path | None) -> int:
    with _terminated_as_exit():
        return _identity(rev, hogs, fresh, keep)


def _identity(rev: str, hogs: int, fresh: bool, keep: Path | None) -> int:
    sha = _git("rev-parse", rev)
    bases = Path(tempfile.gettempdir())
    cache = bases / f"{BASE_PREFIX}{sha[:12]}" / (f"hogs{hogs}" if hogs else "quiet")
    work = Path(tempfile.mkdtemp(prefix="mfvs-identity-"))
    try:
        snapshot(work / "tree")
        print(f"base {rev} ({sha[:12]}) against this tree ({_git('rev-parse', '--short', 'HEAD')}"
              f"{', with changes not committed' if _git('status', '--porcelain', '--untracked-files=no') else ''})"
              + (f", {hogs} CPU hogs beside" if hogs else ""), flush=True)
        with cpu_hogs(hogs):
            if fresh or not (cache / "identity.json").is_file():
                shutil.rmtree(cache, ignore_errors=True)
                tree = work / "base"
                export(sha, tree)
                print(f"base: running (load {load()})", flush=True)
                base_results = run_identity_set(tree, cache)
            else:
                base_results = json.loads((cache / "identity.json").read_text())
                print(f"base: its logs from {cache}", flush=True)
            os.utime(cache.parent)  # used now (prune_bases keeps the most recently used)
            prune_bases(bases)
            print(f"this tree: running (load {load()})", flush=True)
            mine = keep or work / "mine"
            mine_results = run_identity_set(work / "tree", mine)
        print(f"load {load()}")
        for name in base_results:
            runs = ", ".join(f"{r['label']} {r['iterations']} it ‖e‖ {r['final_error_norm']}"
                             for r in mine_results[name]["runs"])
            print(f"  {name}: base {base_results[name]['wall_s']:.1f} s, here {mine_results[name]['wall_s']:.1f} s "
                  f"({runs})")
        problems = compare(cache, mine)
        for problem in problems:
            print(f"DIFFERS: {problem}")
        count = len(list(Path(mine).rglob("trajectory.jsonl")))
        print(f"identical: {count} trajectory logs byte for byte, and every run's iterations, status and final "
              f"error" if not problems else f"{len(problems)} difference(s)")
        return 1 if problems else 0
    finally:
        shutil.rmtree(work, ignore_errors=True)


# ------------------------------------------------------------------------------------------------ command line
def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="mfvs bench lockstep", description=__doc__.split("\n\n")[0])
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--scenario", default=str(SCENARIOS / "table2.yaml"),
                        help="the scenario (default examples/scenarios/table2.yaml)")
    parser.add_argument("--law", default="p-joint",
                        help="run this law, with Table 3's gains where it has them (default p-joint; 'scenario': "
                             "the scenario's own law and gains)")
    parser.add_argument("--hogs", type=int, default=0, metavar="N", help="N CPU hogs beside the run(s)")
    parser.add_argument("--identity", action="store_true",
                        help="check instead that lockstep runs are bit-identical to --base's")
    parser.add_argument("--base", default=None, help="the commit to compare with (default: git merge-base HEAD main)")
    parser.add_argument("--fresh", action="store_true", help="run the base again rather than reuse its logs")
    parser.add_argument("--keep", default=None, help="keep this tree's identity outputs in this directory")
    add_arm_option(parser, default=None, what="the scenario's; --identity: the runs' own")
    args = parser.parse_args(argv)
    if args.arm is not None and unknown_arm(parser, args):
        return 2
    if args.hogs < 0:
        print("mfvs bench lockstep: --hogs must be 0 or more", file=sys.stderr)
        return 2
    if args.identity:
        base = args.base or _git("merge-base", "HEAD", "main")
        return identity(base, args.hogs, args.fresh, Path(args.keep) if args.keep else None)
    from services.runtime.config import ConfigError

    try:
        scenario = on_arm(load_scenario(args.scenario), args.arm, args.scenario)
    except (ConfigError, ValueError) as exc:
        print(f"mfvs bench lockstep: {exc}", file=sys.stderr)
        return 2
    if args.law != "scenario":
        if args.law not in LAW_NAMES:
            print(f"mfvs bench lockstep: unknown law {args.law!r}; known: {', '.join(LAW_NAMES)}", file=sys.stderr)
            return 2
        scenario.law = args.law
        scenario.gains = TABLE3_GAINS.get(args.law, scenario.gains)
    figures = profile_run(scenario, args.hogs)
    figures["composed"] = composed_run(scenario, args.hogs)
    if args.json:
        print(json.dumps(figures))
    else:
        camera = scenario.camera
        print_profile(figures, f"{Path(args.scenario).name}, law {scenario.law}, {camera.width}×{camera.height}, "
                               "sim profile, lockstep, every service a process of its own (--processes)")
        print_composed(figures["composed"])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
