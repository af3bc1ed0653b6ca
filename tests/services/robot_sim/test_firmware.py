"""The emulated actuators as their data sheets give them (services/model/actuators.yaml): what a motor can give,
where friction acts, what the torque sensors read."""
import numpy as np
import pytest

from services.model.arm import load_arm
from services.model.kinematics import ArmKinematics
from services.robot.hardware import JointTargets
from services.robot_sim.firmware import GOES_ON_PAST_SEGMENT_S
from services.robot_sim.hardware import SimulatedHardware
from services.robot_sim.sim import Simulation
from services.runtime.metrics import Counters


def in_torque_mode(name: str):
    arm = load_arm(name)
    counters = Counters()
    sim = Simulation(render=False, arm=arm, counters=counters)
    hardware = SimulatedHardware(sim)
    start = reading = hardware.read()
    for _ in range(100):  # 0.2 s holding where it starts: the motors carry the arm's weight
        reading = hardware.exchange(JointTargets(q=start.q))
    hardware.enter_torque_mode(ArmKinematics(arm).gravity(reading.q))
    return arm, sim, hardware, counters, reading


@pytest.mark.parametrize("name", ["j2s7s300", "j2n6s300"])
def test_a_torque_demand_above_the_peak_is_held_at_the_peak_and_along_the_torque_speed_line(name):
    """Every joint asked for three times its peak, in torque mode: no motor gives more than its actuator's peak
    (the data sheet's software limitation), and once turning, no more than the torque-speed line allows in the
    direction it turns (stall torque falling to 0 at the no-load speed); the firmware counts the limited steps."""
    arm, sim, hardware, counters, reading = in_torque_mode(name)
    peak = np.array([j.peak_torque_nm for j in arm.joints])
    stall = np.array([j.spec.stall_torque_nm for j in arm.joints])
    no_load = np.array([j.spec.no_load_speed for j in arm.joints])
    demand = 3.0 * peak * np.where(np.arange(arm.n_joints) % 2 == 0, 1.0, -1.0)
    applied, speeds = [], []
    for _ in range(40):  # 80 ms: the wrist joints reach a fair share of their no-load speed
        reading = hardware.exchange(JointTargets(q=reading.q, torques=demand))
        applied.append(np.abs(sim.firmware.applied_torque_nm()))
        speeds.append(np.abs(reading.dq))
    applied, speeds = np.array(applied), np.array(speeds)
    assert np.all(applied <= peak + 1e-9)
    assert np.any(np.isclose(applied, peak))  # held at the peak, not below it
    along_line = np.maximum(stall * (1.0 - speeds / no_load), 0.0)
    assert np.all(applied <= np.maximum(np.minimum(along_line, peak), 0.0) + 0.05 * peak)  # a cycle's lag
    assert counters.get("torque.limited_ms") > 0


@pytest.mark.parametrize("name", ["j2s7s300", "j2n6s300"])
def test_the_motor_limit_is_the_torque_speed_line_to_the_bit_around_where_it_crosses_the_peak(name):
    """apply skips computing the torque-speed line while every joint is slower than where the line crosses the peak
    (less a margin): at speeds on both sides of that crossing, down to the last representable speed below it, the
    torque given to a joint turning the way it is pushed is exactly the line's, capped at the peak."""
    arm, sim, hardware, _, reading = in_torque_mode(name)
    firmware, n = sim.firmware, arm.n_joints
    peak = np.array([j.peak_torque_nm for j in arm.joints])
    stall = np.array([j.spec.stall_torque_nm for j in arm.joints])
    no_load = np.array([j.spec.no_load_speed for j in arm.joints])
    direction = np.where(np.arange(n) % 2 == 0, 1.0, -1.0)
    hardware.set_gravity_compensation(False)  # every joint then asks for exactly its peak (the clamped demand)
    hardware.exchange(JointTargets(q=reading.q, torques=3.0 * peak * direction))
    crossing = no_load * (1.0 - peak / stall)
    assert np.all(crossing > 0)  # these actuators' stall torque is above their peak
    near = [crossing * (1.0 + sign * 10.0**-k) for k in range(4, 16) for sign in (-1.0, 1.0)]
    speeds = [np.zeros(n), 0.5 * crossing, *near, np.nextafter(crossing, 0.0), crossing,
              np.nextafter(crossing, np.inf), 0.5 * (crossing + no_load), no_load]
    for speed in speeds:
        sim.data.qvel[:n] = direction * speed
        firmware.apply(sim.time_ns * 1e-9)
        line = np.minimum(peak, np.maximum(stall * (1.0 - np.abs(sim.data.qvel[:n]) / no_load), 0.0))
        assert np.array_equal(sim.data.ctrl[:n], direction * line), speed / crossing


