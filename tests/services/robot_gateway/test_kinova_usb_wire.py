"""Kinova's real USB comm layer (``USBCommLayerUbuntu.so``) over a stand-in libusb whose transfers the emulated
arm base (:mod:`services.robot_sim.usb_base`) answers: what the binary puts on the USB wire and what it returns
(docs/kinova-usb-wire.md). The stand-in is built here with the system C compiler; Kinova's SDK is found at
``$MFVS_KINOVA_SDK`` or ``../shared/reference/kinova-sdk`` beside the project, else the tests skip saying why.

Each scenario runs in its own Python process (the comm layer keeps global state and crashes on some calls), which
loads the stand-in with RTLD_GLOBAL before the comm layer, serves the base on a Unix socket from a thread, and
prints one JSON line; the stand-in's call log shows the wire.

Kinova's command layer (``USBCommandLayerUbuntu.so``: InitAPI, GetAngularPosition, CloseAPI) runs the same way, but
its process is started with ``LD_LIBRARY_PATH=<stand-in dir>:<SDK lib dir>`` and loads nothing beforehand: InitAPI
``dlopen``s the comm layer by bare name, which only the loader's search path resolves."""
from __future__ import annotations

import ctypes
import json
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from protocol import rs485
from services.robot_sim.usb_base import stand_in_libusb

REPO = Path(__file__).resolve().parents[3]
REFERENCE = REPO.parent / "shared" / "reference" / "kinova-sdk"
SDK_ENV = "MFVS_KINOVA_SDK"
COMM_LAYER = "USBCommLayerUbuntu.so"
COMMAND_LAYER = "USBCommandLayerUbuntu.so"

NO_ERROR, UNKNOWN_ERROR = 1, 666
ERROR_NOT_INITIALIZED, ERROR_NO_DEVICE_FOUND, ERROR_OPERATION_INCOMPLETED, ERROR_RS485_TIMEOUT = 1010, 1015, 1016, 1020
SIGSEGV = -11
ERROR_LOAD_COMM_DLL, JACO_NACK_FIRST, JACO_COMM_FAILED = 2002, 2003, 2004
ERROR_FUNCTION_NOT_ACCESSIBLE = 1021
#: joint angles the base is given (degrees: Actuator1-7, Finger1-3); not exact in float32 on purpose
ANGLES = [180.1, -45.25, 270.3, 89.9, -0.001, 123.456, 359.99, 6.5, 7000.7, -1e-3]
SERIAL, MODEL = "PJ00000001030703130", "JACO2 7DOF"


# ------------------------------------------------------------------------------------------------ fixtures
def _comm_layer() -> Path:
    given = os.environ.get(SDK_ENV)
    root = Path(given) if given else REFERENCE
    if not root.is_dir():
        pytest.skip(f"Kinova's SDK is not here: ${SDK_ENV} names {given!r}, not a directory" if given else
                    f"Kinova's SDK is not here: ${SDK_ENV} is not set and {REFERENCE} does not exist")
    found = sorted(root.rglob(COMM_LAYER))
    if not found:
        pytest.skip(f"no {COMM_LAYER} under {root}")
    return found[0]


@pytest.fixture(scope="module")
def comm_layer() -> Path:
    return _comm_layer()


@pytest.fixture(scope="module")
def fake_libusb(tmp_path_factory) -> Path:
    """The stand-in libusb-1.0.so.0 (services/robot_sim/libusb_stand_in.c), built here with the system compiler."""
    try:
        return stand_in_libusb(tmp_path_factory.mktemp("libusb")) / "libusb-1.0.so.0"
    except RuntimeError as exc:
        pytest.skip(str(exc))


@pytest.fixture(scope="module")
def command_layer(comm_layer) -> Path:
    path = comm_layer.with_name(COMMAND_LAYER)
    if not path.is_file():
        pytest.skip(f"no {COMMAND_LAYER} beside {comm_layer}")
    return path


