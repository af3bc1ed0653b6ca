"""A CAN bus between processes on one machine, over TCP loopback: the wire between robot_sim's emulated actuators
and robot_gateway when both run as separate processes.

python-can's ``virtual`` interface only connects buses inside one process, ``udp_multicast`` needs multicast
groups and ``socketcan``'s ``vcan`` needs a kernel module; none of them can be assumed on a deploy host. So mfvs
ships a small hub that behaves like a bus: every frame one node sends reaches every other node, never the sender,
in order; a node that does not read loses frames (an overrun, counted) instead of stalling the others.

``HubBus`` is an ordinary python-can interface (registered as ``mfvs_hub`` through the ``can.interface`` entry
point), so the RS-485 transport uses it like any other: ``{interface: mfvs_hub, channel: "127.0.0.1:7448"}``.
``CanHub`` is the relay (``mfvs bus-hub --port 7448``, or in-process for tests).

Wire format, both directions: a 14-byte header ``<IBBd`` (arbitration id, flags, data length, the frame's
timestamp in seconds, 0 for none) then the data. A frame sent without a timestamp is stamped when received.
"""
from __future__ import annotations

import collections
import logging
import select
import selectors
import socket
import struct
import threading
import time
from typing import Optional

import can
import numpy as np

from services.runtime.metrics import Counters
from services.runtime.threads import start_thread

log = logging.getLogger("mfvs.can_hub")

HEADER = struct.Struct("<IBBd")
FLAG_EXTENDED = 0x01
FLAG_FD = 0x02
FLAG_BRS = 0x04
MAX_DATA = 64
#: a node whose hub went away tries to reconnect at most this often
RECONNECT_S = 0.5
#: a node this far behind loses frames rather than holding the others up (about 0.5 s of RS-485 traffic)
MAX_BACKLOG_BYTES = 1 << 18


def parse_channel(channel: str) -> tuple[str, int]:
    """``"host:port"`` (or ``"port"``) → (host, port)."""
    host, _, port = str(channel).rpartition(":")
    try:
        number = int(port)
    except ValueError:
        raise ValueError(f"mfvs_hub channel {channel!r} is not host:port") from None
    if not 0 < number < 65536:
        raise ValueError(f"mfvs_hub channel {channel!r}: port out of range")
    return host or "127.0.0.1", number


def encode_frame(message: can.Message) -> bytes:
    data = bytes(message.data)
    if len(data) > MAX_DATA:
        raise ValueError(f"a CAN frame carries at most {MAX_DATA} bytes, not {len(data)}")
    flags = ((FLAG_EXTENDED if message.is_extended_id else 0) | (FLAG_FD if message.is_fd else 0)
             | (FLAG_BRS if message.bitrate_switch else 0))
    return HEADER.pack(message.arbitration_id, flags, len(data), float(message.timestamp or 0.0)) + data


def wire_dtype(data_size: int) -> np.dtype:
    """A frame with ``data_size`` data bytes as a numpy record (the header's fields, then the data)."""
    return np.dtype([("arbitration_id", "<u4"), ("flags", "u1"), ("length", "u1"), ("timestamp", "<f8"),
                     ("data", f"V{data_size}")])


def uniform_frames(buffer: bytearray, data_size: int) -> np.ndarray:
    """The frames at the start of ``buffer`` that carry ``data_size`` bytes each, up to the first that does not
    or is incomplete, as records (a copy). Read sequentially a frame of that size ends where the next would start
    at the same stride, so checking the length byte at every stride is the whole parse."""
    stride = HEADER.size + data_size
    count = len(buffer) // stride
    if count == 0 or buffer[5] != data_size:
        return np.zeros(0, dtype=wire_dtype(data_size))
    records = np.frombuffer(bytes(buffer[: count * stride]), dtype=wire_dtype(data_size))
    uniform = records["length"] == data_size
    if not uniform.all():
        records = records[: int(np.argmin(uniform))]
    return records


