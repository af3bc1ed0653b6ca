"""The task's phase machine: a move phase, driven by the arm's state, in a kinematic loop (ideal joint tracking)."""
import numpy as np
import pytest

from protocol import messages as m
from protocol.conventions import AngularConvention
from services.controller.core import ControllerCore
from services.controller.phases import MoveConfig, MovePhase
from services.controller.service import ControllerConfig
from services.model import frames
from services.model.arm import load_arm
from services.model.kinematics import ArmKinematics
from services.robot_sim.scene import CameraConfig
from tests.helpers import ARM_DECLARED

ARM = load_arm("j2s7s300")
KIN = ArmKinematics(ARM)
CAMERA_IN_EE = CameraConfig().camera_in_ee.matrix()
PERIOD_NS = 33_333_333


def state(q, dq, stamp_ns):
    R, p = KIN.pose(q)
    return m.RobotState(**ARM_DECLARED, header=m.Header(stamp_ns=stamp_ns), q=list(q), dq=list(dq), tau=[0.0] * 7,
                        pose=m.KinovaPose(**frames.kinova_pose(R, p)), control_mode=m.ControlMode.CARTESIAN_VELOCITY,
                        arm_check=m.ArmCheckState.WAIVED)


def lost_features(stamp_ns):
    """A frame without the target: a move goes on (it is driven by the arm's state), paced by the frames."""
    return m.Features(header=m.Header(stamp_ns=stamp_ns, source_stamp_ns=stamp_ns), status=m.FeatureStatus.TARGET_LOST)


def run_move(core: ControllerCore, q0, frames_max=400, track=1.0):
    """The core's output applied as ideal joint velocities (``track``: the fraction of the command the arm makes)
    until the task ends; (q at the end, the statuses' details, the frames it took)."""
    q, dq, t = np.array(q0, dtype=float), np.zeros(7), 10_000_000_000
    for frame in range(frames_max):
        step = core.step(lost_features(t), state(q, dq, t), CAMERA_IN_EE, t)
        if not core.task.running:
            return q, step, frame
        if step.output is None:
            dq = np.zeros(7)
        elif step.output.joint_velocities is not None:
            dq = track * step.output.joint_velocities
        else:  # the mixed twist (seed000) realised through the mixed Jacobian, as the DSP does
            R, _, J = KIN.pose_and_jacobian(q)
            dq = track * np.linalg.pinv(frames.mixed_jacobian(J, R)) @ step.output.twist
        q = q + dq * PERIOD_NS * 1e-9
        t += PERIOD_NS
    return q, step, frames_max


@pytest.mark.parametrize("law", ["adaptive-pd-mixed", "p-joint"])
@pytest.mark.parametrize("frame, displacement", [(m.MoveFrame.CAMERA, (0.03, 0.0, 0.0)),
                                                 (m.MoveFrame.TOOL, (0.0, 0.0, -0.05)),
                                                 (m.MoveFrame.BASE, (0.0, 0.0, 0.1))])
def test_a_move_arrives_where_it_was_asked_holding_its_orientation_and_ends_the_task(law, frame, displacement):
    core = ControllerCore(ControllerConfig(arm="j2s7s300", law=law))
    q0 = ARM.home.copy()
    reply = core.start_task(m.TaskRequest(operator="test", plan=m.TaskPlan.MOVE, move_m=displacement,
                                          move_frame=frame), 0)
    assert reply.ok and reply.plan is m.TaskPlan.MOVE and reply.phase == "move"
    q, step, taken = run_move(core, q0)
    assert not core.task.running and core.task.outcome == "done", step.detail
    assert step.kind is m.ControllerState.IDLE and "task done" in step.detail
    R0, p0 = KIN.pose(q0)
    R1, p1 = KIN.pose(q)
    expected = {m.MoveFrame.BASE: np.eye(3), m.MoveFrame.TOOL: R0, m.MoveFrame.CAMERA: R0 @ CAMERA_IN_EE[:3, :3]}[frame]
    assert np.linalg.norm(p1 - (p0 + expected @ np.array(displacement))) < 1e-3
    assert np.degrees(np.arccos(np.clip((np.trace(R0.T @ R1) - 1) / 2, -1, 1))) < 0.2  # its orientation held
    distance = np.linalg.norm(displacement)
    assert taken * PERIOD_NS * 1e-9 < 2.5 * distance / MoveConfig().speed_mps + 2.0  # at its speed, not a creep


