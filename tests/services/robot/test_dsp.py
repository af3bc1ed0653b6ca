"""The emulated DSP driving the MuJoCo arm (no zenoh): what robot_sim promises in lockstep, cycle by cycle."""
import math

import numpy as np
import pytest

from protocol import kinova
from protocol import messages as m
from protocol.conventions import AngularConvention, Frame
from services.model import frames
from services.model.kinematics import ArmKinematics
from services.robot.dsp import CommandRefused, DeadBand, DSPConfig, KinovaDSP, for_arm
from services.robot.hardware import JointReading
from services.model.zones import BoxZone
from services.robot_sim.scene import SceneConfig
from services.robot_sim.sim_robot import SimulatedRobot
from services.model.arm import load_arm

ARM = load_arm("j2s7s300")


def twist_command(linear, rotational, convention=AngularConvention.SEED000, frame=Frame.MIXED, seq=0):
    twist = m.Twist(header=m.Header(seq=seq), frame=frame, angular=convention, linear=tuple(linear),
                    rotational=tuple(rotational))
    return m.RobotCommand(header=m.Header(seq=seq), mode=m.CommandMode.CARTESIAN_VELOCITY, twist=twist)


def joint_command(dq):
    return m.RobotCommand(header=m.Header(), mode=m.CommandMode.JOINT_VELOCITY, joint_velocities=list(dq))


def make_sim(**dsp):
    return SimulatedRobot(SceneConfig(), DSPConfig(**dsp))


def run(sim, command, cycles):
    out = []
    for _ in range(cycles):
        if command is not None:
            sim.dsp.submit(command)
        sim.step_cycle()
        out.append((sim.q, sim.ee_twist_base(), sim.ee_pose()))
    return out


@pytest.mark.parametrize("convention", list(AngularConvention), ids=lambda c: c.value)
def test_mixed_velocity_moves_the_end_effector_as_declared(convention):
    sim = make_sim(angular_convention=convention)
    linear, rotational = np.array([0.04, -0.03, 0.05]), np.array([0.15, -0.1, 0.2])
    trace = run(sim, twist_command(linear, rotational, convention), 60)
    assert not {"speed", "joint_limit", "singularity"} & set(sim.dsp.status.active_limits)
    for _, twist_base, T in trace[30:]:  # after the acceleration ramp
        R = T[:3, :3]
        assert np.linalg.norm(twist_base[:3] - linear) <= 0.02 * np.linalg.norm(linear)
        achieved = frames.angular_from_omega_ee(R.T @ twist_base[3:], R, convention)
        assert np.linalg.norm(achieved - rotational) <= 0.02 * np.linalg.norm(rotational)


def test_the_three_conventions_differ_on_the_arm():
    """The same numbers under another convention produce a different motion (so the declared one matters)."""
    finals = []
    for convention in AngularConvention:
        sim = make_sim(angular_convention=convention)
        run(sim, twist_command((0, 0, 0), (0.3, 0.0, 0.3), convention), 50)
        finals.append(frames.rotation_log(sim.ee_pose()[:3, :3]))
    assert min(np.linalg.norm(a - b) for i, a in enumerate(finals) for b in finals[i + 1:]) > 0.01


def test_comes_to_rest_within_acceleration_limits_after_commands_stop():
    sim = make_sim()
    run(sim, twist_command((0.12, -0.1, 0.0), (0.0, 0.0, 0.5)), 80)
    v0 = np.linalg.norm(sim.ee_twist_base()[:3])
    trace = run(sim, None, 120)
    dt = sim.dsp.config.cycle_s
    twists = np.array([t for _, t, _ in trace])
    joints = np.array([q for q, _, _ in trace])
    lin_acc = np.linalg.norm(np.diff(twists[:, :3], axis=0), axis=1) / dt
    ang_acc = np.linalg.norm(np.diff(twists[:, 3:], axis=0), axis=1) / dt
    joint_vel = np.diff(joints, axis=0) / dt
    joint_acc = np.abs(np.diff(joint_vel, axis=0)) / dt
    assert lin_acc.max() <= 0.64 * 1.1
    assert ang_acc.max() <= 2.75 * 1.1
    assert np.degrees(joint_acc.max()) <= 200 * 1.15
    assert np.linalg.norm(twists[-1, :3]) < 1e-4 and np.linalg.norm(twists[-1, 3:]) < 1e-3
    # it stops about as fast as the deceleration limit allows, not much slower
    moving = np.flatnonzero(np.linalg.norm(twists[:, :3], axis=1) > 1e-3)
    assert (moving[-1] + 1) * dt <= v0 / 0.64 + 0.15
    assert sim.dsp.status.watchdog_tripped and sim.dsp.status.mode is m.ControlMode.IDLE


