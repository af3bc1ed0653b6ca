"""RS-485 frames over a python-can bus: the transport between a host (the gateway) and the actuators (a real
arm's, or robot_sim's emulation).

One RS485_Message travels as one CAN FD frame whose 20 data bytes are the message itself (20 is a valid CAN FD
length); the arbitration id is the destination address, so receivers can filter. Any python-can interface works
(``virtual`` by default for the emulator and tests, ``socketcan`` on Linux hardware). A frame that is not a valid
RS-485 message (wrong length, unknown command) is dropped and counted, never passed on.
"""
from __future__ import annotations

from typing import Optional

import can
import msgspec

from protocol.rs485 import MESSAGE_SIZE, RS485Error, RS485Message
from services.common.config import ConfigStruct
from services.common.metrics import Counters


class BusConfig(ConfigStruct):
    interface: str = "virtual"
    channel: str = "mfvs-rs485"
    #: extra python-can arguments (bitrate, data_bitrate, ...)
    options: dict = msgspec.field(default_factory=dict)


class BusError(RuntimeError):
    """The bus itself failed (interface down, the hub gone): counted as ``bus.errors``; callers hold the arm."""


class RS485Bus:
    def __init__(self, config: BusConfig | None = None, counters: Counters | None = None) -> None:
        self.config = config or BusConfig()
        self.counters = counters or Counters()
        self._bus = can.Bus(interface=self.config.interface, channel=self.config.channel, fd=True,
                            **self.config.options)
        self.last_error = ""

    def _failed(self, exc: can.CanError) -> BusError:
        self.counters.inc("bus.errors")
        self.last_error = str(exc)
        return BusError(str(exc))

    def send(self, message: RS485Message) -> None:
        self.send_all([message])

    def send_all(self, messages) -> None:
        """Several messages, in order; in one write where the interface can batch (the mfvs CAN hub)."""
        frames = [can.Message(arbitration_id=message.destination, data=message.encode(), is_fd=True,
                              is_extended_id=False) for message in messages]
        if not frames:
            return
        batch = getattr(self._bus, "send_batch", None)
        try:
            if batch is not None:
                batch(frames)
                return
            for frame in frames:
                self._bus.send(frame)
        except can.CanError as exc:
            raise self._failed(exc) from exc

    def send_raw(self, data: bytes, arbitration_id: int = 0) -> None:
        """Put arbitrary bytes on the bus (tests of garbled frames)."""
        try:
            self._bus.send(can.Message(arbitration_id=arbitration_id, data=data, is_fd=True, is_extended_id=False))
        except can.CanError as exc:
            raise self._failed(exc) from exc

    def recv(self, timeout: Optional[float] = 0.0) -> Optional[RS485Message]:
        """The next valid message, or None when none arrived within ``timeout``; invalid frames are counted. A
        failing bus raises :class:`BusError`."""
        while True:
            try:
                frame = self._bus.recv(timeout)
            except can.CanError as exc:
                raise self._failed(exc) from exc
            if frame is None:
                return None
            try:
                if len(frame.data) != MESSAGE_SIZE:
                    raise RS485Error(f"frame of {len(frame.data)} bytes")
                return RS485Message.decode(bytes(frame.data))
            except RS485Error as exc:
                self.counters.inc("bus.rejected")
                self.last_error = str(exc)
                timeout = 0.0  # keep draining what is already there

    def drain(self) -> list[RS485Message]:
        out = []
        while (message := self.recv(0.0)) is not None:
            out.append(message)
        return out

    def close(self) -> None:
        self._bus.shutdown()
