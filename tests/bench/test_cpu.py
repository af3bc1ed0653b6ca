"""bench cpu's memory figures."""
import os
import subprocess
import sys

import pytest

from bench.cpu import mapping_name, mappings_mb, process_tree, pss_mb, resident_mappings, resident_mb, rss_mb


def test_proportional_memory_divides_what_processes_share():
    """A child that maps the same interpreter and libraries as this process: its RSS counts them whole, its PSS
    only its share (the sum of both PSS is at most the sum of both RSS, and each is positive)."""
    child = subprocess.Popen([sys.executable, "-c", "import sys; print('up', flush=True); sys.stdin.read()"],
                             stdin=subprocess.PIPE, stdout=subprocess.PIPE)
    try:
        # measured once the interpreter is up: before, a slow host shows the bare fork (a page, shared by nobody)
        assert child.stdout.readline() == b"up\n"
        me, mine_and_child = os.getpid(), (os.getpid(), child.pid)
        assert 0 < pss_mb(child.pid) < rss_mb(child.pid)
        assert 0 < sum(pss_mb(p) for p in mine_and_child) <= sum(rss_mb(p) for p in mine_and_child)
        assert pss_mb(me) >= pss_mb(child.pid) > 0  # this process's tree includes the child
    finally:
        child.stdin.close()
        child.wait(timeout=10)


def test_a_stack_resident_memory_counts_a_shared_page_once():
    """A process holding 64 MB it wrote, and a child forked from it that only reads them: both RSS count the 64 MB
    (the sum twice), the pages are the same physical ones, and the resident memory of the two counts them once."""
    script = ("import os, sys\n"
              "buffer = bytearray(os.urandom(64 * 2**20))\n"
              "if os.fork() == 0:\n"
              "    sum(buffer[::4096])\n"  # reads every page: resident in the child too, not copied
              "    print('child', flush=True); sys.stdin.read(); os._exit(0)\n"
              "sys.stdin.read(); os.wait()\n")
    parent = subprocess.Popen([sys.executable, "-c", script], stdin=subprocess.PIPE, stdout=subprocess.PIPE)
    try:
        assert parent.stdout.readline() == b"child\n"
        child = process_tree(parent.pid)[1]
        assert rss_mb(child) > 64
        resident = resident_mb([parent.pid])
        if resident is None:
            pytest.skip("page frames are hidden from this process (no CAP_SYS_ADMIN)")
        assert resident < rss_mb(parent.pid) - 60  # the tree's RSS: the 64 MB in each
        assert resident >= max(_own_rss_mb(parent.pid), _own_rss_mb(child)) - 1
    finally:
        parent.stdin.close()
        parent.wait(timeout=10)


def _own_rss_mb(pid: int) -> float:
    return sum(kb for _start, _end, _name, kb in resident_mappings(pid)) / 1024


def test_the_mappings_name_where_a_process_resident_memory_lies():
    """NumPy imported here: its package's libraries appear by the package's name, the names' sum is the RSS."""
    import numpy  # noqa: F401  (mapped by this process)

    mappings = mappings_mb(os.getpid())
    assert mappings["numpy"] > 0 and "anonymous" in mappings and "[heap]" in mappings
    assert abs(sum(mappings.values()) - rss_mb(os.getpid())) < 2
    assert mapping_name("/x/lib/python3.11/site-packages/cmeel.prefix/lib/libpinocchio.so.3") == \
        "pinocchio's libraries (cmeel.prefix)"
    assert mapping_name("/usr/lib/x86_64-linux-gnu/libLLVM-15.so.1") == "libLLVM-15"
    assert mapping_name("/dev/shm/2027017702.zenoh") == "zenoh's shared memory"