def complete_frames(buffer: bytearray) -> tuple[int, int]:
    """How many bytes at the start of ``buffer`` are complete frames, and how many frames that is (a frame's
    length is checked, its bytes are not copied: the hub forwards them as they came)."""
    if len(buffer) > HEADER.size and buffer[5] <= MAX_DATA:  # the usual batch: frames of one size
        offset = len(uniform_frames(buffer, buffer[5])) * (HEADER.size + buffer[5])
        count = offset // (HEADER.size + buffer[5])
    else:
        offset = count = 0
    size = len(buffer)
    while size - offset >= HEADER.size:
        length = buffer[offset + 5]
        if length > MAX_DATA:
            raise ValueError(f"frame length {length} > {MAX_DATA}")
        end = offset + HEADER.size + length
        if end > size:
            break
        offset, count = end, count + 1
    return offset, count


def split_frames(buffer: bytearray) -> list[bytes]:
    """Remove and return the complete frames at the start of ``buffer`` (as wire bytes)."""
    end, _ = complete_frames(buffer)  # checked there: every length up to ``end`` is valid
    frames, offset = [], 0
    while offset < end:
        stop = offset + HEADER.size + buffer[offset + 5]
        frames.append(bytes(buffer[offset:stop]))
        offset = stop
    del buffer[:end]
    return frames


def decode_frame(frame: bytes, channel: str) -> can.Message:
    arbitration_id, flags, length, timestamp = HEADER.unpack_from(frame)
    return can.Message(timestamp=timestamp if timestamp > 0 else time.time(), arbitration_id=arbitration_id,
                       data=frame[HEADER.size:],
                       is_extended_id=bool(flags & FLAG_EXTENDED), is_fd=bool(flags & FLAG_FD),
                       bitrate_switch=bool(flags & FLAG_BRS), is_rx=True, channel=channel, check=False)


