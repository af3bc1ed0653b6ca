"""robot_gateway's ``kinova_sdk`` backend: the arm through Kinova's own SDK library (the JACO-2 command layer that
Kinova ships in kinova-ros, ``kinova_driver/lib/x86_64-linux-gnu``), loaded with ctypes. The arm's own DSP
interprets the commands, so the gateway forwards rather than emulates.

Finding the SDK (:func:`locate_command_layer`): the ``sdk_library`` setting, else the ``MFVS_KINOVA_SDK``
environment variable, names Kinova's SDK directory (the one holding the library, or the kinova_driver folder above
``lib/x86_64-linux-gnu``) or the command-layer file itself (``USBCommandLayerUbuntu.so``; over Ethernet
``EthCommandLayerUbuntu.so``). The command layer loads its comm layer (``USBCommLayerUbuntu.so``, which needs
libusb-1.0) by bare name at InitAPI, so the directory must be on the loader's path when the process starts:
``python -m services.robot_gateway`` puts it there itself (:func:`put_sdk_on_loader_path`, one re-exec), as the ROS
driver's environment does for it.

Starting (:func:`open_arm`), as Kinova's own driver (kinova_comm.cpp) does: InitAPI (or InitEthernetAPI with the
arm's address), the device list refreshed and read, the arm chosen by serial number (or the only one), made
active, its reported model checked against the configured arm (:func:`protocol.kinova.arm_type_refusal`), then
StartControlAPI, StopControlAPI and StartControlAPI again (an arm after a cold boot does not obey the API until
then), and a zero velocity point. Every way out of a failed start closes the API; each failure is one line a
person can act on (:class:`ArmStartError`). At the end: the trajectories erased, StopControlAPI, CloseAPI.

Running (:class:`SdkArm`):

* robot commands → ``SendBasicTrajectory`` every DSP cycle (10 ms, latest command wins, like the ROS driver):
  a mixed twist as a CARTESIAN_VELOCITY point (m/s, rad/s in the convention the arm is configured with; another
  convention is refused, as robot_sim's DSP does), joint velocities as an ANGULAR_VELOCITY point (deg/s, physical
  signs); stop and emergency stop as the driver stops: EraseAllTrajectories and a zero-velocity point;
* state ← ``GetAngularPosition`` / ``GetAngularVelocity`` / ``GetAngularForce`` / ``GetCartesianPosition``;
* the ``robot/api/*`` queryables ← the SDK functions of the same name that the backend knows the signature of.

The structs mirror KinovaTypes.h and the comm layer's header (the tests compile the headers with the system C++
compiler and compare every size and offset, every enum value and every bound function's type); getters take a
reference (a pointer here), SendBasicTrajectory and SetActiveDevice take their struct by value. There is no
low-level torque API through the command layer.
"""
from __future__ import annotations

import contextlib
import ctypes
import ipaddress
import logging
import os
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, Optional

import msgspec
import numpy as np

from protocol import kinova
from protocol.conventions import AngularConvention
from protocol.messages import CommandMode, ControlMode, FingerMode, MotionLimits, RobotCommand
from services.model import frames
from services.model.arm import ArmDescription
from services.robot.dsp import CommandRefused, DSPConfig, DSPStatus, motion_limits
from services.robot.hardware import FingerReading, JointReading
from services.runtime.config import ConfigStruct
from services.runtime.service import StartupError

#: the environment variable naming Kinova's SDK (its directory or its command-layer file) where no setting does
SDK_ENV = "MFVS_KINOVA_SDK"
#: where Kinova's kinova_driver folder (and this project's reference copy) keeps the x86_64 libraries
SDK_LIB_SUBDIR = Path("lib") / "x86_64-linux-gnu"
#: set by :func:`put_sdk_on_loader_path` in the process it re-executes, so that it does so once
_REEXEC_ENV = "MFVS_KINOVA_SDK_LOADER_PATH"

Transport = Literal["usb", "ethernet"]


@dataclass(frozen=True)
class CommandLayerFiles:
    """What Kinova ships for one transport: the command layer, the comm layer it loads by bare name at InitAPI,
    and the prefix of the command layer's function names."""

    command_layer: str
    comm_layer: str
    prefix: str


LAYERS: dict[str, CommandLayerFiles] = {
    "usb": CommandLayerFiles("USBCommandLayerUbuntu.so", "USBCommLayerUbuntu.so", ""),
    "ethernet": CommandLayerFiles("EthCommandLayerUbuntu.so", "EthCommLayerUbuntu.so", "Ethernet_"),
}


class SdkError(RuntimeError):
    def __init__(self, function: str, code: int, hint: str = "") -> None:
        detail = f": {hint}" if hint else ""
        super().__init__(f"Kinova SDK {function} returned {code} ({kinova.error_name(code)}){detail}")
        self.function, self.code = function, code


