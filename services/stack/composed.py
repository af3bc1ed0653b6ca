"""A lockstep stack composed in one process: the same services, on one zenoh session.

What ROS 2 calls composition (several nodes in one container process, talking through intra-process
communication): safety, vision, the controller and robot_sim run here as the very objects their processes would
run (:func:`services.runtime.service.service_main` builds the same ones from the same configs), each declaring its
subscribers, publishers, queryables and liveliness token on one zenoh session that has no network at all (peer
mode, no listen endpoint, no scouting): zenoh delivers every message within the session, as bytes, encoded and
decoded and validated as over a network. robot_sim renders its camera in its loop's thread, as it does in lockstep
as a process (:class:`services.robot_sim.camera.LoopCamera`).

Only for lockstep, where what a run computes does not depend on how its processes are scheduled (the robot waits for
every answer; :mod:`services.runtime.service`): a run composed gives the same trajectory log, byte for byte, as
the same run with every service a process of its own (:class:`services.stack.LocalStack`;
``tests/services/stack/test_composed.py``, ``mfvs bench lockstep --identity``). What it saves is what a run spends
moving messages between five processes: the router's hop, the sockets, a dozen process switches an iteration (Table 3's
run on one core: 11.8-12.4 → 8.1-9.0 ms an iteration). In realtime the services keep a process each: in one
interpreter they take turns on its lock, and the arm's 500 Hz loop with them (:class:`~services.stack.LocalStack`).

Every subscriber's callbacks, the services' and the runner's, run on one thread of the stack's, in the order their
samples arrived (:class:`CallbackExecutor`, ROS 2's single-threaded executor), where zenoh would run each
subscriber's on a Python thread of its own.

What differs from processes, besides speed: a native crash in one service (MuJoCo, OpenCV, zenoh) ends the whole
run rather than its process, and the services' logs go to their files here through :mod:`logging` handlers of this
process (``<name>.log``, kept when the start fails) rather than through each process's stderr.
"""
from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import json
import logging
import threading
from collections import deque
from pathlib import Path
from typing import Any, Callable, Optional

import zenoh

from protocol.conventions import ClockMode
from services.controller.service import ControllerService
from services.robot_sim.service import robot_sim_service
from services.runtime.logs import LOG_FORMAT, RateLimitedLogger, log_level
from services.runtime.service import Service
from services.runtime.threads import start_thread
from services.safety.service import SafetyService
from services.stack.local import PIPELINE, StackConfig, StackLogs, lockstep_robot
from services.vision.service import VisionService

log = logging.getLogger("mfvs.composed")

#: the services of a composed stack by name, as their processes build them (``python -m services.<name>``)
SERVICE_TYPES: dict[str, Callable[..., Service]] = {"safety": SafetyService, "vision": VisionService,
                                                    "controller": ControllerService, "robot_sim": robot_sim_service}


def composable(config: StackConfig) -> bool:
    """Whether this stack can run composed: lockstep, with robot_sim driving its simulated arm itself (the gateway
    profile's emulated bus runs between processes, as on a real arm)."""
    return config.clock is ClockMode.LOCKSTEP and config.profile == "sim"


def open_local_session() -> zenoh.Session:
    """A zenoh session that reaches nothing beyond this process: peer mode with no endpoint to listen on or connect
    to, no scouting (without the empty listen list zenoh opens a TCP port of its choice)."""
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps("peer"))
    conf.insert_json5("listen/endpoints", "[]")
    conf.insert_json5("connect/endpoints", "[]")
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("scouting/gossip/enabled", "false")
    return zenoh.open(conf)


def return_freed_memory() -> None:
    """Give the memory freed in this process back to the system (glibc's ``malloc_trim``; nothing elsewhere). glibc
    keeps what a thread frees in that thread's arena, and every composed run starts threads of its own: a process
    running one composed run after another (an experiment's runs in one process, a worker of ``--jobs``) grew by
    ~20 MB a run, to ~500 MB after 16 runs; trimmed after each, by ~1 MB a run (24 runs measured)."""
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        libc.malloc_trim(0)
    except (OSError, AttributeError):  # not glibc
        pass