def test_a_move_that_cannot_arrive_fails_the_task_and_says_why():
    core = ControllerCore(ControllerConfig(arm="j2s7s300"))
    core.start_task(m.TaskRequest(operator="test", plan=m.TaskPlan.MOVE, move_m=(0.03, 0.0, 0.0)), 0)
    _, step, _ = run_move(core, ARM.home.copy(), frames_max=1000, track=0.0)  # the arm never moves
    assert core.task.outcome.startswith("failed: the move did not arrive within") and "30.0 mm away" in step.detail
    assert core.task.status().outcome == core.task.outcome and core.task.status().state is m.TaskState.IDLE


def test_a_move_needs_a_displacement_within_bounds():
    core = ControllerCore(ControllerConfig(arm="j2s7s300"))
    reply = core.start_task(m.TaskRequest(operator="test", plan=m.TaskPlan.MOVE), 0)
    assert not reply.ok and "needs a displacement" in reply.message and not core.task.running
    with pytest.raises(m.ProtocolError, match="move_m"):
        m.convert({"operator": "t", "plan": "move", "move_m": [0.5, 0.0, 0.0]}, m.TaskRequest)


def test_the_outputs_of_a_move_name_their_phase_to_safety():
    from services.controller.service import ControllerService

    service = ControllerService(ControllerConfig(arm="j2s7s300"))
    service.start_task(m.TaskRequest(operator="test", plan=m.TaskPlan.MOVE, move_m=(0.0, 0.02, 0.0)))
    assert service._source(m.ControllerStatus(header=m.Header(), law="x", status=m.ControllerState.CONVERGING,
                                              iteration=1, phase="move")) == "controller/move"
    assert service._source(m.ControllerStatus(header=m.Header(), law="x", status=m.ControllerState.IDLE,
                                              iteration=0)) == "controller/servo"


def test_a_stale_image_stops_a_move_like_a_servo():
    core = ControllerCore(ControllerConfig(arm="j2s7s300"))
    core.start_task(m.TaskRequest(operator="test", plan=m.TaskPlan.MOVE, move_m=(0.03, 0.0, 0.0)), 0)
    t = 10_000_000_000
    old = m.Features(header=m.Header(stamp_ns=t, source_stamp_ns=t - 400_000_000), status=m.FeatureStatus.TARGET_LOST)
    step = core.step(old, state(ARM.home, np.zeros(7), t), CAMERA_IN_EE, t)
    assert step.kind is m.ControllerState.STALE_INPUT and step.output is None and core.task.running


# ------------------------------------------------------------------------------------------------ the hand's phases
from services.controller.phases import GraspConfig, GraspPhase, HoldPhase, phases_for  # noqa: E402
from services.model.grasp import GraspDetector  # noqa: E402

HAND = ARM.hand


def hand_state(stamp_ns, position, current, target):
    n = HAND.n_fingers
    fingers = m.FingerState(position=[position] * n if np.isscalar(position) else list(position), velocity=[0.0] * n,
                            current_a=[current] * n if np.isscalar(current) else list(current), target=[target] * n)
    s = state(ARM.home, np.zeros(7), stamp_ns)
    return m.RobotState(**{f: getattr(s, f) for f in s.__struct_fields__ if f != "fingers"}, fingers=fingers)


def hand_core(phases):
    core = ControllerCore(ControllerConfig(arm="j2s7s300", law="adaptive-pd-mixed"))
    core.task.start(m.TaskRequest(operator="test", plan=m.TaskPlan.GRASP), 0, phases)
    return core