class ArmStartError(StartupError):
    """The arm could not be opened; the message is one line saying what to do."""


# ------------------------------------------------------------------------------------------------ the structs
def _floats(*names: str) -> list:
    return [(name, ctypes.c_float) for name in names]


class CartesianInfo(ctypes.Structure):
    _fields_ = _floats("X", "Y", "Z", "ThetaX", "ThetaY", "ThetaZ")


class AngularInfo(ctypes.Structure):
    _fields_ = _floats(*(f"Actuator{i}" for i in range(1, kinova.MAX_ACTUATORS + 1)))


class FingersPosition(ctypes.Structure):
    _fields_ = _floats("Finger1", "Finger2", "Finger3")


class AngularPosition(ctypes.Structure):
    _fields_ = [("Actuators", AngularInfo), ("Fingers", FingersPosition)]


class CartesianPosition(ctypes.Structure):
    _fields_ = [("Coordinates", CartesianInfo), ("Fingers", FingersPosition)]


class UserPosition(ctypes.Structure):
    _fields_ = [("Type", ctypes.c_int), ("Delay", ctypes.c_float), ("CartesianPosition", CartesianInfo),
                ("Actuators", AngularInfo), ("HandMode", ctypes.c_int), ("Fingers", FingersPosition)]


class Limitation(ctypes.Structure):
    _fields_ = _floats(*(f"{kind}Parameter{i}" for kind in ("speed", "force", "acceleration") for i in (1, 2, 3)))


class TrajectoryPoint(ctypes.Structure):
    _fields_ = [("Position", UserPosition), ("LimitationsActive", ctypes.c_int), ("SynchroType", ctypes.c_int),
                ("Limitations", Limitation)]


class TrajectoryFIFO(ctypes.Structure):
    _fields_ = [("TrajectoryCount", ctypes.c_uint), ("UsedPercentage", ctypes.c_float), ("MaxSize", ctypes.c_uint)]


#: SERIAL_LENGTH and MAX_KINOVA_DEVICE of the comm layer's header
SERIAL_LENGTH = 20
MAX_KINOVA_DEVICE = 20


class KinovaDevice(ctypes.Structure):
    """An arm the comm layer can talk to (GetDevices): its serial number and model, its firmware version."""

    _fields_ = [("SerialNumber", ctypes.c_char * SERIAL_LENGTH), ("Model", ctypes.c_char * SERIAL_LENGTH),
                ("VersionMajor", ctypes.c_int), ("VersionMinor", ctypes.c_int), ("VersionRelease", ctypes.c_int),
                ("DeviceType", ctypes.c_int), ("DeviceID", ctypes.c_int)]


class EthernetCommConfig(ctypes.Structure):
    """InitEthernetAPI's argument: IPv4 addresses as inet_addr gives them (network byte order in memory) in
    ``unsigned long`` fields, ports, and the receive timeout (ms)."""

    _fields_ = [("localIpAddress", ctypes.c_ulong), ("subnetMask", ctypes.c_ulong), ("robotIpAddress", ctypes.c_ulong),
                ("localCmdport", ctypes.c_ushort), ("localBcastPort", ctypes.c_ushort), ("robotPort", ctypes.c_ushort),
                ("rxTimeOutInMs", ctypes.c_ulong)]


def inet_addr(address: str) -> int:
    """What C's inet_addr returns for a dotted IPv4 address: its bytes in network order, read in host order."""
    return int.from_bytes(ipaddress.IPv4Address(address).packed, sys.byteorder)


def to_c(message, c_type):
    """A protocol.kinova message as its ctypes struct (field names are the SDK's on both sides)."""
    out = c_type()
    for name, field_type in c_type._fields_:
        value = getattr(message, name)
        if isinstance(field_type, type) and issubclass(field_type, ctypes.Structure):
            value = to_c(value, field_type)
        setattr(out, name, int(value) if field_type in (ctypes.c_int, ctypes.c_uint) else value)
    return out


def from_c(struct, message_type):
    """A ctypes struct as the protocol.kinova message of the same shape (validated like any decoded message)."""
    def plain(value):
        if isinstance(value, ctypes.Structure):
            return {name: plain(getattr(value, name)) for name, _ in value._fields_}
        return value
    return msgspec.convert(plain(struct), message_type, strict=False)


# ------------------------------------------------------------------------------------------------ the functions
@dataclass(frozen=True)
class Binding:
    """One command-layer function: its type as the header declares it (C++; the tests compile it against the
    header) and the ctypes argument types that pass the same thing (a reference or an array as a pointer)."""

    cpp: str
    argtypes: tuple = ()


def _ref(c_type) -> type:
    return ctypes.POINTER(c_type)


