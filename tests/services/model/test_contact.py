"""The contact monitor's momentum observer and thresholds: on exact rigid-body dynamics (Pinocchio's own forward
dynamics, a known external torque), on white sensor noise, and on the emulated arm (MuJoCo, its torque sensors'
bias and noise, its hand heavier than described) moving at assistive speeds and pushed on a link."""
import math

import mujoco
import numpy as np
import pinocchio as pin
import pytest

from services.model.arm import load_arm
from services.model.contact import (GAIN_TIMES_PERIOD, ContactMonitor, Uncertainty, contact_thresholds,
                                    filtered_noise_sigma, generalized_momentum,
                                    generalized_momentum_by_rnea, isolated_joint, model_error_bound)
from services.model.dynamics import DynamicsModel
from services.model.kinematics import ArmKinematics
from services.robot.core import RobotCore
from services.robot.dsp import DSPConfig, KinovaDSP
from services.robot.hardware import CYCLES_PER_DSP
from services.robot_sim import scene as sc
from services.robot_sim.hardware import SimulatedHardware
from services.robot_sim.sim import Simulation
from tests.grasping import command

ARMS = ["j2n6s300", "j2s7s300"]


def exact_arm(arm, tau_ext, seconds, period_s, start_q=None):
    """The description's own dynamics integrated finely (Pinocchio's ABA, 0.1 ms), the joints held by a PD about
    home plus gravity (from ``start_q``), a constant ``tau_ext`` from the first sample on; the readings at
    ``period_s``, each with the joint torque at its instant."""
    dynamics = DynamicsModel(arm, rotor_inertia=True, friction=True)
    model, data = dynamics.model, dynamics.data
    q = arm.home.copy() if start_q is None else start_q.copy()
    dq = np.zeros(arm.n_joints)
    h, per_sample = 1e-4, int(round(period_s / 1e-4))

    def torque():
        return pin.computeGeneralizedGravity(model, data, q) + 40.0 * (arm.home - q) - 4.0 * dq

    readings = []
    for k in range(int(round(seconds / period_s))):
        readings.append((q.copy(), dq.copy(), torque(), k * period_s))
        for _ in range(per_sample):
            ddq = pin.aba(model, data, q, dq, torque() - dynamics.friction * dq + tau_ext)
            dq = dq + h * ddq
            q = q + h * dq
    return readings


@pytest.mark.parametrize("period_s", [0.002, 0.01])
def test_on_exact_dynamics_the_residual_follows_the_external_torque_as_a_first_order_filter(period_s):
    arm = load_arm("j2n6s300")
    tau_ext = np.array([0.0, 3.0, -2.0, 0.0, 1.0, 0.0])
    monitor = ContactMonitor(arm, period_s)
    residuals = [monitor.update(*r).residual for r in exact_arm(arm, tau_ext, 0.2, period_s)]
    # ṙ = K_O (τ_ext − r): n samples after the step (it acts from the first sample on) (1 − K_O·Δt)ⁿ of it is left
    for n in (2, 5, 10):
        left = (1.0 - GAIN_TIMES_PERIOD) ** n
        assert np.allclose(residuals[n], tau_ext * (1.0 - left), atol=0.05 + 0.02 * np.abs(tau_ext).max()), n
    assert np.allclose(residuals[-1], tau_ext, atol=0.02)
    # with no external torque it stays near zero while the PD swings the arm about home from 0.2 rad off (8 N·m at
    # the start: far harder than an assistive motion): what is left is the trapezoid's error over a sample
    still = ContactMonitor(arm, period_s)
    moving = exact_arm(arm, np.zeros(arm.n_joints), 0.5, period_s, start_q=arm.home + 0.2)
    assert max(np.abs(still.update(*r).residual).max() for r in moving) < (0.02 if period_s < 0.005 else 0.25)


