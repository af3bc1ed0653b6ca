"""CPU hogs: processes spinning on a core each, as another program on a shared machine would, for benchmarks and
tests that must stay correct beside them (late, counted, never faster).

Plain processes, not multiprocessing's (those would re-import the caller's main module). Each hog ends with the
thread that started it, however that ends (a bench killed by a signal, a test run interrupted): it asks the kernel
for SIGKILL when its parent goes (PR_SET_PDEATHSIG), and checks it was not orphaned before it asked. Start them
from a thread that outlives the block (the main thread)."""
from __future__ import annotations

import contextlib
import os
import subprocess
import sys
from collections.abc import Iterator

#: the hog: SIGKILL when its parent ends (prctl PR_SET_PDEATHSIG = 1), unless that happened already, then spin
HOG = """
import ctypes, os, signal, sys
ctypes.CDLL(None).prctl(1, signal.SIGKILL)
if os.getppid() != int(sys.argv[1]):
    sys.exit(0)
while True:
    pass
"""


@contextlib.contextmanager
def cpu_hogs(count: int | None = None) -> Iterator[list[subprocess.Popen]]:
    """``count`` hogs (default: one per core) for as long as the block runs."""
    count = (os.cpu_count() or 1) if count is None else count
    hogs = [subprocess.Popen([sys.executable, "-c", HOG, str(os.getpid())]) for _ in range(count)]
    try:
        yield hogs
    finally:
        for hog in hogs:
            hog.kill()
            hog.wait(timeout=5)
