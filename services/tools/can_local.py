"""A CAN bus between threads of one process (python-can interface ``mfvs_local``): every frame one node sends
reaches every other node on the same channel, in order, never the sender. What python-can's ``virtual`` interface
does, without its copy of every frame for every receiver, and with the batch path of the RS-485 transport
(``send_raw``/``recv_raw``), so that an emulated arm and its host in one process (tests, benchmarks) do not spend
their bus cycle copying frames. Timestamps are the sender's (0 when it gave none).
"""
from __future__ import annotations

import collections
import threading
import time
from typing import Optional

import can

_channels: dict[str, list["LocalBus"]] = {}
_channels_lock = threading.Lock()


class LocalBus(can.BusABC):
    def __init__(self, channel: str = "mfvs-local", can_filters=None, **kwargs) -> None:
        self._channel = str(channel)
        self._queue: collections.deque = collections.deque()
        self._cond = threading.Condition()
        self.channel_info = f"mfvs in-process bus {self._channel}"
        with _channels_lock:
            _channels.setdefault(self._channel, []).append(self)
        super().__init__(channel=channel, can_filters=can_filters, **kwargs)

    def _deliver(self, items: list) -> None:
        with _channels_lock:
            peers = [node for node in _channels.get(self._channel, []) if node is not self]
        for node in peers:
            with node._cond:
                node._queue.extend(items)
                node._cond.notify()

    def send(self, msg: can.Message, timeout: Optional[float] = None) -> None:
        self._deliver([(msg.arbitration_id, msg.timestamp or 0.0, bytes(msg.data), msg.is_fd,
                        msg.is_extended_id)])

    def send_raw(self, arbitration_ids, payloads, timestamp: float = 0.0) -> None:
        self._deliver([(i, timestamp, p, True, False) for i, p in zip(arbitration_ids, payloads, strict=True)])

    def _wait(self, timeout: Optional[float]) -> bool:
        with self._cond:
            return self._cond.wait_for(lambda: bool(self._queue), timeout)

    def recv_raw(self, timeout: Optional[float]) -> list[tuple[int, float, bytes]]:
        if not self._wait(timeout):
            return []
        with self._cond:
            items, self._queue = self._queue, collections.deque()
        return [(i, ts, data) for i, ts, data, _fd, _ext in items]

    def _recv_internal(self, timeout: Optional[float]):
        if not self._wait(timeout):
            return None, False
        with self._cond:
            arbitration_id, timestamp, data, fd, extended = self._queue.popleft()
        return can.Message(timestamp=timestamp or time.time(), arbitration_id=arbitration_id, data=data, is_fd=fd,
                           is_extended_id=extended, is_rx=True, channel=self._channel, check=False), False

    def shutdown(self) -> None:
        with _channels_lock:
            nodes = _channels.get(self._channel, [])
            if self in nodes:
                nodes.remove(self)
            if not nodes:
                _channels.pop(self._channel, None)
        super().shutdown()
