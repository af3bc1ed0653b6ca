"""RS-485 frames over a python-can bus: the transport between a host (the gateway) and robot_sim's emulated
actuators. It is the emulation's only: RS-485 is not CAN, and a real JACO-2's actuator bus is inside the arm, reached
only through the base with Kinova's comm layer (USB ``OpenRS485_*``), which no CAN adapter replaces (issue 46).

One RS485_Message travels as one CAN FD frame whose 20 data bytes are the message itself (20 is a valid CAN FD
length); the arbitration id is the destination address, so receivers can filter. Any python-can interface works
(``socketcan`` with vcan or between the hosts of an emulation, ``virtual``); mfvs's own ``mfvs_hub`` (between processes) and ``mfvs_local``
(between threads of one process) also carry a whole batch without a python-can object per frame, which is what a
500 Hz loop in Python can afford. A frame that is not a valid RS-485 message (wrong length, unknown command) is
dropped and counted (``bus.rejected``), never passed on.

The hot path works on batches (``send_batch``/``recv_batch``, arrays of ``protocol.rs485.MESSAGE_DTYPE``), as the
SDK's OpenRS485_Write/Read do; single messages (``send_all``/``recv``) are for handshakes and tests.

Stamps: a frame's python-can timestamp says when the reading it carries was taken. robot_sim's emulated actuators
stamp their replies with the time of their cycle on the arm's own timeline (carried by ``mfvs_hub``,
``mfvs_local`` and ``virtual``, whose timestamps mfvs preserves); on real hardware the interface stamps each frame
when it receives it. A frame without a stamp gets its receive time.
"""
from __future__ import annotations

import collections
import time
from typing import Optional

import msgspec
import numpy as np

from protocol.rs485 import MESSAGE_DTYPE, MESSAGE_SIZE, RS485Error, RS485Message, from_records, known_commands, \
    to_records
from services.robot.hardware import BusTiming
from services.runtime.config import ConfigStruct
from services.runtime.metrics import Counters


_NO_MESSAGES = np.zeros(0, dtype=MESSAGE_DTYPE)
_NO_STAMPS = np.zeros(0, dtype=np.int64)


#: the interfaces that carry the sender's stamps (mfvs_hub, mfvs_local: mfvs's own; virtual: with
#: ``preserve_timestamps``); a real interface stamps each frame when it receives it
SENDER_STAMPED_INTERFACES = frozenset({"mfvs_hub", "mfvs_local", "virtual"})


