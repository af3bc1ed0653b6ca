"""The robot's states as pure functions (services/robot/state_message.py): what a tick's state says of the joints,
the end effector, the DSP, the faults and the check, with no zenoh and no node."""
import numpy as np

from protocol import messages as m
from services.model import frames
from services.model.kinematics import ArmKinematics
from services.robot.dsp import DSPConfig, KinovaDSP
from services.robot.hardware import JointReading
from services.robot.state_message import (MAX_FAULTS, STATES_NAMING_A_REFUSAL, RecentRefusal, lowlevel_state,
                                          robot_state)
from tests.helpers import ARM

HEADER = m.Header(seq=7, stamp_ns=1_000_000_000)


def reading(arm_pose=None, fault=None) -> JointReading:
    q = ARM.home
    return JointReading(q=q, dq=np.linspace(-0.1, 0.1, ARM.n_joints), tau=np.arange(ARM.n_joints, dtype=float),
                        fault=fault, stamp_ns=HEADER.stamp_ns, arm_pose=arm_pose)


def state(joints: JointReading, dsp=None, **fields) -> m.RobotState:
    kin = ArmKinematics(ARM)
    fields = {"link_faults": [], "refused": "", "applied": None, "timing": m.LoopTiming(rate_hz=500.0),
              "arm_check": m.ArmCheckState.NEVER, **fields}
    return robot_state(HEADER, ARM, joints, kin, dsp or KinovaDSP(DSPConfig(), kin), **fields)


def test_the_state_is_the_tick_s_joints_and_the_description_s_pose_of_them():
    joints = reading()
    out = state(joints, arm_check=m.ArmCheckState.PASSED, applied=m.Header(seq=3))
    assert out.header is HEADER and (out.arm, out.arm_digest) == (ARM.name, ARM.digest)
    assert out.q == joints.q.tolist() and out.dq == joints.dq.tolist() and out.tau == joints.tau.tolist()
    R, p = ArmKinematics(ARM).pose(joints.q)
    assert out.pose == m.KinovaPose(**frames.kinova_pose(R, p))
    assert out.arm_pose is None  # no report of the arm's own (an RS-485 bus): the description's pose is all there is
    assert out.arm_check is m.ArmCheckState.PASSED and out.applied_command.seq == 3 and out.timing.rate_hz == 500.0
    assert out.limits is not None and len(out.limits.joint_speed_rps) == ARM.n_joints
    assert out.control_mode is m.ControlMode.IDLE and out.fifo_count == 0 and not out.faults


def test_the_arm_s_own_report_of_its_pose_goes_out_beside_the_description_s():
    T = frames.homogeneous(frames.euler_xyz_to_matrix([0.1, -0.2, 0.3]), [0.4, 0.1, 0.5])
    out = state(reading(arm_pose=T))
    assert out.arm_pose == m.KinovaPose(**frames.kinova_pose(T[:3, :3], T[:3, 3]))
    assert out.arm_pose != out.pose


def test_faults_come_in_order_the_dsp_s_the_link_s_the_actuators_and_a_refusal_at_most_32():
    kin = ArmKinematics(ARM)
    dsp = KinovaDSP(DSPConfig(), kin)
    dsp.status.active_limits = ["speed"]
    fault = np.zeros(ARM.n_joints, dtype=int)
    fault[2] = 4
    out = state(reading(fault=fault), dsp, link_faults=["bus: timeout"], refused="sequence 3 after 5" + "!" * 200)
    assert out.faults[:3] == ["speed", "bus: timeout", "actuator 3: fault 4"]
    assert out.faults[3].startswith("refused: sequence 3 after 5") and len(out.faults[3]) == 120
    dsp.status.active_limits = [f"zone:{k}" for k in range(40)]
    assert len(state(reading(), dsp, link_faults=["bus: timeout"]).faults) == MAX_FAULTS


def test_a_refused_command_is_named_in_the_next_hundred_states_then_no_more():
    refusal = RecentRefusal()
    assert refusal.for_next_state() == ""
    refusal.note("stale")
    named = [refusal.for_next_state() for _ in range(STATES_NAMING_A_REFUSAL + 5)]
    assert named == ["stale"] * STATES_NAMING_A_REFUSAL + [""] * 5
    refusal.note("future")  # a new refusal is named afresh
    assert refusal.for_next_state() == "future"


def test_the_lowlevel_state_says_the_mode_the_bus_cycle_and_the_faults():
    fault = np.zeros(ARM.n_joints, dtype=int)
    fault[0] = 2
    joints = reading(fault=fault)
    out = lowlevel_state(HEADER, joints, True, ["bus: nack"], 2_500_000)
    assert out.mode is m.ActuatorMode.TORQUE and out.cycle_ns == 2_500_000
    assert out.faults == ["bus: nack", "actuator 1: fault 2"] and out.q == joints.q.tolist()
    assert lowlevel_state(HEADER, joints, False, [], 2_000_000).mode is m.ActuatorMode.POSITION