def test_a_resent_command_keeps_moving_and_one_missed_cycle_is_tolerated():
    sim = make_sim()
    command = twist_command((0.05, 0, 0), (0, 0, 0))
    run(sim, command, 40)
    sim.step_cycle()  # one cycle without a command: the watchdog's grace
    assert not sim.dsp.status.watchdog_tripped
    assert sim.ee_twist_base()[0] == pytest.approx(0.05, rel=0.02)
    sim.step_cycle()  # the second missed cycle trips it
    assert sim.dsp.status.watchdog_tripped


def test_protection_zone_is_never_entered_and_motion_continues_along_it():
    T = ARM.dh_forward_kinematics(ARM.home)
    p0 = T[:3, 3]
    # a wall 4 cm in front of the end effector (toward −y), wide and tall
    zone = BoxZone(name="user", min_xyz=(p0[0] - 1.0, p0[1] - 0.6, 0.0), max_xyz=(p0[0] + 1.0, p0[1] - 0.04, 1.5))
    sim = make_sim(zones=[zone])
    trace = run(sim, twist_command((0.05, -0.08, 0.0), (0, 0, 0)), 250)
    distances = [zone.signed_distance(T[:3, 3])[0] for _, _, T in trace]
    assert min(distances) >= 0.0
    assert min(distances) < 0.02  # it did reach the zone ...
    late = np.array([t for _, t, _ in trace[-50:]])
    assert np.all(late[:, 0] > 0.045)  # ... and glides along it at the commanded tangential speed
    assert np.all(np.abs(late[:, 1]) < 0.005)
    assert "zone:user" in sim.dsp.status.active_limits


def test_default_base_zone_protects_the_column():
    sim = make_sim()
    trace = run(sim, twist_command((0.0, 0.2, -0.1), (0, 0, 0)), 400)  # drive toward the base
    zone = sim.dsp.zones[0]
    assert min(zone.signed_distance(T[:3, 3])[0] for _, _, T in trace) >= 0.0


def within_limits(q):
    lower, upper = ARM.model_limits()
    return bool(np.all(q >= lower) and np.all(q <= upper))


def test_joint_limits_hold_under_adversarial_joint_commands():
    sim = make_sim()
    lower, upper = ARM.model_limits()
    for joint in (1, 3, 5):
        for direction in (-1.0, 1.0):
            sim.reset()
            dq = np.zeros(7)
            dq[joint] = direction * 10.0  # far beyond the joint's speed
            for q, _, _ in run(sim, joint_command(dq), 1200):
                assert within_limits(q)
            # it ends parked at the limit's margin, not before
            limit = upper[joint] if direction > 0 else lower[joint]
            assert abs(sim.q[joint] - limit) < math.radians(3.0)


def test_joint_limits_hold_under_random_commands(rng):
    sim = make_sim()
    for _ in range(40):
        if rng.random() < 0.5:
            command = twist_command(rng.uniform(-0.3, 0.3, 3), rng.uniform(-1.5, 1.5, 3))
        else:
            command = joint_command(rng.uniform(-2, 2, 7))
        for q, _, _ in run(sim, command, int(rng.integers(5, 60))):
            assert within_limits(q)
        assert np.all(np.abs(sim.dq) <= ARM.max_speed * 1.05)


def test_speed_limits_hold():
    sim = make_sim()
    trace = run(sim, twist_command((0.5, 0.0, 0.0), (0.0, 0.0, 3.0)), 60)
    for _, twist, _ in trace[30:]:
        assert np.linalg.norm(twist[:3]) <= 0.2 * 1.02
    assert "speed" in sim.dsp.status.active_limits


def test_a_twist_over_one_speed_limit_keeps_its_direction():
    """Linear 2.5× over its limit, angular well within: the whole motion slows by one factor (issue 34), so the
    end effector turns at 0.4× the rate it was asked for, not the full rate with a cut translation."""
    sim = make_sim(angular_convention=AngularConvention.OMEGA)
    linear, omega_ee = np.array([0.0, 0.5, 0.0]), np.array([0.0, 0.0, 0.3])
    trace = run(sim, twist_command(linear, omega_ee, AngularConvention.OMEGA), 60)
    assert "speed" in sim.dsp.status.active_limits
    asked = np.concatenate([linear, trace[0][2][:3, :3] @ omega_ee])
    for _, twist_base, T in trace[40:]:
        assert np.linalg.norm(twist_base[:3]) == pytest.approx(0.2, rel=0.02)
        asked = np.concatenate([linear, T[:3, :3] @ omega_ee])  # ω is turned into the base frame as the arm turns
        assert np.linalg.norm(twist_base - asked * 0.2 / 0.5) <= 0.02 * np.linalg.norm(asked * 0.2 / 0.5)


