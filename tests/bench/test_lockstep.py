"""mfvs bench lockstep: the profile of a lockstep run is complete and adds up; the identity check finds a
difference, keeps a few bases' logs and leaves no tree copy behind when stopped."""
import json
import math
import os
import signal
import subprocess
import sys
import time

import pytest

from bench.cpu import process_tree
from bench.lockstep import (BASE_PREFIX, REPO, ROWS, SCENARIOS, _RunChildren, compare, composed_run, profile_run,
                            prune_bases)
from services.servo.scenario import load_scenario
from services.vision.core import VisionCore


def test_the_profile_of_a_run_has_every_row_and_they_add_up_to_the_iteration():
    scenario = load_scenario(SCENARIOS / "easy.yaml")
    scenario.convergence.max_iterations = 25
    figures = profile_run(scenario)
    assert figures["iterations"] == 25 and figures["lockstep_timeouts"] == 0
    assert figures["frames"] >= 25
    rows = figures["per_iteration_ms"]
    assert set(rows) == {key for key, _ in ROWS} | {"total"}
    assert all(math.isfinite(v) for v in rows.values())
    # every part of the loop and every service on the path was timed (a renamed function would show as 0)
    for key in ("  physics", "  actuators", "  bus", "  node", "  state", "  publish", "  detection", "  law",
                "  safety", "  messages", "waits"):
        assert rows[key] > 0, key
    assert rows["rendering"] + rows["  render_process"] > 0
    parts = rows["robot_loop"] + rows["rendering"] + rows["waits"]
    assert parts == pytest.approx(rows["total"], abs=0.01)
    assert rows["robot_loop"] == pytest.approx(sum(rows[k] for k in ("  physics", "  actuators", "  bus", "  node",
                                                                      "  state", "  publish", "  frame_snapshot")),
                                               abs=0.01)
    assert set(figures["cpu_per_iteration_ms"]) == {"robot_sim", "vision", "controller", "safety", "router", "runner"}
    assert all(v > 0 for v in figures["cpu_per_iteration_ms"].values())


def test_the_composed_run_is_timed_as_the_same_run(tmp_path):
    """The bench's composed figures are of composed runs of the same run as the profiled one (25 iterations): one
    as it is for the time and CPU, one timed for the split as the processes' run is; the timers are gone
    afterwards."""
    scenario = load_scenario(SCENARIOS / "easy.yaml")
    scenario.convergence.max_iterations = 25
    figures = composed_run(scenario)
    assert not getattr(VisionCore.process, "__wrapped_by_profile__", False)
    assert (figures["stack"], figures["iterations"], figures["lockstep_timeouts"]) == ("composed", 25, 0)
    assert figures["iteration_ms"] > 0 and figures["cpu_per_iteration_ms"]["the process"] > 0
    assert figures["profiled_iteration_ms"] > 0 and figures["frames"] >= 25
    assert figures["cpu_per_iteration_ms"]["its children"] == 0  # lockstep renders in robot_sim's loop thread
    # every service's part timed in the one process they shared (a function renamed would show as 0)
    rows = figures["per_iteration_ms"]
    assert set(rows) == {key for key, _ in ROWS} | {"total"}
    for key in ("  physics", "  actuators", "  bus", "  node", "  state", "  publish", "rendering", "  detection",
                "  law", "  safety", "  messages", "waits"):
        assert rows[key] > 0, key
    assert rows["  render_process"] == 0
    assert rows["robot_loop"] + rows["rendering"] + rows["waits"] == pytest.approx(rows["total"], abs=0.01)


BURN = ("import sys, time\nstart = time.process_time()\nwhile time.process_time() - start < 0.2:\n    pass\n"
        "print('burnt', flush=True)\nsys.stdin.read()\n")


