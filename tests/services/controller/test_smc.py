"""Muñoz 2018's sliding-mode law: the level-1 equality, abort, gradient error injection, and the chattering band."""
import math

import numpy as np
import pytest

from services.model.frames import PoseConfig
from tests.kinematic_loop import KinematicLoop
from services.controller.law import ConstraintAbort, ServoInput
from services.controller.laws import make_law
from services.controller.smc import GRADIENT_ERROR_SIGNS
from services.robot_sim.scene import CameraConfig
from services.servo.run import run
from services.servo.scenario import load_scenario
from services.model.kinematics import ArmKinematics
from tests.helpers import REPO
from services.model.arm import load_arm

ARM = load_arm("j2s7s300")

T_EC = CameraConfig().camera_in_ee.matrix()
GOAL = np.array([[-0.1666, -0.1666], [0.1666, -0.1666], [0.1666, 0.1666], [-0.1666, 0.1666]])


def hand_input(points, q=None):
    return ServoInput(t_s=1.0, points=np.array(points), depths=np.full(4, 0.4), goal_points=GOAL,
                      goal_depths=np.full(4, 0.2888), q=ARM.home.copy() if q is None else q, camera_in_ee=T_EC)


def test_level_one_equality_on_a_hand_built_case():
    """A feature outside the field of view activates its constraint: the acceleration satisfies the level-1
    equality K∇σᵀ q̈ = −u⁺ exactly (eq. 40), whatever the tracking task asks."""
    law = make_law("smc", None, ArmKinematics(ARM), fov={"margin": 0.05, "K": 0.1, "u_plus": 2.0}, joint_speed=None, joint_range=None)
    a, b = law.options.fov.semi_axes
    points = [(-0.1, -0.1), (a * 1.01, 0.0), (0.1, 0.1), (-0.1, 0.1)]  # point 1 just outside
    law.step(hand_input(points))
    A1, b1, ddq, active = law.last_level1
    assert [law._names(4)[i] for i in active] == ["fov:1"]
    assert np.allclose(A1 @ ddq, b1) and np.allclose(b1, [-2.0])


@pytest.mark.parametrize("form", ["radius", "polynomial"])
def test_fov_gradient_matches_finite_differences(form):
    tag_in_camera = PoseConfig(xyz=(0.12, 0.0, 0.4), rpy_deg=(180.0, 0.0, 10.0)).matrix()
    T_be = ARM.dh_forward_kinematics(ARM.home)
    loop = KinematicLoop(make_law("smc", None, ArmKinematics(ARM)), T_be @ T_EC @ tag_in_camera, T_EC, ARM.home, GOAL, np.full(4, 0.2888))
    law = make_law("smc", None, ArmKinematics(ARM), joint_speed=None, joint_range=None, fov={"form": form})
    fov = law.options.fov
    a, b = fov.semi_axes

    def sigmas(q):
        loop.q = q
        pts, _ = loop.observe()
        h = np.abs(pts[:, 0] / a) ** fov.exponent + np.abs(pts[:, 1] / b) ** fov.exponent
        return h - 1.0 if form == "polynomial" else h ** (1.0 / fov.exponent) - 1.0

    q = ARM.home.copy()
    loop.q = q
    pts, depths = loop.observe()
    inp = ServoInput(t_s=1.0, points=pts, depths=depths, goal_points=GOAL, goal_depths=np.full(4, 0.2888), q=q,
                     camera_in_ee=T_EC)
    J_c, _, J_base = law._camera_jacobian(q, T_EC)
    Js = law._L(inp) @ J_c
    cs = law.constraints(inp, Js, J_base, np.zeros(3), np.zeros(7))
    rows, phis = cs.rows, cs.phis
    h = 1e-6
    for k in range(7):
        dq = np.zeros(7)
        dq[k] = h
        fd = (sigmas(q + dq) - sigmas(q - dq)) / (2 * h)
        analytic = np.array([rows[i][k] / fov.K for i in range(4)])
        assert np.allclose(analytic, fd, rtol=1e-4, atol=1e-6)
    assert np.allclose(phis[:4], sigmas(q))  # q̇ = 0: φ = σ