@pytest.mark.parametrize("bad", [
    twist_command((0.05, 0, 0), (0, 0, 0.1), convention=AngularConvention.OMEGA),
    twist_command((0.05, 0, 0), (0, 0, 0.1), convention=AngularConvention.EULER_XYZ_RATES),
    twist_command((0.05, 0, 0), (0, 0, 0.1), frame=Frame.END_EFFECTOR),
    twist_command((0.05, 0, 0), (0, 0, 0.1), frame=Frame.CAMERA),
])
def test_refused_commands_leave_the_arm_at_rest(bad):
    sim = make_sim()  # reads seed000 in the mixed frame
    q0 = sim.q
    for _ in range(50):
        with pytest.raises(CommandRefused):
            sim.dsp.submit(bad)
        sim.step_cycle()
    assert np.abs(sim.q - q0).max() < 1e-6


def test_stop_command_stops_without_grace():
    sim = make_sim()
    run(sim, twist_command((0.1, 0, 0), (0, 0, 0)), 50)
    sim.dsp.submit(m.RobotCommand(header=m.Header(), mode=m.CommandMode.STOP))
    before = np.linalg.norm(sim.ee_twist_base()[:3])
    sim.step_cycle()
    sim.step_cycle()
    assert np.linalg.norm(sim.ee_twist_base()[:3]) < before - 0.005


# ------------------------------------------------------------------------------ Kinova API semantics


def velocity_point(x):
    return kinova.TrajectoryPoint(Position=kinova.UserPosition(
        Type=kinova.POSITION_TYPE.CARTESIAN_VELOCITY, CartesianPosition=kinova.CartesianInfo(X=x)))


def test_velocity_points_queue_in_the_fifo_one_per_cycle():
    sim = make_sim()
    for _ in range(50):
        assert sim.dsp.send_basic_trajectory(velocity_point(0.05)) == kinova.ErrorCode.NO_ERROR_KINOVA
    assert sim.dsp.fifo_count == 50
    x0 = sim.ee_pose()[0, 3]
    for i in range(50):
        sim.step_cycle()
        assert sim.dsp.fifo_count == 49 - i
    assert sim.ee_twist_base()[0] > 0.04  # still moving on queued points
    for _ in range(60):
        sim.step_cycle()
    assert abs(sim.ee_twist_base()[0]) < 1e-4
    assert sim.ee_pose()[0, 3] - x0 > 0.02


def test_fifo_holds_2000_points():
    sim = make_sim()
    for _ in range(kinova.TRAJECTORY_FIFO_SIZE):
        sim.dsp.send_basic_trajectory(velocity_point(0.0))
    assert sim.dsp.send_basic_trajectory(velocity_point(0.0)) == kinova.ErrorCode.ERROR_INVALID_PARAM
    sim.dsp.erase_all_trajectories()
    assert sim.dsp.fifo_count == 0


def test_angular_position_and_move_home():
    sim = make_sim()
    target = ARM.home_deg + np.array([10, -8, 12, 10, -15, 10, 20])
    point = kinova.TrajectoryPoint(Position=kinova.UserPosition(
        Type=kinova.POSITION_TYPE.ANGULAR_POSITION, Actuators=kinova.AngularInfo.from_list(target)))
    assert sim.dsp.send_basic_trajectory(point) == kinova.ErrorCode.NO_ERROR_KINOVA
    for _ in range(400):
        sim.step_cycle()
    assert ARM.model_to_physical_deg(sim.q) == pytest.approx(target, abs=0.1)
    assert sim.dsp.fifo_count == 0
    sim.dsp.move_home()
    for _ in range(400):
        sim.step_cycle()
    assert ARM.model_to_physical_deg(sim.q) == pytest.approx(ARM.home_deg, abs=0.1)


def test_angular_position_outside_limits_is_refused():
    sim = make_sim()
    target = ARM.home_deg.copy()
    target[1] = 20.0  # joint 2 range is 47-313
    point = kinova.TrajectoryPoint(Position=kinova.UserPosition(
        Type=kinova.POSITION_TYPE.ANGULAR_POSITION, Actuators=kinova.AngularInfo.from_list(target)))
    assert sim.dsp.send_basic_trajectory(point) == kinova.ErrorCode.ERROR_INVALID_PARAM


