"""The JACO-2's base as Kinova's USB comm layer (``USBCommLayerUbuntu.so``) sees it: the USB packets it answers.

:class:`UsbBase` is the protocol, pure (no sockets, no threads): it takes the host's OUT transfers and makes the IN
transfers the comm layer expects, and it hands the RS-485 messages that ``OpenRS485_Write`` packs to a callback
(``forward(records)``, numpy records of :data:`protocol.rs485.MESSAGE_DTYPE`); replies given to
:meth:`UsbBase.deliver` come back through ``OpenRS485_Read``. :class:`UsbBaseServer` serves it on a Unix socket
with the framing of the stand-in libusb (``services/robot_sim/libusb_stand_in.c``), so the real
comm layer can run over it with no arm. Every layout here is the comm layer's, read from its disassembly; the
offsets cited are in ``USBCommLayerUbuntu.so`` (x86-64, from kinova-ros), see ``docs/kinova-usb-wire.md``.

Kinova's command layer (``USBCommandLayerUbuntu.so``, the high-level API, which sends its packets through the comm
layer's ``SendPacket``) needs one more packet for ``InitAPI``/``GetAngularPosition``/``CloseAPI``: 0x69, get angular
position (InitAPI and CloseAPI send nothing of their own). Offsets cited as "cmd 0x…" are in that binary (same SDK).

What the real base does that the binaries cannot show (our choices, documented in the doc): the reply header of a
command packet (the comm layer never reads it, the command layer checks only its sign/0x4000 bits and its data size;
we echo the command id and give the data size); whether the base still answers the device-info command after RS-485
activation (we answer it, and nothing else but 700); what it does with RS-485 packets before activation (we drop
them); how a bulk IN ends when fewer records are queued than asked (we return what is queued at once, as a short
transfer) and what it returns when none are (a timeout, ``empty_in``); that a base of device type ≠ 8 sends 6
actuator angles, not 7 (the command layer reads 6 then).
"""
from __future__ import annotations

import hashlib
import os
import shutil
import socket
import socketserver
import struct
import subprocess
import threading
import time
from collections import deque
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from protocol import kinova, rs485

# ------------------------------------------------------------------------------------ endpoints and codes
#: command packets: interrupt OUT then interrupt IN, 64 bytes each (SendPacketInternal, 0x83d0 and 0x8443)
EP_COMMAND_OUT, EP_COMMAND_IN = 0x02, 0x82
#: RS-485 batches: bulk OUT (OpenRS485_Write, 0x8dcb) and bulk IN (OpenRS485_Read, 0x8fdc)
EP_RS485_OUT, EP_RS485_IN = 0x01, 0x81
LIBUSB_SUCCESS, LIBUSB_ERROR_NO_DEVICE, LIBUSB_ERROR_TIMEOUT = 0, -4, -7

# ------------------------------------------------------------------------------------ command packets
#: USB packet size (SendPacketInternal copies 8 header + 0x38 data bytes into a 64-byte buffer, 0x8293-0x8335)
PACKET_SIZE = 64
#: struct Packet's header on the wire: short IdPacket, TotalPacketCount, IdCommand, TotalDataSize (0x8293-0x8312)
PACKET_HEADER = struct.Struct("<hhhh")
PACKET_DATA_SIZE = PACKET_SIZE - PACKET_HEADER.size  # 56
#: GetDeviceInfo's request: IdCommand 0x79, TotalDataSize 1, Data[0] 1 (0x79fb-0x7a4b)
CMD_GET_DEVICE_INFO = 0x79
#: OpenRS485_Activate's request: IdCommand 0x2BC, TotalDataSize 0x40, Data[0] 0 (0x934a-0x936c)
CMD_RS485_ACTIVATE = 700
#: GetDeviceInfo's reading of the reply's Data (0x7aa6-0x7c64): SerialNumber = Data[0:20], Model = Data[20:40],
#: VersionRelease = Data[40], VersionMinor = Data[41], VersionMajor = Data[42], Data[43] skipped,
#: DeviceType = int32 Data[44:48]
DEVICE_INFO = struct.Struct("<20s20sBBBxi")
SERIAL_LENGTH = 20  # KinovaDevice.SerialNumber / Model (header: SERIAL_LENGTH)

