import os
import signal
import subprocess
import sys
import time

from tests.helpers import REPO

PARENT = """
import sys, time
from bench.hogs import cpu_hogs
with cpu_hogs(2) as hogs:
    print(" ".join(str(h.pid) for h in hogs), flush=True)
    time.sleep(60)
"""


def _running(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as stat:
            return stat.read().rsplit(")", 1)[1].split()[0] not in ("Z", "X")
    except FileNotFoundError:
        return False


def test_hogs_end_with_a_parent_killed_by_a_signal():
    """A bench or a test killed (SIGKILL: no finally runs) leaves no process spinning behind it."""
    parent = subprocess.Popen([sys.executable, "-c", PARENT], cwd=REPO, stdout=subprocess.PIPE, text=True)
    pids = [int(p) for p in parent.stdout.readline().split()]
    assert len(pids) == 2 and all(_running(pid) for pid in pids)
    os.kill(parent.pid, signal.SIGKILL)
    parent.wait(timeout=10)
    deadline = time.monotonic() + 10
    while any(_running(pid) for pid in pids) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not any(_running(pid) for pid in pids)


def test_hogs_end_with_their_block():
    from bench.hogs import cpu_hogs

    with cpu_hogs(1) as hogs:
        assert _running(hogs[0].pid)
    assert hogs[0].poll() is not None
