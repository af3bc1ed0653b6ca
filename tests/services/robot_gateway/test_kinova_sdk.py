"""robot_gateway's kinova_sdk backend against a stand-in for Kinova's command layer with the same C ABI
(tests/services/robot_gateway/fake_kinova_sdk, compiled here, with a stub comm layer beside it as Kinova ships
one): the start-up sequence Kinova's driver uses (recorded by the stand-in), commands forwarded as
SendBasicTrajectory points, state read back, the Kinova API answered by the library, and one clear line for each
way the start fails. Kinova's real library is checked against its headers in test_kinova_sdk_real.py; the stand-in
cannot move a real arm, which is what it is for."""
import ctypes
import ctypes.util
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from protocol import kinova
from protocol import messages as m
from protocol.conventions import AngularConvention, Frame
from services.runtime.transport import ZenohConfig, free_loopback_port, loopback_endpoint, open_session
from services.robot_gateway import kinova_sdk as sdk_mod
from services.robot_gateway.kinova_sdk import ArmStartError, KinovaSdk
from services.robot_gateway.service import GatewayConfig, SdkEthernetConfig, robot_gateway_service
from tests.helpers import REPO
from tests.stack import KEYS, Recorder, next_seq, wait_for
from services.model.arm import load_arm

ARM = load_arm("j2s7s300")

SOURCE = Path(__file__).resolve().parent / "fake_kinova_sdk" / "fake_kinova_sdk.c"
#: the start-up sequence of Kinova's driver (kinova_comm.cpp), as the stand-in records it
STARTUP = ["InitAPI", "RefresDevicesList", "GetDevices", "SetActiveDevice", "StartControlAPI", "StopControlAPI",
           "EraseAllTrajectories", "StartControlAPI", "SendBasicTrajectory"]


@pytest.fixture(scope="module")
def sdk_dir(tmp_path_factory):
    """A directory laid out as Kinova ships its libraries: the stand-in command layers (USB and Ethernet) and a
    stub comm layer beside each."""
    compiler = shutil.which("cc") or shutil.which("gcc")
    if compiler is None:
        pytest.skip("no C compiler to build the stand-in SDK (deploy/install.sh installs gcc)")
    out = tmp_path_factory.mktemp("sdk")
    build = [compiler, "-shared", "-fPIC", "-O1"]
    subprocess.run([*build, "-o", str(out / "USBCommandLayerUbuntu.so"), str(SOURCE)], check=True)
    subprocess.run([*build, "-DPREFIX=Ethernet_", "-o", str(out / "EthCommandLayerUbuntu.so"), str(SOURCE)],
                   check=True)
    for comm in ("USBCommLayerUbuntu.so", "EthCommLayerUbuntu.so"):
        subprocess.run([*build, "-x", "c", "-o", str(out / comm), "/dev/null"], check=True)
    return out


@pytest.fixture
def free_port():
    """A loopback port nothing listens on (a router that is not there)."""
    return free_loopback_port()


@pytest.fixture(scope="module")
def library(sdk_dir):
    return str(sdk_dir / "USBCommandLayerUbuntu.so")


def _hooks(path):
    lib = ctypes.CDLL(path)  # the same handle the backend gets: dlopen shares it
    lib.FakeCount.argtypes, lib.FakeSizeof.argtypes = [ctypes.c_char_p], [ctypes.c_char_p]
    lib.FakeDevices.argtypes, lib.FakeFail.argtypes = [ctypes.c_char_p], [ctypes.c_char_p, ctypes.c_int]
    lib.FakeCalls.restype = lib.FakeActiveSerial.restype = ctypes.c_char_p
    lib.FakeLastPoint.argtypes = [ctypes.POINTER(sdk_mod.TrajectoryPoint)]
    lib.FakeEthernet.argtypes = [ctypes.POINTER(sdk_mod.EthernetCommConfig)]
    lib.FakeTorqueSetup.restype = ctypes.c_float
    lib.FakeReset()
    return lib


@pytest.fixture
def fake(library):
    return _hooks(library)


def calls(fake) -> list[str]:
    return fake.FakeCalls().decode().split(",") if fake.FakeCalls() else []


