"""The loopback ports tests and `mfvs up` listen on: free, and outside the range the kernel hands out to outgoing
connections (a port from there may be taken by any process's next connection before the listener binds it)."""
import socket

from services.runtime.transport import _ephemeral_ports, free_loopback_port


def test_a_free_port_is_below_the_ephemeral_range_and_can_be_listened_on():
    low, high = _ephemeral_ports()
    assert 1024 < low <= high
    ports = [free_loopback_port() for _ in range(20)]
    assert all(port < low for port in ports), (ports, low)
    assert len(set(ports)) > 15  # spread over the range, not one port handed to everyone
    for port in ports[:5]:
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            s.bind(("127.0.0.1", port))
            s.listen()


def test_a_port_someone_listens_on_is_not_handed_out():
    taken = []
    try:
        for _ in range(300):  # a good share of the candidates' first picks
            s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            s.bind(("127.0.0.1", free_loopback_port()))
            s.listen()
            taken.append(s)
        held = {s.getsockname()[1] for s in taken}
        assert len(held) == len(taken)  # every one free when handed out
    finally:
        for s in taken:
            s.close()