class CallbackExecutor:
    """One thread that runs the subscriber callbacks of a composed stack, one after another, in the order their
    samples arrived (ROS 2's single-threaded executor). zenoh hands each sample over inline, in the publisher's
    ``put`` (``handlers.Callback(indirect=False)``): an append and a wake-up, so no service's code runs inside zenoh
    or inside a publisher's critical section. zenoh's default runs each subscriber's callbacks on a Python thread of
    its own instead: about 25 deliveries an iteration, each a thread to wake that then waits its turn for the
    interpreter's lock (p-joint on two cores: 8.9-9.8 → 8.5-8.8 ms an iteration, interleaved in one hour).

    One thread runs them all, so a callback must not wait for another one: the services' and the runner's take
    their own locks briefly and notify (a vision frame goes to vision's worker, the law runs in the controller's
    features callback). A callback that raises is logged and counted (:attr:`failures`); the next one runs."""

    def __init__(self, name: str = "composed-callbacks") -> None:
        self._queue: deque[tuple[Callable[[Any], None], Any]] = deque()
        self._ready = threading.Condition(threading.Lock())
        self._closed = False
        self.failures = 0
        self._limited_log = RateLimitedLogger(log)
        self._thread = start_thread(self._run, name)

    def submit(self, callback: Callable[[Any], None], sample: Any) -> None:
        with self._ready:
            if not self._closed:
                self._queue.append((callback, sample))
                self._ready.notify()

    def _run(self) -> None:
        while True:
            with self._ready:
                while not self._queue and not self._closed:
                    self._ready.wait()
                if self._closed:
                    return
                callback, sample = self._queue.popleft()
            try:
                callback(sample)
            except Exception as exc:  # the services catch their handlers' failures: this is a runner's or a recorder's
                self.failures += 1
                if self._limited_log.error(type(exc).__name__, "a subscriber's callback failed (%d so far): %r",
                                           self.failures, exc):
                    log.debug("callback failure", exc_info=True)

    def close(self, timeout_s: float = 5.0) -> None:
        """Stop the thread; callbacks still queued are dropped (their subscribers' services have stopped)."""
        with self._ready:
            self._closed = True
            self._queue.clear()
            self._ready.notify()
        if self._thread is not threading.current_thread():
            self._thread.join(timeout_s)


def _inline(callback: Callable[[Any], None]):
    """``callback`` for zenoh to call in the thread that delivers the sample (the publisher's, within a session);
    a zenoh without that choice (unstable in zenoh-python 1.10) calls it on a thread of its own, which then hands
    the sample over: slower, the same run."""
    try:
        return zenoh.handlers.Callback(callback, indirect=False)
    except TypeError:
        return callback


class _ExecutedCallback:
    """A subscriber's callback, run by the stack's executor while the subscriber is declared (samples still queued
    when it is undeclared are dropped, as zenoh drops those of an undeclared subscriber)."""

    def __init__(self, callback: Callable[[Any], None], executor: CallbackExecutor) -> None:
        self.callback, self.executor, self.declared = callback, executor, True

    def hand_over(self, sample: Any) -> None:
        self.executor.submit(self._run, sample)

    def _run(self, sample: Any) -> None:
        if self.declared:
            self.callback(sample)


class _ExecutedSubscriber:
    def __init__(self, subscriber, callback: _ExecutedCallback) -> None:
        self._subscriber, self._callback = subscriber, callback

    def __getattr__(self, name: str):
        return getattr(self._subscriber, name)

    def undeclare(self) -> None:
        self._callback.declared = False
        self._subscriber.undeclare()


class SharedSession:
    """The composed stack's session as a service or a client of it sees it (the runner, a recorder): everything but
    ``close``, which the stack does when it stops, and with an executor, every subscriber's callbacks run by it."""

    def __init__(self, session: zenoh.Session, executor: Optional[CallbackExecutor] = None) -> None:
        self._session = session
        self._executor = executor

    def __getattr__(self, name: str):
        return getattr(self._session, name)

    def declare_subscriber(self, key_expr, handler=None, **options):
        if self._executor is None or not callable(handler) or isinstance(handler, zenoh.handlers.Callback):
            return self._session.declare_subscriber(key_expr, handler, **options)
        callback = _ExecutedCallback(handler, self._executor)
        return _ExecutedSubscriber(self._session.declare_subscriber(key_expr, _inline(callback.hand_over), **options),
                                   callback)

    def close(self) -> None:
        pass

    def __enter__(self) -> "SharedSession":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


#: the loggers of libraries that one service of a composed stack alone uses, logged with its own (MuJoCo's warnings,
#: :func:`services.model.arm.mujoco_module`, are robot_sim's)
LIBRARY_LOGGERS = {"robot_sim": ("mujoco",)}