def test_a_grasp_plan_is_reach_approach_grasp_lift_hold_and_needs_a_hand():
    plan = phases_for(m.TaskRequest(operator="t", plan=m.TaskPlan.GRASP), MoveConfig(), GraspConfig(), HAND)
    assert [p.name for p in plan] == ["servo", "approach", "grasp", "lift", "hold"]
    assert plan[0].until_converged and plan[1].frame is m.MoveFrame.TOOL and plan[3].frame is m.MoveFrame.BASE
    assert plan[1].config.speed_mps == GraspConfig().speed_mps
    assert plan[2].detector is plan[3].detector is plan[4].detector  # one detector watches the grasp, lift and hold
    assert [p.name for p in phases_for(m.TaskRequest(operator="t", plan=m.TaskPlan.RELEASE), MoveConfig(),
                                       GraspConfig(), HAND)] == ["release"]
    with pytest.raises(ValueError, match="needs a hand"):
        phases_for(m.TaskRequest(operator="t", plan=m.TaskPlan.GRASP), MoveConfig(), GraspConfig(), None)


def test_the_grasp_phase_closes_the_hand_with_the_arm_still_until_it_holds_then_the_hold_sends_no_finger_part():
    detector = GraspDetector(HAND)
    core = hand_core([GraspPhase(detector, 1.0), HoldPhase(detector)])
    closed = HAND.closed_angle
    t = 10_000_000_000
    steps = []
    for k in range(12):  # 0.4 s at the frames' rate, the fingers stopped on an object, pushing
        steps.append(core.step(lost_features(t), hand_state(t, 0.7, 1.0, closed), CAMERA_IN_EE, t))
        t += PERIOD_NS
    first = steps[0]
    assert first.phase == "grasp" and first.kind is m.ControllerState.CONVERGING
    assert np.all(first.output.twist == 0.0) and first.output.fingers.values == [closed] * 3
    done = next(s for s in steps if "phase done" in s.detail)
    assert "the hand holds it" in done.detail and core.task.grasp is m.GraspVerdict.GRASPED
    after = steps[-1]
    assert after.phase == "hold" and after.output.fingers is None and np.all(after.output.twist == 0.0)
    # the object leaves the hand: the fingers close on, the current goes: the task fails, with no finger part
    gone = core.step(lost_features(t), hand_state(t, closed, 0.0, closed), CAMERA_IN_EE, t)
    assert "slipping" in gone.detail and gone.output is None and not core.task.running
    assert core.task.status().grasp is m.GraspVerdict.SLIPPING and "slipping" in core.task.outcome


def test_a_grasp_on_nothing_fails_as_empty_and_a_release_opens_the_hand():
    detector = GraspDetector(HAND)
    core = hand_core([GraspPhase(detector, 1.0), HoldPhase(detector)])
    closed, t = HAND.closed_angle, 10_000_000_000
    for _ in range(12):
        step = core.step(lost_features(t), hand_state(t, closed, 0.0, closed), CAMERA_IN_EE, t)
        t += PERIOD_NS
        if not core.task.running:
            break
    assert "closed on nothing" in core.task.outcome and step.output is None
    reply = core.start_task(m.TaskRequest(operator="person", plan=m.TaskPlan.RELEASE), t)
    assert reply.ok and reply.phase == "release"
    step = core.step(lost_features(t), hand_state(t, closed, 0.0, closed), CAMERA_IN_EE, t)
    assert step.output.fingers.values == [0.0] * 3  # only a release opens the hand
    for _ in range(12):
        t += PERIOD_NS
        step = core.step(lost_features(t), hand_state(t, 0.0, 0.0, 0.0), CAMERA_IN_EE, t)
    assert core.task.outcome == "done"