_NO_ARGUMENT = Binding("int()")
#: getter → (the ctypes struct it fills through a reference, the protocol.kinova type of the value); replies are
#: the types of kinova.API_FUNCTIONS, as with the emulated API
_GETTERS = {
    "GetAngularPosition": (AngularPosition, kinova.AngularPosition),
    "GetAngularVelocity": (AngularPosition, kinova.AngularPosition),
    "GetAngularForce": (AngularPosition, kinova.AngularPosition),
    "GetAngularCommand": (AngularPosition, kinova.AngularPosition),
    "GetAngularCurrent": (AngularPosition, kinova.AngularPosition),
    "GetCartesianPosition": (CartesianPosition, kinova.CartesianPosition),
    "GetCartesianCommand": (CartesianPosition, kinova.CartesianPosition),
    "GetGlobalTrajectoryInfo": (TrajectoryFIFO, kinova.TrajectoryFIFO),
}
#: Kinova API functions without arguments that a client may call through robot/api/*
_ACTIONS = ("MoveHome", "EraseAllTrajectories", "SetCartesianControl", "SetAngularControl")
#: every function the backend calls (the command layer's names without the transport's prefix), by its type
BINDINGS: dict[str, Binding] = {
    "CloseAPI": _NO_ARGUMENT,
    "RefresDevicesList": _NO_ARGUMENT,  # sic: Kinova's spelling
    "GetDevices": Binding("int(KinovaDevice*, int&)", (_ref(KinovaDevice), _ref(ctypes.c_int))),
    "SetActiveDevice": Binding("int(KinovaDevice)", (KinovaDevice,)),
    "StartControlAPI": _NO_ARGUMENT,
    "StopControlAPI": _NO_ARGUMENT,
    **{name: _NO_ARGUMENT for name in _ACTIONS},
    "SendBasicTrajectory": Binding("int(TrajectoryPoint)", (TrajectoryPoint,)),
    **{name: Binding(f"int({c_type.__name__}&)", (_ref(c_type),)) for name, (c_type, _) in _GETTERS.items()},
    # the torque-mode setup of the JACO thesis's Table 5.1, passed to the arm as a client gives it
    "SetTorqueSafetyFactor": Binding("int(float)", (ctypes.c_float,)),
    "SetTorqueVibrationController": Binding("int(float)", (ctypes.c_float,)),
    "SetTorqueActuatorGain": Binding("int(float*)", (_ref(ctypes.c_float),)),
    "SetTorqueActuatorDamping": Binding("int(float*)", (_ref(ctypes.c_float),)),
    "SetGravityType": Binding("int(GRAVITY_TYPE)", (ctypes.c_int,)),
    "SetGravityOptimalZParam": Binding("int(float*)", (_ref(ctypes.c_float),)),
    "SetTorqueZero": Binding("int(int)", (ctypes.c_int,)),
    "SetJointZero": Binding("int(int)", (ctypes.c_int,)),
}
#: how each transport starts: the USB command layer's InitAPI; the Ethernet one's InitEthernetAPI (the USB
#: header declares an InitEthernetAPI too, but Kinova's USB library does not export it)
INIT_BINDINGS: dict[str, tuple[str, Binding]] = {
    "usb": ("InitAPI", _NO_ARGUMENT),
    "ethernet": ("InitEthernetAPI", Binding("int(EthernetCommConfig&)", (_ref(EthernetCommConfig),))),
}


# ------------------------------------------------------------------------------------------------ finding it
def locate_command_layer(setting: Optional[str], transport: Transport = "usb",
                         environ: Optional[dict] = None) -> Path:
    """The command-layer file that ``setting`` (else ``$MFVS_KINOVA_SDK``) names: the file itself, or a directory
    holding it directly or under lib/x86_64-linux-gnu. Raises :class:`ArmStartError` saying where it looked."""
    environ = os.environ if environ is None else environ
    name = LAYERS[transport].command_layer
    given, source = (setting, "sdk_library") if setting else (environ.get(SDK_ENV) or None, SDK_ENV)
    if not given:
        raise ArmStartError(f"Kinova's SDK is not given: set sdk_library (or {SDK_ENV}) to the directory holding "
                            f"{name} (kinova-ros: kinova_driver/lib/x86_64-linux-gnu)")
    path = Path(given).expanduser()
    candidates = [path] if not path.is_dir() else [path / name, path / SDK_LIB_SUBDIR / name]
    for candidate in candidates:
        if candidate.is_file():
            return candidate.resolve()
    looked = " or ".join(str(c) for c in candidates)
    raise ArmStartError(f"Kinova's SDK library is not where {source} says: no {looked}")