@pytest.fixture
def run(comm_layer, fake_libusb):
    """run(scenario, devices=1, serve=True, library_path=False, **options) -> (result dict or None, log lines,
    returncode). ``library_path``: start the child with the stand-in's directory, then the SDK's, first on
    LD_LIBRARY_PATH (what the command layer needs); else the inherited environment as is."""
    workdir = Path(tempfile.mkdtemp(prefix="mfvs-usb-", dir="/tmp"))  # short: a socket path has ≤ 107 bytes

    def _run(scenario: str, devices: int = 1, serve: bool = True, library_path: bool = False, **options):
        log = workdir / f"{scenario}.log"
        if log.exists():
            log.unlink()
        env = {**os.environ, "MFVS_FAKE_USB_DEVICES": str(devices), "MFVS_FAKE_USB_LOG": str(log),
               "MFVS_FAKE_USB_SOCKET": str(workdir / "usb.sock"), "PYTHONPATH": str(REPO)}
        if library_path:  # first, before whatever the environment had
            env["LD_LIBRARY_PATH"] = os.pathsep.join(
                [str(fake_libusb.parent), str(comm_layer.parent)] + ([env["LD_LIBRARY_PATH"]] if env.get(
                    "LD_LIBRARY_PATH") else []))
        config = {"scenario": scenario, "fake": str(fake_libusb), "comm": str(comm_layer), "devices": devices,
                  "serve": serve, **options}
        proc = subprocess.run([sys.executable, "-c", CHILD, json.dumps(config)], env=env, cwd=REPO,
                              capture_output=True, text=True, timeout=60)
        results = [line[7:] for line in proc.stdout.splitlines() if line.startswith("RESULT ")]
        if proc.returncode == 0:
            assert results, proc.stderr
        lines = log.read_text().splitlines() if log.exists() else []
        return (json.loads(results[0]) if results else None), lines, proc.returncode

    yield _run
    shutil.rmtree(workdir, ignore_errors=True)


CHILD = "from tests.services.robot_gateway.test_kinova_usb_wire import child; child()"


# ------------------------------------------------------------------------------------------------ the child
class KinovaDevice(ctypes.Structure):
    _fields_ = [("SerialNumber", ctypes.c_char * 20), ("Model", ctypes.c_char * 20), ("VersionMajor", ctypes.c_int),
                ("VersionMinor", ctypes.c_int), ("VersionRelease", ctypes.c_int), ("DeviceType", ctypes.c_int),
                ("DeviceID", ctypes.c_int)]


def _commands(n: int, first_destination: int = 0x10) -> np.ndarray:
    batch = rs485.records(n)
    batch["command"] = rs485.Command.POSITION_AND_TORQUE_COMMAND
    batch["destination"] = (first_destination + np.arange(n)) & 0xFF
    batch["data"][:, 0] = np.arange(n)
    return batch


def _replies(n: int) -> np.ndarray:
    batch = rs485.records(n)
    batch["command"] = rs485.Command.SEND_ALL_VALUES_1
    batch["source"] = np.arange(n) & 0xFF
    batch["data"][:, 1] = np.arange(n) * 1.5
    return batch


