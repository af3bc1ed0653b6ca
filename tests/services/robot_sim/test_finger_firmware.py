"""The KG-3's fingers in the emulated arm (scene.py's hand, finger_firmware.py), driven as the robot node drives
them: its core's finger group over the in-process hardware, a bus cycle per exchange. Figures against the data
sheet's as dm_control's kinova_test.py checks its own hand: the fingers close in 1.2 ± 0.1 s and squeeze a ball at
the pinch with 25 N (dm_control allows 20-30 N; here within 10 %)."""
import dataclasses

import mujoco
import numpy as np
import pytest

from protocol import kinova
from protocol import messages as m
from services.model import frames
from services.model.arm import load_arm
from services.model.frames import PoseConfig
from services.model.kinematics import ArmKinematics
from services.robot.core import RobotCore
from services.robot.dsp import DSPConfig, KinovaDSP
from services.robot.hardware import CYCLES_PER_DSP
from services.robot_sim import scene as sc
from services.robot_sim.hardware import SimulatedHardware
from services.robot_sim.sim import Simulation

ARMS = ["j2s7s300", "j2n6s300"]
#: the ball the grip is measured on: 4 cm across (dm_control's 2 cm radius), on the hand's axis where the closing
#: fingers' distal links meet it
BALL_M = 0.04
PINCH_DEPTH_M = 0.035


def ball_at_the_pinch(arm):
    R, p = ArmKinematics(arm).pose(arm.home)
    T = frames.homogeneous(R, p) @ frames.homogeneous(np.eye(3), [0.0, 0.0, PINCH_DEPTH_M])
    return sc.SceneObject(name="ball", kind=sc.ObjectKind.SPHERE, size_m=(BALL_M, BALL_M, BALL_M), solid=True,
                          pose_in_base=PoseConfig(xyz=tuple(T[:3, 3]), rpy_deg=(0.0, 0.0, 0.0)))


def robot(arm, objects=()):
    sim = Simulation(sc.SceneConfig(objects=list(objects)), arm=arm, render=False)
    hardware = SimulatedHardware(sim)
    return sim, hardware, RobotCore(KinovaDSP(DSPConfig(), ArmKinematics(arm)), hardware.read())


def fingers(mode, value, arm):
    return m.RobotCommand(header=m.Header(), mode=m.CommandMode.STOP,
                          fingers=m.FingerCommand(mode=mode, values=[value] * arm.hand.n_fingers))


def run(hardware, core, cycles, first=None, then=None):
    """``cycles`` bus cycles; the DSP every fifth, with ``first`` at the first DSP cycle and ``then`` after it."""
    readings = []
    for k in range(cycles):
        reading = hardware.exchange(core.targets())
        core.observe(reading)
        readings.append(reading)
        if k % CYCLES_PER_DSP == CYCLES_PER_DSP - 1:
            core.dsp_cycle(first if k == CYCLES_PER_DSP - 1 else then)
    return readings


def grip_n(sim):
    """The fingers' normal forces on the ball together (N), as dm_control's touch sensor sums them."""
    ball = sim.model.body("object_ball").id
    force = np.zeros(6)
    total = 0.0
    for i in range(sim.data.ncon):
        contact = sim.data.contact[i]
        if ball in (sim.model.geom_bodyid[contact.geom1], sim.model.geom_bodyid[contact.geom2]):
            mujoco.mj_contactForce(sim.model, sim.data, i, force)
            total += force[0]
    return total


@pytest.mark.parametrize("arm_name", ARMS)
def test_the_fingers_close_in_the_data_sheets_time_and_the_arm_holds_still(arm_name):
    arm = load_arm(arm_name)
    sim, hardware, core = robot(arm)
    closed = arm.hand.closed_angle
    readings = run(hardware, core, 1000, first=fingers(m.FingerMode.POSITION, closed, arm))
    reached = next(k for k, r in enumerate(readings) if np.all(r.fingers.position >= 0.999 * closed))
    assert reached * hardware.timing.period_s == pytest.approx(arm.hand.closing_time_s, abs=0.1)
    assert np.abs(readings[-1].q - arm.home).max() < 1e-3  # the palm's reaction does not move the arm
    # and open again, as fast
    readings = run(hardware, core, 1000, first=fingers(m.FingerMode.POSITION, 0.0, arm))
    opened = next(k for k, r in enumerate(readings) if np.all(r.fingers.position <= 0.001 * closed))
    assert opened * hardware.timing.period_s == pytest.approx(arm.hand.closing_time_s, abs=0.1)


