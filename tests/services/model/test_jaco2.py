import math

import mujoco
import numpy as np
import pinocchio as pin
import pytest

from services.model import frames, jaco2
from tests.helpers import PinArm, random_q


@pytest.fixture(scope="module")
def mj():
    model = jaco2.load_mujoco()
    return model, mujoco.MjData(model), model.body(jaco2.EE_LINK).id


@pytest.fixture(scope="module")
def arm():
    return PinArm()


def mujoco_pose(mj, q):
    model, data, body = mj
    data.qpos[:] = q
    mujoco.mj_kinematics(model, data)
    return data.xmat[body].reshape(3, 3).copy(), data.xpos[body].copy()


def mujoco_jacobian(mj, q):
    model, data, body = mj
    data.qpos[:] = q
    mujoco.mj_kinematics(model, data)
    mujoco.mj_comPos(model, data)
    jacp, jacr = np.zeros((3, model.nv)), np.zeros((3, model.nv))
    mujoco.mj_jacBody(model, data, jacp, jacr, body)
    return np.vstack([jacp, jacr])


def test_both_loaders_see_seven_joints_in_order(mj, arm):
    model = mj[0]
    assert model.nq == model.nv == 7 and arm.model.nq == arm.model.nv == 7
    assert [model.joint(i).name for i in range(7)] == list(jaco2.JOINT_NAMES)
    assert list(arm.model.names)[1:] == list(jaco2.JOINT_NAMES)


def test_forward_kinematics_agree_to_1e9(mj, arm, rng):
    for _ in range(200):
        q = random_q(rng)
        R_mj, p_mj = mujoco_pose(mj, q)
        R_pin, p_pin = arm.pose(q)
        T_dh = jaco2.dh_forward_kinematics(q)
        assert np.abs(p_mj - p_pin).max() < 1e-9
        assert np.abs(R_mj - R_pin).max() < 1e-9
        assert np.abs(T_dh[:3, 3] - p_pin).max() < 1e-9
        assert np.abs(T_dh[:3, :3] - R_pin).max() < 1e-9


def test_jacobians_agree_to_1e8(mj, arm, rng):
    for _ in range(200):
        q = random_q(rng)
        assert np.abs(mujoco_jacobian(mj, q) - arm.jacobian_base(q)).max() < 1e-8


def test_straight_up_at_the_centre_of_the_ranges(arm):
    q = jaco2.physical_deg_to_model([0, 180, 0, 180, 0, 180, 0])
    R, p = arm.pose(q)
    height = jaco2.D1 + jaco2.STRAIGHT_REACH
    assert p == pytest.approx([0.0, jaco2.E2, height], abs=1e-9)
    assert height == pytest.approx(1.2604, abs=1e-4)


def test_reach_is_about_0_9_m(arm, rng):
    shoulder = np.array([0.0, 0.0, jaco2.D1])
    reaches = [np.linalg.norm(arm.pose(random_q(rng))[1] - shoulder) for _ in range(2000)]
    assert max(reaches) <= jaco2.STRAIGHT_REACH + 1e-9
    # the product sheet's 0.9 m reach is reached with the wrist (0.985 m includes the hand's 0.16 m)
    assert 0.9 <= jaco2.STRAIGHT_REACH <= 1.0
    assert jaco2.STRAIGHT_REACH - jaco2.D7 == pytest.approx(0.825, abs=1e-3)
    q = jaco2.physical_deg_to_model([0, 90, 0, 180, 0, 180, 0])
    assert np.linalg.norm(arm.pose(q)[1] - shoulder) == pytest.approx(jaco2.STRAIGHT_REACH, abs=1e-3)


def test_home_pose_is_plausible(arm):
    q = jaco2.HOME
    R, p = arm.pose(q)
    assert -0.55 < p[1] < -0.35 and abs(p[0]) < 0.05 and 0.4 < p[2] < 0.6  # in front of the base, at 0.5 m
    approach = R[:, 2]
    assert approach[1] < -0.7 and approach[2] < 0  # looking forward and down
    lower, upper = jaco2.model_limits()
    limited = np.isfinite(lower)
    margin = np.minimum(q - lower, upper - q)[limited]
    assert np.degrees(margin).min() >= 40.0
    J = arm.jacobian_base(q)
    sv = np.linalg.svd(J, compute_uv=False)
    assert sv.min() > 0.05  # far from singular
    # the wrist (joint 6) is 40° from its singular straight position
    assert abs(jaco2.HOME_DEG[5] - 180.0) >= 40.0


