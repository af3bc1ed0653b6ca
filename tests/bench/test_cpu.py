"""bench cpu's memory figures."""
import os
import subprocess
import sys

from bench.cpu import pss_mb, rss_mb


def test_proportional_memory_divides_what_processes_share():
    """A child that maps the same interpreter and libraries as this process: its RSS counts them whole, its PSS
    only its share (the sum of both PSS is at most the sum of both RSS, and each is positive)."""
    child = subprocess.Popen([sys.executable, "-c", "import sys; sys.stdin.read()"], stdin=subprocess.PIPE)
    try:
        me, mine_and_child = os.getpid(), (os.getpid(), child.pid)
        assert 0 < pss_mb(child.pid) < rss_mb(child.pid)
        assert 0 < sum(pss_mb(p) for p in mine_and_child) <= sum(rss_mb(p) for p in mine_and_child)
        assert pss_mb(me) >= pss_mb(child.pid) > 0  # this process's tree includes the child
    finally:
        child.stdin.close()
        child.wait(timeout=10)