def test_abort_when_active_constraints_exceed_the_freedom():
    law = make_law("smc", None, ArmKinematics(ARM), joint_speed={"speed_scale": 0.3}, joint_range=None)
    # every joint over its speed, moving the feature (already outside) further out
    law.dq_c = ARM.max_speed * 0.3 * 1.01 * np.array([-1, 1, -1, 1, -1, 1, -1])
    a, _ = law.options.fov.semi_axes
    with pytest.raises(ConstraintAbort, match="leave no freedom"):
        law.step(hand_input([(-0.1, -0.1), (a * 1.3, 0.0), (0.1, 0.1), (-0.1, 0.1)]))


def test_gradient_error_changes_every_row_by_the_pattern_and_leaves_sigma_exact():
    """Eq. 49 on every constraint's gradient (field of view, occlusion, joint range, joint speed, sphere): each
    row becomes row + c_e·signs∘|row|; σ is measured, so it is the same with and without the error."""
    options = dict(joint_speed={"speed_scale": 0.3}, joint_range={"joints_deg": {2: [100, 250]}},
                   spheres=[{"centre": [0.0, -0.4, 0.5], "radius": 0.05}],
                   occlusions=[{"centre": [0.0, 0.0], "semi_axes": [0.05, 0.05]}])
    a = make_law("smc", None, ArmKinematics(ARM), **options)
    b = make_law("smc", None, ArmKinematics(ARM), gradient_error=0.3, **options)
    half = a.options.fov.semi_axes[0] * 1.01
    inp = hand_input([(-0.1, -0.1), (half, 0.0), (0.1, 0.1), (-0.1, 0.1)])
    J_c, _, J_base = a._camera_jacobian(inp.q, T_EC)
    Js = a._L(inp) @ J_c
    dq = np.full(7, 0.05)
    exact = a.constraints(inp, Js, J_base, np.array([0.01, -0.42, 0.5]), dq)
    erroneous = b.constraints(inp, Js, J_base, np.array([0.01, -0.42, 0.5]), dq)
    kinds = {name.split(":")[0] for name in exact.names}
    assert kinds == {"fov", "occlusion", "joint_range", "joint_speed", "sphere"}
    for ra, rb in zip(exact.rows, erroneous.rows, strict=True):
        assert np.allclose(rb, ra + 0.3 * GRADIENT_ERROR_SIGNS * np.abs(ra))
    assert np.array_equal(exact.sigmas, erroneous.sigmas)
    assert not np.allclose(exact.phis, erroneous.phis)


def test_occlusion_sigma_is_positive_inside_and_its_gradient_matches_finite_differences():
    tag_in_camera = PoseConfig(xyz=(0.05, 0.02, 0.4), rpy_deg=(180.0, 0.0, 10.0)).matrix()
    T_be = ARM.dh_forward_kinematics(ARM.home)
    loop = KinematicLoop(make_law("smc", None, ArmKinematics(ARM)), T_be @ T_EC @ tag_in_camera, T_EC, ARM.home, GOAL, np.full(4, 0.2888))
    pts, depths = loop.observe()
    region = {"centre": [float(pts[0, 0]) + 0.01, float(pts[0, 1])], "semi_axes": [0.03, 0.02], "exponent": 4}
    law = make_law("smc", None, ArmKinematics(ARM), fov=None, joint_speed=None, joint_range=None, occlusions=[region])
    inp = ServoInput(t_s=1.0, points=pts, depths=depths, goal_points=GOAL, goal_depths=np.full(4, 0.2888),
                     q=ARM.home.copy(), camera_in_ee=T_EC)
    J_c, _, J_base = law._camera_jacobian(inp.q, T_EC)
    cs = law.constraints(inp, law._L(inp) @ J_c, J_base, np.zeros(3), np.zeros(7))
    assert cs.sigmas[0] > 0 > max(cs.sigmas[1:])  # point 0 inside the region, the others outside

    def sigma0(q):
        loop.q = q
        p, _ = loop.observe()
        r = (np.abs((p[0, 0] - region["centre"][0]) / 0.03) ** 4 + np.abs((p[0, 1] - region["centre"][1]) / 0.02) ** 4)
        return 1.0 - r ** 0.25

    h = 1e-6
    for k in range(7):
        step = np.zeros(7)
        step[k] = h
        fd = (sigma0(ARM.home + step) - sigma0(ARM.home - step)) / (2 * h)
        assert cs.rows[0][k] / 0.1 == pytest.approx(fd, rel=1e-4, abs=1e-6)


