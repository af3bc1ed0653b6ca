"""The arm's actuator bus through Kinova's USB comm layer (``bus.interface: kinova_usb``): how a host reaches a
real JACO-2's RS-485 bus, which is inside the arm, behind its base. :class:`KinovaUsbBus` has the surface of
:class:`services.robot.rs485_bus.RS485Bus` that the actuator link uses (``send_batch``, ``recv_batch``,
``arm_timeline``, ``counters``, ``close``), on ``USBCommLayerUbuntu.so``'s ``InitCommunication``,
``OpenRS485_Activate``, ``OpenRS485_Write`` and ``OpenRS485_Read``, loaded with ctypes by path.

What the library does, read from its disassembly and run against a libusb written for the tests
(docs/kinova-usb-wire.md), and what this module does about it:

* ``OpenRS485_Write``/``Read`` dereference the first device found without checking: called before a successful
  ``InitCommunication`` (or after one that found no arm) they crash the process. They are never reached unless
  ``InitCommunication`` returned 1 (:func:`open_kinova_usb`).
* Activation goes to the first Kinova device libusb lists, whichever is "active": with more than one arm connected
  the bus could be another arm's. Refused.
* Activation disables the arm's joystick and its high-level API until the arm is power-cycled (Kinova's header):
  logged, once, before it is done.
* ``Read`` asks for ``ceil(1.2·wanted/3)`` whole 64-byte packets and unpacks up to 3 records from each, past the
  quantity wanted (50 wanted: up to 60 written): the buffer here holds every record it can write.
* ``Write`` reports packets (3 messages each), not messages, in ``QtySent``: a write is whole when
  ``QtySent == ceil(n/3)``.
* Every call opens the device, claims its interface and closes it again; a call overlapping another fails (the
  claim is busy: 666). One lock around every call into the library.
* An empty read is 1016 (the transfer ended with no record) or 1020 (it timed out: the library waits up to 5 s,
  a time this module cannot shorten); both are "nothing came".

Stamps: the USB wire carries none; a reply is stamped when the read that brought it returned (``arm_timeline`` is
False: the robot node runs its DSP every fifth cycle, as on any real arm).
"""
from __future__ import annotations

import ctypes
import logging
import math
import os
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Optional

import numpy as np

from protocol import kinova
from protocol.rs485 import MAX_BATCH, MESSAGE_DTYPE, MESSAGES_PER_USB_PACKET
from services.robot.rs485_bus import BusError, known_only
from services.robot_gateway.kinova_sdk import (LAYERS, MAX_KINOVA_DEVICE, SDK_ENV, SDK_LIB_SUBDIR, AngularPosition,
                                               ArmStartError, KinovaDevice, from_c)
from services.runtime.metrics import Counters, DurationStats

log = logging.getLogger("mfvs.robot_gateway.kinova_usb")

#: Kinova's USB comm layer and the command layer (the high-level API) beside it (kinova-ros:
#: kinova_driver/lib/x86_64-linux-gnu)
COMM_LAYER, COMMAND_LAYER = LAYERS["usb"].comm_layer, LAYERS["usb"].command_layer
#: the RS-485 functions' names as public builds of the comm layer export them (Activate, Write, Read): the SDK's
#: header and kinova-ros's library; older SDKs; Kinova's Windows-derived builds
RS485_SPELLINGS = (("OpenRS485_Activate", "OpenRS485_Write", "OpenRS485_Read"),
                   ("RS485_Activate", "RS485_Write", "RS485_Read"),
                   ("Communication_OpenRS485_Activate", "Communication_OpenRS485_Write",
                    "Communication_OpenRS485_Read"))
OK = kinova.ErrorCode.NO_ERROR_KINOVA
#: what an empty read returns: the transfer completed with no record / timed out (docs/kinova-usb-wire.md)
EMPTY_READ = frozenset({kinova.ErrorCode.ERROR_OPERATION_INCOMPLETED, kinova.ErrorCode.ERROR_RS485_TIMEOUT})
#: the library's own Read packs at most 3 records into each of ceil(1.2·wanted/3) packets
_READ_FACTOR = 1.2
#: after activation, how long the base may still be sending what it had queued, and how many reads to empty it
SETTLE_S = 0.05
MAX_SETTLE_READS = 20