def last_point(fake) -> kinova.TrajectoryPoint:
    point = sdk_mod.TrajectoryPoint()
    fake.FakeLastPoint(ctypes.byref(point))
    return sdk_mod.from_c(point, kinova.TrajectoryPoint)


def test_struct_layouts_match_the_stand_ins(fake):
    for name in ("TrajectoryPoint", "UserPosition", "AngularPosition", "CartesianPosition", "TrajectoryFIFO",
                 "KinovaDevice", "EthernetCommConfig"):
        assert ctypes.sizeof(getattr(sdk_mod, name)) == fake.FakeSizeof(name.encode()), name


def open_fake_arm(library, **kw):
    sdk = KinovaSdk(library)
    return sdk, sdk_mod.open_arm(sdk, **{"serial": None, "arm_name": "j2s7s300", "n_joints": 7, **kw})


def test_the_arm_opens_with_kinovas_start_up_sequence_and_closes_with_stop_control(library, fake):
    sdk, session = open_fake_arm(library)
    assert calls(fake) == STARTUP
    assert fake.FakeActiveSerial() == b"PJ00000001030703130" and session.device.model == "j2s7s300"
    start = last_point(fake)  # the driver's zero velocity after the wake-up
    assert start.Position.Type == kinova.POSITION_TYPE.CARTESIAN_VELOCITY and start == sdk_mod.velocity_point(
        kinova.POSITION_TYPE.CARTESIAN_VELOCITY, cartesian=[0.0] * 6)
    session.close()
    session.close()  # once
    assert calls(fake)[len(STARTUP):] == ["EraseAllTrajectories", "StopControlAPI", "CloseAPI"]
    assert fake.FakeCount(b"initialized") == 0


def test_table_5_1_reaches_the_arm_through_the_sdk_as_the_client_gave_it(library, fake):
    """The torque-mode setup through the kinova_sdk backend: each function called with the client's value (arrays
    as float pointers, the gravity type as its enum's int, an address as an int)."""
    sdk, session = open_fake_arm(library)
    for function, argument in [
            ("SetTorqueSafetyFactor", kinova.FloatArgument(value=0.75)),
            ("SetTorqueVibrationController", kinova.FloatArgument(value=1.0)),
            ("SetTorqueActuatorGain", kinova.CommandArray(values=[0.0] * 69 + [2.5])),
            ("SetTorqueActuatorDamping", kinova.CommandArray(values=[0.0] * 5 + [0.25] + [0.0] * 64)),
            ("SetGravityType", kinova.GravityTypeArgument(type=kinova.GRAVITY_TYPE.OPTIMAL)),
            ("SetGravityOptimalZParam", kinova.GravityParameters(values=[0.0] * 41 + [3.5])),
            ("SetTorqueZero", kinova.ActuatorAddress(address=0x15)),
            ("SetJointZero", kinova.ActuatorAddress(address=0x11))]:
        assert sdk.call(function, argument).code == kinova.ErrorCode.NO_ERROR_KINOVA, function
    assert [fake.FakeTorqueSetup(i) for i in range(8)] == [0.75, 1.0, 2.5, 0.25, 1.0, 3.5, 0x15, 0x11]
    assert calls(fake)[-2:] == ["SetTorqueZero", "SetJointZero"]
    session.close()


def test_the_arm_is_chosen_by_serial_number_and_two_without_one_is_an_error(library, fake):
    fake.FakeDevices(b"PJ1:j2s7s300;PJ2:j2s7s300")
    with pytest.raises(ArmStartError, match=r"2 arms found on USB \(PJ1 \(j2s7s300\), PJ2 \(j2s7s300\)\) and no "
                                            r"sdk_serial"):
        open_fake_arm(library)
    assert calls(fake)[-1] == "CloseAPI" and "StartControlAPI" not in calls(fake)
    _, session = open_fake_arm(library, serial="PJ2")
    assert fake.FakeActiveSerial() == b"PJ2"
    session.close()
    with pytest.raises(ArmStartError, match="no arm with serial number PJ3 on USB; found PJ1 .*PJ2"):
        open_fake_arm(library, serial="PJ3")