@pytest.mark.parametrize("name", ["j2s7s300", "j2n6s300"])
def test_friction_acts_in_torque_mode_only(name):
    """The joints' Coulomb friction (the description's emulation section) is in the physics while the actuators
    are in torque mode; in position mode their own position loop rejects it."""
    arm, sim, hardware, _, reading = in_torque_mode(name)
    hardware.exchange(JointTargets(q=reading.q, torques=np.zeros(arm.n_joints)))
    assert sim.model.dof_frictionloss[: arm.n_joints] == pytest.approx(arm.true_friction_nm)
    assert np.all(arm.true_friction_nm > 0)
    hardware.leave_torque_mode()
    hardware.exchange(JointTargets(q=reading.q))
    assert not sim.model.dof_frictionloss[: arm.n_joints].any()


def test_the_torque_sensors_read_a_bias_and_noise_until_zeroed():
    """The sensors read the applied torque plus a bias within the data sheet's drift (±0.3 N·m) and noise of its
    precision (±0.4 N·m as 2σ); SetTorqueZero takes the bias, with whatever load the joint carries, out."""
    arm = load_arm("j2n6s300")
    sim = Simulation(render=False, arm=arm)
    firmware = sim.firmware
    errors = np.array([firmware.sensed_torque_nm() - firmware.applied_torque_nm() for _ in range(2000)])
    bias, noise = errors.mean(axis=0), errors.std(axis=0)
    assert np.all(np.abs(bias) <= 0.3 + 0.02) and np.any(np.abs(bias) > 0.02)
    assert noise == pytest.approx(np.full(arm.n_joints, 0.2), rel=0.1)
    firmware.zero_torque(5)
    after = np.array([firmware.sensed_torque_nm()[5] for _ in range(2000)])
    assert abs(after.mean()) < 0.03  # the joint reads 0 where it stands (load and bias taken as zero)


def test_a_joint_past_its_range_faults_its_actuator_once_and_a_continuous_joint_never():
    """The j2n6s300's joint 2 put past its upper limit and joint 3 below its lower one, joint 1 (continuous) turned
    three times round: at the next boundary actuators 2 and 3 latch a position-limit fault, reported once each in
    actuator order; actuator 1 goes on; the boundary after reports nothing new."""
    from protocol import rs485 as r

    arm = load_arm("j2n6s300")
    counters = Counters()
    sim = Simulation(render=False, arm=arm, counters=counters)
    firmware = sim.firmware
    lower, upper = arm.model_limits()
    assert np.isinf(lower[0]) and np.isfinite(lower[1]) and np.isfinite(lower[2])
    sim.data.qpos[0] += 6 * np.pi
    sim.data.qpos[1] = upper[1] + 0.01
    sim.data.qpos[2] = lower[2] - 0.01
    for i in range(arm.n_joints):
        firmware.command(i, firmware.position_deg(i), 0.0)
    firmware.begin_cycle(1.0)
    faults = [a.fault for a in firmware.actuators]
    assert faults[1] == faults[2] == r.ActuatorError.POSITION_LIMIT
    assert all(f == r.ActuatorError.NONE for i, f in enumerate(faults) if i not in (1, 2))
    addresses = [a.address for a in firmware.actuators]
    assert firmware.reports == [(addresses[1], r.ActuatorError.POSITION_LIMIT),
                                (addresses[2], r.ActuatorError.POSITION_LIMIT)]
    assert counters.snapshot().get("faults.position_limit") == 2
    firmware.reports.clear()
    firmware.begin_cycle(1.002)
    assert firmware.reports == [] and counters.snapshot().get("faults.position_limit") == 2


