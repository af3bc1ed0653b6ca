"""Seed 003's computed-torque control over the RS-485 link, in torque mode, against robot_sim's actuators."""
import time

import numpy as np
import pytest

from services.controller.computed_torque import ComputedTorque, cubic
from services.robot_gateway.link import expected_torques_physical
from services.stack import simulated_link
from services.model.arm import load_arm

ARM = load_arm("j2s7s300")


def test_cubic_reference_matches_eq_5_1_and_its_derivatives():
    q0, qf, tf = np.zeros(7), np.arange(7.0), 2.0
    assert cubic(q0, qf, tf, 0.0)[0] == pytest.approx(q0) and cubic(q0, qf, tf, tf)[0] == pytest.approx(qf)
    assert cubic(q0, qf, tf, 0.0)[1] == pytest.approx(0) and cubic(q0, qf, tf, tf)[1] == pytest.approx(0)
    h = 1e-6
    for t in (0.3, 1.0, 1.7):
        q_m, dq_m, _ = cubic(q0, qf, tf, t - h)
        q_p, dq_p, _ = cubic(q0, qf, tf, t + h)
        _, dq, ddq = cubic(q0, qf, tf, t)
        assert (q_p - q_m) / (2 * h) == pytest.approx(dq, abs=1e-6)
        assert (dq_p - dq_m) / (2 * h) == pytest.approx(ddq, abs=1e-5)


def test_torque_is_inverse_dynamics_of_the_commanded_acceleration(rng):
    ct = ComputedTorque(ARM, actuator_gravity_compensation=False)
    q, dq = ARM.home + rng.normal(scale=0.1, size=7), rng.normal(scale=0.2, size=7)
    q_d, dq_d, ddq_d = q + 0.01, dq - 0.02, rng.normal(size=7)
    tau = ct.torque(q, dq, q_d, dq_d, ddq_d)
    w = ddq_d + ct.kp * (q_d - q) + ct.kd * (dq_d - dq)
    data = ct.model.createData()
    # an independent route: ABA's forward dynamics of that torque gives back the commanded acceleration, with the
    # rotors' inertia and friction as MuJoCo simulates them
    import mujoco

    model = ARM.load_mujoco()
    d = mujoco.MjData(model)
    d.qpos[:], d.qvel[:] = q, dq
    d.qfrc_applied[:] = tau
    mujoco.mj_forward(model, d)
    assert d.qacc == pytest.approx(w, abs=1e-6)
    del data


def test_computed_torque_tracks_the_cubic_within_one_degree_over_the_bus():
    with simulated_link(settle_s=0.3) as (runner, link):
        with runner.lock:
            q0 = runner.sim.q
        link.switch_to_torque(expected_torques_physical(ARM, q0))
        qf = q0 + np.radians([10.0, -8.0, 12.0, 10.0, -15.0, 10.0, 20.0])
        tf = 2.0
        ct = ComputedTorque(ARM)
        reading = link.command(ARM.model_to_physical_deg(q0), np.zeros(7))
        errors = []
        start = time.monotonic()
        while (t := time.monotonic() - start) < tf + 0.5:
            q = ARM.physical_deg_to_model(reading.position_deg)
            dq = ARM.physical_rate_to_model(reading.velocity_dps)
            q_d, dq_d, ddq_d = cubic(q0, qf, tf, t)
            errors.append(np.degrees(np.abs(q_d - q)).max())
            tau = ct.torque(q, dq, q_d, dq_d, ddq_d)
            reading = link.command(reading.position_deg, ARM.sign * tau)  # safety reference: where it is
        link.switch_to_position()
    print(f"computed torque over the bus: max joint error {max(errors):.3f}° over {len(errors)} cycles")
    assert len(errors) > 500  # at least one exchange per 2 ms cycle of the arm for 2.5 s
    assert max(errors) < 1.0, f"max joint error {max(errors):.3f}°"