def test_each_way_the_start_fails_is_one_line_and_closes_the_api(library, fake):
    fake.FakeInitCode(1015)
    with pytest.raises(ArmStartError) as failed:
        open_fake_arm(library)
    line = str(failed.value)
    assert "1015 (ERROR_NO_DEVICE_FOUND)" in line and "powered, plugged in" in line and "\n" not in line
    assert calls(fake) == ["InitAPI", "CloseAPI"]
    fake.FakeReset()
    fake.FakeInitCode(2002)
    with pytest.raises(ArmStartError, match="ERROR_LOAD_COMM_DLL.*LD_LIBRARY_PATH"):
        open_fake_arm(library)
    fake.FakeReset()
    fake.FakeDevices(b"")
    with pytest.raises(ArmStartError, match="no arm found on USB: is it powered"):
        open_fake_arm(library)
    fake.FakeReset()
    fake.FakeDevices(b"PJ1:j2n6s300")  # a 6-DoF arm, a 7-joint description: refused before the API controls it
    with pytest.raises(ArmStartError, match="arm PJ1 refused: the arm is a j2n6s300 with 6 joints; the configured "
                                            "arm j2s7s300 has 7"):
        open_fake_arm(library)
    assert "StartControlAPI" not in calls(fake) and calls(fake)[-1] == "CloseAPI"
    fake.FakeReset()
    fake.FakeFail(b"StartControlAPI", 1022)
    with pytest.raises(ArmStartError, match="StartControlAPI returned 1022 \\(ERROR_COMM_TIMEOUT\\): the arm did "
                                            "not answer"):
        open_fake_arm(library)
    assert calls(fake)[-1] == "CloseAPI" and fake.FakeCount(b"initialized") == 0


def test_the_sdk_is_found_from_a_setting_or_the_environment(sdk_dir, tmp_path, monkeypatch):
    monkeypatch.delenv(sdk_mod.SDK_ENV, raising=False)
    usb = sdk_dir / "USBCommandLayerUbuntu.so"
    assert sdk_mod.locate_command_layer(str(sdk_dir)) == usb  # the directory
    assert sdk_mod.locate_command_layer(str(usb)) == usb  # the file
    assert sdk_mod.locate_command_layer(str(sdk_dir), "ethernet") == sdk_dir / "EthCommandLayerUbuntu.so"
    kinova_driver = tmp_path / "kinova_driver"  # kinova-ros's layout: lib/x86_64-linux-gnu below
    (kinova_driver / "lib").mkdir(parents=True)
    (kinova_driver / "lib" / "x86_64-linux-gnu").symlink_to(sdk_dir)
    assert sdk_mod.locate_command_layer(str(kinova_driver)).samefile(usb)
    monkeypatch.setenv(sdk_mod.SDK_ENV, str(kinova_driver))
    assert sdk_mod.locate_command_layer(None).samefile(usb)
    with pytest.raises(ArmStartError, match=f"not where {sdk_mod.SDK_ENV} says: no {tmp_path}/USBCommandLayer"):
        sdk_mod.locate_command_layer(None, environ={sdk_mod.SDK_ENV: str(tmp_path)})
    with pytest.raises(ArmStartError, match="Kinova's SDK is not given: set sdk_library"):
        sdk_mod.locate_command_layer(None, environ={})
    assert sdk_mod.check_comm_layer(usb) == sdk_dir / "USBCommLayerUbuntu.so"
    alone = tmp_path / "alone"
    alone.mkdir()
    shutil.copy(usb, alone)  # the stand-in's command layer without its comm layer
    with pytest.raises(ArmStartError, match="comm layer is missing: USBCommandLayerUbuntu.so loads "
                                            "USBCommLayerUbuntu.so from beside it"):
        KinovaSdk.find(str(alone))
    # a comm layer whose libusb is not installed: a stub that needs a library that is not there
    compiler = shutil.which("cc") or shutil.which("gcc")
    missing = tmp_path / "libusb-gone.so"
    subprocess.run([compiler, "-shared", "-fPIC", "-x", "c", "-o", str(missing), "/dev/null"], check=True)
    subprocess.run([compiler, "-shared", "-fPIC", "-x", "c", "-o", str(alone / "USBCommLayerUbuntu.so"), "/dev/null",
                    "-x", "none", "-L", str(tmp_path), "-Wl,--no-as-needed", "-l:libusb-gone.so"], check=True)
    missing.unlink()
    with pytest.raises(ArmStartError, match="comm layer USBCommLayerUbuntu.so needs libusb-1.0.so.0: install "
                                            "libusb-1.0-0"):
        KinovaSdk.find(str(alone))