# ------------------------------------------------------------------------------------ the command layer's packets
# (offsets "cmd 0x…" in USBCommandLayerUbuntu.so; its SendGetCommand, cmd 0x202de, sends them through SendPacket)
#: GetAngularPosition's request: IdPacket 1, TotalPacketCount 1, IdCommand 0x69, TotalDataSize 1, Data[0:4] = 1, 0,
#: 0, 0 (cmd 0x16463-0x1649c; Data[4:56] are never initialised: stack bytes go on the wire)
CMD_GET_ANGULAR_POSITION = 0x69
#: AngularPosition as GetAngularPosition fills it: Actuators.Actuator1-7 (float, at +0x0 … +0x18), then
#: Fingers.Finger1-3 (+0x1c, +0x20, +0x24) (DeserializeAngularPosition, cmd 0x2646c: stores at 0x2653a-0x26811)
ANGULAR_ACTUATORS, ANGULAR_FINGERS = 7, 3
#: each value is 4 bytes of the reply's data at a running index, little-endian float32 (GetFloatFromVector, cmd
#: 0x20bd5-0x20c4b; the index starts at 0, cmd 0x16459)
ANGULAR_VALUE = struct.Struct("<f")
#: Actuator7 is read only when the active device's DeviceType (KinovaDevice +0x34, from GetActiveDevice at cmd
#: 0x264b7, i.e. our DEVICE_INFO's int32) is 8 (cmd 0x266d8 ``cmp eax,0x8``; KinovaTypes.h:
#: eRobotType_Spherical_7DOF_Service); otherwise Finger1-3 are read right after Actuator6 and Actuator7 is untouched
DEVICE_TYPE_7DOF = 8
#: SendGetCommand's checks of each reply header (cmd 0x203a7-0x20467): IdCommand < 0 → 2003 (first packet) / 2005;
#: IdCommand & 0x4000 → 2004; the reply's IdCommand is not compared with the request's, TotalPacketCount not read
REPLY_ERROR_BIT = 0x4000
#: and its loop (cmd 0x204e7-0x20548): it appends the reply's 56 data bytes (merge, cmd 0x204ab) and asks for
#: IdPacket + 1 until it holds ≥ the reply's TotalDataSize bytes, so a reply with TotalDataSize ≤ 56 is the only one
#: (a negative TotalDataSize, compared unsigned, would never end the loop)

# ------------------------------------------------------------------------------------ RS-485 packets
#: OpenRS485_Write/Read's packet: byte 0 = records in this packet (Write 0x877c/0x8930; Read 0x904d, capped at 3
#: at 0x907e), byte 1 = the batch's total count, low byte (Write 0x8732; Read ignores it), bytes 2-3 = 0
#: (0x8744, 0x8757), then 3 records of 20 bytes at 4, 24, 44 (0x87e5, 0x8a99, 0x8bc4); unused slots zero (0x8cf5)
RS485_HEADER_SIZE = 4
RS485_PER_PACKET = rs485.MESSAGES_PER_USB_PACKET  # 3
RS485_SLOT_OFFSETS = tuple(RS485_HEADER_SIZE + i * rs485.MESSAGE_SIZE for i in range(RS485_PER_PACKET))

Records = np.ndarray


def command_packet(id_command: int, data: bytes = b"", id_packet: int = 1, total_packets: int = 1,
                   total_data_size: int | None = None) -> bytes:
    """One 64-byte command packet (struct Packet's header, then 56 data bytes, zero-padded)."""
    if len(data) > PACKET_DATA_SIZE:
        raise ValueError(f"a packet carries at most {PACKET_DATA_SIZE} data bytes")
    size = len(data) if total_data_size is None else total_data_size
    return PACKET_HEADER.pack(id_packet, total_packets, id_command, size) + data.ljust(PACKET_DATA_SIZE, b"\0")