@pytest.mark.parametrize("arm_name", ARMS)
def test_blocked_on_a_ball_at_the_pinch_the_fingers_squeeze_it_with_the_data_sheets_grip(arm_name):
    arm = load_arm(arm_name)
    sim, hardware, core = robot(arm, [ball_at_the_pinch(arm)])
    readings = run(hardware, core, 1000, first=fingers(m.FingerMode.POSITION, arm.hand.closed_angle, arm))
    assert grip_n(sim) == pytest.approx(arm.hand.grip_force_n, rel=0.10)
    last = readings[-1].fingers
    assert np.all(last.position < 0.9 * arm.hand.closed_angle)  # stopped on the ball, short of closed
    assert np.allclose(last.current_a, arm.hand.full_force_current_a, rtol=0.02)  # each at its full force


def test_the_grip_holds_through_an_emergency_stop_stops_and_silence():
    arm = load_arm("j2s7s300")
    sim, hardware, core = robot(arm, [ball_at_the_pinch(arm)])
    run(hardware, core, 1000, first=fingers(m.FingerMode.POSITION, arm.hand.closed_angle, arm))
    held = grip_n(sim)
    for later in (m.RobotCommand(header=m.Header(), mode=m.CommandMode.EMERGENCY_STOP),
                  m.RobotCommand(header=m.Header(), mode=m.CommandMode.STOP), None):
        run(hardware, core, 250, first=later, then=later)
        assert grip_n(sim) == pytest.approx(held, rel=0.01)


def test_the_fingers_weigh_what_the_hand_leaves_of_the_last_link_and_the_arm_what_its_description_says():
    arm = load_arm("j2s7s300")
    model = sc.build_model(sc.SceneConfig(), arm)
    bare = sc.build_model(sc.SceneConfig(), dataclasses.replace(arm, hand=None))
    last = arm.link_names[-1]
    assert model.body(last).subtreemass[0] == pytest.approx(bare.body(last).mass[0])
    # (the emulated arm's truth may scale the last link: arm.true_link_mass_scale; the palm takes the rest)
    assert model.body(last).mass[0] == pytest.approx(bare.body(last).mass[0] - 3 * arm.hand.finger_mass_kg)
    assert model.nv == arm.n_joints + 3 and model.nu == arm.n_joints + 3


@pytest.mark.parametrize("arm_name", ARMS)
def test_the_eye_in_hand_camera_sees_no_finger_open_or_closed(arm_name):
    """The fingers stay out of the camera's view (mounted 6.5 cm off the approach axis, looking along it): a tag's
    images are the very pixels they were before the hand."""
    arm = load_arm(arm_name)
    bare = Simulation(arm=dataclasses.replace(arm, hand=None))
    with_hand = Simulation(arm=arm)
    try:
        expected = bare.render()
        assert np.array_equal(with_hand.render(), expected)
        hinges = [with_hand.model.joint(joint).qposadr[0] for _, joint, _ in sc.finger_names(arm)]
        with_hand.data.qpos[hinges] = arm.hand.closed_angle
        assert np.array_equal(with_hand.render(), expected)
    finally:
        bare.close()
        with_hand.close()


# ------------------------------------------------------------------------------------------------ Kinova's API
def api_on(arm, objects=()):
    from services.robot.arm_driver import CoreView
    from services.robot.kinova_api import KinovaApi

    sim, hardware, core = robot(arm, objects)
    return sim, hardware, core, KinovaApi(CoreView(core, ArmKinematics(arm)), core.dsp)


def point(arm, hand_mode, fingers, kind=None, q_deg=None):
    position = kinova.UserPosition(
        Type=kind or kinova.POSITION_TYPE.NOMOVEMENT_POSITION, HandMode=hand_mode,
        Fingers=kinova.FingersPosition.from_list(fingers),
        Actuators=kinova.AngularInfo.from_list(q_deg if q_deg is not None else [0.0] * arm.n_joints))
    return kinova.TrajectoryPoint(Position=position)


