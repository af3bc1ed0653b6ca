"""Threads the operating system can tell apart.

Python names its threads for itself only: ``top -H``, ``ps -L`` and ``mfvs bench cpu --threads`` see every thread
of a service as ``python``. :func:`start_thread` gives the kernel the thread's name too (PR_SET_NAME, first 15
bytes), so the CPU a loop costs can be read per thread, next to zenoh's own named threads.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import threading
from typing import Callable

PR_SET_NAME = 15
_KERNEL_NAME_BYTES = 15

try:
    _libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
except OSError:  # not glibc/musl: names stay Python's own
    _libc = None


def name_os_thread(name: str) -> bool:
    """The calling thread's kernel name (``/proc/<pid>/task/<tid>/comm``); False where the OS has none."""
    if _libc is None:
        return False
    return _libc.prctl(PR_SET_NAME, name.encode()[:_KERNEL_NAME_BYTES], 0, 0, 0) == 0


def start_thread(target: Callable[[], object], name: str, daemon: bool = True) -> threading.Thread:
    """A started thread running ``target``, named ``name`` for Python and for the kernel."""
    def named_target() -> None:
        name_os_thread(name)
        target()

    thread = threading.Thread(target=named_target, name=name, daemon=daemon)
    thread.start()
    return thread


#: how often a waiting main thread runs the signal handlers that may have been tripped meanwhile
SIGNAL_CHECK_S = 0.2


def wait_until_set(event: threading.Event) -> None:
    """Until ``event`` is set, on the main thread of a process whose SIGTERM/SIGINT handlers set it. The kernel
    hands a signal sent to the process to any of its threads: when that is one of zenoh's, Python only notes it, and
    runs the handler when the main thread next runs Python code, which a wait without a timeout never does (mfvs
    router then ignored SIGTERM until its stack killed it 10 s later, about one lockstep run in twenty with the
    stack's processes on one core). Waking now and then runs it."""
    while not event.wait(SIGNAL_CHECK_S):
        pass


def run_loop(body: Callable[[], object], what: str, log, counters, finished: threading.Event) -> None:
    """Run a service's loop ``body`` to its end: a failure is logged (``what`` failed) and counted
    (``errors.loop``), never raised into the thread, and ``finished`` is set however it ends."""
    try:
        body()
    except Exception:
        log.exception(f"{what} failed")
        counters.inc("errors.loop")
    finally:
        finished.set()
