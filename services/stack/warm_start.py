"""Services started warm: forked from a server that has imported them already (a local stack in lockstep).

A lockstep experiment starts a whole stack for every run; each service's interpreter then imported NumPy, MuJoCo,
Pinocchio, OpenCV and zenoh again (0.2-0.4 s of CPU a service, four services a run, before the first frame). Here
those imports happen once, in a fork server (:mod:`multiprocessing`'s ``forkserver``: a clean interpreter started
for this purpose, not a copy of the caller), and every service of every later run is a fork of it that runs exactly
what ``python -m services.<name> ARGS`` runs: the same module as ``__main__``, the same arguments, in a session of
its own, its output in its log. What a service computes is unchanged; only its imports are shared.

Fork safety: the server must have no thread but its own when it forks, and the libraries it imports start none
(measured: none after the imports below) except OpenBLAS's pool, which NumPy and OpenCV start at import with more
than one core: the server is started with ``OPENBLAS_NUM_THREADS=1``, so the services it forks run their (small,
7×7) linear algebra on the calling thread. Realtime stacks keep starting every service as a process of its own
(:func:`services.stack.launcher.spawn`), as ``mfvs up`` does.

The workers of :mod:`services.experiments.pool` are forks of the same server (a composed run,
:mod:`services.stack.composed`, then runs its services in the worker itself, imported already), and fork their stacks' services from it too when
each runs as a process (``--processes``; :func:`fork_from_server_at`): one server for a whole experiment. This
leans further on CPython's forkserver internals (the server's address and "alive" descriptor, 3.8-3.13), like
:class:`_ServicePopen`.
"""
from __future__ import annotations

import atexit
import io
import multiprocessing
import os
import runpy
import subprocess
import sys
import threading
from multiprocessing import forkserver, popen_forkserver, process, reduction, spawn, util
from pathlib import Path
from typing import Optional

#: what the fork server imports before its first fork: every service a local lockstep stack runs, and the runner
#: of experiments (services.experiments.pool's workers are forked from it too)
PRELOADED = ("services.safety.service", "services.vision.service", "services.controller.service",
             "services.robot_sim.service", "services.servo", "services.experiments.pool")

_server_lock = threading.Lock()
_server_started = False


