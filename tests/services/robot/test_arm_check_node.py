"""The commissioning check through the robot node on the emulated arm (robot_sim, lockstep, its own router): it
passes on the arm that is its description and names the joint of one that is not; the verdict goes out in the
robot's state, and the controller starts no task on an arm that has not passed."""
import pytest

from protocol import messages as m
from protocol.keys import Keys
from services.commissioning.check import request_check
from services.controller.service import ControllerConfig, ControllerService
from services.robot.arm_check import ArmCheckConfig
from services.robot_sim.firmware import ActuatorConfig
from services.robot_sim.scene import CameraConfig, SceneConfig
from services.robot_sim.service import RobotSimConfig, RobotSimService
from services.runtime.transport import open_session
from tests.stack import Recorder, wait_for

KEYS = Keys()


def robot(router, mirrored=(), record=None):
    return RobotSimService(RobotSimConfig(
        clock="lockstep", zenoh=router.client_config(), scene=SceneConfig(camera=CameraConfig(enabled=False)),
        actuators=ActuatorConfig(mirrored_joints=list(mirrored)),
        arm_check=ArmCheckConfig(waived=False, record=str(record) if record else None)))


def ask(session, **fields):
    request = m.ArmCheckRequest(header=m.Header(), confirm=True, joints=[1, 2], **fields)
    return request_check(session, KEYS, request, timeout_s=120.0)


@pytest.mark.parametrize("mirrored", [(), (1,)])
def test_the_robot_node_checks_its_arm_and_says_so_in_its_state(router, tmp_path, mirrored):
    record = tmp_path / "arm_check.json"
    service = robot(router, mirrored, record)
    service.start()
    session = open_session(router.client_config())
    states = Recorder(session, KEYS.robot_state, m.RobotState)
    try:
        assert wait_for(lambda: len(states) > 0, timeout=20.0)
        assert states.last().arm_check is m.ArmCheckState.NEVER and states.last().arm_pose is not None
        refused = request_check(session, KEYS, m.ArmCheckRequest(header=m.Header()), timeout_s=10.0)
        assert not refused.ok and "--yes" in refused.message  # nothing moves without the confirmation
        reply = ask(session)
        assert wait_for(lambda: states.last().arm_check is not m.ArmCheckState.RUNNING, timeout=10.0)
        final = states.last().arm_check
    finally:
        session.close()
        service.stop()
    assert reply.ok and [j.joint for j in reply.joints] == [1, 2]
    if mirrored:
        assert not reply.passed and final is m.ArmCheckState.FAILED
        assert reply.joints[0].direction == "reversed" and reply.joints[1].direction == "ok"
    else:
        assert reply.passed and final is m.ArmCheckState.PASSED
    assert record.exists()  # the verdict stays with the arm: a restart starts from it
    again = robot(router, mirrored, record)
    assert again.commissioning.state is final


def test_the_controller_starts_no_task_on_an_unchecked_arm(router):
    service = robot(router)
    controller = ControllerService(ControllerConfig(clock="lockstep", zenoh=router.client_config()))
    service.start()
    controller.start()
    try:
        assert wait_for(lambda: controller.robot_state is not None, timeout=20.0)
        refused = controller.start_task(m.TaskRequest(operator="test"))
        assert not refused.ok and "commissioning check is never" in refused.message
        session = open_session(router.client_config())
        try:
            assert ask(session).passed
        finally:
            session.close()
        assert wait_for(lambda: controller.robot_state.arm_check is m.ArmCheckState.PASSED, timeout=10.0)
        assert controller.start_task(m.TaskRequest(operator="test")).ok
    finally:
        controller.stop()
        service.stop()