class HubBus(can.BusABC):
    """A python-can bus whose wire is a ``CanHub``: ``can.Bus(interface="mfvs_hub", channel="127.0.0.1:7448")``."""

    def __init__(self, channel: str, can_filters=None, connect_timeout_s: float = 5.0, **kwargs) -> None:
        self._host, self._port = parse_channel(channel)
        self._socket: Optional[socket.socket] = None
        self._buffer = bytearray()
        self._received: collections.deque[bytes] = collections.deque()
        self._send_lock = threading.Lock()
        self._next_attempt = 0.0
        self.channel_info = f"mfvs CAN hub at {self._host}:{self._port}"
        self._channel = str(channel)
        deadline = time.monotonic() + connect_timeout_s
        while True:  # the hub may be starting in another process at the same moment
            try:
                self._connect(timeout_s=1.0)
                break
            except OSError as exc:
                if time.monotonic() > deadline:
                    raise can.CanInitializationError(f"no mfvs CAN hub at {self._host}:{self._port}: {exc}") from exc
                time.sleep(0.05)
        try:
            super().__init__(channel=channel, can_filters=can_filters, **kwargs)
        except BaseException:
            self._disconnect()
            raise

    def _connect(self, timeout_s: float) -> None:
        sock = socket.create_connection((self._host, self._port), timeout=timeout_s)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        sock.setblocking(False)
        self._socket = sock

    def _disconnect(self) -> None:
        """Drop a broken connection (and any half-received frame); the next call reconnects."""
        if self._socket is not None:
            self._socket.close()
            self._socket = None
        try:  # the complete frames that came before the break are still news
            self._received.extend(split_frames(self._buffer))
        except ValueError:
            pass
        self._buffer.clear()

    def _ensure_connected(self) -> None:
        """Reconnect after the hub restarted: one quick attempt, at most every RECONNECT_S."""
        if self._socket is not None:
            return
        now = time.monotonic()
        if now < self._next_attempt:
            raise can.CanOperationError("mfvs CAN hub: not connected")
        self._next_attempt = now + RECONNECT_S
        try:
            self._connect(timeout_s=0.2)
        except OSError as exc:
            raise can.CanOperationError(f"mfvs CAN hub: reconnecting failed: {exc}") from exc

    def _fail(self, reason: str, exc: Optional[BaseException] = None) -> can.CanOperationError:
        self._disconnect()
        error = can.CanOperationError(f"mfvs CAN hub: {reason}")
        error.__cause__ = exc
        return error

    def send(self, msg: can.Message, timeout: Optional[float] = None) -> None:
        self._write(encode_frame(msg), timeout)

    def send_batch(self, messages: list[can.Message], timeout: Optional[float] = None) -> None:
        """Several frames in one write (they still arrive as separate frames, in order): a 2 ms bus cycle's
        seven commands, or twenty-one replies, cost one system call instead of one each."""
        self._write(b"".join(encode_frame(msg) for msg in messages), timeout)

    def send_raw(self, arbitration_ids, payloads, timestamp: float = 0.0) -> None:
        """CAN FD frames from plain ids and payloads, in one write, without python-can Message objects (the
        RS-485 transport's fast path)."""
        header = HEADER.pack
        self._write(b"".join(header(i, FLAG_FD, len(p), timestamp) + p
                             for i, p in zip(arbitration_ids, payloads, strict=True)), None)

    def recv_raw(self, timeout: Optional[float]) -> list[tuple[int, float, bytes]]:
        """Every frame that has arrived, waiting up to ``timeout`` for the first: (arbitration id, timestamp or
        0, data)."""
        if not self._fill(timeout):
            return []
        self._split()
        out = []
        unpack = HEADER.unpack_from
        while self._received:
            frame = self._received.popleft()
            arbitration_id, _flags, _length, timestamp = unpack(frame)
            out.append((arbitration_id, timestamp, frame[HEADER.size:]))
        return out

    def send_block(self, arbitration_ids, data: bytes, data_size: int, timestamp: float = 0.0) -> None:
        """CAN FD frames of ``data_size`` bytes each, their data concatenated in ``data``, in one write and
        without a Python object per frame (the RS-485 transport's 500 Hz path)."""
        records = np.empty(len(arbitration_ids), dtype=wire_dtype(data_size))
        records["arbitration_id"] = arbitration_ids
        records["flags"] = FLAG_FD
        records["length"] = data_size
        records["timestamp"] = timestamp
        records["data"] = np.frombuffer(data, dtype=f"V{data_size}")
        self._write(records.tobytes(), None)

    def recv_block(self, timeout: Optional[float], data_size: int) -> tuple[np.ndarray, np.ndarray, bytes, int]:
        """Every frame that has arrived (waiting up to ``timeout`` for the first) with ``data_size`` data bytes:
        (arbitration ids, timestamps (0: none), their data concatenated, how many frames of another size were
        dropped), without a Python object per frame."""
        if not self._fill(timeout):
            return np.zeros(0, np.uint32), np.zeros(0), b"", 0
        parts, dropped = [], 0
        while self._received:  # split already by a single-frame receive: in order, one by one
            frame = self._received.popleft()
            if frame[5] != data_size:
                dropped += 1
                continue
            parts.append(np.frombuffer(frame, dtype=wire_dtype(data_size)))
        while self._has_frame():
            records = uniform_frames(self._buffer, data_size)
            if len(records):
                parts.append(records)
                del self._buffer[: len(records) * (HEADER.size + data_size)]
            elif self._buffer[5] != data_size:  # a complete frame of another size: dropped, counted
                del self._buffer[: HEADER.size + self._buffer[5]]
                dropped += 1
        if not parts:
            return np.zeros(0, np.uint32), np.zeros(0), b"", dropped
        records = parts[0] if len(parts) == 1 else np.concatenate(parts)
        return records["arbitration_id"], records["timestamp"], records["data"].tobytes(), dropped

    def _write(self, data: bytes, timeout: Optional[float]) -> None:
        pending = memoryview(data)
        deadline = time.monotonic() + (1.0 if timeout is None else timeout)
        with self._send_lock:
            self._ensure_connected()
            while pending:
                try:
                    pending = pending[self._socket.send(pending):]
                except BlockingIOError:
                    remaining = deadline - time.monotonic()
                    if remaining <= 0 or not select.select([], [self._socket], [], remaining)[1]:
                        if len(pending) < len(data):  # part of a frame may be on the wire: start afresh
                            raise self._fail("send timed out mid-frame") from None
                        raise can.CanOperationError("mfvs CAN hub: send timed out") from None
                except OSError as exc:
                    raise self._fail(f"send failed: {exc}", exc) from exc

    def _has_frame(self) -> bool:
        """Whether a complete frame is here (split or still in the buffer); a bad length drops the connection."""
        if self._received:
            return True
        buffer = self._buffer
        if len(buffer) < HEADER.size:
            return False
        if buffer[5] > MAX_DATA:
            raise self._fail(f"the hub sent a bad frame: frame length {buffer[5]} > {MAX_DATA}")
        return len(buffer) >= HEADER.size + buffer[5]

    def _split(self) -> None:
        """The buffer's complete frames into :attr:`_received` (the paths that hand out frames one by one)."""
        try:
            self._received.extend(split_frames(self._buffer))
        except ValueError as exc:
            raise self._fail(f"the hub sent a bad frame: {exc}", exc) from exc

    def _fill(self, timeout: Optional[float]) -> bool:
        """Wait up to ``timeout`` until at least one frame is in; read everything that is there. Whether any is.
        Frames stay as bytes in the buffer until a receive takes them (a batch at once, or one by one)."""
        if self._has_frame():
            self._read_available()
            return True
        self._ensure_connected()
        deadline = None if timeout is None else time.monotonic() + timeout
        while not self._has_frame():
            remaining = None if deadline is None else max(0.0, deadline - time.monotonic())
            # select(), not epoll: its timeout has microseconds, epoll's whole milliseconds (rounded up), which
            # would make a 2 ms loop that waits here for frames or its next cycle wake up to 1 ms late
            try:
                readable, _, _ = select.select([self._socket], [], [], remaining)
            except (OSError, ValueError) as exc:
                raise self._fail(f"waiting failed: {exc}", exc) from exc
            if not readable:
                return False
            self._read_available()
            if deadline is not None and time.monotonic() >= deadline and not self._has_frame():
                return False
        return True

    def _read_available(self) -> None:
        while True:
            try:
                chunk = self._socket.recv(65536)
            except BlockingIOError:
                return
            except OSError as exc:
                raise self._fail(f"receive failed: {exc}", exc) from exc
            if not chunk:
                raise self._fail("the hub closed the connection")
            self._buffer += chunk
            if len(chunk) < 65536:
                return

    def _recv_internal(self, timeout: Optional[float]):
        if not self._fill(timeout):
            return None, False
        self._split()
        return decode_frame(self._received.popleft(), self._channel), False

    def shutdown(self) -> None:
        super().shutdown()
        self._disconnect()