def test_calls_round_trip_through_the_library(library, fake):
    sdk, _ = open_fake_arm(library)
    point = sdk_mod.velocity_point(kinova.POSITION_TYPE.ANGULAR_VELOCITY, angular_dps=[1, 2, 3, 4, 5, 6, 7])
    assert sdk.send_basic_trajectory(point) == kinova.ErrorCode.NO_ERROR_KINOVA
    assert last_point(fake) == point
    code, position = sdk.get("GetAngularPosition")
    assert code == 1 and len(position.Actuators.as_list()) == 7
    reply = sdk.call("GetCartesianPosition", None)
    assert isinstance(reply, kinova.CartesianPositionReply) and reply.result.Coordinates.Z != 0.0
    fifo = sdk.call("GetGlobalTrajectoryInfo", None)
    assert isinstance(fifo, kinova.TrajectoryFIFOReply) and fifo.result.MaxSize == 2000
    assert sdk.call("SetCartesianControl", None).code == kinova.ErrorCode.NO_ERROR_KINOVA
    assert sdk.call("GetProtectionZone", None).code == kinova.ErrorCode.ERROR_INVALID_PARAM
    # the session is the gateway's: a client's CloseAPI does not close it
    assert sdk.call("CloseAPI", None).code == 1 and fake.FakeCount(b"initialized") == 1
    # a value beyond float32 would reach the arm as inf: refused
    huge = sdk_mod.velocity_point(kinova.POSITION_TYPE.CARTESIAN_VELOCITY, cartesian=[1e39, 0, 0, 0, 0, 0])
    sent = fake.FakeCount(b"points")
    reply = sdk.call("SendBasicTrajectory", huge)
    assert reply.code == kinova.ErrorCode.ERROR_INVALID_PARAM and "float32" in reply.message
    assert fake.FakeCount(b"points") == sent


def test_a_library_that_is_not_the_sdk_is_refused(tmp_path):
    with pytest.raises(ArmStartError, match="cannot be loaded"):
        KinovaSdk(str(tmp_path / "missing.so"))
    with pytest.raises(ArmStartError, match="not Kinova's usb command layer: it has no CloseAPI"):
        KinovaSdk(ctypes.util.find_library("m") or "libm.so.6")


@pytest.fixture
def gateway(router, library, fake):
    service = robot_gateway_service(GatewayConfig(zenoh=router.client_config(), backend="kinova_sdk",
                                                sdk_library=library)).start()
    client = open_session(router.client_config())
    yield client, service
    client.close()
    service.stop()
    assert calls(fake)[-3:] == ["EraseAllTrajectories", "StopControlAPI", "CloseAPI"]


def command(mode, **fields):
    header = m.Header(stamp_ns=time.time_ns(), seq=next_seq())
    return m.encode(m.RobotCommand(header=header, mode=mode, **fields))