def check_comm_layer(command_layer: Path, transport: Transport = "usb") -> Path:
    """The comm layer beside the command layer, loaded once here so that what it lacks is said plainly (the
    command layer, failing to load it, says only ERROR_LOAD_COMM_DLL)."""
    comm = command_layer.parent / LAYERS[transport].comm_layer
    if not comm.is_file():
        raise ArmStartError(f"Kinova's comm layer is missing: {command_layer.name} loads {comm.name} from beside it, "
                            f"and {command_layer.parent} has none (install the SDK's lib directory whole)")
    try:
        ctypes.CDLL(str(comm))
    except OSError as exc:
        if "libusb" in str(exc):
            raise ArmStartError(f"Kinova's comm layer {comm.name} needs libusb-1.0.so.0: install libusb-1.0-0 "
                                "(bash deploy/install.sh does)") from None
        raise ArmStartError(f"Kinova's comm layer {comm} cannot be loaded: {exc}") from None
    return comm


def loader_finds(name: str) -> bool:
    """Whether the dynamic loader finds ``name`` by bare name from this process, as the command layer asks for its
    comm layer (the loader's path is fixed when the process starts: LD_LIBRARY_PATH then, ld.so.cache)."""
    try:
        ctypes.CDLL(name)
    except OSError:
        return False
    return True


def put_sdk_on_loader_path(command_layer: Path, transport: Transport = "usb") -> None:
    """Make the comm layer beside ``command_layer`` reachable by bare name: when the loader does not find it,
    execute this process's command line again with the SDK's directory first on LD_LIBRARY_PATH (once; the
    loader reads that variable only when a process starts). For a process's entry point only: nothing may be
    open yet."""
    comm = LAYERS[transport].comm_layer
    if loader_finds(comm):
        return
    directory = str(command_layer.parent)
    if os.environ.get(_REEXEC_ENV) == directory:
        raise ArmStartError(f"the loader does not find {comm} in {directory} even on LD_LIBRARY_PATH")
    env = dict(os.environ)
    env["LD_LIBRARY_PATH"] = os.pathsep.join(p for p in (directory, env.get("LD_LIBRARY_PATH")) if p)
    env[_REEXEC_ENV] = directory
    sys.stdout.flush()
    sys.stderr.flush()
    os.execve(sys.executable, [sys.executable, *sys.orig_argv[1:]], env)


@contextlib.contextmanager
def vendor_output_to_log(log: logging.Logger):
    """Kinova's Ethernet layers print their progress on standard output ("Initializing sockets . . ."): while a
    start-up or closing call runs, what they print goes to the log (debug) instead. Only while nothing else
    writes to standard output: at start-up and at the end."""
    libc = ctypes.CDLL(None)
    sys.stdout.flush()
    saved = os.dup(1)
    with tempfile.TemporaryFile() as sink:
        os.dup2(sink.fileno(), 1)
        try:
            yield
        finally:
            libc.fflush(None)  # the C library's buffered stdout, written while fd 1 is still the sink
            os.dup2(saved, 1)
            os.close(saved)
            sink.seek(0)
            printed = " | ".join(line.strip() for line in sink.read().decode(errors="replace").splitlines()
                                 if line.strip())
            if printed:
                log.debug("Kinova's SDK printed: %s", printed)


