"""The loopback CAN hub: python-can's ``mfvs_hub`` interface behaves like a bus shared by several nodes (every
frame to every other node, in order, byte for byte), a misbehaving node is cut off without disturbing the others,
and RS-485 traffic to robot_sim's emulated actuators crosses it."""
import socket
import time

import can
import pytest

from protocol import rs485 as r
from services.tools.can_hub import HEADER, CanHub, parse_channel
from services.robot.rs485_bus import BusConfig
from services.stack.local import simulated_link
from tests.stack import wait_for
from tests.helpers import ARM


@pytest.fixture
def hub():
    with CanHub() as running:
        yield running


def node(hub):
    return can.Bus(interface="mfvs_hub", channel=hub.channel, fd=True)


def frame(arbitration_id, data):
    return can.Message(arbitration_id=arbitration_id, data=bytes(data), is_fd=True, is_extended_id=False)


def test_frames_reach_every_other_node_in_order_and_byte_exact(hub):
    a, b, c = node(hub), node(hub), node(hub)
    try:
        assert wait_for(lambda: hub.counters.get("nodes") == 3)
        sent = [frame(0x10 + k % 7, bytes((k + i) % 256 for i in range(20))) for k in range(200)]
        for message in sent:
            a.send(message)
        for receiver in (b, c):
            got = [receiver.recv(2.0) for _ in sent]
            assert [(g.arbitration_id, bytes(g.data), g.is_fd) for g in got] == \
                   [(s.arbitration_id, bytes(s.data), True) for s in sent]
        assert a.recv(0.1) is None  # a bus does not echo a node's own frames
        b.send(frame(0x00, b"\x01" * 8))
        assert bytes(a.recv(2.0).data) == b"\x01" * 8
        b.send_batch([frame(0x00, bytes([k]) * 20) for k in range(21)])  # one write, 21 frames
        assert [bytes(a.recv(2.0).data) for _ in range(21)] == [bytes([k]) * 20 for k in range(21)]
    finally:
        for bus in (a, b, c):
            bus.shutdown()


def test_a_node_that_sends_a_malformed_frame_is_cut_off_and_the_bus_keeps_working(hub):
    a, b = node(hub), node(hub)
    rogue = socket.create_connection(("127.0.0.1", hub.port))
    try:
        assert wait_for(lambda: hub.counters.get("nodes") == 3)
        rogue.sendall(HEADER.pack(0x10, 0, 200, 0.0) + bytes(200))  # longer than any CAN frame
        assert wait_for(lambda: hub.counters.get("bad_frames") == 1)
        assert rogue.recv(16) == b""  # the hub closed it
        a.send(frame(0x11, range(20)))
        assert bytes(b.recv(2.0).data) == bytes(range(20))
    finally:
        rogue.close()
        a.shutdown()
        b.shutdown()


def test_without_a_hub_the_interface_fails_clearly():
    with pytest.raises(can.CanInitializationError, match="no mfvs CAN hub"):
        can.Bus(interface="mfvs_hub", channel="127.0.0.1:1", connect_timeout_s=0.2)
    with pytest.raises(ValueError, match="host:port"):
        parse_channel("localhost")


def test_rs485_exchange_with_the_emulated_actuators_across_the_hub(hub):
    with simulated_link(BusConfig(interface="mfvs_hub", channel=hub.channel), settle_s=0.0) as (_, link):
        positions = link.positions_deg()
        assert len(positions) == len(ARM.bus_addresses)
        started = time.monotonic()
        for _ in range(50):
            reading = link.command(positions)
        per_exchange_ms = (time.monotonic() - started) / 50 * 1e3
        assert reading.position_deg == pytest.approx(positions, abs=0.05)
        assert per_exchange_ms < 20.0  # generous: about 2-3 ms on an idle machine (`mfvs bench rs485`)


def test_the_link_survives_a_hub_restart():
    """The hub goes away: exchanges fail as counted link errors (no loop dies), and once a hub listens again on
    the same port both ends reconnect by themselves."""
    from services.robot_gateway.link import LinkError

    hub = CanHub().start()
    port = hub.port
    try:
        with simulated_link(BusConfig(interface="mfvs_hub", channel=hub.channel), settle_s=0.0) as (runner, link):
            positions = link.positions_deg()
            hub.close()
            for _ in range(5):
                with pytest.raises(LinkError):
                    link.command(positions)
            assert link.counters.get("bus.errors") >= 1
            hub = CanHub(port=port).start()

            def exchange_works():
                try:
                    link.command(positions)
                    return True
                except LinkError:
                    return False
            assert wait_for(exchange_works, timeout=10)
            assert runner._thread.is_alive()
    finally:
        hub.close()