def test_white_sensor_noise_shows_in_the_residual_as_the_filter_passes_it():
    arm = load_arm("j2s7s300")
    monitor = ContactMonitor(arm, 0.002)
    dynamics = DynamicsModel(arm, rotor_inertia=True)
    g = dynamics.gravity(arm.home)
    rng = np.random.default_rng(7)
    sigma = 0.2
    residuals = np.array([monitor.update(arm.home, np.zeros(arm.n_joints), g + sigma * rng.standard_normal(arm.n_joints),
                                         k * 0.002).residual for k in range(20000)])[100:]
    expected = filtered_noise_sigma(np.array([sigma]), GAIN_TIMES_PERIOD)[0]
    assert np.allclose(residuals.std(axis=0), expected, rtol=0.05)
    assert np.abs(residuals).max() < contact_thresholds(arm).noise_nm.min()  # 6σ: never crossed in 40 s


def test_the_thresholds_add_what_the_sources_give_and_grow_with_the_uncertainty():
    arm = load_arm("j2n6s300")
    terms = contact_thresholds(arm)
    assert np.allclose(terms.drift_nm, 0.3)  # the sheets' ±0.3 N·m
    assert np.allclose(terms.noise_nm, 6.0 * 0.2 * 0.5)  # σ·sqrt(K_O·Δt / 2)
    assert np.allclose(terms.total_nm, terms.drift_nm + terms.noise_nm + terms.model_nm + terms.friction_nm)
    # gravity does not act on the vertical first joint; the shoulder carries the most of the hand's error
    assert int(np.argmax(terms.model_nm)) == 1
    heavier = model_error_bound(arm, Uncertainty(hand_mass_fraction=0.8))
    with_payload = model_error_bound(arm, Uncertainty(payload_kg=0.5))
    assert np.all(heavier[:5] > terms.model_nm[:5]) and np.all(with_payload[1:3] > terms.model_nm[1:3])
    assert np.array_equal(model_error_bound(arm, Uncertainty()), terms.model_nm)  # seeded


def test_the_momentum_by_inverse_dynamics_is_the_momentum_by_the_mass_matrix():
    arm = load_arm("j2s7s300")
    dynamics = DynamicsModel(arm, rotor_inertia=True)
    rng = np.random.default_rng(3)
    for _ in range(20):
        q, dq = arm.home + rng.uniform(-1, 1, arm.n_joints), rng.uniform(-1, 1, arm.n_joints)
        at_rest = pin.rnea(dynamics.model, dynamics.data, q, np.zeros(arm.n_joints), dq).copy()
        assert np.allclose(generalized_momentum_by_rnea(at_rest, dynamics.gravity(q)),
                           generalized_momentum(dynamics.mass(q), dq), atol=1e-12)


def test_isolation_names_the_most_distal_joint_out_of_its_band():
    threshold = np.ones(6)
    assert isolated_joint(np.zeros(6), threshold) == 0
    assert isolated_joint(np.array([3.0, -2.0, 0.5, 0.0, 0.0, 0.0]), threshold) == 2
    assert isolated_joint(np.array([0.0, 0.0, 0.0, 0.0, -1.01, 0.0]), threshold) == 5


def test_a_gap_in_the_readings_restarts_the_observer_rather_than_integrating_it():
    arm = load_arm("j2n6s300")
    monitor = ContactMonitor(arm, 0.002)
    readings = exact_arm(arm, np.zeros(arm.n_joints), 0.1, 0.002, start_q=arm.home + 0.2)
    for q, dq, tau, t in readings[:20]:
        monitor.update(q, dq, tau, t)
    for q, dq, tau, t in readings[40:]:  # 40 ms missing, then a reading stamped earlier than the last
        assert np.abs(monitor.update(q, dq, tau, t).residual).max() < 0.02
    monitor.update(*readings[10])
    assert monitor.restarts == 2
    with pytest.raises(ValueError, match="within"):
        ContactMonitor(arm, 0.002, gain_times_period=2.0)
    with pytest.raises(ValueError, match="positive"):
        ContactMonitor(arm, 0.0)