class KinovaSdk:
    """Kinova's command layer with its functions declared; every call returns the SDK's code (1 = success).
    Calls are serialised (the SDK is not reentrant: Kinova's driver holds one mutex around all of them)."""

    def __init__(self, path: str | os.PathLike, transport: Transport = "usb") -> None:
        self.path = str(path)
        self.transport = transport
        self.prefix = LAYERS[transport].prefix
        try:
            self.lib = ctypes.CDLL(self.path)
        except OSError as exc:
            raise ArmStartError(f"Kinova's SDK library {self.path} cannot be loaded ({exc})") from None
        init_name, init_binding = INIT_BINDINGS[transport]
        self._functions = {}
        wanted = {**BINDINGS, init_name: init_binding}
        missing = [self.prefix + name for name in wanted if not hasattr(self.lib, self.prefix + name)]
        if missing:
            raise ArmStartError(f"{self.path} is not Kinova's {transport} command layer: it has no "
                                f"{', '.join(missing[:4])}{' …' if len(missing) > 4 else ''}")
        for name, binding in wanted.items():
            function = getattr(self.lib, self.prefix + name)
            function.argtypes, function.restype = list(binding.argtypes), ctypes.c_int
            self._functions[name] = function
        self.init_name = init_name
        self._lock = threading.Lock()

    @classmethod
    def find(cls, setting: Optional[str], transport: Transport = "usb") -> "KinovaSdk":
        """The SDK the setting (or $MFVS_KINOVA_SDK) names, its comm layer checked (:class:`ArmStartError`)."""
        command_layer = locate_command_layer(setting, transport)
        check_comm_layer(command_layer, transport)
        return cls(command_layer, transport)

    def raw(self, name: str, *args) -> int:
        with self._lock:
            return int(self._functions[name](*args))

    def action(self, name: str) -> int:
        return self.raw(name)

    def send_basic_trajectory(self, point: kinova.TrajectoryPoint) -> int:
        return self.raw("SendBasicTrajectory", to_c(point, TrajectoryPoint))

    def get(self, name: str):
        """(code, value as a protocol.kinova message) of a getter."""
        c_type, message_type = _GETTERS[name]
        out = c_type()
        code = self.raw(name, ctypes.byref(out))
        return code, from_c(out, message_type)

    def checked(self, name: str):
        code, value = self.get(name)
        if code != kinova.ErrorCode.NO_ERROR_KINOVA:
            raise SdkError(name, code)
        return value

    def devices(self) -> tuple[int, list["ArmDevice"]]:
        """(code, the arms the comm layer knows) from GetDevices."""
        found = (KinovaDevice * MAX_KINOVA_DEVICE)()
        result = ctypes.c_int(kinova.ErrorCode.NO_ERROR_KINOVA)
        count = self.raw("GetDevices", found, ctypes.byref(result))
        return result.value, [ArmDevice.from_c(found[i]) for i in range(max(0, min(count, MAX_KINOVA_DEVICE)))]

    def call(self, function: str, argument) -> kinova.ApiReply:
        """A Kinova API call by name (the robot/api/* queryables). The session belongs to the gateway: InitAPI
        and CloseAPI from a client are answered without touching it (as the emulated API does)."""
        if function in ("InitAPI", "CloseAPI"):
            return kinova.ApiReply()
        if function in _ACTIONS:
            return kinova.ApiReply(code=self.action(function))
        if function == "SendBasicTrajectory":
            problem = float32_problem(argument)
            if problem:
                return kinova.ApiReply(code=int(kinova.ErrorCode.ERROR_INVALID_PARAM), message=problem)
            return kinova.ApiReply(code=self.send_basic_trajectory(argument))
        if function in _GETTERS:
            code, value = self.get(function)
            return kinova.API_FUNCTIONS[function][1](code=code, result=value)
        if function in kinova.TORQUE_SETUP_FUNCTIONS:
            return kinova.ApiReply(code=self.raw(function, *_torque_setup_arguments(argument)))
        # zones and client configurations: the SDK's structs hold more than mfvs's types describe
        return kinova.ApiReply(code=int(kinova.ErrorCode.ERROR_INVALID_PARAM),
                               message=f"{function} is not available through the kinova_sdk backend")


def _torque_setup_arguments(argument) -> tuple:
    """A Table 5.1 argument as the command layer takes it."""
    if isinstance(argument, kinova.FloatArgument):
        return (ctypes.c_float(argument.value),)
    if isinstance(argument, (kinova.CommandArray, kinova.GravityParameters)):
        return ((ctypes.c_float * len(argument.values))(*argument.values),)
    if isinstance(argument, kinova.GravityTypeArgument):
        return (int(argument.type),)
    return (int(argument.address),)  # ActuatorAddress


FLOAT32_MAX = 3.4028234663852886e38


def float32_problem(message, path: str = "") -> str:
    """Why a message cannot travel as the SDK's float32 fields (a float beyond float32 would arrive as inf)."""
    for name in message.__struct_fields__:
        value = getattr(message, name)
        if isinstance(value, float) and not abs(value) <= FLOAT32_MAX:
            return f"{path}{name} = {value} does not fit a float32"
        if hasattr(value, "__struct_fields__"):
            problem = float32_problem(value, f"{path}{name}.")
            if problem:
                return problem
    return ""


# ------------------------------------------------------------------------------------------------ starting

@dataclass(frozen=True)
class ArmDevice:
    """An arm in the comm layer's device list."""

    serial: str
    model: str
    version: str
    c_device: KinovaDevice

    @classmethod
    def from_c(cls, device: KinovaDevice) -> "ArmDevice":
        copy = KinovaDevice.from_buffer_copy(device)  # the list's buffer goes away; SetActiveDevice takes it by value
        return cls(kinova.device_text(device.SerialNumber), kinova.device_text(device.Model),
                   f"{device.VersionMajor}.{device.VersionMinor}.{device.VersionRelease}", copy)

    def describe(self) -> str:
        return f"{self.serial or '(no serial)'} ({self.model or 'model not reported'})"


#: what to check when no arm answers, by transport
NO_ARM_HINTS = {
    "usb": "is it powered, plugged in, and does the udev rule give you the device? (deploy/udev/, README)",
    "ethernet": "is it powered, cabled to this computer's network, and is sdk_ethernet.robot_ip its address?",
}


def choose_device(devices: list[ArmDevice], serial: Optional[str], where: str, transport: Transport = "usb"
                  ) -> ArmDevice:
    """The arm to drive: the one with ``serial``, or the only one. Raises :class:`ArmStartError` when there is
    none, when the serial is not among them, or when there are several and no serial chooses."""
    if not devices:
        raise ArmStartError(f"no arm found {where}: {NO_ARM_HINTS[transport]}")
    if serial:
        for device in devices:
            if device.serial == serial.strip():
                return device
        raise ArmStartError(f"no arm with serial number {serial.strip()} {where}; found "
                            f"{', '.join(d.describe() for d in devices)}: set sdk_serial to one of them")
    if len(devices) > 1:
        raise ArmStartError(f"{len(devices)} arms found {where} ({', '.join(d.describe() for d in devices)}) and no "
                            "sdk_serial: set sdk_serial to the serial number of the arm this gateway drives")
    return devices[0]