def _wire(frames):
    return bytearray(b"".join(HEADER.pack(i, 0x02, len(d), t) + bytes(d) for i, t, d in frames))


def test_the_block_parse_agrees_with_the_frame_by_frame_one_on_mixed_traffic():
    from services.tools.can_hub import complete_frames, split_frames, uniform_frames

    twenty = [(0x10 + k, 0.5 * k, bytes([k]) * 20) for k in range(21)]
    mixed = twenty[:5] + [(0x30, 0.0, b"\x07" * 8)] + twenty[5:]
    buffer = _wire(mixed) + _wire([(0x11, 0.0, bytes(20))])[:-3]  # and a frame cut short
    records = uniform_frames(buffer, 20)
    assert [(int(i), float(t), bytes(d)) for i, t, d in zip(records["arbitration_id"], records["timestamp"],
                                                              records["data"])] == twenty[:5]
    end, count = complete_frames(buffer)
    assert count == len(mixed) and end == len(_wire(mixed))
    assert split_frames(bytearray(buffer)) == [bytes(_wire([f])) for f in mixed]
    assert len(uniform_frames(bytearray(_wire([(0x30, 0.0, b"\x07" * 8)]) + _wire(twenty)), 20)) == 0


def test_blocks_of_frames_cross_the_hub_in_order_and_other_sizes_are_counted_out(hub):
    a, b = node(hub), node(hub)
    try:
        assert wait_for(lambda: hub.counters.get("nodes") == 2)
        data = bytes(range(20)) * 21
        a.send_block(list(range(0x10, 0x10 + 21)), data, 20, timestamp=12.5)
        a.send(frame(0x40, b"\x09" * 8))  # another size between two blocks
        a.send_block([0x10], bytes([200]) * 20, 20)
        ids, stamps, got, dropped = [], [], b"", 0
        deadline = time.monotonic() + 2.0
        while len(ids) < 22 and time.monotonic() < deadline:
            i, t, d, n = b.recv_block(0.2, 20)
            ids += list(i)
            stamps += list(t)
            got += d
            dropped += n
        assert ids == list(range(0x10, 0x10 + 21)) + [0x10] and dropped == 1
        assert got == data + bytes([200]) * 20
        assert stamps[:21] == [12.5] * 21 and stamps[21] == 0.0
        # a single-frame receive and a block receive share one stream, in order
        a.send_block([0x21, 0x22], bytes(40), 20)
        assert b.recv(2.0).arbitration_id == 0x21
        assert list(b.recv_block(2.0, 20)[0]) == [0x22]
    finally:
        a.shutdown()
        b.shutdown()


def test_the_rs485_transport_over_the_hub_refuses_garbled_frames_on_its_block_path(hub):
    import struct

    from services.robot.rs485_bus import RS485Bus

    sender = RS485Bus(BusConfig(interface="mfvs_hub", channel=hub.channel))
    receiver = RS485Bus(BusConfig(interface="mfvs_hub", channel=hub.channel))
    try:
        assert receiver._block  # the path under test
        assert wait_for(lambda: hub.counters.get("nodes") == 2)
        sender.send_raw(bytes(19), 0x10)  # truncated
        sender.send_raw(struct.pack("<hBB", 0x77, 0, 0x10) + bytes(16), 0x10)  # unknown command
        sender.send_raw(bytes(64), 0x10)  # too long
        good = r.RS485Message(r.Command.GET_ACTUAL_POSITION, 0, 0x10)
        sender.send_all([good, good], stamp_ns=123_000_000_000)
        got = []
        deadline = time.monotonic() + 2.0
        while len(got) < 2 and time.monotonic() < deadline:
            batch, stamps = receiver.recv_batch(0.2)
            got += list(zip(r.from_records(batch), stamps.tolist()))
        assert [(message, stamp) for message, stamp in got] == [(good, 123_000_000_000)] * 2
        assert receiver.counters.get("bus.rejected") == 3
    finally:
        sender.close()
        receiver.close()
