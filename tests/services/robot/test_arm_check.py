"""The commissioning check's rules on arms that disagree with the description in each way it must catch: a joint
turning the other way, a joint's zero off, the end-effector frame turned; and on the arm that agrees."""
import math

import numpy as np
import pytest

from protocol.messages import ArmCheckState
from services.model import frames
from services.robot.arm_check import ArmCheckPlan, ArmCheckRun, analyse
from services.model.arm import load_arm

ARM = load_arm("j2s7s300")

Q0 = ARM.home.copy()


def checked(true_fk, plan=ArmCheckPlan(), q0=Q0):
    """Run the check on a kinematic arm whose own pose report is ``true_fk`` (the joints follow the commanded
    velocities exactly, at the DSP's 10 ms)."""
    run = ArmCheckRun(plan, ARM, q0, 0.0)
    q, dq, t = q0.copy(), np.zeros(ARM.n_joints), 0.0
    while True:
        velocity = run.step(t, q, dq, true_fk(q))
        if velocity is None:
            break
        dq = velocity
        q = q + velocity * 0.01
        t += 0.01
        assert t < 600
    return analyse(run.samples, ARM.dh_forward_kinematics, failure=run.failure), run


def test_an_arm_that_agrees_passes_every_joint():
    reply, run = checked(ARM.dh_forward_kinematics)
    assert reply.passed and reply.state is ArmCheckState.PASSED, reply.message
    assert [j.joint for j in reply.joints] == list(range(1, 8)) and all(j.direction == "ok" for j in reply.joints)
    assert all(abs(abs(j.moved_deg) - 5.0) < 0.2 for j in reply.joints)
    assert len(run.samples) == 15 and reply.static_error_mm < 1e-6
    assert np.allclose(run.samples[-1].q, Q0, atol=math.radians(0.2))  # every joint back where it started


@pytest.mark.parametrize("joint", [1, 2, 4, 6])
def test_a_joint_turning_the_other_way_is_named(joint):
    def mirrored(q):
        q = q.copy()
        q[joint - 1] = 2 * Q0[joint - 1] - q[joint - 1]  # the same at the start (as joint 1 at HOME), then not
        return ARM.dh_forward_kinematics(q)

    reply, _ = checked(mirrored)
    assert not reply.passed and reply.state is ArmCheckState.FAILED
    failed = [j for j in reply.joints if not j.passed]
    assert [j.joint for j in failed] == [joint] and failed[0].direction == "reversed"
    assert f"joint {joint} turns the other way" in reply.message


def test_a_joint_zero_off_is_named_with_its_offset():
    offset = np.zeros(ARM.n_joints)
    offset[2] = math.radians(1.5)
    reply, _ = checked(lambda q: ARM.dh_forward_kinematics(q + offset))
    assert not reply.passed and reply.static_error_mm > 3.0
    named = [j for j in reply.joints if abs(j.zero_offset_deg) > 0.5]
    assert [j.joint for j in named] == [3] and named[0].zero_offset_deg == pytest.approx(1.5, abs=0.1)


def test_a_turned_end_effector_frame_is_said_as_such_and_fails_no_joint():
    turn = frames.homogeneous(frames.rot_z(math.pi), np.zeros(3))
    reply, _ = checked(lambda q: ARM.dh_forward_kinematics(q) @ turn)
    assert not reply.passed and all(j.passed for j in reply.joints)  # the base-frame motion is the same
    assert reply.ee_frame_rotation_deg == pytest.approx(180.0, abs=0.01)
    assert np.allclose(np.abs(reply.ee_frame_axis), [0, 0, 1], atol=1e-6) and "turned 180.0°" in reply.message


def test_an_arm_without_a_cartesian_report_of_its_own_cannot_be_checked():
    reply, _ = checked(lambda q: None)
    assert not reply.ok and not reply.passed and "no Cartesian report of its own" in reply.message


def test_a_joint_at_its_limit_steps_the_other_way_and_a_stuck_joint_fails():
    lower, upper = ARM.model_limits()
    q0 = Q0.copy()
    q0[1] = upper[1] - math.radians(4.0)
    reply, run = checked(ARM.dh_forward_kinematics, q0=q0)
    assert reply.passed and [j.moved_deg for j in reply.joints if j.joint == 2][0] < 0

    run = ArmCheckRun(ArmCheckPlan(joints=(3,)), ARM, Q0, 0.0)
    q, t = Q0.copy(), 0.0
    while run.step(t, q, np.zeros(7), ARM.dh_forward_kinematics(q)) is not None:
        t += 0.01  # the joint never moves
    assert "joint 3 did not reach its target" in run.failure