class SdkEthernetConfig(ConfigStruct):
    """The kinova_sdk backend over Ethernet (InitEthernetAPI): this computer's address and ports on the arm's
    network, the arm's address and port, and how long a reply may take (Kinova's driver's defaults)."""

    local_ip: str = "192.168.100.100"
    subnet_mask: str = "255.255.255.0"
    robot_ip: str = "192.168.100.11"
    local_cmd_port: int = 25000
    local_broadcast_port: int = 25025
    robot_port: int = 55000
    rx_timeout_ms: int = 1000

    def __post_init__(self) -> None:
        for name in ("local_ip", "subnet_mask", "robot_ip"):
            try:
                ipaddress.IPv4Address(getattr(self, name))
            except ValueError:
                raise ValueError(f"{name} {getattr(self, name)!r} is not an IPv4 address") from None
        for name in ("local_cmd_port", "local_broadcast_port", "robot_port"):
            if not 1 <= getattr(self, name) <= 65535:
                raise ValueError(f"{name} must be a port, 1-65535")
        if not 1 <= self.rx_timeout_ms <= 60_000:
            raise ValueError("rx_timeout_ms must be 1-60000")

    def to_c(self) -> EthernetCommConfig:
        return EthernetCommConfig(inet_addr(self.local_ip), inet_addr(self.subnet_mask), inet_addr(self.robot_ip),
                                  self.local_cmd_port, self.local_broadcast_port, self.robot_port,
                                  self.rx_timeout_ms)


def _init_hint(code: int, sdk: KinovaSdk, ethernet: Optional[SdkEthernetConfig]) -> str:
    """What to do about a failed InitAPI / InitEthernetAPI."""
    comm = LAYERS[sdk.transport].comm_layer
    directory = Path(sdk.path).parent
    if code in (kinova.ErrorCode.ERROR_NO_DEVICE_FOUND, kinova.ErrorCode.ERROR_LIBUSB_NO_DEVICE):
        return f"no arm found: {NO_ARM_HINTS[sdk.transport]}"
    if code == kinova.ErrorCode.ERROR_LOAD_COMM_DLL:
        return (f"the command layer could not load {comm} by bare name: start the gateway as "
                f"`python -m services.robot_gateway` (it puts {directory} on the loader's path) or start this "
                f"process with LD_LIBRARY_PATH={directory}")
    if code == kinova.ErrorCode.ERROR_LOAD_USB_LIBRARY:
        return "libusb-1.0 could not be loaded: install libusb-1.0-0 (bash deploy/install.sh does)"
    if code == kinova.ErrorCode.ERROR_CLAIM_INTERFACE:
        return ("the arm's USB interface is taken: is another program using the arm (Kinova's Development Center, "
                "a ROS driver, another gateway)?")
    if code == kinova.ErrorCode.ERROR_JACO_CONNECTION:
        return "the USB connection to the arm fails: check the cable and the port"
    if code == kinova.ErrorCode.ERROR_NOT_INITIALIZED and ethernet is not None:
        return (f"could not bind {ethernet.local_ip}:{ethernet.local_cmd_port}: set sdk_ethernet.local_ip to this "
                "computer's address on the arm's network, and free the ports")
    return "see Kinova's header for the code; the arm is not driven"


def _start_hint(function: str, code: int) -> str:
    if code == kinova.ErrorCode.ERROR_COMM_TIMEOUT:
        return "the arm did not answer in time: is it powered and its controller booted?"
    return f"the arm is not driven ({function} is part of Kinova's start-up sequence)"


@dataclass
class ArmSession:
    """The arm opened through the SDK: which one, and whether the API controls it. :meth:`close` ends it (every
    step tried, once)."""

    sdk: KinovaSdk
    device: ArmDevice
    log: logging.Logger
    control_started: bool = False
    closed: bool = False

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        with _quiet(self.sdk, self.log):
            steps = (("EraseAllTrajectories", "StopControlAPI") if self.control_started else ()) + ("CloseAPI",)
            for name in steps:
                code = self.sdk.action(name)
                if code != kinova.ErrorCode.NO_ERROR_KINOVA:
                    self.log.warning("closing the arm: %s", SdkError(name, code))


def _quiet(sdk: KinovaSdk, log: logging.Logger):
    """Kinova's Ethernet layers print on standard output: into the log while they start and close."""
    return vendor_output_to_log(log) if sdk.transport == "ethernet" else contextlib.nullcontext()


