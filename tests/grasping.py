"""A grasp in the emulated arm for tests: the hand beside a free object on the table, its fingers closed, the arm
lifting it, driven as the robot node drives the arm and the hand (its core over the in-process hardware, Cartesian
velocity commands and finger targets); what every cycle's fingers were, with the targets the core held."""
import math

import numpy as np

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
#: the table, its top at the base's height (the hand's grasp is what these measure, anywhere the arm reaches it)
TABLE = sc.TableConfig(top_z_m=0.0, centre_xy_m=(0.55, 0.0))


def grasp_scene(arm, obj: sc.SceneObject, centre_z: float):
    kin = ArmKinematics(arm)
    p = np.array([*PLACE_XY, centre_z]) - AHEAD_M * SIDE_GRASP[:, 2]
    q, ok = inverse_kinematics(kin, arm.home, SIDE_GRASP, p)
    assert ok and arm.within_limits(q)
    scene = sc.SceneConfig(objects=[obj] if obj is not None else [], table=TABLE,
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


def run(hardware, core, seconds, order, each=None):
    """``seconds`` of bus cycles, ``order`` the command of every DSP cycle; ``each(reading, targets)`` per cycle."""
    readings = []
    for k in range(int(round(seconds / 0.002))):
        targets = core.targets()
        reading = hardware.exchange(targets)
        core.observe(reading)
        readings.append(reading)
        if each is not None:
            each(reading, targets.fingers)
        if k % CYCLES_PER_DSP == CYCLES_PER_DSP - 1:
            core.dsp_cycle(order)
    return readings


def close_lift_hold(arm, obj, centre_z, each=None, hold_s=2.0):
    """Settle, close for 1.5 s, lift LIFT_M, hold ``hold_s`` (``obj`` None: the hand where it would be, closing on
    nothing): the figures, and ``each(sim, reading, targets)`` per cycle (``sim`` to see where things are)."""
    sim, hardware, core = grasp_scene(arm, obj, centre_z)
    hook = None if each is None else (lambda reading, targets: each(sim, reading, targets))
    def where():  # the object (nothing: where it would be, the hand's own pose) in the base frame and in the hand
        T = sim.ee_pose() if obj is None else sim.object_pose(obj.name)
        return T, np.linalg.inv(sim.ee_pose()) @ T

    run(hardware, core, 0.3, command(arm, close=False), hook)  # it settles on the table
    on_table = where()[0][2, 3]
    closed = run(hardware, core, 1.5, command(arm), hook)
    run(hardware, core, LIFT_M / LIFT_SPEED, command(arm, (0.0, 0.0, LIFT_SPEED)), hook)
    held_at = where()[1]
    held = run(hardware, core, hold_s, command(arm), hook)
    after = where()
    return {"lifted_m": after[0][2, 3] - on_table, "slip_m": float(np.linalg.norm(after[1][:3, 3] - held_at[:3, 3])),
            "ee_z_m": sim.ee_pose()[2, 3], "closed": closed, "held": held}


def box(friction=1.0):
    return sc.SceneObject(name="box", kind="box", size_m=(0.06, 0.06, 0.10), mass_kg=0.3, friction=friction,
                          pose_in_base=PoseConfig(xyz=(*PLACE_XY, 0.051), rpy_deg=(0.0, 0.0, 0.0)))


def cup(friction=1.0):
    return sc.SceneObject(name="cup", kind="cup", mass_kg=0.35, friction=friction, pose_in_base=PoseConfig(
        xyz=(*PLACE_XY, sc.CupShape().height_m / 2 + 0.001), rpy_deg=(90.0, 0.0, 0.0)))