def child() -> None:
    """One scenario in this process: the base served from a thread, the stand-in libusb, the real comm layer."""
    from services.robot_sim.usb_base import UsbBase, UsbBaseServer

    cfg = json.loads(sys.argv[1])
    forwarded: list[np.ndarray] = []
    bases = [UsbBase(forwarded.append, serial=f"{SERIAL[:-1]}{i}", model=cfg.get("model", MODEL),
                     empty_in=cfg.get("empty_in", "timeout"), device_type=cfg.get("device_type", 0),
                     angular_position=cfg.get("angles")) for i in range(cfg["devices"])]
    server = None
    if cfg["serve"]:
        server = UsbBaseServer(os.environ["MFVS_FAKE_USB_SOCKET"], bases, in_wait_s=cfg.get("in_wait_s", 0.0)).start()
    out: dict = {}
    scenario = cfg["scenario"]
    if scenario == "api":  # the command layer, loaded alone: the loader's path finds the stand-in and the comm layer
        _api(cfg, out)
        print("RESULT " + json.dumps(out), flush=True)
        if server:
            server.close()
        return
    ctypes.CDLL(cfg["fake"], mode=ctypes.RTLD_GLOBAL)
    comm = ctypes.CDLL(cfg["comm"])
    for name in ("OpenRS485_Write", "OpenRS485_Read"):
        getattr(comm, name).argtypes = [ctypes.c_void_p, ctypes.c_int, ctypes.POINTER(ctypes.c_int)]

    def write(batch: np.ndarray, qty: int) -> tuple[int, int]:
        sent = ctypes.c_int(-99)
        return comm.OpenRS485_Write(batch.ctypes.data, qty, ctypes.byref(sent)), sent.value

    def read(buffer: np.ndarray, qty: int) -> tuple[int, int]:
        got = ctypes.c_int(-99)
        return comm.OpenRS485_Read(buffer.ctypes.data, qty, ctypes.byref(got)), got.value

    def guarded(n: int, guard: int = 20) -> np.ndarray:
        buffer = rs485.records(n + guard)
        buffer["command"] = -1  # a record the library did not write still has command -1
        return buffer

    def devices() -> list[dict]:
        table = (KinovaDevice * 20)()
        result = ctypes.c_int(-99)
        n = comm.GetDevices(table, ctypes.byref(result))
        out["get_devices"] = [n, result.value]
        return [{"serial": d.SerialNumber.decode(), "model": d.Model.decode(),
                 "version": [d.VersionMajor, d.VersionMinor, d.VersionRelease], "type": d.DeviceType,
                 "id": d.DeviceID} for d in table[:n]]

    if scenario == "init":
        out["activate_before_init"] = comm.OpenRS485_Activate()
        out["init"] = comm.InitCommunication()
        count = ctypes.c_int(-99)
        out["count"] = [comm.GetDeviceCount(ctypes.byref(count)), count.value]
        out["devices"] = devices() if out["init"] == NO_ERROR else []
        out["activate"] = comm.OpenRS485_Activate()
    elif scenario == "write":
        out["init"] = comm.InitCommunication()
        if cfg.get("activate", True):
            out["activate"] = comm.OpenRS485_Activate()
        qty, size = cfg["qty"], max(cfg["qty"], 50)
        out["write"] = write(_commands(size), qty)
        out["forwarded"] = np.concatenate(forwarded).tobytes().hex() if forwarded else ""
        out["dropped"] = bases[0].dropped_records if bases else None
    elif scenario == "read":
        out["init"], out["activate"] = comm.InitCommunication(), comm.OpenRS485_Activate()
        if cfg["deliver"]:
            server.deliver(_replies(cfg["deliver"]))
        buffer = guarded(cfg["array"])
        out["read"] = read(buffer, cfg["qty"])
        out["written"] = int(np.count_nonzero(buffer["command"] != -1))
        out["records"] = buffer[: out["written"]].tobytes().hex()
        out["left_queued"] = bases[0].queued
    elif scenario == "overlap":
        out["init"], out["activate"] = comm.InitCommunication(), comm.OpenRS485_Activate()
        results: dict = {}
        reader = threading.Thread(target=lambda: results.__setitem__("read", read(guarded(50), 50)))
        reader.start()
        time.sleep(cfg["in_wait_s"] / 3)  # the read is now waiting in the base, its interface claimed
        results["write"] = write(_commands(50), 6)
        reader.join()
        out.update(results)
    elif scenario == "crash_before_init":
        write(_commands(50), 3)
    elif scenario == "crash_no_device":
        out["init"] = comm.InitCommunication()
        print("RESULT " + json.dumps(out), flush=True)
        read(guarded(50), 3)
    print("RESULT " + json.dumps(out), flush=True)
    if server:
        server.close()


def _kinova_mutex_value() -> int | None:
    """The value of the named semaphore "KinovaMutex" (/dev/shm/sem.KinovaMutex) that the command layer creates and
    shares between all its processes; None when it does not exist."""
    libc = ctypes.CDLL(None, use_errno=True)
    libc.sem_open.restype, libc.sem_open.argtypes = ctypes.c_void_p, [ctypes.c_char_p, ctypes.c_int]
    sem = libc.sem_open(b"/KinovaMutex", 0)
    if not sem:
        return None
    value = ctypes.c_int(-1)
    libc.sem_getvalue(ctypes.c_void_p(sem), ctypes.byref(value))
    libc.sem_close(ctypes.c_void_p(sem))
    return value.value


