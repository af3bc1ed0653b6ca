"""Seed 002's sliding-mode law: the level-1 equality, abort, gradient error injection, and the chattering band."""
import math
from pathlib import Path

import numpy as np
import pytest

from services.model import jaco2
from services.runtime.config import PoseConfig
from tests.kinematic_loop import KinematicLoop
from services.controller.law import ConstraintAbort, ServoInput
from services.controller.laws import make_law
from services.controller.smc import GRADIENT_ERROR_SIGNS
from services.robot_sim.scene import CameraConfig
from services.servo import load_scenario, run
from tests.helpers import REPO

T_EC = CameraConfig().camera_in_ee.matrix()
GOAL = np.array([[-0.1666, -0.1666], [0.1666, -0.1666], [0.1666, 0.1666], [-0.1666, 0.1666]])


def hand_input(points, q=None):
    return ServoInput(t_s=1.0, points=np.array(points), depths=np.full(4, 0.4), goal_points=GOAL,
                      goal_depths=np.full(4, 0.2888), q=jaco2.HOME.copy() if q is None else q, camera_in_ee=T_EC)


def test_level_one_equality_on_a_hand_built_case():
    """A feature outside the field of view activates its constraint: the acceleration satisfies the level-1
    equality K∇σᵀ q̈ = −u⁺ exactly (eq. 40), whatever the tracking task asks."""
    law = make_law("smc", fov={"margin": 0.05, "K": 0.1, "u_plus": 2.0}, joint_speed=None, joint_range=None)
    a, b = law.options.fov.semi_axes
    points = [(-0.1, -0.1), (a * 1.01, 0.0), (0.1, 0.1), (-0.1, 0.1)]  # point 1 just outside
    law.step(hand_input(points))
    A1, b1, ddq, active = law.last_level1
    assert [law._names(4)[i] for i in active] == ["fov:1"]
    assert np.allclose(A1 @ ddq, b1) and np.allclose(b1, [-2.0])


def test_fov_gradient_matches_finite_differences():
    tag_in_camera = PoseConfig(xyz=(0.12, 0.0, 0.4), rpy_deg=(180.0, 0.0, 10.0)).matrix()
    T_be = jaco2.dh_forward_kinematics(jaco2.HOME)
    loop = KinematicLoop(make_law("smc"), T_be @ T_EC @ tag_in_camera, T_EC, jaco2.HOME, GOAL, np.full(4, 0.2888))
    law = make_law("smc", joint_speed=None, joint_range=None)
    fov = law.options.fov
    a, b = fov.semi_axes

    def sigmas(q):
        loop.q = q
        pts, _ = loop.observe()
        return np.abs(pts[:, 0] / a) ** fov.exponent + np.abs(pts[:, 1] / b) ** fov.exponent - 1.0

    q = jaco2.HOME.copy()
    loop.q = q
    pts, depths = loop.observe()
    inp = ServoInput(t_s=1.0, points=pts, depths=depths, goal_points=GOAL, goal_depths=np.full(4, 0.2888), q=q,
                     camera_in_ee=T_EC)
    J_c, _, J_base = law._camera_jacobian(q, T_EC)
    Js = law._L(inp) @ J_c
    rows, _, phis, _ = law.constraints(inp, Js, J_base, np.zeros(3), np.zeros(7))
    h = 1e-6
    for k in range(7):
        dq = np.zeros(7)
        dq[k] = h
        fd = (sigmas(q + dq) - sigmas(q - dq)) / (2 * h)
        analytic = np.array([rows[i][k] / fov.K for i in range(4)])
        assert np.allclose(analytic, fd, rtol=1e-4, atol=1e-6)
    assert np.allclose(phis[:4], sigmas(q))  # q̇ = 0: φ = σ


def test_abort_when_active_constraints_exceed_the_freedom():
    law = make_law("smc", joint_speed={"speed_scale": 0.3}, joint_range=None)
    # every joint over its speed, moving the feature (already outside) further out
    law.dq_c = jaco2.MAX_SPEED * 0.3 * 1.01 * np.array([-1, 1, -1, 1, -1, 1, -1])
    a, _ = law.options.fov.semi_axes
    with pytest.raises(ConstraintAbort, match="leave no freedom"):
        law.step(hand_input([(-0.1, -0.1), (a * 1.3, 0.0), (0.1, 0.1), (-0.1, 0.1)]))


def test_gradient_error_injection_changes_the_fov_rows_by_the_pattern():
    a = make_law("smc", joint_speed=None, joint_range=None)
    b = make_law("smc", joint_speed=None, joint_range=None, gradient_error=0.3)
    half = a.options.fov.semi_axes[0] * 1.01
    inp = hand_input([(-0.1, -0.1), (half, 0.0), (0.1, 0.1), (-0.1, 0.1)])
    J_c, _, J_base = a._camera_jacobian(inp.q, T_EC)
    Js = a._L(inp) @ J_c
    rows_a = a.constraints(inp, Js, J_base, np.zeros(3), np.zeros(7))[0]
    rows_b = b.constraints(inp, Js, J_base, np.zeros(3), np.zeros(7))[0]
    for ra, rb in zip(rows_a, rows_b, strict=True):
        assert np.allclose(rb, ra + 0.3 * GRADIENT_ERROR_SIGNS * np.abs(ra))


def test_tracking_gain_is_exponential():
    law = make_law("smc", joint_speed=None, joint_range=None, fov=None)
    out = law.step(hand_input([tuple(p * 0.5) for p in GOAL]))
    norm = np.linalg.norm((np.array([tuple(p * 0.5) for p in GOAL]) - GOAL).reshape(-1))
    assert out.gain == pytest.approx(4.0 * math.exp(-(10.0 / 4.0) * norm))


def test_kinematic_loop_converges_with_constraints_active_within_their_bands():
    T_be = jaco2.dh_forward_kinematics(jaco2.HOME)
    tag = PoseConfig(xyz=(0.06, 0.04, 0.5247), rpy_deg=(172.0, -6.0, 30.0)).matrix()
    law = make_law("smc", joint_speed={"speed_scale": 0.3})
    loop = KinematicLoop(law, T_be @ T_EC @ tag, T_EC, jaco2.HOME, GOAL, np.full(4, 0.2888))
    steps = loop.run(1500, 5e-5)
    assert steps[-1].error_norm < 5e-5
    assert sum(1 for s in steps if s.output.notes["active"] > 0) > 0
    for kind in ("fov", "joint_range", "joint_speed"):
        assert max(s.output.notes[f"max_phi.{kind}"] for s in steps) <= steps[0].output.notes[f"band.{kind}"]


def test_smc_through_mfvs_servo_keeps_phi_within_the_band():
    result = run(load_scenario(REPO / "examples" / "scenarios" / "smc_table2.yaml"))
    assert result.converged, (result.status, result.iterations, result.final_error_norm)
    figures = result.law_figures
    assert figures["active"] >= 1  # constraints did act
    for kind in ("fov", "joint_range", "joint_speed"):
        assert figures[f"max_phi.{kind}"] <= figures[f"band.{kind}"], kind