def test_limits_match_the_reference(mj, arm):
    ref = {2: (47.0, 313.0), 4: (30.0, 330.0), 6: (65.0, 295.0)}
    lower, upper = jaco2.model_limits()
    model = mj[0]
    for i, spec in enumerate(jaco2.JOINTS, start=1):
        if i in ref:
            assert not spec.continuous
            assert (spec.lower_deg, spec.upper_deg) == ref[i]
            assert (lower[i - 1], upper[i - 1]) == pytest.approx(np.radians(ref[i]))
            assert model.jnt_limited[i - 1]
            assert model.jnt_range[i - 1] == pytest.approx(np.radians(ref[i]))
            assert arm.model.lowerPositionLimit[i - 1] == pytest.approx(math.radians(ref[i][0]))
            assert arm.model.upperPositionLimit[i - 1] == pytest.approx(math.radians(ref[i][1]))
        else:
            assert spec.continuous and not model.jnt_limited[i - 1]
            assert np.isinf(lower[i - 1]) and np.isinf(upper[i - 1])
    assert jaco2.MAX_SPEED_DPS.tolist() == [36, 36, 36, 36, 48, 48, 48]
    assert jaco2.MAX_TORQUE.tolist() == [40, 80, 40, 40, 20, 20, 20]
    assert arm.model.velocityLimit == pytest.approx(jaco2.MAX_SPEED)
    assert arm.model.effortLimit == pytest.approx(jaco2.MAX_TORQUE)


def test_masses_agree_and_are_plausible(mj, arm):
    model = mj[0]
    moving = sum(spec.link_mass_kg for spec in jaco2.JOINTS)
    assert 4.0 < moving < 5.5  # 4.4 kg arm without gripper, 5.2 kg with three fingers (base included)
    mj_moving = sum(model.body_mass[model.body(n).id] for n in jaco2.LINK_NAMES)
    pin_moving = sum(arm.model.inertias[i].mass for i in range(1, 8))
    assert mj_moving == pytest.approx(moving) and pin_moving == pytest.approx(moving)


def test_physical_model_conversion(rng):
    q_phys = rng.uniform(0, 360, 7)
    q = jaco2.physical_deg_to_model(q_phys)
    assert q[0] == pytest.approx(-math.radians(q_phys[0]))
    assert q[1:] == pytest.approx(np.radians(q_phys[1:]))
    assert jaco2.model_to_physical_deg(q) == pytest.approx(q_phys)
    dq = jaco2.physical_rate_to_model([10, 0, 0, 0, 0, 0, 0])
    assert dq[0] == pytest.approx(-math.radians(10))
    assert jaco2.model_rate_to_physical(dq) == pytest.approx([10, 0, 0, 0, 0, 0, 0])
    # unwrapped physical angles (e.g. 440.8°) stay unwrapped
    assert jaco2.model_to_physical_deg(jaco2.physical_deg_to_model([440.8] * 7))[0] == pytest.approx(440.8)


def test_physical_joint_1_turns_counterclockwise_about_up(arm):
    q0 = jaco2.HOME
    p0 = arm.pose(q0)[1]
    p1 = arm.pose(q0 + jaco2.physical_rate_to_model([1e-4, 0, 0, 0, 0, 0, 0]))[1]
    # +physical q1 rotates about +z (up): the tangent is z × p
    tangent = np.cross([0, 0, 1.0], p0)
    assert np.dot(p1 - p0, tangent) > 0


def test_urdf_is_the_single_description(arm):
    text = jaco2.urdf()
    assert text.count("<joint ") == 9 and 'name="end_effector"' in text
    # Pinocchio and MuJoCo both load the same text (loaders only add MuJoCo's unlimited flags)
    assert pin.buildModelFromXML(text).nq == 7
    assert mujoco.MjModel.from_xml_string(text).nq == 7


def test_home_euler_is_away_from_the_representation_singularity(arm):
    R, _ = arm.pose(jaco2.HOME)
    pitch = frames.matrix_to_euler_xyz(R)[1]
    assert abs(math.degrees(pitch)) < 80


def test_mujoco_warnings_go_to_the_log_not_to_a_file_in_the_working_directory(tmp_path, monkeypatch, caplog):
    """MuJoCo's own warning handler writes MUJOCO_LOG.TXT wherever the process runs; ours logs instead."""
    import logging

    mujoco = jaco2.mujoco_module()
    monkeypatch.chdir(tmp_path)
    model = mujoco.MjModel.from_xml_string('<mujoco><worldbody><body><joint/><geom size="0.1"/></body>'
                                           '</worldbody></mujoco>')
    data = mujoco.MjData(model)
    data.qpos[0] = float("nan")
    with caplog.at_level(logging.WARNING, logger="mujoco"):
        mujoco.mj_step(model, data)
    assert not (tmp_path / "MUJOCO_LOG.TXT").exists()
    assert any("Nan, Inf or huge value" in r.getMessage() for r in caplog.records)