def known_only(batch: np.ndarray, stamps: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """The records of a received batch whose command id the codec knows, their stamps, and how many were not (a
    garbled or unknown message never reaches a link or an actuator model): every transport's receive filter."""
    known = known_commands(batch)
    if known.all():
        return batch, stamps, 0
    return batch[known], stamps[known], int(np.count_nonzero(~known))


class BusConfig(ConfigStruct):
    interface: str = "virtual"
    channel: str = "mfvs-rs485"
    #: extra python-can arguments (bitrate, data_bitrate, ...)
    options: dict = msgspec.field(default_factory=dict)
    #: the host's bus cycle (ms): 2, 2.5, 3.33 or 5, a whole fraction of the DSP's 10 ms tick
    #: (services.robot.hardware.BusTiming, which says why these); robot_sim's emulated actuators keep their own
    #: 2 ms cycle, whatever their host's
    period_ms: float = 2.0

    def __post_init__(self) -> None:
        BusTiming.from_period_ms(self.period_ms)

    @property
    def timing(self) -> BusTiming:
        return BusTiming.from_period_ms(self.period_ms)


class BusError(RuntimeError):
    """The bus itself failed (interface down, the hub gone): counted as ``bus.errors``; callers hold the arm."""


def _python_can():
    """python-can, imported when a bus opens: robot_sim imports this module for :class:`BusConfig` in every mode,
    and python-can's 13 MB resident are the actuator_bus mode's only."""
    import can
    return can


class RS485Bus:
    #: looking at what has arrived is a look at a queue, no traffic (the actuator link drains before every request)
    polling_is_free = True

    def __init__(self, config: BusConfig | None = None, counters: Counters | None = None) -> None:
        self.config = config or BusConfig()
        self.counters = counters or Counters()
        options = dict(self.config.options)
        if self.config.interface == "virtual":
            options.setdefault("preserve_timestamps", True)  # the sender's stamps (the emulated arm's timeline)
        can = self._can = _python_can()
        self._bus = can.Bus(interface=self.config.interface, channel=self.config.channel, fd=True, **options)
        self._raw = hasattr(self._bus, "send_raw") and hasattr(self._bus, "recv_raw")
        #: the interface moves a batch as one block of equal-sized frames (mfvs_hub): no Python object per frame
        self._block = hasattr(self._bus, "send_block") and hasattr(self._bus, "recv_block")
        self._pending: collections.deque[tuple[RS485Message, int]] = collections.deque()
        #: the frames' stamps are the sender's (robot_sim's emulated actuators: their own timeline), not receive times
        self.arm_timeline = self.config.interface in SENDER_STAMPED_INTERFACES
        self.last_error = ""

    def _failed(self, exc: Exception) -> BusError:  # a python-can CanError
        self.counters.inc("bus.errors")
        self.last_error = str(exc)
        return BusError(str(exc))

    # ------------------------------------------------------------------ batches (the hot path)
    def send_batch(self, batch: np.ndarray, stamp_ns: int = 0) -> None:
        """A batch of messages, in order, in one write where the interface can. ``stamp_ns``: when the values
        they carry were taken (0: no stamp)."""
        if len(batch) == 0:
            return
        timestamp = stamp_ns * 1e-9
        raw = batch.tobytes()
        if self._block:
            try:
                self._bus.send_block(batch["destination"], raw, MESSAGE_SIZE, timestamp)
            except self._can.CanError as exc:
                raise self._failed(exc) from exc
            return
        payloads = [raw[i : i + MESSAGE_SIZE] for i in range(0, len(raw), MESSAGE_SIZE)]
        ids = batch["destination"].tolist()
        try:
            if self._raw:
                self._bus.send_raw(ids, payloads, timestamp)
                return
            frames = [self._can.Message(timestamp=timestamp, arbitration_id=i, data=p, is_fd=True,
                                        is_extended_id=False)
                      for i, p in zip(ids, payloads)]
            batch_send = getattr(self._bus, "send_batch", None)
            if batch_send is not None:
                batch_send(frames)
            else:
                for frame in frames:
                    self._bus.send(frame)
        except self._can.CanError as exc:
            raise self._failed(exc) from exc

    def recv_batch(self, timeout: Optional[float] = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """Every valid message that has arrived (waiting up to ``timeout`` for the first), and their stamps (ns):
        two arrays, empty when nothing came. Invalid frames are counted and dropped; a failing bus raises
        :class:`BusError`."""
        try:
            if self._block:
                _, seconds, data, dropped = self._bus.recv_block(timeout, MESSAGE_SIZE)
                if dropped:
                    self._reject(dropped, "frame of another length")
                return self._validated(np.frombuffer(data, dtype=MESSAGE_DTYPE), seconds)
            if self._raw:
                items = self._bus.recv_raw(timeout)
            else:
                items = []
                frame = self._bus.recv(timeout)
                while frame is not None:
                    items.append((frame.arbitration_id, frame.timestamp, bytes(frame.data)))
                    frame = self._bus.recv(0.0)
        except self._can.CanError as exc:
            raise self._failed(exc) from exc
        return self._decode(items)

    def _decode(self, items) -> tuple[np.ndarray, np.ndarray]:
        if not items:
            return _NO_MESSAGES, _NO_STAMPS
        if any(len(data) != MESSAGE_SIZE for _, _, data in items):
            bad = next(len(d) for _, _, d in items if len(d) != MESSAGE_SIZE)
            good = [item for item in items if len(item[2]) == MESSAGE_SIZE]
            self._reject(len(items) - len(good), f"frame of {bad} bytes")
            if not good:
                return _NO_MESSAGES, _NO_STAMPS
            items = good
        batch = np.frombuffer(b"".join([data for _, _, data in items]), dtype=MESSAGE_DTYPE)
        return self._validated(batch, np.array([timestamp for _, timestamp, _ in items]))

    def _validated(self, batch: np.ndarray, seconds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The batch's messages with a known command, and their stamps (ns; a frame without one: now)."""
        if len(batch) == 0:
            return _NO_MESSAGES, _NO_STAMPS
        stamps = np.where(seconds > 0, np.rint(seconds * 1e9), time.time_ns()).astype(np.int64)
        batch, stamps, rejected = known_only(batch, stamps)
        if rejected:
            self._reject(rejected, "unknown command id")
        return batch, stamps

    def _reject(self, count: int, reason: str) -> None:
        self.counters.inc("bus.rejected", count)
        self.last_error = reason

    # ------------------------------------------------------------------ single messages
    def send(self, message: RS485Message, stamp_ns: int = 0) -> None:
        self.send_all([message], stamp_ns)

    def send_all(self, messages, stamp_ns: int = 0) -> None:
        """Several messages, in order, in one write where the interface can."""
        messages = list(messages)
        if messages:
            self.send_batch(to_records(messages), stamp_ns)

    def send_raw(self, data: bytes, arbitration_id: int = 0) -> None:
        """Put arbitrary bytes on the bus (tests of garbled frames)."""
        try:
            self._bus.send(self._can.Message(arbitration_id=arbitration_id, data=data, is_fd=True,
                                             is_extended_id=False))
        except self._can.CanError as exc:
            raise self._failed(exc) from exc

    def recv(self, timeout: Optional[float] = 0.0) -> Optional[RS485Message]:
        """The next valid message, or None when none arrived within ``timeout``."""
        received = self.recv_stamped(timeout)
        return None if received is None else received[0]

    def recv_stamped(self, timeout: Optional[float] = 0.0) -> Optional[tuple[RS485Message, int]]:
        """The next valid message and its stamp (ns)."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while not self._pending:
            remaining = None if deadline is None else max(0.0, deadline - time.monotonic())
            batch, stamps = self.recv_batch(remaining)
            try:
                self._pending.extend(zip(from_records(batch), (int(s) for s in stamps)))
            except RS485Error:  # recv_batch has filtered unknown commands out already
                self._reject(1, "undecodable message")
            if not self._pending and deadline is not None and time.monotonic() >= deadline:
                return None
        return self._pending.popleft()

    def drain(self) -> list[RS485Message]:
        out = []
        while (message := self.recv(0.0)) is not None:
            out.append(message)
        return out

    def close(self) -> None:
        self._bus.shutdown()