class _Node:
    __slots__ = ("sock", "address", "inbox", "outbox", "writing")

    def __init__(self, sock: socket.socket, address) -> None:
        self.sock = sock
        self.address = address
        self.inbox = bytearray()
        self.outbox = bytearray()
        #: registered for EVENT_WRITE (its outbox did not all go)
        self.writing = False


class CanHub:
    """The relay: accepts nodes on a loopback TCP port and copies every frame to every other node.

    Runs in a thread (``start()``/``close()`` or a context manager); ``serve_forever()`` for ``mfvs bus-hub``.
    Counters: ``frames`` relayed, ``overruns`` (frames a slow node lost), ``bad_frames`` (a node that sent a
    malformed frame is disconnected), ``nodes``.
    """

    def __init__(self, port: int = 0, host: str = "127.0.0.1") -> None:
        self.host = host
        #: the port it listens on (0 before ``bind``/``start`` when asked for any free port)
        self.port = port
        self.counters = Counters()
        self._selector = selectors.DefaultSelector()
        self._listener: Optional[socket.socket] = None
        self._nodes: dict[socket.socket, _Node] = {}
        self._stop = threading.Event()
        self._thread: Optional[threading.Thread] = None
        self._wake_r, self._wake_w = socket.socketpair()

    @property
    def channel(self) -> str:
        return f"{self.host}:{self.port}"

    def bind(self) -> None:
        """Listen now (``start``/``serve_forever`` do it when not done yet): a taken port fails here."""
        if self._listener is not None:
            return
        listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        listener.bind((self.host, self.port))  # port 0: the kernel picks one, with no window for anyone else
        self.port = listener.getsockname()[1]
        listener.listen(16)
        listener.setblocking(False)
        self._listener = listener
        self._selector.register(listener, selectors.EVENT_READ, "accept")
        self._selector.register(self._wake_r, selectors.EVENT_READ, "wake")

    def start(self) -> "CanHub":
        self.bind()
        self._thread = start_thread(self._run, "can-hub")
        return self

    def serve_forever(self) -> None:
        self.bind()
        self._run()

    def stop(self) -> None:
        self._stop.set()
        try:
            self._wake_w.send(b"x")
        except OSError:
            pass

    def close(self) -> None:
        self.stop()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None

    def __enter__(self) -> "CanHub":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    def _run(self) -> None:
        try:
            while not self._stop.is_set():
                for key, events in self._selector.select(timeout=0.5):
                    if key.data == "accept":
                        self._accept()
                    elif key.data == "wake":
                        self._wake_r.recv(64)
                    else:
                        node = self._nodes.get(key.fileobj)
                        if node is None:
                            continue
                        if events & selectors.EVENT_READ:
                            self._read(node)
                        if events & selectors.EVENT_WRITE and node.sock in self._nodes:
                            self._flush(node)
        finally:
            for node in list(self._nodes.values()):
                self._drop(node, "hub stopping")
            self._selector.close()
            if self._listener is not None:
                self._listener.close()
            self._wake_r.close()
            self._wake_w.close()

    def _accept(self) -> None:
        try:
            sock, address = self._listener.accept()
        except OSError:  # nothing to accept after all, or the peer gave up (ECONNABORTED), or out of descriptors
            self.counters.inc("accept_errors")
            return
        try:
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            sock.setblocking(False)
        except OSError:
            sock.close()
            self.counters.inc("accept_errors")
            return
        node = _Node(sock, address)
        self._nodes[sock] = node
        self._selector.register(sock, selectors.EVENT_READ, "node")
        self.counters.inc("nodes")
        log.info("node %s joined (%d on the bus)", address, len(self._nodes))

    def _read(self, node: _Node) -> None:
        try:
            chunk = node.sock.recv(65536)
        except BlockingIOError:
            return
        except OSError as exc:
            self._drop(node, str(exc))
            return
        if not chunk:
            self._drop(node, "disconnected")
            return
        node.inbox += chunk
        try:
            end, count = complete_frames(node.inbox)
        except ValueError as exc:
            self.counters.inc("bad_frames")
            self._drop(node, f"malformed frame: {exc}")
            return
        if not count:
            return
        payload = bytes(node.inbox[:end])
        del node.inbox[:end]
        self.counters.inc("frames", count)
        for other in list(self._nodes.values()):
            if other is not node:
                self._queue(other, payload, count)

    def _queue(self, node: _Node, payload: bytes, count: int) -> None:
        if len(node.outbox) + len(payload) > MAX_BACKLOG_BYTES:
            self.counters.inc("overruns", count)
            return
        was_empty = not node.outbox
        node.outbox += payload
        if was_empty:
            self._flush(node)

    def _flush(self, node: _Node) -> None:
        try:
            sent = node.sock.send(node.outbox)
        except BlockingIOError:
            sent = 0
        except OSError as exc:
            self._drop(node, str(exc))
            return
        del node.outbox[:sent]
        writing = bool(node.outbox)
        if writing != node.writing:  # a system call only when the interest changes (not per relayed batch)
            node.writing = writing
            events = selectors.EVENT_READ | (selectors.EVENT_WRITE if writing else 0)
            self._selector.modify(node.sock, events, "node")

    def _drop(self, node: _Node, why: str) -> None:
        self._nodes.pop(node.sock, None)
        try:
            self._selector.unregister(node.sock)
        except (KeyError, ValueError):
            pass
        node.sock.close()
        log.info("node %s left: %s", node.address, why)