@pytest.mark.parametrize("arm_name", ARMS)
def test_kinovas_api_moves_the_fingers_in_its_units_and_reports_them_where_kinova_ros_reads_them(arm_name):
    arm = load_arm(arm_name)
    sim, hardware, core, api = api_on(arm)
    reply = api.call("SendBasicTrajectory", point(arm, kinova.HAND_MODE.POSITION_MODE, [3400.0] * 3))
    assert reply.code == kinova.ErrorCode.NO_ERROR_KINOVA, reply.message
    run(hardware, core, 600)
    angular = api.call("GetAngularPosition", None).result.Fingers.as_list()
    cartesian = api.call("GetCartesianPosition", None).result.Fingers.as_list()  # kinova-ros's getFingerPositions
    command = api.call("GetAngularCommand", None).result.Fingers.as_list()
    assert np.allclose(angular, 3400.0, atol=64.0) and np.allclose(cartesian, angular)  # kinova-ros's tolerance
    assert np.allclose(command, 3400.0)
    assert np.allclose(sim.fingers.position, arm.hand.units_to_angle(3400.0), atol=1e-3)
    # HAND_NOMOVEMENT leaves them, whatever its Fingers say; an unknown hand mode is refused
    assert api.call("SendBasicTrajectory", point(arm, kinova.HAND_MODE.HAND_NOMOVEMENT, [0.0] * 3)).code == \
        kinova.ErrorCode.ERROR_INVALID_PARAM  # (a NOMOVEMENT point with no hand part moves nothing at all)
    refused = api.call("SendBasicTrajectory", point(arm, kinova.HAND_MODE.THREE_FINGERS, [0.0] * 3))
    assert refused.code == kinova.ErrorCode.ERROR_INVALID_PARAM and "HandMode THREE_FINGERS" in refused.message
    run(hardware, core, 100)
    assert np.allclose(api.call("GetAngularCommand", None).result.Fingers.as_list(), 3400.0)


def test_the_init_struct_trap_opens_the_hand_as_on_the_real_arm():
    """Kinova's UserPosition::InitStruct() leaves HandMode POSITION_MODE with every finger at 0: a client that sends
    its angular point so opens the hand (kinova-ros clears the whole point after InitStruct for that reason)."""
    arm = load_arm("j2s7s300")
    sim, hardware, core, api = api_on(arm)
    api.call("SendBasicTrajectory", point(arm, kinova.HAND_MODE.POSITION_MODE, [6000.0] * 3))
    run(hardware, core, 700)
    here = api.call("GetAngularPosition", None).result.Actuators.as_list()[:arm.n_joints]
    trap = point(arm, kinova.HAND_MODE.POSITION_MODE, [0.0] * 3, kinova.POSITION_TYPE.ANGULAR_POSITION, here)
    assert api.call("SendBasicTrajectory", trap).code == kinova.ErrorCode.NO_ERROR_KINOVA
    run(hardware, core, 700)
    assert np.allclose(api.call("GetAngularPosition", None).result.Fingers.as_list(), 0.0, atol=64.0)


def test_get_angular_current_gives_the_fingers_current_at_their_full_force_on_a_ball():
    arm = load_arm("j2s7s300")
    sim, hardware, core, api = api_on(arm, [ball_at_the_pinch(arm)])
    api.call("SendBasicTrajectory", point(arm, kinova.HAND_MODE.POSITION_MODE, [arm.hand.closed_units] * 3))
    run(hardware, core, 1000)
    current = api.call("GetAngularCurrent", None).result
    assert np.allclose(current.Fingers.as_list(), arm.hand.full_force_current_a, rtol=0.02)
    assert current.Actuators.as_list()[1] != 0.0  # the joints' currents beside them (joint 2 carries the arm)


@pytest.mark.parametrize("arm_name", ARMS)
def test_the_controllers_model_carries_the_hands_mass_where_the_fingers_are(arm_name, rng):
    """The description's last link is the palm with the fingers' masses rigid on it, open (arm.py): Pinocchio's
    gravity is the emulated arm's, the fingers open, wherever the arm is, once the emulation's deliberate mass
    errors are taken away (every link at its description's mass)."""
    import pinocchio as pin

    arm = load_arm(arm_name)
    exact = dataclasses.replace(arm, true_link_mass_scale=np.ones(arm.n_joints))
    sim = Simulation(arm=exact, render=False)
    model = arm.load_pinocchio().model
    data = model.createData()
    lower, upper = arm.model_limits()
    for _ in range(10):
        q = np.where(np.isfinite(lower), rng.uniform(np.maximum(lower, -3.0), np.minimum(upper, 3.0)),
                     rng.uniform(-3.0, 3.0, arm.n_joints))
        sim.data.qpos[:] = 0.0
        sim.data.qpos[:arm.n_joints] = q
        mujoco.mj_forward(sim.model, sim.data)
        assert np.allclose(sim.data.qfrc_bias[:arm.n_joints], pin.computeGeneralizedGravity(model, data, q),
                           atol=1e-9)