def _burnt_child() -> subprocess.Popen:
    """A child that has spent 0.2 s of CPU and waits for its stdin to close."""
    child = subprocess.Popen([sys.executable, "-c", BURN], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    assert child.stdout.readline() == "burnt\n"
    return child


def test_a_runs_children_are_the_processes_it_started_not_one_reaped_during_it():
    """The composed figures' children's CPU is that of the processes the run started: a child this process had
    before (an earlier run's, an earlier test's) and reaps during the run is not counted; one started during it is."""
    older = _burnt_child()
    run_children = _RunChildren(older=set(process_tree(os.getpid())), period_s=0.02)
    reaped_before = os.times()
    run_children.start()
    older.stdin.close()
    older.wait(timeout=10)  # reaped in the window: os.times() would count its 0.2 s
    new = _burnt_child()
    time.sleep(0.2)  # sampled
    new.stdin.close()
    new.wait(timeout=10)
    spent = run_children.stop()
    reaped_after = os.times()
    reaped = sum(reaped_after[2:4]) - sum(reaped_before[2:4])  # what os.times counts: both children, whole
    assert reaped >= 0.4 and 0.2 <= spent < 0.4, (reaped, spent)  # the new child's 0.2 s and its start-up

def _identity_set(root, logs):
    runs = {}
    for name, text in logs.items():
        (root / name).mkdir(parents=True)
        (root / name / "trajectory.jsonl").write_text(text)
        runs[name] = {"wall_s": 1.0, "runs": [{"label": name, "iterations": text.count("\n")}]}
    (root / "identity.json").write_text(json.dumps(runs))


def test_the_identity_check_finds_a_log_that_differs(tmp_path):
    _identity_set(tmp_path / "a", {"x": '{"i": 1}\n{"i": 2}\n', "y": '{"i": 1}\n'})
    _identity_set(tmp_path / "b", {"x": '{"i": 1}\n{"i": 3}\n', "y": '{"i": 1}\n'})
    _identity_set(tmp_path / "c", {"x": '{"i": 1}\n{"i": 2}\n', "y": '{"i": 1}\n'})
    assert compare(tmp_path / "a", tmp_path / "c") == []
    problems = compare(tmp_path / "a", tmp_path / "b")
    assert len(problems) == 1 and problems[0].startswith("x/trajectory.jsonl: differs from line 2")


def test_the_identity_check_keeps_the_most_recently_used_bases_logs(tmp_path):
    for age, name in enumerate(["aaa", "bbb", "ccc", "ddd", "eee", "fff"]):
        base = tmp_path / f"{BASE_PREFIX}{name}"
        (base / "quiet").mkdir(parents=True)
        os.utime(base, (1e9 - age * 100, 1e9 - age * 100))  # aaa used last
    (tmp_path / "mfvs-identity-elsewhere").mkdir()
    removed = prune_bases(tmp_path, kept=4)
    assert sorted(p.name for p in removed) == [f"{BASE_PREFIX}eee", f"{BASE_PREFIX}fff"]
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        [f"{BASE_PREFIX}{n}" for n in ("aaa", "bbb", "ccc", "ddd")] + ["mfvs-identity-elsewhere"])


def test_an_identity_check_stopped_with_sigterm_removes_its_tree_copy(tmp_path):
    """The check copies this tree before it runs anything; a SIGTERM (a runner's timeout, `kill`) then ends it
    through its cleanup, as Ctrl-C does, rather than leaving the copy in the temporary directory."""
    env = dict(os.environ, TMPDIR=str(tmp_path))
    check = subprocess.Popen([sys.executable, "-m", "services.cli", "bench", "lockstep", "--identity", "--base",
                              "HEAD"], cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        deadline = time.monotonic() + 60
        while not any((copy / "tree" / "README.md").exists() for copy in tmp_path.glob("mfvs-identity-*")):
            assert check.poll() is None and time.monotonic() < deadline, check.stdout.read()
            time.sleep(0.05)
        check.send_signal(signal.SIGTERM)
        output, _ = check.communicate(timeout=60)
    finally:
        check.kill()
    assert check.returncode == 128 + signal.SIGTERM, output
    assert [p.name for p in tmp_path.iterdir() if not p.name.startswith(BASE_PREFIX)] == []