_EMPTY = np.zeros(0, dtype=MESSAGE_DTYPE)
_NO_STAMPS = np.zeros(0, dtype=np.int64)


def read_capacity(wanted: int) -> int:
    """How many records ``OpenRS485_Read(buffer, wanted, ...)`` can write into ``buffer``: 3 in each whole packet
    it asks for, ``ceil(wanted·1.2/3)`` packets computed as the library does (float, then double)."""
    packets = math.ceil(float(np.float32(wanted)) * _READ_FACTOR / MESSAGES_PER_USB_PACKET)
    return MESSAGES_PER_USB_PACKET * max(packets, 0)


def packets_for(messages: int) -> int:
    """How many packets ``OpenRS485_Write`` sends for ``messages`` messages: its ``QtySent`` when all went out."""
    return math.ceil(messages / MESSAGES_PER_USB_PACKET)


#: how far the first RS-485 positions may be from Kinova's high-level reading before activation (deg) and agree
#: (our choice: a position read from the wrong field or actuator is tens of degrees off; the two readings' own
#: difference on a real arm is not public, ``mfvs check rs485`` measures it)
HIGH_LEVEL_CHECK_DEG = 3.0


def around_deg(measured_deg, expected_deg) -> np.ndarray:
    """``measured - expected`` in degrees, taken around the circle (continuous joints report any turn)."""
    return (np.asarray(measured_deg, dtype=float) - np.asarray(expected_deg, dtype=float) + 180.0) % 360.0 - 180.0


def high_level_disagreement(measured_deg, expected_deg, tolerance_deg: float) -> str:
    """The joints whose RS-485 position differs from the high-level reading by more than ``tolerance_deg``, as
    text; empty when none does (a NaN never agrees)."""
    return ", ".join(f"joint {i + 1}: {m:.2f}° on RS-485, {e:.2f}° before"
                     for i, (m, e, d) in enumerate(zip(measured_deg, expected_deg, around_deg(measured_deg,
                                                                                            expected_deg)))
                     if not abs(d) <= tolerance_deg)


def describe(code: int) -> str:
    return f"{code} ({kinova.error_name(code)})"


# ------------------------------------------------------------------------------------------------ the library
def locate_comm_layer(setting: Optional[str], environ: Optional[dict] = None) -> Path:
    """``USBCommLayerUbuntu.so`` where ``setting`` (else ``$MFVS_KINOVA_SDK``) says: the file, or a directory
    holding it directly or under lib/x86_64-linux-gnu (a kinova-ros kinova_driver folder). Raises
    :class:`ArmStartError` saying where it looked."""
    environ = os.environ if environ is None else environ
    given, source = (setting, "sdk_library") if setting else (environ.get(SDK_ENV) or None, SDK_ENV)
    if not given:
        raise ArmStartError(f"Kinova's SDK is not given: set sdk_library (or {SDK_ENV}) to the directory holding "
                            f"{COMM_LAYER} (kinova-ros: kinova_driver/lib/x86_64-linux-gnu)")
    path = Path(given).expanduser()
    if path.is_file():
        # the setting may name the command layer (the kinova_sdk backend's): its comm layer is beside it
        candidates = [path] if path.name == COMM_LAYER else [path.parent / COMM_LAYER]
    else:
        candidates = [path / COMM_LAYER, path / SDK_LIB_SUBDIR / COMM_LAYER]
    for candidate in candidates:
        if candidate.is_file():
            return candidate.resolve()
    raise ArmStartError(f"Kinova's comm layer is not where {source} says: no {' or '.join(map(str, candidates))}")


def has_command_layer(setting: Optional[str], environ: Optional[dict] = None) -> bool:
    """Whether Kinova's command layer (``USBCommandLayerUbuntu.so``) is beside the comm layer ``setting`` names
    (True where the comm layer is not found either: the gateway then says what is missing)."""
    try:
        comm_layer = locate_comm_layer(setting, environ)
    except ArmStartError:
        return True
    return (comm_layer.parent / COMMAND_LAYER).is_file()


