"""The lab's computers (services/tools/netns.py): a thread moved onto one of them with ``Lab.inside`` opens that
computer's sockets and starts its processes there, and is back on this machine after the block."""
import errno
import socket
import subprocess
import sys
import threading

import pytest

from services.tools import netns

WHY = netns.unavailable()
pytestmark = pytest.mark.skipif(bool(WHY), reason=f"no network namespaces here: {WHY}")


def can_bind(address: str) -> bool:
    with socket.socket() as s:
        try:
            s.bind((address, 0))
        except OSError as exc:
            assert exc.errno == errno.EADDRNOTAVAIL, exc
            return False
        return True


def test_inside_a_host_the_thread_and_what_it_starts_are_that_computers_and_only_until_the_block_ends():
    with netns.Lab(["tablet", "arm-pc"]) as lab:
        tablet, arm_pc = lab.address("tablet"), lab.address("arm-pc")
        assert not can_bind(tablet)
        elsewhere, ask = [], threading.Event()
        running = threading.Thread(target=lambda: ask.wait(30) and elsewhere.append(("running", can_bind(tablet))))
        running.start()
        with lab.inside("arm-pc"):
            listener = socket.create_server((arm_pc, 0))  # a socket stays on the computer it was opened on
        with listener, lab.inside("tablet"):
            assert can_bind(tablet) and not can_bind(arm_pc)
            # a process started meanwhile is on the tablet too, and reaches the other computer through the switch
            seen = subprocess.run(["ip", "-o", "-4", "addr", "show", "dev", "eth0"], capture_output=True, text=True)
            assert f"inet {tablet}/24" in seen.stdout
            reach = subprocess.run([sys.executable, "-c", "import socket, sys; socket.create_connection("
                                    f"('{arm_pc}', {listener.getsockname()[1]}), timeout=10)"],
                                   capture_output=True, text=True, timeout=30)
            assert reach.returncode == 0, reach.stderr
            # a thread it starts is there too; one already running stays where it was
            started = threading.Thread(target=lambda: elsewhere.append(("started", can_bind(tablet))))
            started.start()
            started.join()
            ask.set()
            running.join()
        assert sorted(elsewhere) == [("running", False), ("started", True)]
        assert not can_bind(tablet)
        with pytest.raises(RuntimeError), lab.inside("arm-pc"):
            assert can_bind(arm_pc)
            raise RuntimeError("the block fails")
        assert not can_bind(arm_pc)  # back here after a failure too
