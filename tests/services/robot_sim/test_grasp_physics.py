"""A grasp in the emulated arm: the KG-3's fingers (their worm gear included) close on a free object standing on the
table, the arm lifts it, and it stays in the hand; a slippery one does not. Driven as the robot node drives the arm
and the hand: its core over the in-process hardware, Cartesian velocity commands and finger targets."""
import math

import numpy as np
import pytest

from protocol import messages as m
from protocol.conventions import AngularConvention, Frame
from services.model.arm import load_arm
from services.model.frames import PoseConfig
from services.model.kinematics import ArmKinematics, inverse_kinematics
from services.robot.core import RobotCore
from services.robot.dsp import DSPConfig, KinovaDSP
from services.robot.hardware import CYCLES_PER_DSP
from services.robot_sim import scene as sc
from services.robot_sim.hardware import SimulatedHardware
from services.robot_sim.sim import Simulation

#: the hand beside the object, its approach axis horizontal toward it, the fingers closing across it (the thumb,
#: finger 1, on one side, fingers 2 and 3 on the other, spread along the object's height)
SIDE_GRASP = np.column_stack([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
#: where the object's axis is, and how far ahead of the end effector's origin (m): in front of the palm's face
PLACE_XY = (0.5, -0.1)
AHEAD_M = 0.03
LIFT_M, LIFT_SPEED = 0.10, 0.05


def grasp_scene(arm, obj: sc.SceneObject, centre_z: float):
    kin = ArmKinematics(arm)
    p = np.array([*PLACE_XY, centre_z]) - AHEAD_M * SIDE_GRASP[:, 2]
    q, ok = inverse_kinematics(kin, arm.home, SIDE_GRASP, p)
    assert ok and arm.within_limits(q)
    scene = sc.SceneConfig(objects=[obj], table=sc.TableConfig(),
                           initial_joints_deg=[float(v) for v in arm.model_to_physical_deg(q)])
    sim = Simulation(scene, arm=arm, render=False)
    hardware = SimulatedHardware(sim)
    return sim, hardware, RobotCore(KinovaDSP(DSPConfig(), kin), hardware.read())


def command(arm, linear=None, close=True) -> m.RobotCommand:
    fingers = m.FingerCommand(mode=m.FingerMode.POSITION, values=[arm.hand.closed_angle if close else 0.0] * 3)
    if linear is None:
        return m.RobotCommand(header=m.Header(), mode=m.CommandMode.STOP, fingers=fingers)
    return m.RobotCommand(header=m.Header(), mode=m.CommandMode.CARTESIAN_VELOCITY, fingers=fingers,
                          twist=m.Twist(header=m.Header(), frame=Frame.MIXED, angular=AngularConvention.SEED000,
                                        linear=tuple(linear), rotational=(0.0, 0.0, 0.0)))


def run(hardware, core, seconds, order):
    readings = []
    for k in range(int(round(seconds / 0.002))):
        reading = hardware.exchange(core.targets())
        core.observe(reading)
        readings.append(reading)
        if k % CYCLES_PER_DSP == CYCLES_PER_DSP - 1:
            core.dsp_cycle(order)
    return readings


def close_lift_hold(arm, obj, centre_z):
    sim, hardware, core = grasp_scene(arm, obj, centre_z)
    run(hardware, core, 0.3, command(arm, close=False))  # it settles on the table
    on_table = sim.object_pose(obj.name)[2, 3]
    closed = run(hardware, core, 1.5, command(arm))
    run(hardware, core, LIFT_M / LIFT_SPEED, command(arm, (0.0, 0.0, LIFT_SPEED)))
    held_at = np.linalg.inv(sim.ee_pose()) @ sim.object_pose(obj.name)
    held = run(hardware, core, 2.0, command(arm))
    after = np.linalg.inv(sim.ee_pose()) @ sim.object_pose(obj.name)
    return {"lifted_m": sim.object_pose(obj.name)[2, 3] - on_table, "slip_m": float(np.linalg.norm(
        after[:3, 3] - held_at[:3, 3])), "closed": closed, "held": held}


def cup(friction=1.0):
    return sc.SceneObject(name="cup", kind="cup", mass_kg=0.35, friction=friction, pose_in_base=PoseConfig(
        xyz=(*PLACE_XY, sc.CupShape().height_m / 2 + 0.001), rpy_deg=(90.0, 0.0, 0.0)))


@pytest.mark.parametrize("arm_name", ["j2s7s300", "j2n6s300"])
def test_the_hand_closes_on_a_cup_and_the_arm_lifts_it_ten_centimetres_and_holds_it(arm_name):
    arm = load_arm(arm_name)
    out = close_lift_hold(arm, cup(), sc.CupShape().height_m / 2)
    assert out["lifted_m"] > 0.095
    assert out["slip_m"] < 0.003
    grip = out["held"][-1].fingers
    # short of closed, each finger pushing at its full force (the current of a blocked finger)
    assert np.all(grip.position < arm.hand.closed_angle - 0.3)
    assert np.all(grip.current_a > 0.9)


def test_the_thumb_alone_on_its_side_is_not_pushed_open_by_the_two_fingers_facing_it():
    """The worm gear holds each finger where it stopped: the thumb (finger 1) against the two others' force."""
    arm = load_arm("j2s7s300")
    out = close_lift_hold(arm, cup(), sc.CupShape().height_m / 2)
    thumb = np.array([r.fingers.position[0] for r in out["closed"]])
    stopped = thumb[int(np.argmax(thumb))]
    assert thumb[-1] > stopped - math.radians(1.0)


def test_a_slippery_box_is_held_on_the_table_and_slips_out_of_the_hand_when_lifted():
    arm = load_arm("j2s7s300")
    box = sc.SceneObject(name="box", kind="box", size_m=(0.06, 0.06, 0.10), mass_kg=0.3, friction=0.1,
                         pose_in_base=PoseConfig(xyz=(*PLACE_XY, 0.051), rpy_deg=(0.0, 0.0, 0.0)))
    out = close_lift_hold(arm, box, 0.05)
    assert np.all(out["closed"][-1].fingers.position < arm.hand.closed_angle - 0.3)  # it had it on the table
    assert out["lifted_m"] < 0.02
    assert np.all(out["held"][-1].fingers.position > arm.hand.closed_angle - 0.05)  # closed on nothing
