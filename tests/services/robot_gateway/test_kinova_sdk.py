"""robot_gateway's kinova_sdk backend against a stand-in for Kinova's USB command layer with the same C ABI
(tests/services/robot_gateway/fake_kinova_sdk, compiled here): struct layouts, commands forwarded as SendBasicTrajectory points, state
read back, the Kinova API answered by the library, and clear failures."""
import ctypes
import ctypes.util
import shutil
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from protocol import kinova
from protocol import messages as m
from protocol.conventions import AngularConvention, Frame
from services.model import jaco2
from services.runtime.transport import open_session
from services.robot_gateway import kinova_sdk as sdk_mod
from services.robot_gateway.kinova_sdk import KinovaSdk, SdkError
from services.robot_gateway.service import GatewayConfig, robot_gateway_service
from tests.stack import KEYS, Recorder, next_seq, wait_for

SOURCE = Path(__file__).resolve().parent / "fake_kinova_sdk" / "fake_kinova_sdk.c"


@pytest.fixture(scope="module")
def library(tmp_path_factory):
    compiler = shutil.which("cc") or shutil.which("gcc")
    if compiler is None:
        pytest.skip("no C compiler to build the stand-in SDK (deploy/install.sh installs gcc)")
    path = tmp_path_factory.mktemp("sdk") / "libfake_kinova_sdk.so"
    subprocess.run([compiler, "-shared", "-fPIC", "-O1", "-o", str(path), str(SOURCE)], check=True)
    return str(path)


@pytest.fixture
def fake(library):
    lib = ctypes.CDLL(library)  # the same handle the backend gets: dlopen shares it
    lib.FakeCount.argtypes, lib.FakeSizeof.argtypes = [ctypes.c_char_p], [ctypes.c_char_p]
    lib.FakeLastPoint.argtypes = [ctypes.POINTER(sdk_mod.TrajectoryPoint)]
    lib.FakeFailInit(0)
    return lib


def last_point(fake) -> kinova.TrajectoryPoint:
    point = sdk_mod.TrajectoryPoint()
    fake.FakeLastPoint(ctypes.byref(point))
    return sdk_mod.from_c(point, kinova.TrajectoryPoint)


def test_struct_layouts_match_the_c_headers(fake):
    for name in ("TrajectoryPoint", "UserPosition", "AngularPosition", "CartesianPosition", "TrajectoryFIFO"):
        assert ctypes.sizeof(getattr(sdk_mod, name)) == fake.FakeSizeof(name.encode()), name


def test_calls_round_trip_through_the_library(library, fake):
    sdk = KinovaSdk(library)
    assert sdk.action("InitAPI") == kinova.ErrorCode.NO_ERROR_KINOVA
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
    with pytest.raises(RuntimeError, match="not installed or not loadable"):
        KinovaSdk(str(tmp_path / "missing.so"))
    with pytest.raises(RuntimeError, match="not Kinova's USB command layer"):
        KinovaSdk(ctypes.util.find_library("m") or "libm.so.6")


@pytest.fixture
def gateway(router, library, fake):
    service = robot_gateway_service(GatewayConfig(zenoh=router.client_config(), backend="kinova_sdk",
                                                sdk_library=library)).start()
    client = open_session(router.client_config())
    yield client, service
    client.close()
    service.stop()


def command(mode, **fields):
    header = m.Header(stamp_ns=time.time_ns(), seq=next_seq())
    return m.encode(m.RobotCommand(header=header, mode=mode, **fields))


def test_the_gateway_drives_the_arm_through_the_sdk(gateway, fake):
    client, service = gateway
    states = Recorder(client, KEYS.robot_state, m.RobotState)
    assert wait_for(lambda: len(states) > 5)
    angles = np.array(service.sdk.checked("GetAngularPosition").Actuators.as_list())
    assert states.last().q == pytest.approx(jaco2.physical_deg_to_model(angles).tolist(), abs=1e-5)
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
    assert wait_for(lambda: states.last().applied_command is not None)
    # joint velocities become an ANGULAR_VELOCITY point in deg/s with the arm's signs
    dq = [0.1, 0.0, -0.2, 0.0, 0.0, 0.05, 0.0]
    before = fake.FakeCount(b"points")
    client.put(KEYS.robot_command, command(m.CommandMode.JOINT_VELOCITY, joint_velocities=dq))
    assert wait_for(lambda: fake.FakeCount(b"points") > before)
    point = last_point(fake)
    assert point.Position.Type == kinova.POSITION_TYPE.ANGULAR_VELOCITY
    assert point.Position.Actuators.as_list() == pytest.approx(jaco2.model_rate_to_physical(dq).tolist(), abs=1e-4)
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


def test_a_failing_init_stops_the_start_with_the_sdk_code(router, library, fake):
    fake.FakeFailInit(1)
    with pytest.raises(SdkError, match="InitAPI returned 1015"):
        robot_gateway_service(GatewayConfig(zenoh=router.client_config(), backend="kinova_sdk",
                                          sdk_library=library)).start()


def test_the_commissioning_check_runs_through_the_sdk_against_kinovas_own_report(gateway, fake):
    """Behind the SDK the arm's own Cartesian report is Kinova's DSP's: it goes out in the state, and the check
    moves the joint through the SDK and compares with it. The stand-in reports a pose that neither matches the
    description nor follows the joints: the check fails and says why."""
    from services.check import request_check

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