def test_the_gateway_drives_the_arm_through_the_sdk(gateway, fake):
    client, service = gateway
    assert calls(fake)[:len(STARTUP)] == STARTUP  # the gateway opens the arm as Kinova's driver does
    states = Recorder(client, KEYS.robot_state, m.RobotState)
    assert wait_for(lambda: len(states) > 5)
    angles = np.array(service.sdk.checked("GetAngularPosition").Actuators.as_list())
    assert states.last().q == pytest.approx(ARM.physical_deg_to_model(angles).tolist(), abs=1e-5)
    # a mixed twist becomes a CARTESIAN_VELOCITY point, in the arm's convention
    twist = m.Twist(header=m.Header(), frame=Frame.MIXED, angular=AngularConvention.SEED000,
                    linear=(0.05, -0.02, 0.01), rotational=(0.0, 0.1, -0.2))
    before = fake.FakeCount(b"points")
    client.put(KEYS.robot_command, command(m.CommandMode.CARTESIAN_VELOCITY, twist=twist))
    assert wait_for(lambda: fake.FakeCount(b"points") > before)
    point = last_point(fake)
    assert point.Position.Type == kinova.POSITION_TYPE.CARTESIAN_VELOCITY
    c = point.Position.CartesianPosition
    assert [c.X, c.Y, c.Z, c.ThetaX, c.ThetaY, c.ThetaZ] == pytest.approx([0.05, -0.02, 0.01, 0.0, 0.1, -0.2])
    assert wait_for(lambda: any(s.applied_command is not None for s in states.snapshot()))  # one state carries it
    # joint velocities become an ANGULAR_VELOCITY point in deg/s with the arm's signs
    dq = [0.1, 0.0, -0.2, 0.0, 0.0, 0.05, 0.0]
    before = fake.FakeCount(b"points")
    client.put(KEYS.robot_command, command(m.CommandMode.JOINT_VELOCITY, joint_velocities=dq))
    assert wait_for(lambda: fake.FakeCount(b"points") > before)
    point = last_point(fake)
    assert point.Position.Type == kinova.POSITION_TYPE.ANGULAR_VELOCITY
    assert point.Position.Actuators.as_list() == pytest.approx(ARM.model_rate_to_physical(dq).tolist(), abs=1e-4)
    # another angular convention is refused, not reinterpreted
    refused = service.counters.get("rejected.command")
    wrong = m.Twist(header=m.Header(), frame=Frame.MIXED, angular=AngularConvention.OMEGA, linear=(0.0, 0.0, 0.0),
                    rotational=(0.0, 0.0, 0.1))
    client.put(KEYS.robot_command, command(m.CommandMode.CARTESIAN_VELOCITY, twist=wrong))
    assert wait_for(lambda: service.counters.get("rejected.command") == refused + 1)
    # a stop erases the arm's trajectories
    erased = fake.FakeCount(b"erased")
    client.put(KEYS.robot_command, command(m.CommandMode.STOP))
    assert wait_for(lambda: fake.FakeCount(b"erased") > erased)
    # the Kinova API is the library's
    replies = list(client.get(KEYS.robot_api("GetAngularPosition"), timeout=5.0))
    reply = m.decode(replies[0].ok.payload.to_bytes(), kinova.AngularPositionReply)
    assert reply.code == 1 and len(reply.result.Actuators.as_list()) == 7
    homed = fake.FakeCount(b"homed")
    replies = list(client.get(KEYS.robot_api("MoveHome"), timeout=5.0))
    assert m.decode(replies[0].ok.payload.to_bytes(), kinova.ApiReply).code == 1
    assert fake.FakeCount(b"homed") == homed + 1
    # no low-level torque API through the USB layer: refused and counted
    client.put(KEYS.lowlevel_command, m.encode(m.TorqueCommand(header=m.Header(), torques=[0.0] * 7)))
    assert wait_for(lambda: service.counters.get("rejected.lowlevel_command") == 1)