@dataclass(frozen=True)
class CommLayer:
    """Kinova's comm layer, loaded, with its functions bound (the RS-485 ones under whichever spelling it
    exports)."""

    path: Path
    init: Callable[[], int]
    close: Callable[[], int]
    get_devices: Callable
    activate: Callable[[], int]
    write: Callable
    read: Callable
    spelling: str

    @classmethod
    def load(cls, path: Path) -> "CommLayer":
        """The comm layer at ``path`` (the object already loaded, if Kinova's command layer loaded it by name from
        there: one library, one state)."""
        try:
            library = ctypes.CDLL(str(path))
        except OSError as exc:
            if "libusb" in str(exc):
                raise ArmStartError(f"Kinova's comm layer {path.name} needs libusb-1.0.so.0: install libusb-1.0-0 "
                                    "(bash deploy/install.sh does)") from None
            raise ArmStartError(f"Kinova's comm layer {path} cannot be loaded: {exc}") from None
        rs485 = next((names for names in RS485_SPELLINGS if all(hasattr(library, n) for n in names)), None)
        missing = [n for n in ("InitCommunication", "CloseCommunication", "GetDevices") if not hasattr(library, n)]
        if rs485 is None or missing:
            wanted = missing + ([] if rs485 else [" / ".join(s[0].replace("Activate", "*") for s in RS485_SPELLINGS)])
            raise ArmStartError(f"{path} is not Kinova's USB comm layer: it exports no {', '.join(wanted)}")
        int_ref = ctypes.POINTER(ctypes.c_int)

        def bound(name: str, argtypes: list):
            function = getattr(library, name)
            function.argtypes, function.restype = argtypes, ctypes.c_int
            return function

        activate, write, read = rs485
        return cls(path=path, init=bound("InitCommunication", []), close=bound("CloseCommunication", []),
                   get_devices=bound("GetDevices", [ctypes.POINTER(KinovaDevice), int_ref]),
                   activate=bound(activate, []), write=bound(write, [ctypes.c_void_p, ctypes.c_int, int_ref]),
                   read=bound(read, [ctypes.c_void_p, ctypes.c_int, int_ref]), spelling=activate[:-len("Activate")])