def start_server() -> None:
    """The fork server, started if it is not running (with the environment it must import in): on first use, or
    earlier by a command whose own imports its imports (~0.35 s of CPU) can then run beside, on another core."""
    global _server_started
    with _server_lock:
        if _server_started:
            return
        multiprocessing.get_context("forkserver").set_forkserver_preload(list(PRELOADED))
        server_env = {"OPENBLAS_NUM_THREADS": "1", "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
        saved = {name: os.environ.get(name) for name in server_env}
        os.environ.update(server_env)  # the server copies this process's environment as it starts
        try:
            forkserver.ensure_running()
        finally:
            for name, value in saved.items():
                if value is None:
                    os.environ.pop(name, None)
                else:
                    os.environ[name] = value
        _server_started = True


def server_address() -> str:
    """The fork server's address (started if it was not): a process forked from it may fork from it too
    (:func:`fork_from_server_at`)."""
    start_server()
    return forkserver._forkserver._forkserver_address


def fork_from_server_at(address: str) -> None:
    """In a process the fork server forked (services.experiments.pool's workers): fork services from that same server
    instead of starting a server of its own (0.3-0.4 s of imports a worker, before its first run). Such a process
    holds the server's "alive" descriptor already (multiprocessing hands it to every child of the server); what it
    lacks is the address, and a ``ensure_running`` that would start a server because it did not start this one."""
    global _server_started
    server = forkserver._forkserver
    if server._forkserver_alive_fd is None:
        raise RuntimeError("not a process the fork server forked")
    with _server_lock:
        server._forkserver_address = address
        server.ensure_running = lambda: None  # the server runs: its caller keeps it (and it them) alive
        _server_started = True


def _run_module(module: str, argv: list[str], env: dict, log: str, cwd: str, cores: set[int]) -> None:
    """In the forked child: ``python -m module *argv`` with this environment, on these cores, output to ``log``."""
    os.sched_setaffinity(0, cores)  # the caller's, as a process it spawned would inherit them (services.experiments.pool)
    os.setsid()  # a session of its own, as launcher.spawn gives: a terminal's Ctrl-C is the stack's to handle
    out = os.open(log, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
    os.dup2(out, 1)
    os.dup2(out, 2)
    os.close(out)
    os.chdir(cwd)
    os.environ.clear()
    os.environ.update(env)
    sys.argv = [module, *argv]
    code = 0
    try:
        runpy.run_module(module, run_name="__main__", alter_sys=True)
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
        if not isinstance(exc.code, (int, type(None))):
            print(exc.code, file=sys.stderr)
    finally:
        atexit._run_exitfuncs()  # what the interpreter runs at its exit (the service's own, logging's), as it would
        sys.stdout.flush()
        sys.stderr.flush()
    os._exit(code)


class _ServicePopen(popen_forkserver.Popen):
    """The fork server's child, told nothing of this process's ``__main__``: a service is a program of its own
    (``multiprocessing`` has every child import the parent's main module, as spawn must: an experiment's command,
    a test runner, a script read from standard input). CPython's own launch otherwise (3.8-3.13)."""

    def _launch(self, process_obj):
        prep_data = spawn.get_preparation_data(process_obj._name)
        prep_data.pop("init_main_from_name", None)
        prep_data.pop("init_main_from_path", None)
        buf = io.BytesIO()
        multiprocessing.context.set_spawning_popen(self)
        try:
            reduction.dump(prep_data, buf)
            reduction.dump(process_obj, buf)
        finally:
            multiprocessing.context.set_spawning_popen(None)
        self.sentinel, w = forkserver.connect_to_new_process(self._fds)
        parent_w = os.dup(w)  # the child's sign that this process lives (as the base keeps it)
        self.finalizer = util.Finalize(self, util.close_fds, (parent_w, self.sentinel))
        with open(w, "wb", closefd=True) as f:
            f.write(buf.getbuffer())
        self.pid = forkserver.read_signed(self.sentinel)


class WarmProcessObject(process.BaseProcess):
    """A process forked from the fork server, knowing nothing of this process's ``__main__``."""

    _start_method = "forkserver"

    @staticmethod
    def _Popen(process_obj):
        start_server()
        return _ServicePopen(process_obj)


class WarmContext(multiprocessing.context.ForkServerContext):
    """multiprocessing's forkserver context, its processes :class:`WarmProcessObject` (for a process pool whose
    workers start with the experiments' imports done: ``ProcessPoolExecutor(mp_context=WarmContext())``)."""

    Process = WarmProcessObject


class WarmProcess:
    """A forked service, with the part of :class:`subprocess.Popen`'s interface the stack uses."""

    def __init__(self, args: list[str], process) -> None:
        self.args = args
        self._process = process
        self.pid = process.pid
        self.stdout = None

    @property
    def returncode(self) -> Optional[int]:
        return self._process.exitcode

    def poll(self) -> Optional[int]:
        return self._process.exitcode

    def terminate(self) -> None:
        if self._process.exitcode is None:
            self._process.terminate()

    def kill(self) -> None:
        if self._process.exitcode is None:
            self._process.kill()

    def wait(self, timeout: Optional[float] = None) -> int:
        self._process.join(timeout)
        if self._process.exitcode is None:
            raise subprocess.TimeoutExpired(self.args, timeout)
        return self._process.exitcode


def spawn_warm(args: list[str], log: Path, cwd: Path) -> WarmProcess:
    """``args`` (``[python, -m, services.<name>, ...]``, as :func:`services.stack.launcher.service_command` gives them)
    forked from the fork server, logging to ``log``."""
    if len(args) < 3 or args[1] != "-m":
        raise ValueError(f"not a `python -m module` command: {args}")
    from services.stack.launcher import service_environment

    process = WarmProcessObject(target=_run_module, name=args[2], args=(
        args[2], args[3:], service_environment(), str(log), str(cwd), os.sched_getaffinity(0)))
    process.start()
    return WarmProcess(args, process)