def test_cartesian_position_reaches_the_pose():
    sim = make_sim()
    T0 = sim.ee_pose()
    euler = frames.matrix_to_euler_xyz(T0[:3, :3]) + np.radians([5, -5, 8])
    goal = T0[:3, 3] + np.array([0.05, 0.04, -0.05])
    point = kinova.TrajectoryPoint(Position=kinova.UserPosition(
        Type=kinova.POSITION_TYPE.CARTESIAN_POSITION,
        CartesianPosition=kinova.CartesianInfo(X=goal[0], Y=goal[1], Z=goal[2], ThetaX=euler[0], ThetaY=euler[1],
                                               ThetaZ=euler[2])))
    sim.dsp.send_basic_trajectory(point)
    for _ in range(300):
        sim.step_cycle()
    T = sim.ee_pose()
    assert np.linalg.norm(T[:3, 3] - goal) < 1.5e-3
    assert np.degrees(np.linalg.norm(frames.rotation_log(frames.euler_xyz_to_matrix(euler) @ T[:3, :3].T))) < 0.5


def test_client_max_velocities_are_range_checked_and_applied():
    sim = make_sim()
    with pytest.raises(CommandRefused):
        sim.dsp.set_max_velocities(linear_mps=0.5)
    sim.dsp.set_max_velocities(linear_mps=0.05)
    trace = run(sim, twist_command((0.2, 0, 0), (0, 0, 0)), 50)
    assert np.linalg.norm(trace[-1][1][:3]) == pytest.approx(0.05, rel=0.02)


def test_config_ranges():
    with pytest.raises(ValueError, match="dsp.max_linear_speed_mps must be within the j2s7s300's range"):
        for_arm(DSPConfig(max_linear_speed_mps=0.3), ARM)
    with pytest.raises(ValueError, match="dsp.max_angular_speed_rps"):
        for_arm(DSPConfig(max_angular_speed_rps=0.1), ARM)
    with pytest.raises(ValueError, match="max_linear_speed_mps must be positive"):
        DSPConfig(max_linear_speed_mps=-0.1)


def test_emergency_stop_brakes_at_the_emergency_deceleration_along_the_path():
    sim = make_sim()
    run(sim, twist_command((0.15, -0.05, 0.02), (0.0, 0.0, 0.1)), 80)
    v0 = np.linalg.norm(sim.ee_twist_base()[:3])
    direction = sim.ee_twist_base()[:3] / v0
    sim.dsp.submit(m.RobotCommand(header=m.Header(), mode=m.CommandMode.EMERGENCY_STOP))
    speeds, directions = [], []
    for _ in range(40):
        sim.step_cycle()
        v = sim.ee_twist_base()[:3]
        speeds.append(np.linalg.norm(v))
        if speeds[-1] > 0.01:
            directions.append(v / speeds[-1])
    stopped = next(i for i, s in enumerate(speeds) if s < 1e-3)
    a_stop = sim.dsp.config.emergency_linear_decel_mps2
    assert (stopped + 1) * sim.dsp.config.cycle_s <= v0 / a_stop + 0.03
    assert (stopped + 1) * sim.dsp.config.cycle_s < v0 / 0.64  # faster than a normal stop
    assert min(float(d @ direction) for d in directions) > 0.98  # it brakes along its path
    assert sim.dsp.status.emergency_stop
    # a new motion command after the e-stop moves the arm again
    run(sim, twist_command((0.05, 0, 0), (0, 0, 0)), 40)
    assert sim.ee_twist_base()[0] == pytest.approx(0.05, rel=0.02) and not sim.dsp.status.emergency_stop


# ------------------------------------------------------------------------------------------ the dead-band
def dsp_speed(command, band: DeadBand) -> np.ndarray:
    """The end-effector twist (base) the DSP's first cycle asks of the arm at rest at home for ``command``."""
    dsp = KinovaDSP(DSPConfig(dead_band=band), ArmKinematics(ARM))
    dsp.submit(command)
    dq = dsp.cycle(JointReading(q=ARM.home.copy(), dq=np.zeros(7), tau=np.zeros(7)))
    return dsp.kin.jacobian_base(ARM.home) @ dq, dsp.status.active_limits