def _api(cfg: dict, out: dict) -> None:
    """InitAPI [, InitAPI again] [, the comm layer's OpenRS485_Activate], GetAngularPosition, CloseAPI; ``marks``:
    how many stand-in log lines there were after each step (to split the wire by call)."""
    log = Path(os.environ["MFVS_FAKE_USB_LOG"])
    marks = out["marks"] = {}

    def mark(step: str) -> None:
        marks[step] = len(log.read_text().splitlines()) if log.exists() else 0

    api = ctypes.CDLL(str(Path(cfg["comm"]).with_name(COMMAND_LAYER)))
    out["init"] = api.InitAPI()
    mark("init")
    if cfg.get("init_again"):
        out["init_again"] = api.InitAPI()
        mark("init_again")
    if out["init"] == ERROR_LOAD_COMM_DLL:
        return
    comm = ctypes.CDLL(COMM_LAYER)  # by bare name, as InitAPI did: the very object InitAPI loaded
    out["same_comm"] = ctypes.cast(comm.SendPacket, ctypes.c_void_p).value == ctypes.cast(
        ctypes.CDLL(cfg["comm"]).SendPacket, ctypes.c_void_p).value
    if cfg.get("activate"):
        out["activate"] = comm.OpenRS485_Activate()
        mark("activate")
    angles = (ctypes.c_float * 10)(*([-1.0] * 10))  # AngularPosition: Actuators.Actuator1-7, Fingers.Finger1-3
    before = _kinova_mutex_value()
    out["get"] = api.GetAngularPosition(ctypes.byref(angles))
    after = _kinova_mutex_value()
    out["mutex_change"] = None if before is None or after is None else after - before
    out["angles"] = list(angles)
    mark("get")
    out["close"] = api.CloseAPI()
    mark("close")


# ------------------------------------------------------------------------------------------------ log helpers
def calls(lines: list[str], name: str) -> list[dict]:
    """The log lines of one libusb function as dicts (key=value fields, data as bytes)."""
    found = []
    for line in lines:
        head, *fields = line.split(" ")
        if head == name:
            entry = dict(f.split("=", 1) for f in fields)
            entry["data"] = bytes.fromhex(entry.get("data", ""))
            found.append(entry)
    return found


def packets(data: bytes) -> list[bytes]:
    return [data[i:i + 64] for i in range(0, len(data), 64)]


# ------------------------------------------------------------------------------------------------ tests
def test_no_device_listed_init_gives_1015_and_no_transfer(run):
    result, log, rc = run("init", devices=0)
    assert rc == 0
    assert result["activate_before_init"] == ERROR_NOT_INITIALIZED
    assert result["init"] == ERROR_NO_DEVICE_FOUND
    assert result["count"] == [0, ERROR_NOT_INITIALIZED]  # GetDeviceCount: JacoCount, result set only on error
    assert result["activate"] == ERROR_NOT_INITIALIZED
    assert [line.split()[0] for line in log] == ["libusb_init", "libusb_get_device_list", "libusb_free_device_list"]


def test_one_device_init_lists_what_the_base_reported(run):
    result, log, rc = run("init", devices=1)
    assert rc == 0
    assert result["init"] == NO_ERROR
    assert result["count"] == [1, -99]
    assert result["get_devices"] == [1, NO_ERROR]
    assert result["devices"] == [{"serial": SERIAL[:-1] + "0", "model": MODEL, "version": [6, 2, 5], "type": 0,
                                  "id": 1}]
    # GetDeviceInfo: one command packet, interrupt OUT 0x02 then interrupt IN 0x82, 64 bytes, 5 s, interface 0
    out, back = calls(log, "libusb_interrupt_transfer")[:2]
    assert (out["ep"], out["len"], out["timeout"]) == ("0x02", "64", "5000")
    assert out["data"] == bytes.fromhex("0100 0100 7900 0100") + b"\x01" + bytes(55)
    assert (back["ep"], back["len"], back["status"]) == ("0x82", "64", "0")
    assert calls(log, "libusb_claim_interface")[0]["interface"] == "0"
    names = [line.split()[0] for line in log]
    assert names[:9] == ["libusb_init", "libusb_get_device_list", "libusb_get_device_descriptor", "libusb_open",
                         "libusb_claim_interface", "libusb_interrupt_transfer", "libusb_interrupt_transfer",
                         "libusb_release_interface", "libusb_close"]


