"""Teach by showing through the real services (lockstep, composed): the teach's steps over zenoh (vision's first view,
the controller's probe and its return, safety checking every command), then the servo back to the taught view from
elsewhere; a goal that does not fit the stack is refused in one line and nothing moves."""
from pathlib import Path

import msgspec
import numpy as np
import pytest

from protocol import messages as m
from protocol.keys import Keys
from services.experiments.markerless import GOAL_IN_CAMERA, pose_error, truth_camera
from services.model.frames import PoseConfig
from services.robot_sim.scene import TargetKind
from services.servo.run import run
from services.servo.scenario import load_scenario, stack_config
from services.stack.composed import ComposedStack
from services.vision.service import GoalConfig
from services.controller.task_client import call_task
from services.model.arm import load_arm
from services.robot_sim.scene import target_in_base
from services.servo.result import read_log
from services.vision.taught import read_goal
from services.vision.teach_client import TeachFailed, set_taught_goal, teach

BASE = load_scenario(Path(__file__).parents[3] / "examples" / "scenarios" / "markerless.yaml")


def scenario_with(target_pose: PoseConfig, **kw):
    scenario = msgspec.convert(msgspec.to_builtins(BASE), type(BASE))
    scenario.target = msgspec.structs.replace(scenario.target, kind=TargetKind.PLANE, pose_in_camera=target_pose)
    for name, value in kw.items():
        setattr(scenario, name, value)
    return scenario


@pytest.fixture(scope="module")
def taught(tmp_path_factory):
    """The plane taught at the arm's home, where it is at Table 2's goal before the camera."""
    config = stack_config(scenario_with(GOAL_IN_CAMERA))
    lines = []
    with ComposedStack(config) as stack:
        session = stack.open_session()
        try:
            result = teach(session, Keys(config.robot.robot_id), "box", "test", say=lines.append,
                           region_px=[(140.0, 100.0), (500.0, 100.0), (500.0, 380.0), (140.0, 380.0)])
            task = call_task(session, Keys(config.robot.robot_id), m.GET_TASK)
        finally:
            session.close()
    path = tmp_path_factory.mktemp("goal") / "box.mfvsgoal"
    path.write_bytes(result.file)
    return result, path, lines, task


def test_the_teach_runs_its_steps_through_the_stack_and_keeps_a_goal_file(taught):
    result, path, lines, task = taught
    assert [line.split(":")[0] for line in lines] == ["begin", "second_view", "finish"]
    # two moves (the probe and its return), each ended by itself, the controller idle again
    assert task.state is m.TaskState.IDLE and task.outcome == "done" and task.plan is m.TaskPlan.MOVE and task.task == 2
    assert result.planar and result.keypoints >= 100 and result.triangulation_error_px < 0.2
    assert np.linalg.norm(result.probe_m) == pytest.approx(0.03, abs=1e-3)  # the probe, as the arm measured it
    goal, _ = read_goal(path)
    assert goal.digest == result.digest and goal.name == "box"
    # the arm came back to where it was taught from (the second probe move), within the move's tolerance
    assert np.abs(np.median(goal.points_camera[:, 2]) - 0.2888) < 2e-3


def test_the_arm_servos_back_to_the_taught_view_from_elsewhere(taught, tmp_path):
    _, path, _, _ = taught
    start = scenario_with(PoseConfig(xyz=(0.03, -0.02, 0.4), rpy_deg=(175.0, 4.0, 15.0)))
    start.goal = GoalConfig(features=None, taught=str(path))
    start.convergence = msgspec.structs.replace(start.convergence, max_iterations=400)
    result = run(start, tmp_path, plots=False)
    assert result.converged, result.detail
    assert result.front_end["ms_per_frame"]["n"] >= result.iterations
    final_q = read_log(result.trajectory_log)[-1]["q"]
    # MuJoCo's camera at the end, in the object's frame, against where the view was taught from
    scene = stack_config(start).robot.scene
    camera_in_object = np.linalg.inv(target_in_base(scene, load_arm(start.robot.arm))) @ truth_camera(start, final_q)
    mm, deg = pose_error(np.linalg.inv(GOAL_IN_CAMERA.matrix()), camera_in_object)
    assert mm < 1.0 and deg < 0.5


def test_a_goal_taught_through_another_camera_is_refused_in_one_line_and_nothing_moves(taught):
    _, path, _, _ = taught
    small = scenario_with(GOAL_IN_CAMERA, camera=msgspec.structs.replace(BASE.camera, width=320, height=240,
                                                                           fx=307.5, fy=307.5))
    config = stack_config(small)
    with ComposedStack(config) as stack:
        session = stack.open_session()
        try:
            reply = set_taught_goal(session, Keys(config.robot.robot_id), path.read_bytes())
            with pytest.raises(TeachFailed, match="teach begin: the region is not inside"):
                teach(session, Keys(config.robot.robot_id), "x", "test",
                      region_px=[(140.0, 100.0), (500.0, 100.0), (500.0, 380.0)])
        finally:
            session.close()
    assert not reply.ok and "taught at 640x480; the camera gives 320x240" in reply.message
    assert "\n" not in reply.message