# ------------------------------------------------------------------------------------------------ the bus
class KinovaUsbBus:
    """The RS-485 bus behind an arm's base, through the comm layer, once activated (:func:`open_kinova_usb`)."""

    #: the USB wire carries no stamps: replies are stamped when they are read
    arm_timeline = False
    #: every look at what has arrived is a USB read through the library (the actuator link does not poll it)
    polling_is_free = False

    def __init__(self, comm: CommLayer, counters: Counters | None = None, device: KinovaDevice | None = None,
                 high_level_deg: Optional[np.ndarray] = None) -> None:
        self.comm = comm
        #: the joint angles (physical degrees) Kinova's high-level API read just before activation, that the first
        #: RS-485 positions are checked against (None: not read)
        self.high_level_deg = high_level_deg
        #: the arm whose bus this is, as the comm layer lists it
        self.serial = kinova.device_text(device.SerialNumber) if device is not None else ""
        self.model = kinova.device_text(device.Model) if device is not None else ""
        self.counters = counters or Counters()
        self.last_error = ""
        self._lock = threading.Lock()
        self._read_buffer = np.zeros(read_capacity(MAX_BATCH), dtype=MESSAGE_DTYPE)
        self._closed = False
        #: how long each kind of call into the library takes (``mfvs check rs485`` and the health report them)
        self.call_times = {name: DurationStats() for name in ("activate", "write", "read")}

    def _call(self, name: str, function, *args) -> int:
        """One call into the library, never two at once (overlapping calls fail: 666)."""
        with self._lock:
            if self._closed:
                raise BusError("the Kinova USB bus is closed")
            started = time.perf_counter()
            code = function(*args)
            self.call_times[name].add(time.perf_counter() - started)
        return code

    def _failed(self, what: str, code: int) -> BusError:
        self.counters.inc(f"usb.errors.{kinova.error_name(code).lower()}")
        self.last_error = f"{what} returned {describe(code)}"
        return BusError(self.last_error)

    def send_batch(self, batch: np.ndarray, stamp_ns: int = 0) -> None:
        """The messages in order, at most 50 a call (the library's array); ``stamp_ns`` is not carried (USB has no
        stamps)."""
        for first in range(0, len(batch), MAX_BATCH):
            chunk = np.ascontiguousarray(batch[first : first + MAX_BATCH], dtype=MESSAGE_DTYPE)
            sent = ctypes.c_int(0)
            code = self._call("write", self.comm.write, chunk.ctypes.data, len(chunk), ctypes.byref(sent))
            if code != OK:
                raise self._failed("OpenRS485_Write", code)
            if sent.value != packets_for(len(chunk)):
                self.counters.inc("usb.incomplete_writes")
                self.last_error = (f"OpenRS485_Write sent {sent.value} of {packets_for(len(chunk))} packets "
                                   f"({len(chunk)} messages)")
                raise BusError(self.last_error)
            self.counters.inc("usb.messages_sent", len(chunk))

    def recv_batch(self, timeout: Optional[float] = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """What the base has for the host: one read, then more while nothing came and ``timeout`` has not passed
        (each read may itself take up to the library's 5 s when the base sends nothing: a read that takes longer
        than it was given is counted, ``usb.late_reads``)."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            started = time.monotonic()
            batch = self._read_once()
            if deadline is not None and time.monotonic() - started > max(timeout, 0.0) + 0.05:
                self.counters.inc("usb.late_reads")
            if len(batch) or (deadline is not None and time.monotonic() >= deadline):
                break
        if len(batch) == 0:
            return _EMPTY, _NO_STAMPS
        batch, stamps, rejected = known_only(batch, np.full(len(batch), time.time_ns(), dtype=np.int64))
        if rejected:
            self.counters.inc("bus.rejected", rejected)
            self.last_error = "unknown command id"
        return batch, stamps

    def _read_once(self) -> np.ndarray:
        received = ctypes.c_int(0)
        code = self._call("read", self.comm.read, self._read_buffer.ctypes.data, MAX_BATCH, ctypes.byref(received))
        if code in EMPTY_READ:
            self.counters.inc("usb.empty_reads")
            return _EMPTY
        if code != OK:
            raise self._failed("OpenRS485_Read", code)
        count = received.value
        if not 0 <= count <= len(self._read_buffer):  # the library cannot write more: a broken build if it says so
            self.counters.inc("usb.bad_reads")
            raise BusError(f"OpenRS485_Read reported {count} records, more than it can write "
                           f"({len(self._read_buffer)})")
        self.counters.inc("usb.messages_received", count)
        return self._read_buffer[:count].copy()

    def drain(self) -> int:
        """Read until the base has nothing more (at most ``MAX_SETTLE_READS`` reads); returns the records
        dropped."""
        dropped = 0
        for _ in range(MAX_SETTLE_READS):
            batch = self._read_once()
            if len(batch) == 0:
                break
            dropped += len(batch)
        return dropped

    def close(self) -> None:
        """The comm layer closed (the arm stays in RS-485 mode until it is power-cycled: Kinova's header)."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            self.comm.close()


def devices(comm: CommLayer) -> list[KinovaDevice]:
    listed = (KinovaDevice * MAX_KINOVA_DEVICE)()
    result = ctypes.c_int(0)
    count = comm.get_devices(listed, ctypes.byref(result))
    if result.value != OK:
        raise ArmStartError(f"Kinova's comm layer: GetDevices said {describe(result.value)}")
    return list(listed[: max(0, min(count, MAX_KINOVA_DEVICE))])


def init_api(command_layer: Path):
    """Kinova's command layer, loaded and initialised (InitAPI loads the comm layer by name and initialises it: the
    process must find it on the loader's path). Raises :class:`ArmStartError` naming the code."""
    try:
        api = ctypes.CDLL(str(command_layer))
    except OSError as exc:
        raise ArmStartError(f"Kinova's command layer {command_layer} cannot be loaded: {exc}") from None
    api.InitAPI.argtypes, api.InitAPI.restype = [], ctypes.c_int
    api.GetAngularPosition.argtypes = [ctypes.POINTER(AngularPosition)]
    api.GetAngularPosition.restype = ctypes.c_int
    code = api.InitAPI()
    if code != OK:
        raise ArmStartError(f"Kinova's command layer: InitAPI returned {describe(code)}")
    return api


def high_level_angles(api, n_joints: int) -> np.ndarray:
    """The joint angles (physical degrees) through the high-level API, before RS-485 is activated: one
    GetAngularPosition. Once only: one that fails takes a machine-wide semaphore of Kinova's
    (``/dev/shm/sem.KinovaMutex``) and never gives it back (docs/kinova-usb-wire.md)."""
    position = AngularPosition()
    code = api.GetAngularPosition(ctypes.byref(position))
    if code != OK:
        raise ArmStartError(f"Kinova's command layer: GetAngularPosition returned {describe(code)} (an arm whose "
                            "RS-485 bus was activated answers no high-level call until it is power-cycled)")
    return np.array(from_c(position, kinova.AngularPosition).Actuators.as_list()[:n_joints], dtype=float)


def open_kinova_usb(comm_layer: Path, arm_name: str, n_joints: int, counters: Counters | None = None,
                    logger: logging.Logger = log, emulated_only: bool = False,
                    command_layer: Optional[Path] = None) -> KinovaUsbBus:
    """The arm's RS-485 bus through the comm layer at ``comm_layer``, activated: InitCommunication (1, else one
    line naming the code), exactly one Kinova device (activation goes to the first one listed), its model the
    configured arm's (:func:`protocol.kinova.arm_type_refusal`), then OpenRS485_Activate and the base read until
    it has nothing queued. ``emulated_only`` (lockstep, which exchanges as fast as the arm answers): refused, before
    activation, unless the arm is robot_sim's emulated base (``protocol.kinova.EMULATED_SERIAL``), a real one keeping
    wall time. ``command_layer``: Kinova's command layer, to read the joint angles through the high-level API first
    (:func:`init_api` initialises the comm layer itself; :func:`high_level_angles` after the device checks).
    Raises :class:`ArmStartError` (one line a person can act on), the library closed."""
    api = None
    if command_layer is not None:
        api = init_api(command_layer)
        comm = CommLayer.load(comm_layer)  # the object InitAPI loaded, initialised
    else:
        comm = CommLayer.load(comm_layer)
        code = comm.init()
        if code != OK:
            comm.close()
            hint = " (is the arm on, its USB cable in, the udev rule installed?)" \
                if code == kinova.ErrorCode.ERROR_NO_DEVICE_FOUND else ""
            raise ArmStartError(f"Kinova's comm layer: InitCommunication returned {describe(code)}{hint}")
    try:
        arms = devices(comm)
        if len(arms) != 1:
            raise ArmStartError(f"{len(arms)} Kinova devices are connected ("
                                f"{', '.join(kinova.device_text(d.SerialNumber) for d in arms)}): the comm layer "
                                "sends RS-485 to the first one it lists; connect only the arm to drive")
        arm = arms[0]
        model = kinova.device_text(arm.Model)
        refusal = kinova.arm_type_refusal(model, arm_name, n_joints)
        if refusal:
            raise ArmStartError(f"refusing the arm's RS-485 bus: {refusal}")
        serial = kinova.device_text(arm.SerialNumber)
        if emulated_only and serial != kinova.EMULATED_SERIAL:
            raise ArmStartError(f"lockstep needs robot_sim's emulated actuators; arm {serial} keeps wall time: run it "
                                "in realtime")
        high_level_deg = None if api is None else high_level_angles(api, n_joints)
        logger.warning("activating the RS-485 bus of arm %s (%s): its joystick and Kinova's high-level API stop "
                       "working until the arm is power-cycled", serial, model)
        bus = KinovaUsbBus(comm, counters, arm, high_level_deg)
        code = bus._call("activate", comm.activate)
        if code != OK:
            raise ArmStartError(f"Kinova's comm layer: {comm.spelling}Activate returned {describe(code)}")
        time.sleep(SETTLE_S)
        dropped = bus.drain()
        if dropped:
            bus.counters.inc("usb.dropped_at_activation", dropped)
        logger.info("RS-485 through %s (%s*): active, %d queued message(s) dropped", comm_layer.name,
                    comm.spelling, dropped)
        return bus
    except BaseException:
        comm.close()
        raise