def test_two_devices_each_asked_and_ids_1_and_3(run):
    result, log, rc = run("init", devices=2)
    assert rc == 0 and result["init"] == NO_ERROR
    assert [(d["serial"], d["id"]) for d in result["devices"]] == [(SERIAL[:-1] + "0", 1), (SERIAL[:-1] + "1", 3)]
    asked = [c["dev"] for c in calls(log, "libusb_interrupt_transfer") if c["ep"] == "0x02"]
    assert asked[:2] == ["0", "1"]
    assert asked[2:] == ["0"]  # Activate: the first device libusb listed


def test_configurable_model_string(run):
    result, _, _ = run("init", devices=1, model="JACO2 6DOF")
    assert result["devices"][0]["model"] == "JACO2 6DOF"


def test_activate_sends_command_700_to_the_first_device_and_returns_1(run):
    result, log, rc = run("init", devices=1)
    assert result["activate"] == NO_ERROR
    out, back = calls(log, "libusb_interrupt_transfer")[2:4]
    id_packet, total, command, size = np.frombuffer(out["data"][:8], "<i2").tolist()
    assert (out["ep"], id_packet, total, command, size, out["data"][8]) == ("0x02", 1, 1, 700, 64, 0)
    assert back["ep"] == "0x82"  # it waits for an answer (and ignores it)


def test_activate_returns_1_when_the_base_never_answers(run):
    # no socket: every transfer fails (-4); Init still lists the device, Activate still says 1, Write says 666
    result, log, rc = run("write", devices=1, serve=False, qty=3)
    assert rc == 0
    assert (result["init"], result["activate"]) == (NO_ERROR, NO_ERROR)
    assert result["write"] == [UNKNOWN_ERROR, 0]
    assert {c["status"] for c in calls(log, "libusb_interrupt_transfer")} == {"-4"}


@pytest.mark.parametrize("qty, expected_headers, qty_sent", [
    (6, [(3, 6), (3, 6)], 2),
    (4, [(3, 4), (1, 4)], 2),
    (1, [(1, 1)], 1),
    (300, [(3, 300 & 0xFF)] * 100, 100),  # beyond the header's 50: the count byte wraps, the array is read on
])
def test_write_packs_three_per_packet_and_reports_packets(run, qty, expected_headers, qty_sent):
    result, log, rc = run("write", devices=1, qty=qty)
    assert rc == 0
    assert result["write"] == [NO_ERROR, qty_sent]
    (bulk,) = calls(log, "libusb_bulk_transfer")
    assert (bulk["ep"], bulk["len"], bulk["timeout"]) == ("0x01", str(64 * len(expected_headers)), "5000")
    sent = _commands(max(qty, 50))[:qty].tobytes()
    for i, packet in enumerate(packets(bulk["data"])):
        n = expected_headers[i][0]
        assert tuple(packet[:4]) == (*expected_headers[i], 0, 0)
        assert packet[4:4 + 20 * n] == sent[60 * i:60 * i + 20 * n]
        assert packet[4 + 20 * n:] == bytes(60 - 20 * n)
    assert bytes.fromhex(result["forwarded"]) == sent  # the base unpacked the same records, in order


def test_write_of_zero_messages_is_a_zero_length_transfer(run):
    result, log, _ = run("write", devices=1, qty=0)
    assert result["write"] == [NO_ERROR, 0]
    assert calls(log, "libusb_bulk_transfer")[0]["len"] == "0"


def test_write_before_activate_goes_out_and_our_base_drops_it(run):
    result, log, _ = run("write", devices=1, qty=6, activate=False)
    assert result["write"] == [NO_ERROR, 2]  # the library does not check activation
    assert result["forwarded"] == "" and result["dropped"] == 6


