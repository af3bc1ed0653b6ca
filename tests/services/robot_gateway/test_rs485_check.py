"""`mfvs check rs485` against robot_sim's emulated base on USB, through Kinova's comm layer (or the stand-in where
Kinova's SDK is not here): every step agrees on an arm that answers as the public drivers read it, the report is
written, and a base whose RS-485 positions disagree with the high-level reading stops the check before any 0x14."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from services.stack.local import RouterProcess
from tests.helpers import REPO
from tests.services.robot_gateway.test_kinova_usb import (DISAGREEING_BASE, _command_ids, kinova_or_stand_in,  # noqa: F401
                                                          stand_in, usb_dir, usb_env)
from tests.services.robot_gateway.test_kinova_usb_wire import _comm_layer, fake_libusb  # noqa: F401
from tests.stack import wait_for

MFVS = str(Path(sys.executable).parent / "mfvs")


def check(comm: Path, env: dict, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([MFVS, "check", "rs485", "--sdk", str(comm.parent), *args], env=env, cwd=REPO,
                          capture_output=True, text=True, timeout=180)


def test_every_step_agrees_on_robot_sims_emulated_base_and_the_report_is_written(kinova_or_stand_in, fake_libusb,
                                                                                  usb_dir):
    socket_path = usb_dir / "usb.sock"
    with RouterProcess() as router:
        robot = subprocess.Popen(
            [sys.executable, "-m", "services.robot_sim", "--connect", router.endpoint, "--set", "mode=actuator_bus",
             "--set", "bus.interface=kinova_usb_base", "--set", f"bus.channel={socket_path}",
             "--set", "scene.camera.enabled=false"], cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            assert wait_for(lambda: socket_path.exists() or robot.poll() is not None, timeout=60)
            done = check(kinova_or_stand_in, usb_env(fake_libusb, usb_dir), "--torque-joint", "7", "--yes", "--json",
                         "--out", str(usb_dir / "report.md"))
        finally:
            robot.terminate()
            robot.wait(timeout=30)
    assert done.returncode == 0, done.stderr[-2000:]
    output = json.loads(done.stdout)
    steps = {step["name"]: step for step in output["steps"]}
    assert [s["verdict"] for s in output["steps"]] == ["agrees"] * 4, output["steps"]
    assert steps["empty read"]["figures"]["empty_reads"] == 5
    assert min(steps["0x01 → 0x02"]["figures"]["replies_per_round"]) == 7
    replies = steps["0x14 replies"]["figures"]["replies"]
    assert set(replies) == {f"0x{a:02X}" for a in (0x10, 0x11, 0x12, 0x13, 0x14, 0x15, 0x19)}
    assert all(kinds == {"SEND_ALL_VALUES_1": 1, "SEND_ALL_VALUES_2": 1, "SEND_ALL_VALUES_3": 1}
               for kinds in replies.values())
    handshake = steps["torque handshake"]["figures"]
    assert (handshake["0x208 ack"], handshake["0x202"], handshake["0x204 torque"], handshake["0x204 position"]) == (
        0x208, 1, 257, 1)
    assert abs(handshake["moved_deg"]) < 1.0
    report = (usb_dir / "report.md").read_text()
    assert "| 0x14 replies | agrees |" in report and "| serial | MFVS-EMULATED |" in report


def test_positions_that_disagree_with_the_high_level_reading_stop_the_check_before_any_command(fake_libusb, usb_dir):
    """0x02's float[1] 10° from GetAngularPosition on joint 3: that step differs, exit 1, and no 0x14 went out
    (the bus log has no 0x14 batch)."""
    comm = _comm_layer()
    base = subprocess.Popen([sys.executable, "-c", DISAGREEING_BASE, str(usb_dir / "usb.sock"), "10.0"], cwd=REPO,
                            stdout=subprocess.PIPE, text=True)
    try:
        assert base.stdout.readline().strip() == "serving"
        done = check(comm, usb_env(fake_libusb, usb_dir), "--json")
    finally:
        base.kill()
        base.wait()
    assert done.returncode == 1, done.stderr[-2000:]
    steps = json.loads(done.stdout)["steps"]
    assert [s["name"] for s in steps] == ["empty read", "0x01 → 0x02"] and steps[1]["verdict"] == "differs"
    assert steps[1]["figures"]["float1_minus_high_level_deg"][2] == pytest.approx(10.0, abs=0.01)
    wire = (usb_dir / "usb.log").read_text()
    writes = [line for line in wire.splitlines() if "ep=0x01" in line and "data=" in line]
    assert writes and not any(bytes.fromhex(line.split("data=")[1].split()[0])[4:6] == b"\x14\x00"
                              for line in writes)


def test_without_a_base_the_check_exits_2_naming_the_code(stand_in, fake_libusb, usb_dir):
    env = usb_env(fake_libusb, usb_dir, devices=0)
    done = check(stand_in, env)
    assert done.returncode == 2 and "1015 (ERROR_NO_DEVICE_FOUND)" in done.stderr, done.stderr
