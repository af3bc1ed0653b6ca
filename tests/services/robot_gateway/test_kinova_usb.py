"""robot_gateway's actuator bus through Kinova's own USB comm layer (``bus.interface: kinova_usb``), run with the
real ``USBCommLayerUbuntu.so`` over the stand-in libusb (services/robot_sim/libusb_stand_in.c) whose transfers
robot_sim's emulated base answers (services/robot_sim/usb_base.py): the gateway as a process, on the loader's path
as a user's would be (LD_LIBRARY_PATH names the stand-in's directory, as it would a libusb of their own). Skipped,
saying why, where Kinova's SDK is not here."""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest

from protocol import messages as m
from services.model.arm import load_arm
from services.robot_gateway.kinova_usb import packets_for, read_capacity
from services.stack.local import RouterProcess
from services.runtime.transport import open_session
from tests.helpers import REPO
from tests.services.robot_gateway.test_kinova_usb_wire import _comm_layer, fake_libusb  # noqa: F401 (a fixture)
from tests.stack import KEYS, Recorder, wait_for

ARM = load_arm("j2s7s300")


def test_the_read_buffer_holds_every_record_the_library_can_write():
    """OpenRS485_Read asks for ceil(1.2·wanted/3) packets of 3 records (docs/kinova-usb-wire.md): 50 wanted, 60
    written; Write's QtySent counts packets."""
    assert [read_capacity(n) for n in (1, 3, 21, 50)] == [3, 6, 27, 60]
    assert [packets_for(n) for n in (1, 3, 4, 7, 21)] == [1, 1, 2, 3, 7]


#: the comm layer for hosts without Kinova's SDK (C, built here), checked against Kinova's below
STAND_IN_SOURCE = Path(__file__).with_name("comm_layer_stand_in.c")


def build_stand_in_comm_layer(directory: Path, libusb: Path) -> Path:
    """``USBCommLayerUbuntu.so`` built from the stand-in's source, linked against the libusb at ``libusb``."""
    out = directory / "USBCommLayerUbuntu.so"
    subprocess.run([shutil.which("cc") or "gcc", "-shared", "-fPIC", "-O1", "-Wall", "-Werror", "-o", str(out),
                    str(STAND_IN_SOURCE), f"-L{libusb.parent}", "-l:libusb-1.0.so.0", "-lm"], check=True)
    return out


@pytest.fixture(scope="module")
def stand_in(tmp_path_factory, fake_libusb) -> Path:
    return build_stand_in_comm_layer(tmp_path_factory.mktemp("comm_layer"), fake_libusb)


@pytest.fixture(params=["kinova", "stand_in"])
def comm(request, stand_in) -> Path:
    """Each test below runs on Kinova's comm layer (skipped, saying why, where the SDK is not here) and on the
    stand-in."""
    return _comm_layer() if request.param == "kinova" else stand_in


@pytest.fixture
def kinova_or_stand_in(stand_in) -> Path:
    """Kinova's comm layer where the SDK is here, else the stand-in (a long run made once)."""
    try:
        return _comm_layer()
    except pytest.skip.Exception:
        return stand_in


@pytest.fixture
def usb_dir():
    path = Path(tempfile.mkdtemp(prefix="mfvs-usb-", dir="/tmp"))  # short: a socket path has at most 107 bytes
    yield path
    shutil.rmtree(path, ignore_errors=True)


def usb_env(fake_libusb: Path, usb_dir: Path, devices: int = 1) -> dict:
    """The environment of a process whose libusb is the stand-in, its device robot_sim's base at the socket."""
    return {**os.environ, "LD_LIBRARY_PATH": str(fake_libusb.parent), "MFVS_FAKE_USB_DEVICES": str(devices),
            "MFVS_FAKE_USB_SOCKET": str(usb_dir / "usb.sock"), "MFVS_FAKE_USB_LOG": str(usb_dir / "usb.log"),
            "PYTHONPATH": str(REPO)}


def gateway_command(comm: Path, endpoint: str = "tcp/127.0.0.1:1", *settings: str) -> list[str]:
    """robot_gateway on ``kinova_usb`` with the comm layer ``comm``: with Kinova's, the first RS-485 positions are
    checked against its high-level API (its command layer beside it); the stand-in has none, so no check."""
    check = [] if (comm.parent / "USBCommandLayerUbuntu.so").is_file() else ["--set", "high_level_check_deg=null"]
    return [sys.executable, "-m", "services.robot_gateway", "--connect", endpoint, "--set", "bus.interface=kinova_usb",
            "--set", f"sdk_library={comm.parent}", "--set", "connect_timeout_s=5", *check, *settings]