def test_read_returns_the_base_replies_in_order(run):
    result, log, rc = run("read", devices=1, deliver=21, qty=21, array=50)
    assert rc == 0
    assert result["read"] == [NO_ERROR, 21]
    assert bytes.fromhex(result["records"]) == _replies(21).tobytes()
    (bulk,) = calls(log, "libusb_bulk_transfer")
    assert (bulk["ep"], bulk["len"], bulk["timeout"]) == ("0x81", str(9 * 64), "5000")  # ceil(21 * 1.2 / 3) = 9


def test_read_of_50_asks_20_packets_and_writes_60_records(run):
    result, log, _ = run("read", devices=1, deliver=70, qty=50, array=50)
    assert calls(log, "libusb_bulk_transfer")[0]["len"] == str(20 * 64)
    assert result["read"] == [NO_ERROR, 60]
    assert result["written"] == 60  # 10 past a 50-record array
    assert bytes.fromhex(result["records"]) == _replies(60).tobytes()
    assert result["left_queued"] == 10


def test_read_writes_whole_packets_beyond_what_was_asked(run):
    result, _, _ = run("read", devices=1, deliver=30, qty=21, array=21)
    assert result["read"] == [NO_ERROR, 27] and result["written"] == 27


def test_empty_read_times_out_with_1020(run):
    result, log, _ = run("read", devices=1, deliver=0, qty=21, array=50)
    assert result["read"] == [ERROR_RS485_TIMEOUT, 0] and result["written"] == 0
    assert calls(log, "libusb_bulk_transfer")[0]["status"] == "-7"


def test_empty_zero_length_read_gives_1016(run):
    result, _, _ = run("read", devices=1, deliver=0, qty=21, array=50, empty_in="zero_length")
    assert result["read"] == [ERROR_OPERATION_INCOMPLETED, 0]


def test_overlapping_calls_one_gets_666(run):
    result, log, rc = run("overlap", devices=1, in_wait_s=1.5)
    assert rc == 0
    assert result["write"] == [UNKNOWN_ERROR, 0]  # its claim of interface 0 was refused: the read held it
    assert result["read"] == [ERROR_RS485_TIMEOUT, 0]
    assert "-6" in [c["rc"] for c in calls(log, "libusb_claim_interface")]
    assert not calls(log, "libusb_bulk_transfer")[1:]  # the write never reached the wire


def test_write_before_init_crashes(run):
    result, _, rc = run("crash_before_init", devices=1)
    assert rc == SIGSEGV and result is None


def test_read_with_no_device_crashes(run):
    result, _, rc = run("crash_no_device", devices=0)
    assert rc == SIGSEGV and result == {"init": ERROR_NO_DEVICE_FOUND}


# ------------------------------------------------------------------------------------------------ the command layer
def _header(packet: bytes) -> tuple[int, int, int, int]:
    return tuple(np.frombuffer(packet[:8], "<i2").tolist())


def test_init_api_sends_only_the_device_info_packet_and_returns_1(run, command_layer):
    result, log, rc = run("api", library_path=True, angles=ANGLES, device_type=8, init_again=True)
    assert rc == 0
    assert (result["init"], result["init_again"]) == (NO_ERROR, NO_ERROR)
    assert result["same_comm"]
    init = log[:result["marks"]["init"]]
    assert [c["data"][:8] for c in calls(init, "libusb_interrupt_transfer") if c["ep"] == "0x02"] == [
        bytes.fromhex("0100 0100 7900 0100")]  # InitCommunication's GetDeviceInfo, nothing of InitAPI's own
    assert result["marks"]["init_again"] == result["marks"]["init"]  # already initialised: nothing at all
    # CloseAPI: CloseCommunication only (libusb_exit), no packet
    assert [line.split()[0] for line in log[result["marks"]["get"]:result["marks"]["close"]]] == ["libusb_exit"]
    assert result["close"] == NO_ERROR