def pack_rs485(records: Records) -> bytes:
    """Records as OpenRS485_Write lays them out (and Read unpacks them): 3 per 64-byte packet."""
    raw = np.ascontiguousarray(records, dtype=rs485.MESSAGE_DTYPE).tobytes()
    count = len(raw) // rs485.MESSAGE_SIZE
    out = bytearray()
    for first in range(0, count, RS485_PER_PACKET):
        n = min(RS485_PER_PACKET, count - first)
        body = raw[first * rs485.MESSAGE_SIZE:(first + n) * rs485.MESSAGE_SIZE]
        out += bytes((n, count & 0xFF, 0, 0)) + body.ljust(PACKET_SIZE - RS485_HEADER_SIZE, b"\0")
    return bytes(out)


def unpack_rs485(payload: bytes) -> Records:
    """The records of whole 64-byte RS-485 packets, as OpenRS485_Read unpacks them: byte 0 of each packet says how
    many (capped at 3; 0 skips the packet), the records sit at 4, 24, 44; a trailing partial packet is ignored."""
    chunks = []
    for start in range(0, len(payload) - PACKET_SIZE + 1, PACKET_SIZE):
        n = min(payload[start], RS485_PER_PACKET)
        for offset in RS485_SLOT_OFFSETS[:n]:
            chunks.append(payload[start + offset:start + offset + rs485.MESSAGE_SIZE])
    return np.frombuffer(b"".join(chunks), dtype=rs485.MESSAGE_DTYPE).copy()


def _fixed(text: str) -> bytes:
    raw = text.encode("ascii")
    if len(raw) >= SERIAL_LENGTH:
        raise ValueError(f"{text!r}: at most {SERIAL_LENGTH - 1} characters (the comm layer copies 20 bytes)")
    return raw.ljust(SERIAL_LENGTH, b"\0")


def angular_position_data(values: Sequence[float], device_type: int) -> bytes:
    """GetAngularPosition's reply data: ``values`` are AngularPosition's 10 floats in degrees (Actuator1-7, then
    Finger1-3); Actuator7 goes on the wire only for device type 8 (the command layer reads it only then)."""
    values = [float(v) for v in values]
    if len(values) != ANGULAR_ACTUATORS + ANGULAR_FINGERS:
        raise ValueError(f"angular position: {ANGULAR_ACTUATORS} actuator + {ANGULAR_FINGERS} finger values, "
                         f"not {len(values)}")
    actuators = values[:ANGULAR_ACTUATORS] if device_type == DEVICE_TYPE_7DOF else values[:ANGULAR_ACTUATORS - 1]
    return b"".join(ANGULAR_VALUE.pack(v) for v in actuators + values[ANGULAR_ACTUATORS:])