def test_the_fingers_go_through_the_sdk_as_a_trajectory_points_hand_part_and_come_back_in_the_state(gateway, fake):
    """A robot command's finger part rides on that cycle's point (HandMode and Fingers in Kinova's units); a
    command without one sends HAND_NOMOVEMENT (the fingers hold); the state carries the arm's own finger report
    (GetAngularPosition's Fingers, GetAngularCurrent's currents)."""
    client, service = gateway
    states = Recorder(client, KEYS.robot_state, m.RobotState)
    assert wait_for(lambda: len(states) > 5)
    hand = ARM.hand
    twist = m.Twist(header=m.Header(), frame=Frame.MIXED, angular=AngularConvention.SEED000,
                    linear=(0.0, 0.0, 0.0), rotational=(0.0, 0.0, 0.0))
    target = float(hand.units_to_angle(3400.0))
    before = fake.FakeCount(b"points")
    client.put(KEYS.robot_command, command(m.CommandMode.CARTESIAN_VELOCITY, twist=twist,
                                           fingers=m.FingerCommand(mode=m.FingerMode.POSITION, values=[target] * 3)))
    assert wait_for(lambda: fake.FakeCount(b"points") > before)
    point = last_point(fake)
    assert point.Position.HandMode == kinova.HAND_MODE.POSITION_MODE
    assert point.Position.Fingers.as_list() == pytest.approx([3400.0] * 3, abs=0.01)
    assert wait_for(lambda: states.last().fingers is not None and states.last().fingers.position
                    == pytest.approx([target] * 3, abs=1e-6))
    assert states.last().fingers.current_a == pytest.approx([0.5, 0.0, 0.0])  # the fake's GetAngularCurrent
    before = fake.FakeCount(b"points")
    client.put(KEYS.robot_command, command(m.CommandMode.CARTESIAN_VELOCITY, twist=twist))
    assert wait_for(lambda: fake.FakeCount(b"points") > before)
    assert last_point(fake).Position.HandMode == kinova.HAND_MODE.HAND_NOMOVEMENT


def test_a_failing_start_stops_the_gateway_before_it_reaches_the_router(library, fake, free_port):
    """No router listens at the configured endpoint: the gateway still says first what is wrong with the arm."""
    fake.FakeInitCode(1015)
    config = GatewayConfig(backend="kinova_sdk", sdk_library=library,
                           zenoh=ZenohConfig(connect=[loopback_endpoint(free_port)]))
    with pytest.raises(ArmStartError, match="InitAPI returned 1015 \\(ERROR_NO_DEVICE_FOUND\\)"):
        robot_gateway_service(config).start()
    assert calls(fake) == ["InitAPI", "CloseAPI"]


def test_a_gateway_that_cannot_reach_its_router_closes_the_arm_again(library, fake, free_port):
    config = GatewayConfig(backend="kinova_sdk", sdk_library=library,
                           zenoh=ZenohConfig(connect=[loopback_endpoint(free_port)]))
    with pytest.raises(Exception, match="Unable to connect"):
        robot_gateway_service(config).start()
    assert calls(fake)[:len(STARTUP)] == STARTUP
    assert calls(fake)[len(STARTUP):] == ["EraseAllTrajectories", "StopControlAPI", "CloseAPI"]


def test_over_ethernet_the_arm_is_opened_with_its_address(router, sdk_dir, free_port):
    fake = _hooks(str(sdk_dir / "EthCommandLayerUbuntu.so"))
    ethernet = SdkEthernetConfig(local_ip="127.0.0.1", robot_ip="127.0.0.2", robot_port=55001, rx_timeout_ms=200)
    service = robot_gateway_service(GatewayConfig(zenoh=router.client_config(), backend="kinova_sdk",
                                                sdk_library=str(sdk_dir), sdk_transport="ethernet",
                                                sdk_ethernet=ethernet)).start()
    try:
        assert calls(fake) == ["InitEthernetAPI", *STARTUP[1:]]
        sent = sdk_mod.EthernetCommConfig()
        fake.FakeEthernet(ctypes.byref(sent))
        assert (sent.localIpAddress, sent.robotIpAddress, sent.robotPort, sent.rxTimeOutInMs) == (
            sdk_mod.inet_addr("127.0.0.1"), sdk_mod.inet_addr("127.0.0.2"), 55001, 200)
        assert bytes(ctypes.c_uint32(sent.robotIpAddress)) == bytes([127, 0, 0, 2])  # network order in memory
    finally:
        service.stop()
    fake.FakeReset()
    fake.FakeDevices(b"")
    with pytest.raises(ArmStartError, match="no arm found at 127.0.0.2:55001 \\(Ethernet\\): is it powered, cabled"):
        robot_gateway_service(GatewayConfig(backend="kinova_sdk", sdk_library=str(sdk_dir), sdk_transport="ethernet",
                                            sdk_ethernet=ethernet)).start()
    with pytest.raises(ValueError, match="robot_ip '192.168.100' is not an IPv4 address"):
        SdkEthernetConfig(robot_ip="192.168.100")