@pytest.mark.parametrize("device_type, sent", [(8, 7), (0, 6)])
def test_get_angular_position_returns_the_base_angles(run, command_layer, device_type, sent):
    result, log, rc = run("api", library_path=True, angles=ANGLES, device_type=device_type)
    assert rc == 0 and result["get"] == NO_ERROR
    expected = np.float32(ANGLES).tolist()
    if sent == 6:  # device type ≠ 8: the library reads 6 actuators then the fingers; Actuator7 is left as it was
        expected[6] = -1.0
    assert result["angles"] == expected  # exact: the float32 the base packed
    out, back = calls(log[result["marks"]["init"]:result["marks"]["get"]], "libusb_interrupt_transfer")
    assert (out["ep"], _header(out["data"]), out["data"][8:12]) == ("0x02", (1, 1, 0x69, 1), bytes((1, 0, 0, 0)))
    assert (back["ep"], back["status"], _header(back["data"])) == ("0x82", "0", (1, 1, 0x69, 4 * (sent + 3)))
    assert result["mutex_change"] == 0


def test_get_angular_position_after_rs485_activation_is_refused_with_1021(run, command_layer):
    result, log, rc = run("api", library_path=True, angles=ANGLES, device_type=8, activate=True)
    assert rc == 0 and result["activate"] == NO_ERROR
    # the comm layer's SendPacket refuses (1021) and SendGetCommand returns it: nothing goes on the wire, the angles
    # are untouched, and KinovaMutex is left taken (one count fewer: SendGetCommand skips its sem_post there)
    assert result["get"] == ERROR_FUNCTION_NOT_ACCESSIBLE
    assert result["angles"] == [-1.0] * 10
    assert result["marks"]["get"] == result["marks"]["activate"]
    assert result["mutex_change"] == -1
    assert result["close"] == NO_ERROR


def test_command_layer_with_no_base(run, command_layer):
    # no socket: InitCommunication still lists the device (GetDeviceInfo's failure is ignored) → InitAPI 1;
    # GetAngularPosition: SendPacket fails (1011) → SendGetCommand's "result ≠ 1" → 1015, KinovaMutex left taken
    result, log, rc = run("api", serve=False, library_path=True)
    assert rc == 0
    assert result["init"] == NO_ERROR
    assert result["get"] == ERROR_NO_DEVICE_FOUND and result["angles"] == [-1.0] * 10
    assert result["mutex_change"] == -1
    assert {c["status"] for c in calls(log, "libusb_interrupt_transfer")} == {"-4"}


def test_base_without_angles_ignores_0x69(run, command_layer):
    result, _, _ = run("api", library_path=True)  # UsbBase(angular_position=None): the IN times out
    assert (result["init"], result["get"]) == (NO_ERROR, ERROR_NO_DEVICE_FOUND)


def test_init_api_with_no_device_gives_1015_then_1(run, command_layer):
    result, _, rc = run("api", devices=0, library_path=True, init_again=True)
    assert rc == 0
    assert (result["init"], result["init_again"]) == (ERROR_NO_DEVICE_FOUND, NO_ERROR)  # m_APIIsInit set anyway
    assert result["get"] == ERROR_NO_DEVICE_FOUND  # SendPacket: 1010 (comm not initialised) → 1015


def test_init_api_without_the_library_path_gives_2002(run, command_layer):
    if any(Path(d or ".").resolve() == command_layer.parent.resolve()
           for d in os.environ.get("LD_LIBRARY_PATH", "").split(os.pathsep) if d):
        pytest.skip("the SDK's library directory is already on this environment's LD_LIBRARY_PATH")
    result, log, rc = run("api", library_path=False, angles=ANGLES)
    assert rc == 0 and result["init"] == ERROR_LOAD_COMM_DLL and log == []