def test_a_joints_range_and_speed_active_together_are_one_constraint_not_an_abort():
    """Joint 2 at the end of its range and over its speed, moving toward the limit: the two rows are parallel
    (the paper aborts); the law keeps the one asking the larger deceleration and goes on."""
    lower_deg = float(ARM.model_to_physical_deg(ARM.home)[1]) - 40.0
    law = make_law("smc", None, ArmKinematics(ARM), fov=None, joint_speed={"speed_scale": 0.3},
                   joint_range={"joints_deg": {2: [lower_deg, float(ARM.home_deg[1]) + 0.2]}})
    law.dq_c = np.zeros(7)
    law.dq_c[1] = ARM.sign[1] * ARM.max_speed[1] * 0.3 * 1.05  # toward the upper end, over its speed
    out = law.step(hand_input([tuple(p * 0.9) for p in GOAL]))
    _, _, ddq, active = law.last_level1
    names = [law._names(4)[i] for i in active]
    assert "joint_range:2" in law._names(4) and "joint_speed:2" in law._names(4)
    assert out.notes["active.joint_range"] == 1 and out.notes["active.joint_speed"] == 1
    assert np.sign(ddq[1]) == -np.sign(law.dq_c[1] - law.options.nominal_period_s * ddq[1])  # decelerating
    assert len(names) == 2


def test_look_ahead_activates_a_constraint_before_it_is_crossed():
    """A feature just inside the field of view, heading out fast: φ < 0 now, but this sample's motion would carry
    it past 0 by the next one. The paper's test alone (φ ≥ 0) leaves the constraint inactive and the crossing
    happens; looking ahead, the law activates it now and the predicted φ stays within the band T_s·u⁺."""
    outcome = {}
    for rounds in (0, 3):
        law = make_law("smc", None, ArmKinematics(ARM), joint_speed=None, joint_range=None, lookahead_rounds=rounds,
                       fov={"K": 0.1, "u_plus": 0.3})
        a, _ = law.options.fov.semi_axes
        inp = hand_input([(-0.1, -0.1), (0.97 * a, 0.0), (0.1, 0.1), (-0.1, 0.1)])
        inp.goal_points = GOAL + np.array([0.45, 0.0])  # the task pulls point 1 out of the view
        J_c, _, J_base = law._camera_jacobian(inp.q, T_EC)
        Js = law._L(inp) @ J_c
        row = Js[2]  # ẋ of point 1
        law.dq_c = 0.26 * a * row / float(row @ row)  # σ̇ = ẋ/a = 0.26/s outward: φ = −0.03 + 0.1·0.26 < 0
        cs = law.constraints(inp, Js, J_base, np.zeros(3), law.dq_c)
        assert cs.phis[1] < 0.0 < cs.phis[1] + law.options.nominal_period_s * cs.drifts[1]
        out = law.step(inp)
        ddq = law.last_level1[2]
        predicted = cs.phis[1] + law.options.nominal_period_s * (cs.drifts[1] + cs.rows[1] @ ddq)
        outcome[rounds] = (out.notes["active.fov"], predicted)
    assert outcome[0][0] == 0 and outcome[0][1] > 0.0
    assert outcome[3][0] == 1 and outcome[3][1] <= law.options.nominal_period_s * 0.3


def test_tracking_gain_is_exponential():
    law = make_law("smc", None, ArmKinematics(ARM), joint_speed=None, joint_range=None, fov=None)
    out = law.step(hand_input([tuple(p * 0.5) for p in GOAL]))
    norm = np.linalg.norm((np.array([tuple(p * 0.5) for p in GOAL]) - GOAL).reshape(-1))
    assert out.gain == pytest.approx(4.0 * math.exp(-(10.0 / 4.0) * norm))


def test_kinematic_loop_converges_with_constraints_active_within_their_bands():
    T_be = ARM.dh_forward_kinematics(ARM.home)
    tag = PoseConfig(xyz=(0.06, 0.04, 0.5247), rpy_deg=(172.0, -6.0, 30.0)).matrix()
    law = make_law("smc", None, ArmKinematics(ARM), joint_speed={"speed_scale": 0.3})
    loop = KinematicLoop(law, T_be @ T_EC @ tag, T_EC, ARM.home, GOAL, np.full(4, 0.2888))
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
