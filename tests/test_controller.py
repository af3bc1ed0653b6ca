"""The controller service's decisions for one features message (no zenoh needed for compute())."""
import time

import numpy as np
import pytest

from protocol import messages as m
from protocol.conventions import AngularConvention
from services.common import frames, jaco2
from services.controller.laws import LawConfig
from services.controller.service import ControllerConfig, ControllerService
from services.robot_sim.scene import CameraConfig

GOAL = [(-0.1666, -0.1666), (0.1666, -0.1666), (0.1666, 0.1666), (-0.1666, 0.1666)]


def features(points=None, status=m.FeatureStatus.OK, age_s=0.0, depth=0.5):
    now = time.time_ns() - int(age_s * 1e9)
    header = m.Header(stamp_ns=now, source_stamp_ns=now)
    if status not in m.USABLE_FEATURE_STATUSES:
        return m.Features(header=header, status=status, detail="test")
    points = points or [(x * 0.5, y * 0.5) for x, y in GOAL]
    e = (np.array(points) - np.array(GOAL)).reshape(-1)
    return m.Features(header=header, status=status, points=points, depths=[depth] * 4, goal_points=GOAL,
                      goal_depths=[0.2888] * 4, error=e.tolist(), error_norm=float(np.linalg.norm(e)))


def controller(law="adaptive-pd-mixed", with_state=True, **kw):
    service = ControllerService(ControllerConfig(law=law, **kw))
    if with_state:
        service._on_state(m.RobotState(header=m.Header(stamp_ns=time.time_ns()), q=jaco2.HOME.tolist(),
                                       dq=[0.0] * 7, tau=[0.0] * 7,
                                       pose=m.KinovaPose(X=0, Y=0, Z=0, ThetaX=0, ThetaY=0, ThetaZ=0),
                                       control_mode=m.ControlMode.IDLE), 0)
    T = CameraConfig().camera_in_ee.matrix()
    service._on_camera_info(m.CameraInfo(header=m.Header(), width=640, height=480, fx=615.0, fy=615.0, cx=319.5,
                                         cy=239.5, camera_in_ee=m.Pose(xyz=tuple(T[:3, 3]), quat_wxyz=tuple(
                                             frames.matrix_to_quat_wxyz(T[:3, :3])))), 0)
    return service


def test_usable_features_give_a_converging_output():
    status, output = controller().compute(features())
    assert status.status is m.ControllerState.CONVERGING and output is not None
    assert status.iteration == 1 and status.gain > 0 and status.camera_twist is not None


@pytest.mark.parametrize("kind, expected", [(m.FeatureStatus.TAG_LOST, m.ControllerState.TAG_LOST),
                                            (m.FeatureStatus.INVALID_IMAGE, m.ControllerState.TAG_LOST),
                                            (m.FeatureStatus.STALE, m.ControllerState.STALE_INPUT)])
def test_lost_or_stale_features_give_zero_output_with_the_reason(kind, expected):
    status, output = controller().compute(features(status=kind))
    assert status.status is expected and output is None and "test" in status.detail


def test_old_images_and_missing_state_are_stale_input():
    status, output = controller().compute(features(age_s=1.0))
    assert status.status is m.ControllerState.STALE_INPUT and output is None and "ms old" in status.detail
    status, output = controller(with_state=False).compute(features())
    assert status.status is m.ControllerState.STALE_INPUT and "robot state" in status.detail


def test_converged_below_the_threshold():
    status, output = controller().compute(features(points=[(x + 1e-6, y) for x, y in GOAL]))
    assert status.status is m.ControllerState.CONVERGED and output is None


def test_output_is_saturated_and_says_so():
    service = controller()
    status, output = service.compute(features(points=[(x * 0.2 + 0.3, y * 0.2) for x, y in GOAL], depth=1.5))
    assert status.saturated
    assert np.linalg.norm(output.twist[:3]) <= 0.15 + 1e-12 and np.linalg.norm(output.twist[3:]) <= 0.8 + 1e-12


def test_joint_law_output_is_saturated_per_joint_speed():
    service = controller("p-joint")
    status, output = service.compute(features(points=[(x * 0.2 + 0.3, y * 0.2) for x, y in GOAL], depth=1.5))
    assert np.all(np.abs(output.joint_velocities) <= jaco2.MAX_SPEED * 0.8 + 1e-12)


def test_degenerate_features_are_ill_conditioned():
    same = [(0.01, 0.01)] * 4
    status, output = controller().compute(features(points=same))
    assert status.status is m.ControllerState.ILL_CONDITIONED and output is None


def test_a_robot_reading_another_convention_is_not_commanded():
    service = controller(control=LawConfig(robot_convention=AngularConvention.OMEGA))
    status, output = service.compute(features())
    assert status.status is m.ControllerState.STALE_INPUT and "seed000" in status.detail


def test_unknown_law_is_refused_in_config():
    with pytest.raises(ValueError, match="unknown law"):
        ControllerConfig(law="pid")