class UsbBase:
    """One arm's base on USB. ``out(endpoint, data) -> (status, taken)``, ``in_(endpoint, length) -> (status,
    data)`` are the two transfer directions; statuses are libusb's (0, -7 timeout, -4 no device).

    ``angular_position``: the arm's joint angles in degrees, 7 actuators then 3 fingers — a callable returning them
    (asked at each request) or a fixed sequence; settable. With it the base answers the command layer's
    GetAngularPosition (0x69) before RS-485 activation; without it (None, the default) 0x69 is ignored like any
    other high-level command. For 7 actuators on the wire give ``device_type=8`` (see DEVICE_TYPE_7DOF)."""

    def __init__(self, forward: Callable[[Records], None], serial: str = "PJ00000001030703130",
                 model: str = "JACO2 7DOF", version: tuple[int, int, int] = (6, 2, 5), device_type: int = 0,
                 empty_in: str = "timeout",
                 angular_position: Callable[[], Sequence[float]] | Sequence[float] | None = None) -> None:
        if empty_in not in ("timeout", "zero_length"):
            raise ValueError("empty_in is 'timeout' or 'zero_length'")
        self.forward = forward
        self.angular_position = angular_position
        self.serial, self.model, self.version, self.device_type = serial, model, version, device_type
        self._serial_field, self._model_field = _fixed(serial), _fixed(model)
        self.empty_in = empty_in
        self.rs485_active = False
        #: command packets the host sent that the base did not answer (unknown, or refused in RS-485 mode)
        self.ignored_commands: list[int] = []
        #: RS-485 records dropped because they came before activation
        self.dropped_records = 0
        self._command_replies: deque[bytes] = deque()
        self._replies = bytearray()  # queued RS-485 replies, 20 bytes each

    # ---- the host's OUT transfers
    def out(self, endpoint: int, data: bytes) -> tuple[int, int]:
        if endpoint == EP_COMMAND_OUT:
            self._command(data)
            return LIBUSB_SUCCESS, len(data)
        if endpoint == EP_RS485_OUT:
            records = unpack_rs485(data)
            if not self.rs485_active:
                self.dropped_records += len(records)
            elif len(records):
                self.forward(records)
            return LIBUSB_SUCCESS, len(data)
        return LIBUSB_ERROR_NO_DEVICE, 0

    def _command(self, packet: bytes) -> None:
        if len(packet) < PACKET_HEADER.size:
            return
        _, _, command, _ = PACKET_HEADER.unpack_from(packet)
        if command == CMD_GET_DEVICE_INFO:
            major, minor, release = self.version
            info = DEVICE_INFO.pack(self._serial_field, self._model_field, release, minor, major, self.device_type)
            self._command_replies.append(command_packet(CMD_GET_DEVICE_INFO, info))
        elif command == CMD_RS485_ACTIVATE:
            self.rs485_active = True
            self._command_replies.append(command_packet(CMD_RS485_ACTIVATE))
        elif command == CMD_GET_ANGULAR_POSITION and not self.rs485_active and self.angular_position is not None:
            # one reply packet: header (1, 1, 0x69, data size ≤ 56) ends SendGetCommand's loop (our choice of header)
            source = self.angular_position
            data = angular_position_data(source() if callable(source) else source, self.device_type)
            self._command_replies.append(command_packet(CMD_GET_ANGULAR_POSITION, data))
        else:
            # the rest of the high-level protocol is not emulated here, nor 0x69 after 700 (what the real arm does
            # with high-level packets after 700 is unknown; the comm layer no longer sends them: 1021)
            self.ignored_commands.append(command)

    # ---- the host's IN transfers
    def in_(self, endpoint: int, length: int) -> tuple[int, bytes]:
        if endpoint == EP_COMMAND_IN:
            if not self._command_replies:
                return LIBUSB_ERROR_TIMEOUT, b""
            return LIBUSB_SUCCESS, self._command_replies.popleft()[:length]
        if endpoint == EP_RS485_IN:
            return self._read(length)
        return LIBUSB_ERROR_NO_DEVICE, b""

    def _read(self, length: int) -> tuple[int, bytes]:
        queued = len(self._replies) // rs485.MESSAGE_SIZE
        take = min(queued, (length // PACKET_SIZE) * RS485_PER_PACKET)
        if take == 0:
            return (LIBUSB_ERROR_TIMEOUT, b"") if self.empty_in == "timeout" else (LIBUSB_SUCCESS, b"")
        raw = bytes(self._replies[:take * rs485.MESSAGE_SIZE])
        del self._replies[:take * rs485.MESSAGE_SIZE]
        return LIBUSB_SUCCESS, pack_rs485(np.frombuffer(raw, dtype=rs485.MESSAGE_DTYPE))

    # ---- the bus's side
    def deliver(self, records: Records) -> None:
        """Queue actuator replies for the host's next OpenRS485_Read (in order)."""
        self._replies += np.ascontiguousarray(records, dtype=rs485.MESSAGE_DTYPE).tobytes()

    @property
    def queued(self) -> int:
        return len(self._replies) // rs485.MESSAGE_SIZE


# ================================================================================= the socket server
#: the stand-in libusb's framing (little-endian): request u8 kind, u8 endpoint, u16 length, u32 timeout_ms,
#: u8 device index (+ length bytes for OUT); answer i32 status, u16 length (+ bytes)
REQUEST = struct.Struct("<BBHIB")
ANSWER = struct.Struct("<iH")
KIND_OUT, KIND_IN = 1, 2


class UsbBaseServer:
    """Serves :class:`UsbBase` objects (device index i → ``bases[i]``) on a Unix stream socket, one thread per
    connection. ``in_wait_s``: how long an IN with nothing to return waits for :meth:`deliver` (at most the
    transfer's timeout) before it answers; 0 answers at once."""

    def __init__(self, path: str, bases: Sequence[UsbBase], in_wait_s: float = 0.0) -> None:
        self.path, self.bases, self.in_wait_s = path, list(bases), in_wait_s
        self.lock = threading.Condition(threading.RLock())
        server = self

        class Handler(socketserver.BaseRequestHandler):
            def handle(self) -> None:
                server._serve(self.request)

        if os.path.exists(path):
            os.unlink(path)
        self._server = socketserver.ThreadingUnixStreamServer(path, Handler)
        self._server.daemon_threads = True
        self._thread = threading.Thread(target=self._server.serve_forever, daemon=True, name="usb-base")

    def start(self) -> "UsbBaseServer":
        self._thread.start()
        return self

    def close(self) -> None:
        self._server.shutdown()
        self._server.server_close()
        if os.path.exists(self.path):
            os.unlink(self.path)

    def __enter__(self) -> "UsbBaseServer":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    def deliver(self, records: Records, device: int = 0) -> None:
        with self.lock:
            self.bases[device].deliver(records)
            self.lock.notify_all()

    def _serve(self, conn: socket.socket) -> None:
        while True:
            head = _recv_exactly(conn, REQUEST.size)
            if head is None:
                return
            kind, endpoint, length, timeout_ms, device = REQUEST.unpack(head)
            payload = _recv_exactly(conn, length) if kind == KIND_OUT else b""
            if payload is None:
                return
            if kind == KIND_OUT:
                status, taken = self._out(device, endpoint, payload)
                conn.sendall(ANSWER.pack(status, taken))  # an OUT answer's length is the bytes taken, no data
            else:
                status, data = self._in(device, endpoint, length, timeout_ms)
                conn.sendall(ANSWER.pack(status, len(data)) + data)

    def _out(self, device: int, endpoint: int, payload: bytes) -> tuple[int, int]:
        with self.lock:
            if device >= len(self.bases):
                return LIBUSB_ERROR_NO_DEVICE, 0
            result = self.bases[device].out(endpoint, payload)
            self.lock.notify_all()
            return result

    def _in(self, device: int, endpoint: int, length: int, timeout_ms: int) -> tuple[int, bytes]:
        with self.lock:
            if device >= len(self.bases):
                return LIBUSB_ERROR_NO_DEVICE, b""
            deadline = time.monotonic() + min(self.in_wait_s, timeout_ms / 1000.0)
            while True:
                status, data = self.bases[device].in_(endpoint, length)
                remaining = deadline - time.monotonic()
                if status != LIBUSB_ERROR_TIMEOUT or remaining <= 0:
                    return status, data
                self.lock.wait(remaining)


def _recv_exactly(conn: socket.socket, n: int) -> bytes | None:
    buf = bytearray()
    while len(buf) < n:
        chunk = conn.recv(n - len(buf))
        if not chunk:
            return None
        buf += chunk
    return bytes(buf)


# ================================================================================= robot_sim's actuators behind it
#: ``bus.interface`` for robot_sim's actuators behind an emulated base on USB (the channel is the socket's path)
INTERFACE = "kinova_usb_base"
#: how long the emulated base holds a host's read open for the actuators' replies (they answer at their next 2 ms
#: cycle boundary): our choice, a bus cycle and a half plus margin; the real base's is not public
IN_WAIT_S = 0.005


class UsbBaseBus:
    """The arm's side of its base, as robot_sim's actuators use a bus (``send_batch``/``recv_batch``): what the
    host writes through the comm layer arrives here; what the actuators send goes back through the host's reads.
    USB carries no stamps: a host stamps replies when it reads them, or in lockstep counts its exchanges (the
    arm's serial number, ``protocol.kinova.EMULATED_SERIAL``, tells it the arm is this emulation)."""

    arm_timeline = False

    def __init__(self, path: str, model: str, counters=None, serial: str = kinova.EMULATED_SERIAL,
                 in_wait_s: float = IN_WAIT_S, device_type: int = 0,
                 angular_position: Callable[[], Sequence[float]] | Sequence[float] | None = None) -> None:
        self.counters = counters
        self._incoming: deque[tuple[Records, int]] = deque()
        self._arrived = threading.Condition()
        self.base = UsbBase(self._from_host, serial=serial, model=model, device_type=device_type,
                            angular_position=angular_position)
        self.server = UsbBaseServer(path, [self.base], in_wait_s=in_wait_s).start()

    def _from_host(self, records: Records) -> None:
        with self._arrived:
            self._incoming.append((records.copy(), time.time_ns()))
            self._arrived.notify_all()

    def send_batch(self, batch: Records, stamp_ns: int = 0) -> None:
        self.server.deliver(batch)

    def recv_batch(self, timeout: float | None = 0.0) -> tuple[Records, np.ndarray]:
        with self._arrived:
            if not self._incoming:
                self._arrived.wait(timeout)
            taken, self._incoming = list(self._incoming), deque()
        if not taken:
            return np.zeros(0, dtype=rs485.MESSAGE_DTYPE), np.zeros(0, dtype=np.int64)
        batch = np.concatenate([records for records, _ in taken])
        stamps = np.concatenate([np.full(len(records), stamp, dtype=np.int64) for records, stamp in taken])
        return batch, stamps

    def close(self) -> None:
        self.server.close()


# ================================================================================= the host's side: a stand-in libusb
#: the stand-in libusb's source (C): Kinova's comm layer, loaded over it, reaches an emulated base's socket
STAND_IN_SOURCE = Path(__file__).with_name("libusb_stand_in.c")
#: the environment variable naming that socket in the host's process
SOCKET_ENV = "MFVS_FAKE_USB_SOCKET"


def stand_in_libusb(cache: Path | None = None) -> Path:
    """The directory holding the stand-in ``libusb-1.0.so.0``, built with the system C compiler once per version
    of its source (under ``$XDG_CACHE_HOME/mfvs``, else ``~/.cache/mfvs``). Raises RuntimeError, saying what is
    missing, where it cannot be built."""
    source = STAND_IN_SOURCE.read_bytes()
    base = cache or Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "mfvs"
    directory = base / f"libusb-stand-in-{hashlib.sha256(source).hexdigest()[:12]}"
    library = directory / "libusb-1.0.so.0"
    if library.is_file():
        return directory
    compiler = shutil.which("cc") or shutil.which("gcc")
    if compiler is None:
        raise RuntimeError("no C compiler (cc or gcc) to build the stand-in libusb: bash deploy/install.sh installs "
                           "gcc")
    directory.mkdir(parents=True, exist_ok=True)
    partial = directory / f".libusb-{os.getpid()}.so"
    built = subprocess.run([compiler, "-shared", "-fPIC", "-O1", "-Wall", "-Werror", "-Wl,-soname,libusb-1.0.so.0",
                            "-o", str(partial), str(STAND_IN_SOURCE), "-lpthread"], capture_output=True, text=True)
    if built.returncode != 0:
        raise RuntimeError(f"the stand-in libusb did not build: {built.stderr.strip()[-500:]}")
    os.replace(partial, library)  # atomic: two processes building at once both end with a whole file
    return directory


def host_environment(socket_path: str, libusb_dir: Path, kinova_lib_dir: Path | None = None) -> dict[str, str]:
    """What a host process (robot_gateway on ``bus.interface: kinova_usb``) needs in its environment to reach the
    emulated base at ``socket_path`` through Kinova's comm layer: the stand-in first on the loader's path (the comm
    layer links libusb-1.0.so.0 by name), and the socket. ``kinova_lib_dir``: the SDK's library directory, put
    second, for a host that uses the command layer (its InitAPI does ``dlopen("USBCommLayerUbuntu.so")`` by bare
    name, cmd 0x11a97, and the comm layer has no SONAME: only the loader's search path finds it). The loader reads
    LD_LIBRARY_PATH when the process starts: this is for a child's environment, not ``os.environ``."""
    path = os.environ.get("LD_LIBRARY_PATH", "")
    dirs = [str(libusb_dir)] + ([str(kinova_lib_dir)] if kinova_lib_dir else []) + ([path] if path else [])
    return {"LD_LIBRARY_PATH": os.pathsep.join(dirs), SOCKET_ENV: socket_path}