@pytest.mark.parametrize("fraction", [0.1, 0.5, 0.9])
def test_a_cartesian_command_below_the_dead_band_creeps_or_stops(fraction):
    """Below the dead-band the arm creeps at (v/v_d)·v, or with a hard dead-band does not move; at or above it
    the command is executed as it is. Linear and angular parts each have their own threshold."""
    band = DeadBand(linear_mps=0.002, angular_rps=0.01)
    v = 0.002 * fraction
    twist, limits = dsp_speed(twist_command((v, 0.0, 0.0), (0.0, 0.0, 0.0)), band)
    assert np.linalg.norm(twist[:3]) == pytest.approx(v * fraction, rel=1e-3) and "dead_band" in limits
    twist, _ = dsp_speed(twist_command((v, 0.0, 0.0), (0.0, 0.0, 0.0)), DeadBand(linear_mps=0.002, shape="hard"))
    assert np.allclose(twist, 0.0)
    twist, limits = dsp_speed(twist_command((0.0, 0.0, 0.0), (0.0, 0.0, 0.01 * fraction)), band)
    assert np.linalg.norm(twist[3:]) == pytest.approx(0.01 * fraction**2, rel=1e-2) and "dead_band" in limits
    # a slow linear part rides along with an angular part above its dead-band: the whole command moves
    twist, limits = dsp_speed(twist_command((v, 0.0, 0.0), (0.0, 0.0, 0.02)), band)
    assert np.linalg.norm(twist[:3]) == pytest.approx(v, rel=1e-2) and "dead_band" not in limits


def test_a_joint_command_is_judged_by_the_end_effector_motion_it_asks():
    band = DeadBand(linear_mps=0.002, angular_rps=0.01)
    J = ArmKinematics(ARM).jacobian_base(ARM.home)
    slow = np.linalg.pinv(J) @ np.array([0.001, 0.0, 0.0, 0.0, 0.0, 0.0])
    twist, limits = dsp_speed(joint_command(slow), band)
    assert np.linalg.norm(twist[:3]) == pytest.approx(0.0005, rel=1e-2) and "dead_band" in limits
    twist, limits = dsp_speed(joint_command(4 * slow), band)
    assert np.linalg.norm(twist[:3]) == pytest.approx(0.004, rel=1e-2) and "dead_band" not in limits
    twist, _ = dsp_speed(joint_command(slow), DeadBand(linear_mps=0.0, angular_rps=0.0))
    assert np.linalg.norm(twist[:3]) == pytest.approx(0.001, rel=1e-2)


def test_the_dsp_declares_the_limits_it_applies():
    dsp = KinovaDSP(DSPConfig(max_linear_speed_mps=0.15), ArmKinematics(ARM))
    limits = dsp.motion_limits()
    assert limits.linear_speed_mps == 0.15 and limits.angular_speed_rps == ARM.max_angular_speed_rps
    assert np.allclose(limits.joint_speed_rps, ARM.max_speed)
    dsp.set_max_velocities(linear_mps=0.1, angular_rps=0.5)
    assert (dsp.motion_limits().linear_speed_mps, dsp.motion_limits().angular_speed_rps) == (0.1, 0.5)
    with pytest.raises(ValueError, match="dead_band"):
        DeadBand(linear_mps=-1.0)


def test_a_command_to_motion_delay_holds_velocity_commands_and_never_a_stop():
    """command_delay_cycles: a velocity command moves the arm that many cycles later than the next one; a stop acts
    at once and drops the commands still on their way."""
    reading = JointReading(q=ARM.home.copy(), dq=np.zeros(7), tau=np.zeros(7))
    for delay in (0, 3):
        dsp = KinovaDSP(DSPConfig(command_delay_cycles=delay, dead_band=DeadBand(linear_mps=0, angular_rps=0)),
                        ArmKinematics(ARM))
        moving = []
        for cycle in range(8):
            dsp.submit(twist_command((0.05, 0.0, 0.0), (0.0, 0.0, 0.0)))
            moving.append(bool(np.any(dsp.cycle(reading))))
        assert moving == [False] * delay + [True] * (8 - delay)
    dsp = KinovaDSP(DSPConfig(command_delay_cycles=3), ArmKinematics(ARM))
    dsp.submit(twist_command((0.05, 0.0, 0.0), (0.0, 0.0, 0.0)))
    dsp.submit(m.RobotCommand(header=m.Header(), mode=m.CommandMode.STOP))
    assert not any(np.any(dsp.cycle(reading)) for _ in range(6))
    with pytest.raises(ValueError, match="command_delay_cycles"):
        DSPConfig(command_delay_cycles=-1)