def test_a_release_during_the_hold_replaces_what_is_left_of_the_grasp_task():
    detector = GraspDetector(HAND)
    core = hand_core([GraspPhase(detector, 1.0), HoldPhase(detector)])
    closed, t = HAND.closed_angle, 10_000_000_000
    for _ in range(12):
        core.step(lost_features(t), hand_state(t, 0.7, 1.0, closed), CAMERA_IN_EE, t)
        t += PERIOD_NS
    assert core.task.phase.name == "hold"
    reply = core.start_task(m.TaskRequest(operator="person", reason="done drinking", plan=m.TaskPlan.RELEASE), t)
    assert reply.ok and "releasing" in reply.message and reply.task == 1 and reply.phase == "release"
    step = core.step(lost_features(t), hand_state(t, 0.7, 1.0, closed), CAMERA_IN_EE, t)
    assert step.phase == "release" and step.output.fingers.values == [0.0] * 3


# ------------------------------------------------------------------------------------------------ pause and resume
def test_another_source_in_control_pauses_the_task_and_only_a_resume_goes_on_from_where_the_arm_is():
    core = ControllerCore(ControllerConfig(arm="j2s7s300"))
    core.start_task(m.TaskRequest(operator="test", plan=m.TaskPlan.MOVE, move_m=(0.0, 0.0, 0.05),
                                  move_frame=m.MoveFrame.BASE), 0)
    q0 = ARM.home.copy()
    t = 10_000_000_000
    assert core.step(lost_features(t), state(q0, np.zeros(7), t), CAMERA_IN_EE, t).output is not None
    assert core.observe_control("controller/move") is None and core.task.running  # itself: nothing
    assert core.observe_control("jog/stick") == "jog/stick took control" and core.task.paused
    paused = core.step(lost_features(t + PERIOD_NS), state(q0, np.zeros(7), t + PERIOD_NS), CAMERA_IN_EE,
                       t + PERIOD_NS)
    assert paused.kind is m.ControllerState.PAUSED and paused.output is None and "mfvs task resume" in paused.detail
    assert core.task.status().state is m.TaskState.PAUSED and core.task.status().phase == "move"
    # the person let go (someone else, or nobody, in control): still paused
    assert core.observe_control("") is None and core.task.paused
    refused = core.start_task(m.TaskRequest(operator="test"), t)
    assert not refused.ok and "paused" in refused.message
    # the person drove the arm 3 cm sideways; the resumed move goes to the target it had, in the time the rest takes
    R, p = KIN.pose(q0)
    J = KIN.jacobian_base(q0)
    q_driven = q0 + np.linalg.pinv(J) @ np.array([0.0, 0.03, 0.0, 0.0, 0.0, 0.0])
    resumed = core.resume_task(m.TaskRequest(operator="test", reason="button"))
    assert resumed.ok and resumed.state is m.TaskState.RUNNING and "resumed at its move phase" in resumed.message
    q, step, _ = run_move(core, q_driven)
    assert core.task.outcome == "done", step.detail
    assert np.linalg.norm(KIN.pose(q)[1] - (p + np.array([0.0, 0.0, 0.05]))) < 1e-3


def test_a_grasp_paused_during_its_approach_resumes_from_the_reach_and_a_stop_ends_a_paused_task():
    plan = phases_for(m.TaskRequest(operator="t", plan=m.TaskPlan.GRASP), MoveConfig(), GraspConfig(), HAND)
    core = hand_core(plan)
    core.task.index = 1  # converged: approaching
    plan[1].target_p = np.zeros(3)
    assert core.observe_control("jog/stick") is not None
    reply = core.resume_task(m.TaskRequest(operator="test"))
    assert reply.ok and core.task.phase is plan[0] and "resumed at its servo phase" in reply.message
    assert plan[1].target_p is None  # begun anew from the pre-grasp view the reach converges to
    core.observe_control("jog/stick")
    assert core.stop_task(m.TaskRequest(operator="test")).state is m.TaskState.IDLE and core.task.outcome == "stopped"
    assert not core.resume_task(m.TaskRequest(operator="test")).ok
