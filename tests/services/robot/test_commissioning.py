"""services/robot/commissioning.py without zenoh: a confirmed request starts the check at the next tick, the node's
commands are held while it runs, an emergency stop ends it, and its verdict is said, kept and answered."""
import logging
import time

import numpy as np
import pytest

from protocol import messages as m
from services.robot.arm_check import ArmCheckConfig
from services.robot.commissioning import Commissioning
from services.robot.hardware import JointReading
from services.runtime.metrics import Counters
from tests.helpers import ARM

TICK_NS = 10_000_000


class TrajectoryQueue:
    """The DSP as the check sees it: its trajectories, erased when a check starts."""

    def __init__(self) -> None:
        self.erased = 0

    def erase_all_trajectories(self) -> None:
        self.erased += 1


class KinematicArm:
    """An arm whose joints follow the commanded velocities exactly, reporting its pose by the description's
    kinematics (the arm that is its description)."""

    def __init__(self) -> None:
        self.q, self.dq, self.t_ns = ARM.home.copy(), np.zeros(ARM.n_joints), 1_000_000_000

    def reading(self) -> JointReading:
        return JointReading(q=self.q.copy(), dq=self.dq.copy(), tau=np.zeros(ARM.n_joints),
                            arm_pose=ARM.dh_forward_kinematics(self.q))

    def follow(self, taken) -> None:
        command = taken[0] if taken is not None else None
        self.dq = (np.asarray(command.joint_velocities) if command is not None and command.joint_velocities
                   else np.zeros(ARM.n_joints))
        self.q = self.q + self.dq * TICK_NS * 1e-9
        self.t_ns += TICK_NS


def commissioning(config=ArmCheckConfig()) -> Commissioning:
    return Commissioning(config, ARM, Counters(), logging.getLogger("test"),
                         header=lambda stream, stamp_ns: m.Header(stamp_ns=stamp_ns))


def request(**fields) -> m.ArmCheckRequest:
    return m.ArmCheckRequest(header=m.Header(), **{"confirm": True, "joints": [1, 2], **fields})


def safety_command(mode=m.CommandMode.STOP):
    return m.RobotCommand(header=m.Header(stamp_ns=time.time_ns()), mode=mode), time.time_ns()


def run_ticks(check: Commissioning, arm: KinematicArm, dsp, taken=lambda k: None, ticks=20_000):
    """The DSP's ticks until the check's verdict is out; what the DSP took at each."""
    took = []
    for k in range(ticks):
        command = check.command(arm.t_ns, taken(k), arm.reading(), dsp)
        took.append(command)
        arm.follow(command)
        if check.state is not m.ArmCheckState.RUNNING and k > 0:
            return took
    raise AssertionError("the check did not end")


def test_a_request_is_refused_unconfirmed_under_torque_control_or_while_one_runs():
    check = commissioning()
    future, reason = check.request(request(confirm=False), torque_mode=False)
    assert future is None and "--yes" in reason
    future, reason = check.request(request(), torque_mode=True)
    assert future is None and reason == "low-level torque control owns the arm"
    future, reason = check.request(request(), torque_mode=False)
    assert future is not None and not reason
    assert check.request(request(), torque_mode=False) == (None, "a check is already running")


def test_the_check_runs_from_the_next_tick_holds_the_node_s_commands_and_keeps_its_verdict(tmp_path):
    record = tmp_path / "arm_check.json"
    check, arm, dsp = commissioning(ArmCheckConfig(record=str(record))), KinematicArm(), TrajectoryQueue()
    assert check.state is m.ArmCheckState.NEVER
    future, _ = check.request(request(), torque_mode=False)
    held = safety_command()
    took = run_ticks(check, arm, dsp, taken=lambda k: held)
    # (at every tick: the last one's too, counted before the check found itself over)
    assert dsp.erased == 1 and check.counters.get("arm_check.commands_held") == len(took)
    moving = [t for t in took[:-1] if np.any(t[0].joint_velocities)]
    assert moving and all(t[0].reason == "commissioning check" for t in took[:-1])  # the check's own, not safety's
    assert took[-1] is held  # over: the node's commands go to the DSP again
    reply = future.result(timeout=0)
    assert reply.ok and reply.passed and [j.joint for j in reply.joints] == [1, 2], reply.message
    assert check.state is m.ArmCheckState.PASSED and check.counters.get("arm_check.passed") == 1
    assert commissioning(ArmCheckConfig(record=str(record))).state is m.ArmCheckState.PASSED  # kept for a restart


def test_an_emergency_stop_ends_the_check_goes_to_the_dsp_and_leaves_the_verdict_as_it_was():
    check, arm = commissioning(), KinematicArm()
    future, _ = check.request(request(), torque_mode=False)
    estop = safety_command(m.CommandMode.EMERGENCY_STOP)
    took = run_ticks(check, arm, TrajectoryQueue(), taken=lambda k: estop if k == 60 else None)
    assert len(took) == 61 and took[-1] is estop
    reply = future.result(timeout=0)
    assert not reply.ok and "emergency stop" in reply.message and reply.state is m.ArmCheckState.NEVER
    assert check.state is m.ArmCheckState.NEVER


def test_a_check_aborted_by_a_failing_bus_ends_at_the_next_tick():
    check, arm = commissioning(), KinematicArm()
    future, _ = check.request(request(), torque_mode=False)
    dsp = TrajectoryQueue()
    for _ in range(5):
        arm.follow(check.command(arm.t_ns, None, arm.reading(), dsp))
    check.abort("the bus is failing")
    assert check.command(arm.t_ns, None, arm.reading(), dsp) is None
    assert future.result(timeout=0).message == "the bus is failing"


@pytest.mark.parametrize("running", [False, True])
def test_a_stopping_node_answers_the_check_requested_or_running(running):
    check, arm = commissioning(), KinematicArm()
    future, _ = check.request(request(), torque_mode=False)
    if running:
        check.command(arm.t_ns, None, arm.reading(), TrajectoryQueue())
    check.stop()
    reply = future.result(timeout=0)
    assert not reply.ok and reply.message == "the robot stopped before the check ended"


def test_a_plan_the_arm_cannot_run_is_answered_at_the_tick_and_nothing_moves():
    check, arm, dsp = commissioning(), KinematicArm(), TrajectoryQueue()
    future, _ = check.request(request(joints=[ARM.n_joints + 1]), torque_mode=False)
    held = safety_command()
    assert check.command(arm.t_ns, held, arm.reading(), dsp) is held and dsp.erased == 0
    reply = future.result(timeout=0)
    assert not reply.ok and f"joints 1 to {ARM.n_joints}" in reply.message
    assert check.state is m.ArmCheckState.NEVER