@contextlib.contextmanager
def _service_logs(directory: Path, levels: dict[str, str]):
    """Each service's log records (its logger ``mfvs.<name>``, the loggers under it and its libraries') into
    ``<name>.log`` in ``directory``, at its configured level, and not to this process's own handlers, while the
    block runs. (Python's ``warnings`` still go to this process's stderr.)"""
    saved = []
    try:
        for name, level in levels.items():
            handler = logging.FileHandler(directory / f"{name}.log")
            handler.setFormatter(logging.Formatter(LOG_FORMAT))
            for logger_name in (f"mfvs.{name}", *LIBRARY_LOGGERS.get(name, ())):
                logger = logging.getLogger(logger_name)
                saved.append((logger, handler, logger.level, logger.propagate))
                logger.addHandler(handler)
                logger.setLevel(log_level(level))
                logger.propagate = False
        yield
    finally:
        for logger, handler, level, propagate in reversed(saved):
            logger.removeHandler(handler)
            handler.close()
            logger.setLevel(level)
            logger.propagate = propagate


class ComposedStack:
    """The sim profile's services in lockstep, in this process on one session (see the module's docstring): the
    same interface as :class:`services.stack.LocalStack` for a runner (``open_session``, ``robot_alive``,
    ``before_robot``, ``logs``). Use as a context manager."""

    def __init__(self, config: StackConfig, before_robot: Optional[Callable[["ComposedStack"], None]] = None) -> None:
        if not composable(config):
            raise ValueError(f"a composed stack runs the sim profile in lockstep, not the {config.profile} profile "
                             f"in {config.clock.value}")
        self.config = config
        self._before_robot = before_robot
        self.services: dict[str, Service] = {}
        self.session: Optional[zenoh.Session] = None
        self.executor: Optional[CallbackExecutor] = None
        self._logs = StackLogs("mfvs-stack-")
        self.logs = self._logs.path
        self._log_context: Optional[contextlib.AbstractContextManager] = None

    def __enter__(self) -> "ComposedStack":
        cfg = self.config
        service_configs = cfg.services()
        for service_cfg in service_configs.values():
            service_cfg.clock = cfg.clock
        lockstep_robot(cfg.robot)
        self._log_context = _service_logs(self.logs, {name: c.log_level for name, c in service_configs.items()})
        self._log_context.__enter__()
        try:
            self.session = open_local_session()
            self.executor = CallbackExecutor()
            for name in PIPELINE:
                self._start(name, service_configs[name])
            if self._before_robot is not None:
                self._before_robot(self)
            self._start("robot_sim", cfg.robot)
        except BaseException:
            self._logs.keep()
            self.__exit__(None, None, None)
            raise
        return self

    def _start(self, name: str, config) -> None:
        try:
            service = SERVICE_TYPES[name](config)
        except (ValueError, OSError) as exc:  # what the config names cannot be had (service_main's StartupError)
            raise RuntimeError(f"{name} did not start: {exc} (logs in {self.logs})") from exc
        # the stack stops it even when its start fails halfway: in a process of its own the threads its on_start
        # began ended with the process, here they would go on in the runner's
        self.services[name] = service
        service.start(session=SharedSession(self.session, self.executor))

    def open_session(self) -> SharedSession:
        """The stack's session, for a client of it in this process (closing it leaves the stack's open)."""
        if self.session is None:
            raise RuntimeError("the composed stack is not running")
        return SharedSession(self.session, self.executor)

    def robot_alive(self) -> bool:
        """The robot service still runs (as its process would: a loop that ended leaves it serving)."""
        robot = self.services.get("robot_sim")
        return robot is not None and robot.state == "running"

    def __exit__(self, *exc) -> None:
        """Every step is taken even when one before it fails (or a Ctrl-C comes during a stop's joins): the
        services, the session, this process's logging and the memory are the runner's afterwards."""
        with contextlib.ExitStack() as steps:  # its callbacks run last-in first-out, each whatever the others did
            steps.callback(return_freed_memory)
            steps.callback(self._logs.close)
            steps.callback(self._restore_logging)
            steps.callback(self._close_session)
            steps.callback(self._close_executor)
            # the robot first: it stops the arm while safety listens; then the pipeline, in reverse
            for name in (*PIPELINE, "robot_sim"):
                service = self.services.pop(name, None)
                if service is not None:
                    steps.callback(service.stop)

    def _close_executor(self) -> None:
        if self.executor is not None:
            executor, self.executor = self.executor, None
            executor.close()

    def _close_session(self) -> None:
        if self.session is not None:
            session, self.session = self.session, None
            session.close()

    def _restore_logging(self) -> None:
        if self._log_context is not None:
            context, self._log_context = self._log_context, None
            context.__exit__(None, None, None)
