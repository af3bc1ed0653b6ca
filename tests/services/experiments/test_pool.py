"""services.experiments.pool's workers and services.stack.warm_start's services: where they run."""
import os
import subprocess
import sys
from concurrent.futures import ProcessPoolExecutor

import pytest

from services.experiments.pool import _init_worker, worker_cores
from services.stack.warm_start import WarmContext, server_address, spawn_warm
from tests.helpers import REPO
from tests.stack import wait_for

CORES = sorted(os.sched_getaffinity(0))
several_cores = pytest.mark.skipif(len(CORES) < 2, reason="needs a host with two cores or more")


def test_workers_take_one_core_each_round_the_cores():
    assert [worker_cores([0, 1], k) for k in range(5)] == [{0}, {1}, {0}, {1}, {0}]
    assert [worker_cores({5, 2, 9}, k) for k in range(4)] == [{2}, {5}, {9}, {2}]
    assert worker_cores([3], 7) == {3}


@several_cores
def test_pool_workers_run_on_one_core_of_the_callers():
    context = WarmContext()
    with ProcessPoolExecutor(max_workers=2, mp_context=context, initializer=_init_worker,
                             initargs=(None, dict(os.environ), context.Value("i", 0), CORES,
                                       server_address())) as pool:
        seen = list(pool.map(os.sched_getaffinity, [0] * 6))
    assert all(len(cores) == 1 and cores <= set(CORES) for cores in seen), seen


def test_pool_workers_fork_their_stacks_from_the_server_they_came_from():
    context = WarmContext()
    with ProcessPoolExecutor(max_workers=2, mp_context=context, initializer=_init_worker,
                             initargs=(None, dict(os.environ), context.Value("i", 0), CORES,
                                       server_address())) as pool:
        addresses = {pool.submit(server_address).result() for _ in range(4)}  # else: a server of its own
    assert addresses == {server_address()}


@several_cores
def test_a_warm_service_runs_on_the_cores_of_the_process_that_started_it(tmp_path):
    before = os.sched_getaffinity(0)
    os.sched_setaffinity(0, {CORES[-1]})
    try:  # the fork server was started with every core (by an earlier test, or now, inheriting this one's)
        process = spawn_warm([sys.executable, "-m", "services.cli", "router", "--port", "0"],
                             tmp_path / "router.log", REPO)
    finally:
        os.sched_setaffinity(0, before)
    try:
        log = tmp_path / "router.log"
        assert wait_for(lambda: log.exists() and '"router"' in log.read_text(), timeout=20)  # the module runs
        status = f"/proc/{process.pid}/status"
        allowed = next(line for line in open(status) if line.startswith("Cpus_allowed_list:")).split()[1]
        assert allowed == str(CORES[-1])
    finally:
        process.terminate()
        process.wait(timeout=10)


def test_rasteriser_threads_one_rule_for_every_renderer():
    script = ("import os, sys; os.sched_setaffinity(0, {int(sys.argv[1])} if sys.argv[1] != 'all' else "
              "os.sched_getaffinity(0));"
              "from services.robot_sim.camera import choose_rasteriser_threads as rule;"
              "rule(realtime=sys.argv[2] == 'rt');"
              "print(os.environ.get('LP_NUM_THREADS'))")

    def threads(cores: str, realtime: bool = False, **env) -> str:
        environment = {k: v for k, v in os.environ.items()
                       if k not in ("LP_NUM_THREADS", "MFVS_LP_NUM_THREADS_CHOSEN")} | env
        return subprocess.run([sys.executable, "-c", script, cores, "rt" if realtime else "lockstep"], cwd=REPO,
                              env=environment, text=True, capture_output=True, check=True).stdout.strip()

    assert threads(str(CORES[0])) == "0"  # lockstep allowed one core: the calling thread renders
    assert threads(str(CORES[0]), LP_NUM_THREADS="2") == "2"  # the user's choice stands
    assert threads("all", realtime=True) == "0"  # realtime: the renderer's own thread, at the camera's priority
    assert threads("all", realtime=True, LP_NUM_THREADS="3") == "3"
    if len(CORES) > 1:
        assert threads("all") == str(2 * len(CORES))  # lockstep on more cores: two a core
    # what a process inherits from one where mfvs chose (a lockstep run's threads) is chosen again, not kept
    inherited = {"LP_NUM_THREADS": "4", "MFVS_LP_NUM_THREADS_CHOSEN": "4"}
    assert threads("all", realtime=True, **inherited) == "0"
    assert threads(str(CORES[0]), **inherited) == "0"