def emulated_arm(arm_name, moves, push=None, seed=0):
    """The emulated arm (robot_sim's physics and actuators, its torque sensors' bias and noise) driven as the robot
    node drives it: ``moves`` (Cartesian velocity, seconds) one after another, then ``push`` (link index, force in
    the base frame, N) on a link's centre of mass for 0.3 s from rest. Each bus cycle's reading goes to a monitor at
    the bus rate, each fifth to one at the DSP's 100 Hz; their samples, and the push's true joint torque."""
    arm = load_arm(arm_name)
    sim = Simulation(sc.SceneConfig(), arm=arm, render=False)
    hardware = SimulatedHardware(sim)
    core = RobotCore(KinovaDSP(DSPConfig(), ArmKinematics(arm)), hardware.read())
    monitors = {"bus": ContactMonitor(arm, 0.002), "dsp": ContactMonitor(arm, 0.01)}
    out = {"bus": [], "dsp": [], "pushed_from": None, "tau_ext": None, "arm": arm}
    k = 0

    def cycles(order, seconds):
        nonlocal k
        for _ in range(int(round(seconds / 0.002))):
            reading = hardware.exchange(core.targets())
            core.observe(reading)
            out["bus"].append(monitors["bus"].update(reading.q, reading.dq, reading.tau, reading.stamp_ns * 1e-9))
            if k % CYCLES_PER_DSP == 0:
                out["dsp"].append(monitors["dsp"].update(reading.q, reading.dq, reading.tau,
                                                         reading.stamp_ns * 1e-9))
            if k % CYCLES_PER_DSP == CYCLES_PER_DSP - 1:
                core.dsp_cycle(order)
            k += 1

    for linear, seconds in moves:
        cycles(command(arm, linear, close=False), seconds)
    if push is not None:
        link, force = push
        cycles(command(arm, None, close=False), 0.3)  # at rest
        body = mujoco.mj_name2id(sim.model, mujoco.mjtObj.mjOBJ_BODY, arm.link_names[link - 1])
        out["pushed_from"] = {name: len(samples) for name, samples in out.items() if name in ("bus", "dsp")}
        sim.data.xfrc_applied[body, :3] = force
        jacobian = np.zeros((3, sim.model.nv))
        mujoco.mj_jacBodyCom(sim.model, sim.data, jacobian, None, body)
        out["tau_ext"] = (jacobian.T @ np.asarray(force))[:arm.n_joints]
        cycles(command(arm, None, close=False), 0.3)
        sim.data.xfrc_applied[body, :3] = 0.0
    return out


@pytest.mark.parametrize("arm_name", ARMS)
def test_moving_at_assistive_speeds_the_emulated_arm_stays_within_its_thresholds(arm_name):
    """Seeded directions at 0.05-0.20 m/s, starts and stops between them: no sample of either path is a contact
    (the hand 30 % heavier than described, the sensors' bias and noise), with a margin."""
    rng = np.random.default_rng(sum(map(ord, arm_name)))
    moves = []
    for _ in range(4):
        direction = rng.normal(size=3)
        moves += [(tuple(rng.uniform(0.05, 0.20) * direction / np.linalg.norm(direction)), 0.8), (None, 0.3)]
    out = emulated_arm(arm_name, moves)
    for path in ("bus", "dsp"):
        ratios = [s.ratio for s in out[path]]
        assert not any(s.in_contact for s in out[path]), path
        assert max(ratios) < 0.8, (path, max(ratios))


@pytest.mark.parametrize("arm_name", ARMS)
def test_a_push_on_a_link_is_detected_within_two_samples_of_crossing_and_the_residual_is_its_joint_torque(arm_name):
    arm = load_arm(arm_name)
    link = arm.n_joints - 2  # the forearm's wrist link: every joint up to it feels a sideways push
    out = emulated_arm(arm_name, [], push=(link, (0.0, 40.0, -40.0)))
    tau_ext = out["tau_ext"]
    for path, period in (("bus", 0.002), ("dsp", 0.01)):
        samples = out[path][out["pushed_from"][path]:]
        detected = next(i for i, s in enumerate(samples) if s.in_contact)
        # the first sample whose residual, as the filter passes the step, can exceed the threshold: the true
        # torque's ratio to the threshold, reached within two samples of it
        threshold = ContactMonitor(arm, period).threshold
        crossing = next(n for n in range(1, 50)
                        if np.any(np.abs(tau_ext) * (1.0 - (1.0 - GAIN_TIMES_PERIOD) ** n) > threshold))
        assert detected <= crossing + 2, (path, detected, crossing)
        assert samples[detected].joint >= 1
        # at steady state the residual is the push's joint torque within the threshold's allowance
        settled = samples[-1].residual
        assert np.all(np.abs(settled - tau_ext) < threshold), (path, settled.round(2), tau_ext.round(2))