# ------------------------------------------------------------------------------------------------ the base alone
# (no SDK needed: the layouts above, from the emulation's side)
def test_base_round_trip_without_the_sdk():
    from services.robot_sim import usb_base as ub

    forwarded = []
    base = ub.UsbBase(forwarded.append, serial="PJ1", model="JACO2 6DOF", version=(6, 1, 2), device_type=7)
    assert base.out(ub.EP_COMMAND_OUT, ub.command_packet(ub.CMD_GET_DEVICE_INFO, b"\x01")) == (0, 64)
    status, reply = base.in_(ub.EP_COMMAND_IN, 64)
    serial, model, release, minor, major, kind = ub.DEVICE_INFO.unpack_from(reply, 8)
    assert (status, serial.rstrip(b"\0"), model.rstrip(b"\0"), major, minor, release, kind) == (
        0, b"PJ1", b"JACO2 6DOF", 6, 1, 2, 7)
    assert base.in_(ub.EP_COMMAND_IN, 64) == (ub.LIBUSB_ERROR_TIMEOUT, b"")
    base.out(ub.EP_RS485_OUT, ub.pack_rs485(_commands(2)))
    assert forwarded == [] and base.dropped_records == 2  # before 700
    base.out(ub.EP_COMMAND_OUT, ub.command_packet(ub.CMD_RS485_ACTIVATE, total_data_size=64))
    base.out(ub.EP_RS485_OUT, ub.pack_rs485(_commands(7)))
    assert forwarded[0].dtype == rs485.MESSAGE_DTYPE and forwarded[0].tobytes() == _commands(7).tobytes()
    base.deliver(_replies(4))
    status, data = base.in_(ub.EP_RS485_IN, 64)  # one packet asked: 3 records, the fourth stays queued
    assert status == 0 and data[:4] == bytes((3, 3, 0, 0)) and base.queued == 1
    assert ub.unpack_rs485(data).tobytes() == _replies(3).tobytes()
    status, data = base.in_(ub.EP_RS485_IN, 128)
    assert data[:4] == bytes((1, 1, 0, 0)) and data[24:] == bytes(40) and len(data) == 64
    assert base.in_(ub.EP_RS485_IN, 128) == (ub.LIBUSB_ERROR_TIMEOUT, b"")


def test_base_rejects_a_model_string_the_library_would_not_terminate():
    from services.robot_sim import usb_base as ub

    with pytest.raises(ValueError):
        ub.UsbBase(lambda records: None, model="J" * 20)


def test_base_answers_angular_position_until_activation_without_the_sdk():
    from services.robot_sim import usb_base as ub

    angles = list(ANGLES)
    base = ub.UsbBase(lambda records: None, device_type=ub.DEVICE_TYPE_7DOF, angular_position=lambda: angles)
    request = ub.command_packet(ub.CMD_GET_ANGULAR_POSITION, bytes((1, 0, 0, 0)), total_data_size=1)
    base.out(ub.EP_COMMAND_OUT, request)
    status, reply = base.in_(ub.EP_COMMAND_IN, 64)
    assert status == 0 and _header(reply) == (1, 1, 0x69, 40)
    assert np.frombuffer(reply[8:48], "<f4").tolist() == np.float32(ANGLES).tolist() and reply[48:] == bytes(16)
    angles[0] = 1.0  # asked at each request
    base.out(ub.EP_COMMAND_OUT, request)
    assert np.frombuffer(base.in_(ub.EP_COMMAND_IN, 64)[1][8:12], "<f4")[0] == 1.0
    base.device_type = 0  # 6 actuators on the wire, then the fingers
    base.out(ub.EP_COMMAND_OUT, request)
    reply = base.in_(ub.EP_COMMAND_IN, 64)[1]
    assert _header(reply)[3] == 36 and np.frombuffer(reply[32:44], "<f4").tolist() == np.float32(ANGLES[7:]).tolist()
    base.out(ub.EP_COMMAND_OUT, ub.command_packet(ub.CMD_RS485_ACTIVATE, total_data_size=64))
    base.in_(ub.EP_COMMAND_IN, 64)
    base.out(ub.EP_COMMAND_OUT, request)  # after 700: ignored, as every high-level command
    assert base.in_(ub.EP_COMMAND_IN, 64) == (ub.LIBUSB_ERROR_TIMEOUT, b"")
    assert base.ignored_commands == [ub.CMD_GET_ANGULAR_POSITION]
    with pytest.raises(ValueError):
        ub.angular_position_data(ANGLES[:7], 8)