def test_the_commissioning_check_runs_through_the_sdk_against_kinovas_own_report(gateway, fake):
    """Behind the SDK the arm's own Cartesian report is Kinova's DSP's: it goes out in the state, and the check
    moves the joint through the SDK and compares with it. The stand-in reports a pose that neither matches the
    description nor follows the joints: the check fails and says why."""
    from services.commissioning.check import request_check

    client, service = gateway
    states = Recorder(client, KEYS.robot_state, m.RobotState)
    assert wait_for(lambda: len(states) > 5)
    reported = service.sdk.checked("GetCartesianPosition").Coordinates
    assert states.last().arm_pose is not None and states.last().arm_pose.Z == pytest.approx(reported.Z, abs=1e-6)
    assert states.last().arm_check is m.ArmCheckState.NEVER  # a real arm's check is not waived by default
    before = fake.FakeCount(b"points")
    reply = request_check(client, KEYS, m.ArmCheckRequest(header=m.Header(), confirm=True, joints=[1]),
                          timeout_s=60.0)
    assert reply.ok and not reply.passed and reply.state is m.ArmCheckState.FAILED
    assert fake.FakeCount(b"points") > before  # the joint moved through the SDK's trajectory points
    assert reply.joints[0].direction == "disagrees" and abs(reply.joints[0].moved_deg) > 4.0
    assert reply.static_error_mm > 100.0  # the stand-in's pose is not the description's
    assert wait_for(lambda: states.last().arm_check is m.ArmCheckState.FAILED, timeout=5.0)


def test_a_slow_sdk_call_holds_no_zenoh_callback_and_what_waits_behind_it_times_out(gateway, fake):
    """MoveHome takes 3 s in the SDK. The queryable hands it to the gateway's worker and returns (zenoh runs one
    queryable's callbacks one after another: a callback that waited for the SDK would hold every later API query
    until MoveHome ended, and the call behind it would then run late). A call queued behind it is answered as
    timed out at its deadline, not run, and counted; MoveHome is answered when it ends."""
    client, service = gateway
    fake.FakeHomeDelayMs(3000)
    start = time.monotonic()
    home = client.get(KEYS.robot_api("MoveHome"), timeout=10.0)
    assert wait_for(lambda: fake.FakeCount(b"homing") == 1, timeout=2.0)  # the worker is in the SDK call
    service.api_calls.timeout_s = 0.5
    queued = time.monotonic()
    late = [m.decode(r.ok.payload.to_bytes(), kinova.ApiReply)
            for r in client.get(KEYS.robot_api("GetAngularPosition"), timeout=10.0)]
    assert late[0].code == kinova.ErrorCode.ERROR_COMM_TIMEOUT and "not run" in late[0].message
    assert time.monotonic() - queued < 2.0 and time.monotonic() - start < 3.0  # at its deadline, before MoveHome
    assert service.counters.get("api.timeouts") == 1
    homed = [m.decode(r.ok.payload.to_bytes(), kinova.ApiReply) for r in home]
    assert homed[0].code == kinova.ErrorCode.NO_ERROR_KINOVA and fake.FakeCount(b"homed") == 1
    assert time.monotonic() - start >= 3.0


def test_a_process_puts_the_sdk_on_its_loaders_path_by_running_again(sdk_dir):
    """The command layer loads its comm layer by bare name and the loader reads LD_LIBRARY_PATH only at a process's
    start: the process's entry runs itself again, once, with the SDK's folder on it, and then finds it."""
    code = ("import os, sys; from pathlib import Path; from services.robot_gateway import kinova_sdk as k; "
            f"print('run', flush=True); k.put_sdk_on_loader_path(Path({str(sdk_dir / 'USBCommandLayerUbuntu.so')!r})); "
            "print(os.environ['LD_LIBRARY_PATH'], k.loader_finds('USBCommLayerUbuntu.so'))")
    env = {k: v for k, v in os.environ.items() if k not in ("LD_LIBRARY_PATH", sdk_mod._REEXEC_ENV)}
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, cwd=REPO, env=env)
    assert run.returncode == 0, run.stderr
    assert run.stdout.splitlines() == ["run", "run", f"{sdk_dir} True"]  # ran twice, then found it