@pytest.mark.parametrize("period_ms", [2.0, 10 / 3, 5.0])
def test_a_host_on_a_slower_bus_moves_the_joints_as_smoothly_as_one_on_a_2_ms_bus(period_ms):
    """The actuators keep their own 2 ms cycle and spread each target over their host's period from when it
    arrived (set_host_period, host_lead_s): a host every 3.33 or 5 ms, its targets taken on the 2 ms boundary after
    they arrive, moves a joint at its rate, at a steady pace (taken from the boundary, a 3.33 ms host's segments
    would start up to 2 ms late and the pace swing ±40 %), with no cycle of the actuators counted missed."""
    arm = load_arm("j2s7s300")
    sim = Simulation(render=False, arm=arm)
    firmware = sim.firmware
    period_s = period_ms / 1e3
    firmware.set_host_period(period_s)
    rate_dps = 20.0
    start = firmware.reference(0.0)[0].copy()
    sent, references = 0, []
    for _ in range(250):  # 0.5 s of the arm's time
        now_s = sim.time_ns * 1e-9
        arrived_s = None
        while sent * period_s <= now_s + 1e-9:  # the host's batches that arrived since the last boundary
            arrived_s = sent * period_s
            sent += 1
            firmware.command_all(start + rate_dps * sent * period_s, np.zeros(arm.n_joints))
        firmware.host_lead_s = now_s - arrived_s if arrived_s is not None else 0.0
        sim.cycle()
        references.append(firmware.reference(sim.time_ns * 1e-9)[0][0])
    assert firmware.counters.get("frames.missed") == 0
    pace = np.diff(references[50:]) / 2e-3  # past the start's ramp
    assert np.mean(pace) == pytest.approx(rate_dps, rel=0.01)
    assert np.all(np.abs(pace - rate_dps) < 0.05 * rate_dps), (pace.min(), pace.max())


@pytest.mark.parametrize("period_ms", [10 / 3, 5.0])
def test_a_slower_hosts_late_batch_bunched_with_the_next_never_moves_the_joints_faster_than_its_targets(period_ms):
    """A slower host's batch late by most of its period arrives just before the next (the host's wake-up, or the
    link, held it): the actuators take one of its cycles per 2 ms boundary (ArmOnBus) and the firmware carries the
    rest of a segment cut short into the next, so the joints never go faster than the host's targets. Cut short,
    each bunch made more than one period's motion in one: up to twice the rate (behind a host slowed to 0.8 of a
    core, the end effector measured 37 % over its limit and safety stopped the arm)."""
    from services.robot_sim.arm_on_bus import HostGrid

    arm = load_arm("j2s7s300")
    sim = Simulation(render=False, arm=arm)
    firmware = sim.firmware
    period_s = period_ms / 1e3
    firmware.set_host_period(period_s)
    grid, rng = HostGrid(period_s), np.random.default_rng(3)
    rate_dps = 20.0
    start = firmware.reference(0.0)[0].copy()
    n_batches = 150
    late = rng.uniform(0.0, 0.5e-3, n_batches)
    late[rng.choice(np.arange(10, n_batches - 5), 12, replace=False)] = 0.9 * period_s  # bunched with the next
    arrivals = period_s * np.arange(n_batches) + late
    taken, references = 0, []
    while sim.time_ns * 1e-9 < arrivals[-1] + 0.02:
        now_s = sim.time_ns * 1e-9
        if taken < n_batches and arrivals[taken] <= now_s + 1e-9:  # one host cycle per boundary, the oldest
            firmware.command_all(start + rate_dps * (taken + 1) * period_s, np.zeros(arm.n_joints))
            firmware.host_lead_s = grid.lead(now_s, arrivals[taken])
            taken += 1
        else:
            firmware.host_lead_s = 0.0
        sim.cycle()
        references.append(firmware.reference(sim.time_ns * 1e-9)[0][0])
    pace = np.diff(references[5:]) / 2e-3  # past the start's ramp
    assert pace.max() < 1.1 * rate_dps, pace.max()  # without the carry: 2.7 times the rate
    last_target = start[0] + rate_dps * n_batches * period_s  # reached (and gone on past it as after any target)
    assert last_target - 1e-6 <= references[-1] <= last_target + 1.01 * rate_dps * GOES_ON_PAST_SEGMENT_S


def test_the_host_grid_follows_a_slower_hosts_period_through_its_jitter_and_jumps_after_a_pause():
    from services.robot_sim.arm_on_bus import HostGrid

    period = 10e-3 / 3
    grid, rng = HostGrid(period), np.random.default_rng(7)
    true_due = 1.0 + period * np.arange(600)
    arrived = true_due + rng.uniform(0.0, 0.8e-3, len(true_due))  # the host's wake-ups and the transport
    arrived[400:] += 0.05  # a 50 ms pause: the grid moves
    for k, t in enumerate(arrived):
        boundary = 2e-3 * np.ceil(t / 2e-3)
        lead = grid.lead(boundary, t)
        assert 0.0 <= lead <= 2e-3
        if 100 <= k < 400 or k >= 500:  # settled: on the true grid, late by the jitter's mean
            assert abs(grid.due - (true_due[k] + 0.4e-3 + (0.05 if k >= 400 else 0.0))) < 0.3e-3, k