@pytest.mark.parametrize("devices, says", [
    (0, "returned 1015 (ERROR_NO_DEVICE_FOUND)"),
    (2, "2 Kinova devices are connected"),
])
def test_without_exactly_one_arm_the_gateway_exits_2_with_one_line_and_never_reaches_the_bus(
        comm, fake_libusb, usb_dir, devices, says):
    """No arm: InitCommunication's code named, exit 2, and OpenRS485_Write/Read (which crash the process with no
    device) never called; two: refused before activation (the comm layer activates the first one it lists)."""
    done = subprocess.run(gateway_command(comm), env=usb_env(fake_libusb, usb_dir, devices), cwd=REPO,
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 2, (done.returncode, done.stderr[-2000:])
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and says in lines[0], done.stderr
    wire = (usb_dir / "usb.log").read_text() if (usb_dir / "usb.log").exists() else ""
    assert "bulk" not in wire  # no RS-485 transfer: the bus was not touched


def test_an_arm_of_another_model_is_refused_before_activation(comm, fake_libusb, usb_dir):
    """The emulated base reports a 6-DoF arm; the gateway is configured for the 7-DoF one: refused, exit 2, the
    activation command (700) never sent."""
    robot = subprocess.Popen([sys.executable, "-c", BASE_ONLY, str(usb_dir / "usb.sock"), "j2n6s300"], cwd=REPO,
                             stdout=subprocess.PIPE, text=True)
    try:
        assert robot.stdout.readline().strip() == "serving"
        done = subprocess.run(gateway_command(comm), env=usb_env(fake_libusb, usb_dir), cwd=REPO,
                              capture_output=True, text=True, timeout=60)
    finally:
        robot.kill()
        robot.wait()
    assert done.returncode == 2 and "j2n6s300 with 6 joints" in done.stderr, done.stderr[-2000:]
    assert "700" not in _command_ids(usb_dir / "usb.log")


BASE_ONLY = """
import sys, time
from services.robot_sim.usb_base import UsbBase, UsbBaseServer
server = UsbBaseServer(sys.argv[1], [UsbBase(lambda records: None, model=sys.argv[2])]).start()
print("serving", flush=True)
time.sleep(60)
"""


def _command_ids(log: Path) -> set[str]:
    """The IdCommand of every command packet the host sent (interrupt OUT on endpoint 0x02)."""
    ids = set()
    for line in log.read_text().splitlines() if log.exists() else []:
        if "interrupt" in line and "ep=0x02" in line and "data=" in line:
            data = bytes.fromhex(line.split("data=")[1].split()[0])
            ids.add(str(int.from_bytes(data[4:6], "little")))
    return ids


def test_the_gateway_drives_robot_sims_arm_through_kinovas_comm_layer(comm, fake_libusb, usb_dir):
    """robot_sim's actuators behind its emulated base on USB, robot_gateway on ``kinova_usb`` with Kinova's real
    comm layer, both processes on a router: the activation is logged with what it costs, the arm's state is
    published at home (the 0x02 positions read right), and a joint velocity command moves the joint it names in
    its direction."""
    with RouterProcess() as router:
        robot = subprocess.Popen(
            [sys.executable, "-m", "services.robot_sim", "--connect", router.endpoint, "--set", "mode=actuator_bus",
             "--set", "bus.interface=kinova_usb_base", "--set", f"bus.channel={usb_dir / 'usb.sock'}"],
            cwd=REPO, stdout=subprocess.DEVNULL, stderr=open(usb_dir / "robot_sim.log", "w"))
        gateway = None
        try:
            assert wait_for(lambda: (usb_dir / "usb.sock").exists() or robot.poll() is not None, timeout=60)
            gateway_log = open(usb_dir / "gateway.log", "w")
            gateway = subprocess.Popen(gateway_command(comm, router.endpoint),
                                       env=usb_env(fake_libusb, usb_dir), cwd=REPO, stdout=gateway_log,
                                       stderr=subprocess.STDOUT)
            client = open_session(router.client_config())
            states = Recorder(client, KEYS.robot_state, m.RobotState)
            assert wait_for(lambda: len(states) > 20 or gateway.poll() is not None, timeout=60), \
                (usb_dir / "gateway.log").read_text()[-3000:]
            assert np.array(states.last().q) == pytest.approx(ARM.home, abs=1e-3)
            log = (usb_dir / "gateway.log").read_text()
            assert "joystick and Kinova's high-level API stop working until the arm is power-cycled" in log
            assert "700" in _command_ids(usb_dir / "usb.log")
            q0 = np.array(states.last().q)
            rates = np.zeros(ARM.n_joints)
            rates[0] = 0.2
            stream_joint_velocity(client, rates, seconds=1.0)
            moved = np.array(states.last().q) - q0
            assert moved[0] > 0.05 and np.abs(moved[1:]).max() < 0.01, moved
            # what `mfvs status` shows of the bus: the interface, its cycle, the library's call times; its counters
            health = [m.decode(reply.ok.payload.to_bytes(), m.ServiceHealth)
                      for reply in client.get(KEYS.health("robot_gateway"), timeout=5.0) if reply.ok is not None]
            assert health and "over kinova_usb, a 2 ms cycle (calls p50/max ms: write " in health[0].detail, health
            assert health[0].errors.get("usb.messages_sent", 0) > 1000, health[0].errors
            states.close()
            client.close()
            shutil.copy(usb_dir / "gateway.log", "/tmp/last-kinova-usb-gateway.log")
            wire = (usb_dir / "usb.log").read_text()
            # every cycle a batch to the seven actuators out (7 messages, 3 packets: as many as the gateway counted
            # sent until its health above, and more since); the replies come in reads of up to 60 records, a read
            # taking those of one or more cycles (the arm moving as commanded above is what they said)
            writes = wire.count("libusb_bulk_transfer dev=0 ep=0x01 len=192")
            reads = wire.count("libusb_bulk_transfer dev=0 ep=0x81 ")
            assert writes >= health[0].errors["usb.messages_sent"] // ARM.n_joints - 5, (writes, health[0].errors)
            assert writes / 3 <= reads <= writes, (reads, writes)
        finally:
            for process in (gateway, robot):
                if process is not None:
                    process.terminate()
                    process.wait(timeout=30)
    assert gateway.returncode == 0, (usb_dir / "gateway.log").read_text()[-3000:]


def stream_joint_velocity(session, rates: np.ndarray, seconds: float) -> None:
    """Joint velocity commands on the robot's command key every 10 ms (the robot's admission wants them fresh)."""
    import time

    from tests.stack import next_seq

    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        header = m.Header(stamp_ns=time.time_ns(), seq=next_seq())
        command = m.RobotCommand(header=header, mode=m.CommandMode.JOINT_VELOCITY, joint_velocities=rates.tolist())
        session.put(KEYS.robot_command, m.encode(command))
        time.sleep(0.01)


def test_a_servo_task_through_kinovas_comm_layer_is_the_same_run_as_the_simulated_arm(kinova_or_stand_in, tmp_path,
                                                                                       monkeypatch):
    """`mfvs servo --profile gateway --bus kinova_usb` in lockstep: robot_gateway reaches robot_sim's emulated base
    through Kinova's real comm layer (every 0x14 batch and its replies through OpenRS485_Write/Read and the stand-in
    libusb), counting the arm's cycles where USB carries no stamps; the run converges and its per-iteration log is
    the sim profile's to the last bit (frames, features, commands, joint angles), as the hub's is
    (tests/services/servo/test_run.py)."""
    from services.servo.run import run
    from services.servo.result import read_log
    from services.servo.scenario import load_scenario

    monkeypatch.setenv("MFVS_KINOVA_SDK", str(kinova_or_stand_in.parent))
    easy = REPO / "examples" / "scenarios" / "easy.yaml"
    simulated = run(load_scenario(easy), tmp_path / "sim", plots=False)
    usb = run(load_scenario(easy), tmp_path / "usb", profile="gateway", bus="kinova_usb", plots=False)
    assert usb.converged and usb.iterations == simulated.iterations > 20
    reference, log = read_log(simulated.trajectory_log), read_log(usb.trajectory_log)
    mismatched = [(a["iteration"], [k for k in a if a[k] != b.get(k)]) for a, b in zip(reference, log) if a != b]
    assert len(log) == len(reference) and not mismatched, mismatched[:5]


def test_lockstep_refuses_an_arm_that_is_not_robot_sims_emulation(comm, fake_libusb, usb_dir):
    """A base that reports a real arm's serial number keeps wall time: the gateway in lockstep refuses it (it would
    drive the arm as fast as it answers), exit 2 with one line, before any motion."""
    robot = subprocess.Popen([sys.executable, "-c", BASE_ONLY, str(usb_dir / "usb.sock"), "j2s7s300"], cwd=REPO,
                             stdout=subprocess.PIPE, text=True)
    try:
        assert robot.stdout.readline().strip() == "serving"
        done = subprocess.run(gateway_command(comm, "tcp/127.0.0.1:1", "--set", "clock=lockstep"),
                              env=usb_env(fake_libusb, usb_dir), cwd=REPO, capture_output=True, text=True, timeout=60)
    finally:
        robot.kill()
        robot.wait()
    assert done.returncode == 2 and "lockstep needs robot_sim's emulated actuators" in done.stderr, \
        done.stderr[-2000:]
    assert "700" not in _command_ids(usb_dir / "usb.log")  # refused before activation


DRIFT_SCENARIO = """
import json, sys
import numpy as np
from protocol import rs485
from services.robot_gateway.kinova_usb import open_kinova_usb
from services.robot_sim.usb_base import UsbBase, UsbBaseServer
from pathlib import Path

comm_layer, socket_path = Path(sys.argv[1]), sys.argv[2]
base = UsbBase(lambda records: None, model="j2s7s300", serial="PJ00000001030703130")
def answer(records):  # every 0x14 answered with its 0x15, 0x16, 0x17
    replies = np.repeat(records, 3)
    replies["command"] = np.tile([0x15, 0x16, 0x17], len(records))
    replies["source"], replies["destination"] = np.repeat(records["destination"], 3), 0
    server.deliver(replies)
base.forward = answer
server = UsbBaseServer(socket_path, [base], in_wait_s=0.002).start()
bus = open_kinova_usb(comm_layer, "j2s7s300", 7)
got = []
for n in (7, 50, 1):
    batch = rs485.position_torque_records(list(range(0x10, 0x10 + n)), np.arange(n) * 1.5, np.zeros(n))
    bus.send_batch(batch)
    records, _ = bus.recv_batch(0.5)
    got.append([len(records), records.tobytes().hex()])
got.append(len(bus.recv_batch(0.0)[0]))
bus.close()
print(json.dumps({"got": got, "counters": bus.counters.snapshot()}))
"""


def test_the_stand_in_comm_layer_puts_on_the_wire_what_kinovas_does(stand_in, fake_libusb, tmp_path):
    """The same session (InitCommunication, GetDevices, activation, the reads until empty, writes of 7, 50 and 1
    messages and their replies, an empty read, CloseCommunication) through Kinova's comm layer and through the
    stand-in: every libusb call the same, in the same order, with the same bytes (but for the 55 bytes of the
    activation packet Kinova's leaves uninitialised), and the same records and counters back."""
    kinova = _comm_layer()
    runs = {}
    for name, library in (("kinova", kinova), ("stand_in", stand_in)):
        work = Path(tempfile.mkdtemp(prefix=f"mfvs-{name}-", dir="/tmp"))
        try:
            env = usb_env(fake_libusb, work)
            done = subprocess.run([sys.executable, "-c", DRIFT_SCENARIO, str(library), env["MFVS_FAKE_USB_SOCKET"]],
                                  env=env, cwd=REPO, capture_output=True, text=True, timeout=60)
            assert done.returncode == 0, (name, done.stderr[-2000:])
            runs[name] = (done.stdout.strip().splitlines()[-1], _wire(work / "usb.log"))
        finally:
            shutil.rmtree(work, ignore_errors=True)
    assert runs["stand_in"][0] == runs["kinova"][0]
    kinova_wire, stand_in_wire = runs["kinova"][1], runs["stand_in"][1]
    assert len(stand_in_wire) == len(kinova_wire) > 20
    different = [(i, a, b) for i, (a, b) in enumerate(zip(kinova_wire, stand_in_wire)) if a != b]
    assert not different, different[:3]


def _wire(log: Path) -> list[str]:
    """The stand-in libusb's log, the activation packet's uninitialised bytes (Data[1:56]) blanked."""
    lines = []
    for line in log.read_text().splitlines():
        if "ep=0x02" in line and "data=" in line:
            head, data = line.split("data=")
            packet = bytes.fromhex(data.split()[0])
            if int.from_bytes(packet[4:6], "little") == 700:
                line = f"{head}data={packet[:9].hex()}"
        lines.append(line)
    return lines


DISAGREEING_BASE = """
import sys, time
import numpy as np
from protocol import rs485
from services.model.arm import load_arm
from services.robot_sim.usb_base import ANGULAR_FINGERS, UsbBase, UsbBaseServer
from protocol.kinova import EMULATED_SERIAL

arm = load_arm("j2s7s300")
high_level = arm.home_deg.copy()
on_the_bus = high_level.copy()
on_the_bus[2] += float(sys.argv[2])  # joint 3 somewhere else on RS-485

def answer(records):  # each 0x01 answered with a 0x02: [current, position, velocity, torque]
    asked = records[records["command"] == rs485.Command.GET_ACTUAL_POSITION]
    replies = rs485.records(len(asked))
    replies["command"], replies["source"] = rs485.Command.SEND_ACTUAL_POSITION, asked["destination"]
    joints = [arm.bus_addresses.index(a) for a in asked["destination"].tolist()]
    replies["data"][:, rs485.POSITION_FLOAT] = on_the_bus[joints]
    replies["data"][:, rs485.CURRENT_FLOAT] = 0.8
    server.deliver(replies)

base = UsbBase(answer, serial=EMULATED_SERIAL, model=arm.name, device_type=arm.robot_type,
               angular_position=list(high_level) + [0.0] * ANGULAR_FINGERS)
server = UsbBaseServer(sys.argv[1], [base], in_wait_s=0.005).start()
print("serving", flush=True)
time.sleep(60)
"""


@pytest.mark.parametrize("offset_deg, refused", [(10.0, True), (0.5, False)])
def test_the_first_rs485_positions_are_checked_against_the_high_level_reading(comm_layer_with_api, fake_libusb,
                                                                             usb_dir, offset_deg, refused):
    """Kinova's high-level API reads the joints before activation (GetAngularPosition through the command layer,
    over the same emulated base); the gateway refuses to drive an arm whose first RS-485 positions (0x02's
    float[1]) differ from that by more than high_level_check_deg (3°): a position read from the wrong field or the
    wrong actuator is never acted on. Within it the start goes on (here to the router, which is not there)."""
    base = subprocess.Popen([sys.executable, "-c", DISAGREEING_BASE, str(usb_dir / "usb.sock"), str(offset_deg)],
                            cwd=REPO, stdout=subprocess.PIPE, text=True)
    try:
        assert base.stdout.readline().strip() == "serving"
        done = subprocess.run(gateway_command(comm_layer_with_api, "tcp/127.0.0.1:1"), env=usb_env(fake_libusb, usb_dir),
                              cwd=REPO, capture_output=True, text=True, timeout=120)
    finally:
        base.kill()
        base.wait()
    says = "disagree with GetAngularPosition read before activation (joint 3:"
    assert (says in done.stderr) == refused, done.stderr[-2000:]
    if not refused:
        assert "activating the RS-485 bus" in done.stderr


def test_positions_around_the_circle_agree():
    from services.robot_gateway.kinova_usb import high_level_disagreement

    assert high_level_disagreement([359.5, 10.0], [0.5, 10.0], 3.0) == ""
    assert high_level_disagreement([90.0, 10.0], [0.8, 10.0], 3.0).startswith("joint 1: 90.00° on RS-485")
    assert high_level_disagreement([float("nan")], [0.0], 3.0) != ""


@pytest.fixture
def comm_layer_with_api() -> Path:
    """Kinova's comm layer with its command layer beside it (skipped where the SDK is not here)."""
    return _comm_layer()


@pytest.mark.parametrize("value", [-1.0, 0.0, float("nan"), float("inf")])
def test_a_tolerance_that_is_not_a_positive_number_of_degrees_is_refused(value):
    from services.robot_gateway.service import GatewayConfig

    with pytest.raises(ValueError, match="high_level_check_deg must be a positive number of degrees"):
        GatewayConfig(high_level_check_deg=value)
    assert GatewayConfig(high_level_check_deg=None).high_level_check_deg is None