#: how long the driver lets the arm settle between StopControlAPI and StartControlAPI when it restarts control
CONTROL_RESTART_PAUSE_S = 0.05


def open_arm(sdk: KinovaSdk, *, serial: Optional[str], arm_name: str, n_joints: int,
             ethernet: Optional[SdkEthernetConfig] = None, log: Optional[logging.Logger] = None) -> ArmSession:
    """Open the arm as Kinova's driver does (see the module's docstring). Raises :class:`ArmStartError` with one
    line a person can act on; the API is closed again on every way out."""
    log = log or logging.getLogger("mfvs.robot_gateway")
    where = "on USB" if sdk.transport == "usb" else (
        f"at {ethernet.robot_ip}:{ethernet.robot_port} (Ethernet)" if ethernet else "on Ethernet")
    with _quiet(sdk, log):
        if sdk.transport == "ethernet":
            settings = (ethernet or SdkEthernetConfig()).to_c()
            code = sdk.raw(sdk.init_name, ctypes.byref(settings))
        else:
            code = sdk.raw(sdk.init_name)
    if code != kinova.ErrorCode.NO_ERROR_KINOVA:
        with _quiet(sdk, log):
            sdk.action("CloseAPI")
        raise ArmStartError(str(SdkError(sdk.init_name, code, _init_hint(code, sdk, ethernet))))
    session = None
    try:
        with _quiet(sdk, log):
            sdk.action("RefresDevicesList")  # as the driver: its code says nothing GetDevices does not
            code, devices = sdk.devices()
        if code != kinova.ErrorCode.NO_ERROR_KINOVA:
            raise ArmStartError(str(SdkError("GetDevices", code, _start_hint("GetDevices", code))))
        device = choose_device(devices, serial, where, sdk.transport)
        _step(sdk, "SetActiveDevice", device.c_device)
        refusal = kinova.arm_type_refusal(device.model, arm_name, n_joints)
        if refusal:
            raise ArmStartError(f"arm {device.serial} refused: {refusal}")
        session = ArmSession(sdk, device, log)
        # an arm after a cold boot does not obey the API at once: start, stop (erasing), start again
        _step(sdk, "StartControlAPI")
        session.control_started = True
        _step(sdk, "StopControlAPI")
        _step(sdk, "EraseAllTrajectories")
        time.sleep(CONTROL_RESTART_PAUSE_S)
        _step(sdk, "StartControlAPI")
        _step(sdk, "SendBasicTrajectory",
              to_c(velocity_point(kinova.POSITION_TYPE.CARTESIAN_VELOCITY, cartesian=[0.0] * 6), TrajectoryPoint))
    except BaseException:
        if session is not None:
            session.close()
        else:
            with _quiet(sdk, log):
                sdk.action("CloseAPI")
        raise
    log.info("arm %s %s, firmware %s: the API controls it", device.describe(), where, device.version)
    return session


def _step(sdk: KinovaSdk, name: str, *args) -> None:
    code = sdk.raw(name, *args)
    if code != kinova.ErrorCode.NO_ERROR_KINOVA:
        raise ArmStartError(str(SdkError(name, code, _start_hint(name, code))))


# ------------------------------------------------------------------------------------------------ running
class SdkArm:
    """The arm behind the SDK as the robot front end sees it: a RobotView (measured state, pose) and the DSP
    surface it drives (submit, erase, status, one cycle per 10 ms)."""

    def __init__(self, sdk: KinovaSdk, config: DSPConfig, arm: ArmDescription) -> None:
        self.sdk = sdk
        self.config = config
        #: the arm's description (its joint count, signs and zeros: how GetAngularPosition's degrees map to the model)
        self.arm = arm
        self.status = DSPStatus()
        self.fifo_count = 0
        self._pending: Optional[RobotCommand] = None
        n = arm.n_joints
        self._state = JointReading(q=np.zeros(n), dq=np.zeros(n), tau=np.zeros(n))
        self._pose = np.eye(4)

    # ---- RobotView
    @property
    def q(self) -> np.ndarray:
        return self._state.q

    @property
    def dq(self) -> np.ndarray:
        return self._state.dq

    @property
    def tau(self) -> np.ndarray:
        return self._state.tau

    def ee_pose(self) -> np.ndarray:
        return self._pose

    def read(self) -> JointReading:
        """Read the arm (4 SDK calls, 5 with a hand: its fingers' currents); raises SdkError when one fails."""
        n, arm = self.arm.n_joints, self.arm  # AngularInfo carries 7 actuators: an arm with fewer reads 0 beyond
        position = self.sdk.checked("GetAngularPosition")
        velocity = self.sdk.checked("GetAngularVelocity")
        forces = self.sdk.checked("GetAngularForce").Actuators.as_list()[:n]
        c = self.sdk.checked("GetCartesianPosition").Coordinates
        angles, rates = position.Actuators.as_list()[:n], velocity.Actuators.as_list()[:n]
        fingers = None
        hand = arm.hand
        if hand is not None:  # Kinova's finger units; the currents in A (GetAngularCurrent)
            k = hand.n_fingers
            current = self.sdk.checked("GetAngularCurrent")
            fingers = FingerReading(position=hand.units_to_angle(position.Fingers.as_list()[:k]),
                                    velocity=hand.units_to_angle(velocity.Fingers.as_list()[:k]),
                                    current_a=np.asarray(current.Fingers.as_list()[:k], dtype=float))
        self._state = JointReading(q=arm.physical_deg_to_model(angles), dq=arm.physical_rate_to_model(rates),
                                   tau=arm.sign * np.asarray(forces, dtype=float), stamp_ns=time.time_ns(),
                                   fingers=fingers)
        self._pose = frames.homogeneous(frames.euler_xyz_to_matrix([c.ThetaX, c.ThetaY, c.ThetaZ]),
                                        [c.X, c.Y, c.Z])
        self._state.arm_pose = self._pose  # Kinova's DSP's own kinematics: what the commissioning check compares
        return self._state

    # ---- the DSP surface
    def motion_limits(self) -> MotionLimits:
        """The arm's own DSP applies its client configuration, which the gateway's config states."""
        return motion_limits(self.config, self.arm)

    def submit(self, command: RobotCommand) -> None:
        mode = CommandMode(command.mode)
        if mode is CommandMode.CARTESIAN_VELOCITY:
            twist = command.twist
            if AngularConvention(twist.angular) is not AngularConvention(self.config.angular_convention):
                raise CommandRefused(f"the arm reads {AngularConvention(self.config.angular_convention).value} "
                                     f"angular velocities, the command declares {twist.angular}")
        self._pending = command

    def erase_all_trajectories(self) -> None:
        self._pending = None
        self._check("EraseAllTrajectories", self.sdk.action("EraseAllTrajectories"))

    def joints_held(self) -> None:
        """Nothing to do: the arm's own DSP ramps its joints, and the host never holds them behind its back."""

    def cycle(self, _reading=None) -> np.ndarray:
        """Forward this cycle's command (velocity commands last one cycle, so nothing pending means no motion).
        The joints are the arm's own DSP's business: no joint velocities come back (zeros)."""
        command, self._pending = self._pending, None
        self.status.cycles += 1
        if command is None:
            self.status.mode = ControlMode.IDLE
            return np.zeros(self.arm.n_joints)
        mode = CommandMode(command.mode)
        if mode in (CommandMode.STOP, CommandMode.EMERGENCY_STOP):
            self.erase_all_trajectories()
            self.status.emergency_stop = mode is CommandMode.EMERGENCY_STOP
            point = velocity_point(kinova.POSITION_TYPE.ANGULAR_VELOCITY)
        elif mode is CommandMode.CARTESIAN_VELOCITY:
            point = velocity_point(kinova.POSITION_TYPE.CARTESIAN_VELOCITY,
                                   cartesian=[*command.twist.linear, *command.twist.rotational])
            self.status.mode, self.status.emergency_stop = ControlMode.CARTESIAN_VELOCITY, False
        else:
            point = velocity_point(kinova.POSITION_TYPE.ANGULAR_VELOCITY,
                                   angular_dps=self.arm.model_rate_to_physical(command.joint_velocities))
            self.status.mode, self.status.emergency_stop = ControlMode.ANGULAR_VELOCITY, False
        if command.fingers is not None and self.arm.hand is not None:  # (without: HAND_NOMOVEMENT, they hold)
            hand = self.arm.hand
            point.Position.HandMode = (kinova.HAND_MODE.POSITION_MODE if command.fingers.mode is FingerMode.POSITION
                                       else kinova.HAND_MODE.VELOCITY_MODE)
            point.Position.Fingers = kinova.FingersPosition.from_list(hand.angle_to_units(command.fingers.values))
        self._check("SendBasicTrajectory", self.sdk.send_basic_trajectory(point))
        return np.zeros(self.arm.n_joints)

    @staticmethod
    def _check(function: str, code: int) -> None:
        if code != kinova.ErrorCode.NO_ERROR_KINOVA:
            raise SdkError(function, code)


def velocity_point(kind: kinova.POSITION_TYPE, cartesian=None, angular_dps=None) -> kinova.TrajectoryPoint:
    """A velocity TrajectoryPoint (zero where not given)."""
    position = kinova.UserPosition(Type=kind)
    if cartesian is not None:
        position.CartesianPosition = kinova.CartesianInfo(**dict(zip(("X", "Y", "Z", "ThetaX", "ThetaY", "ThetaZ"),
                                                                     map(float, cartesian), strict=True)))
    if angular_dps is not None:
        position.Actuators = kinova.AngularInfo.from_list(angular_dps)
    return kinova.TrajectoryPoint(Position=position)
