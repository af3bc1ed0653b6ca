"""The arm descriptions (services/model/arm.py, one file per arm in services/model/arms): MuJoCo and Pinocchio load
the same one and agree with its DH table and each other, each arm matches its sources, and a bad file is refused."""
import math

import mujoco
import numpy as np
import pinocchio as pin
import pytest

from services.model import frames
from services.model.arm import (DEFAULT_ARM, EE_LINK, ArmError, arm_names, check_arm_name, evaluate, load_arm,
                                mujoco_module, read_description)
from tests.helpers import PinArm

#: every arm described (one file each in services/model/arms): a new file is checked as the shipped ones are
ARMS = arm_names()


@pytest.fixture(scope="module", params=ARMS)
def arm(request):
    return load_arm(request.param)


def random_q(arm, rng, margin_deg: float = 2.0) -> np.ndarray:
    lower, upper = arm.model_limits()
    q = rng.uniform(-4 * np.pi, 4 * np.pi, arm.n_joints)
    limited = np.isfinite(lower)
    m = np.radians(margin_deg)
    q[limited] = rng.uniform(lower[limited] + m, upper[limited] - m)
    return q


def mujoco_arm(arm):
    model = arm.load_mujoco()
    return model, mujoco.MjData(model), model.body(EE_LINK).id


def test_the_arms_described_and_the_default():
    assert {"j2s7s300", "j2n6s300", "j2s6s300"} <= set(ARMS) and DEFAULT_ARM == "j2s7s300"
    # the known arms are the files there are, whatever they are
    with pytest.raises(ArmError, match=f"unknown arm 'j2n9s300'; known: {', '.join(sorted(ARMS))}$"):
        check_arm_name("j2n9s300")
    assert load_arm("j2n6s300").n_joints == 6 and load_arm("j2s7s300").n_joints == 7


def test_mujoco_pinocchio_and_the_dh_table_agree(arm, rng):
    """Poses to 1e-9, Jacobians to 1e-8, the same joints in the same order, the same masses."""
    model, data, body = mujoco_arm(arm)
    pin_arm = PinArm(arm)
    assert model.nq == model.nv == arm.n_joints == pin_arm.model.nq
    assert [model.joint(i).name for i in range(arm.n_joints)] == list(arm.joint_names)
    assert list(pin_arm.model.names)[1:] == list(arm.joint_names)
    for _ in range(100):
        q = random_q(arm, rng)
        data.qpos[:] = q
        mujoco.mj_kinematics(model, data)
        mujoco.mj_comPos(model, data)
        R_pin, p_pin = pin_arm.pose(q)
        T = arm.dh_forward_kinematics(q)
        assert np.abs(data.xpos[body] - p_pin).max() < 1e-9 and np.abs(T[:3, 3] - p_pin).max() < 1e-9
        assert np.abs(data.xmat[body].reshape(3, 3) - R_pin).max() < 1e-9 and np.abs(T[:3, :3] - R_pin).max() < 1e-9
        jacp, jacr = np.zeros((3, model.nv)), np.zeros((3, model.nv))
        mujoco.mj_jacBody(model, data, jacp, jacr, body)
        assert np.abs(np.vstack([jacp, jacr]) - pin_arm.jacobian_base(q)).max() < 1e-8
    moving = sum(j.link_mass_kg for j in arm.joints)
    assert sum(model.body_mass[model.body(n).id] for n in arm.link_names) == pytest.approx(moving)
    assert sum(pin_arm.model.inertias[i].mass for i in range(1, arm.n_joints + 1)) == pytest.approx(moving)
    # and the inertia tensors: the same mass matrix at random configurations
    pdata = pin_arm.model.createData()
    for _ in range(20):
        q = random_q(arm, rng)
        data.qpos[:] = q
        mujoco.mj_forward(model, data)
        M = np.zeros((model.nv, model.nv))
        mujoco.mj_fullM(model, data, M)
        assert np.abs(M - pin.crba(pin_arm.model, pdata, q)).max() < 1e-9


def test_the_urdf_is_the_single_description(arm):
    text = arm.urdf()
    assert text.count("<joint ") == arm.n_joints + 2 and f'<robot name="{arm.name}">' in text
    assert pin.buildModelFromXML(text).nq == arm.n_joints and mujoco.MjModel.from_xml_string(text).nq == arm.n_joints


def test_physical_and_model_angles_convert_both_ways(arm, rng):
    q_phys = rng.uniform(-720, 720, arm.n_joints)
    q = arm.physical_deg_to_model(q_phys)
    assert arm.model_to_physical_deg(q) == pytest.approx(q_phys)
    assert arm.model_rate_to_physical(arm.physical_rate_to_model(q_phys)) == pytest.approx(q_phys)
    # unwrapped physical angles (e.g. 440.8°) stay unwrapped
    assert arm.model_to_physical_deg(arm.physical_deg_to_model([440.8] * arm.n_joints))[0] == pytest.approx(440.8)


def test_home_is_within_the_limits_and_away_from_singularities(arm):
    from services.model.kinematics import ArmKinematics, singularity_measure

    assert arm.within_limits(arm.home)
    assert arm.limit_margins_deg(arm.home).min() >= 30.0
    kin = ArmKinematics(arm)
    assert singularity_measure(kin.jacobian_base(arm.home), arm.reach) > 0.05
    assert abs(math.degrees(frames.matrix_to_euler_xyz(kin.pose(arm.home)[0])[1])) < 80  # Euler: not near gimbal


# ------------------------------------------------------------------------------------------------ the 7-DoF arm
def test_j2s7s300_stands_straight_up_at_the_centre_of_its_ranges():
    arm = load_arm("j2s7s300")
    R, p = PinArm(arm).pose(arm.physical_deg_to_model([0, 180, 0, 180, 0, 180, 0]))
    assert p == pytest.approx([0.0, 0.0098, 0.2755 + arm.reach], abs=1e-9)
    assert arm.reach == pytest.approx(0.9849, abs=1e-9)  # 0.2050 + 0.2050 + 0.2073 + 0.1038 + 0.1038 + 0.1600


def test_j2s7s300_limits_speeds_and_joint_1_as_kinova_md_gives_them():
    arm = load_arm("j2s7s300")
    ranges = {j.name: (j.lower_deg, j.upper_deg) for j in arm.joints if not j.continuous}
    assert ranges == {"joint_2": (47.0, 313.0), "joint_4": (30.0, 330.0), "joint_6": (65.0, 295.0)}
    assert arm.max_speed_dps.tolist() == [36, 36, 36, 36, 48, 48, 48]
    assert [j.actuator for j in arm.joints] == ["K-75+"] * 4 + ["K-58"] * 3
    assert arm.bus_addresses == (0x10, 0x11, 0x12, 0x13, 0x14, 0x15, 0x19)
    # +physical q1 turns the arm counterclockwise seen from above (θ_DH,1 = −q1 under the base's Rx(π))
    kin = PinArm(arm)
    p0 = kin.pose(arm.home)[1]
    p1 = kin.pose(arm.home + arm.physical_rate_to_model([1e-4, 0, 0, 0, 0, 0, 0]))[1]
    assert np.dot(p1 - p0, np.cross([0, 0, 1.0], p0)) > 0


# ------------------------------------------------------------------------------------------------ the 6-DoF arm
def seed003_forward_kinematics(q_robot_deg) -> np.ndarray:
    """The JACO thesis's model written out here from its tables, independently of the description file: Table 3.1's
    lengths, Table 3.2's auxiliary variables (aa = π/6), Table 3.3's DH rows as classic DH (eq. 3.4:
    Rz(θ)·Tz(d)·Tx(a)·Rx(α)), Table 3.4's angle transformation, no base transform."""
    D1, D2, e2, D3, D4, D5, D6 = 0.2755, 0.41, 0.0098, 0.2073, 0.0741, 0.0741, 0.16
    aa = math.pi / 6
    sa, s2a = math.sin(aa), math.sin(2 * aa)
    d4b = D3 + sa / s2a * D4
    d5b = sa / s2a * D4 + sa / s2a * D5
    d6b = sa / s2a * D5 + D6
    q1, q2, q3, q4, q5, q6 = np.radians(q_robot_deg)
    theta = [-q1, q2 - math.pi / 2, q3 + math.pi / 2, q4, q5 - math.pi, q6 + math.pi / 2]
    rows = [(math.pi / 2, 0.0, D1), (math.pi, D2, 0.0), (math.pi / 2, 0.0, -e2), (2 * aa, 0.0, -d4b),
            (2 * aa, 0.0, -d5b), (math.pi, 0.0, -d6b)]
    T = np.eye(4)
    for th, (alpha, a, d) in zip(theta, rows):
        ct, st, ca, sa_ = math.cos(th), math.sin(th), math.cos(alpha), math.sin(alpha)
        T = T @ np.array([[ct, -ca * st, sa_ * st, a * ct], [st, ca * ct, -sa_ * ct, a * st], [0, sa_, ca, d],
                          [0, 0, 0, 1]])
    return T


def test_j2n6s300_forward_kinematics_is_seed_003s_tables(rng):
    arm = load_arm("j2n6s300")
    kin = PinArm(arm)
    for _ in range(200):
        q_deg = rng.uniform(-360, 360, 6)
        q_deg[1], q_deg[2] = rng.uniform(47, 313), rng.uniform(19, 341)
        T_thesis = seed003_forward_kinematics(q_deg)
        R, p = kin.pose(arm.physical_deg_to_model(q_deg))
        assert np.abs(p - T_thesis[:3, 3]).max() < 1e-9 and np.abs(R - T_thesis[:3, :3]).max() < 1e-9


def test_j2n6s300_home_is_where_seed_003_read_the_real_arm():
    """Eq. 5.2's X0, the real arm's own GetCartesianPosition at HOME, against the description at Kinova's HOME
    angles: within 1 mm and half a degree (the HOME angles are kinova-ros's, rounded to 0.01°)."""
    arm = load_arm("j2n6s300")
    T = arm.dh_forward_kinematics(arm.home)
    x0 = np.array([0.212444, -0.257293, 0.506643])
    R0 = frames.euler_xyz_to_matrix([1.65789, 1.11875, 0.113634])
    assert np.linalg.norm(T[:3, 3] - x0) < 1e-3
    assert np.degrees(np.linalg.norm(frames.rotation_log(R0.T @ T[:3, :3]))) < 0.5


def test_j2n6s300_joints_masses_and_bus_as_its_sources_give_them():
    arm = load_arm("j2n6s300")
    assert [j.continuous for j in arm.joints] == [True, False, False, True, True, True]
    assert [(j.lower_deg, j.upper_deg) for j in arm.joints[1:3]] == [(47.0, 313.0), (19.0, 341.0)]
    assert arm.max_speed_dps.tolist() == [36, 36, 36, 48, 48, 48]
    assert [j.actuator for j in arm.joints] == ["K-75+"] * 3 + ["K-58"] * 3
    assert arm.bus_addresses == (0x10, 0x11, 0x12, 0x13, 0x14, 0x15)
    # JACO thesis Tables 3.5-3.7: link + actuator + ring, 4.47 kg (spec sheet: 4.4 kg without gripper)
    masses = [j.link_mass_kg for j in arm.joints]
    assert masses == pytest.approx([0.767664, 0.995713, 0.796345, 0.41737, 0.41737, 1.07541])
    assert sum(masses) == pytest.approx(4.470, abs=1e-3)
    assert 0.90 <= arm.reach <= 0.92  # spec sheet: 90 cm


# ------------------------------------------------------------------------------------------------ the 6-DoF spherical
def kinova_ros_j2s6s300_forward_kinematics(q_robot_deg) -> np.ndarray:
    """kinova-ros's j2s6s300.xacro written out here, independently of the description file: each joint's origin
    (xyz, rpy) and a rotation about its z by the raw angle GetAngularPosition reports (kinova_arm.cpp publishes
    them unchanged), then the end_effector's fixed offset."""
    p = math.pi
    joints = [((0, 0, 0.15675), (0, p, 0)), ((0, 0.0016, -0.11875), (-p / 2, 0, p)), ((0, -0.410, 0), (0, p, 0)),
              ((0, 0.2073, -0.0114), (-p / 2, 0, p)), ((0, 0, -0.10375), (p / 2, 0, p)),
              ((0, 0.10375, 0), (-p / 2, 0, p))]

    def origin(xyz, rpy):
        T = np.eye(4)
        T[:3, :3] = frames.rot_z(rpy[2]) @ frames.rot_y(rpy[1]) @ frames.rot_x(rpy[0])
        T[:3, 3] = xyz
        return T

    T = np.eye(4)
    for (xyz, rpy), q in zip(joints, np.radians(q_robot_deg)):
        Rq = np.eye(4)
        Rq[:3, :3] = frames.rot_z(q)
        T = T @ origin(xyz, rpy) @ Rq
    return T @ origin((0, 0, -0.16), (p, 0, p / 2))


def test_j2s6s300_forward_kinematics_is_kinova_ros_s_urdf(rng):
    """The file's table (kinova_arm_kinematics.cpp's, the DSP's lengths) against Kinova's URDF of the same arm: the
    same end-effector frame, its position within 0.2 mm (the URDF's wrist segments are 0.10375 m, the DSP's
    0.1038)."""
    arm = load_arm("j2s6s300")
    kin = PinArm(arm)
    for _ in range(200):
        q_deg = rng.uniform(-360, 360, 6)
        q_deg[1], q_deg[2], q_deg[4] = rng.uniform(47, 313), rng.uniform(19, 341), rng.uniform(30, 330)
        T_urdf = kinova_ros_j2s6s300_forward_kinematics(q_deg)
        R, p = kin.pose(arm.physical_deg_to_model(q_deg))
        assert np.abs(p - T_urdf[:3, 3]).max() < 2e-4 and np.abs(R - T_urdf[:3, :3]).max() < 1e-9


def test_j2s6s300_joints_bus_and_home_as_its_sources_give_them():
    arm = load_arm("j2s6s300")
    assert [j.continuous for j in arm.joints] == [True, False, False, True, False, True]
    assert [(j.lower_deg, j.upper_deg) for j in arm.joints if not j.continuous] == [(47.0, 313.0), (19.0, 341.0),
                                                                                     (30.0, 330.0)]
    assert arm.max_speed_dps.tolist() == [36, 36, 36, 48, 48, 48]
    assert [j.actuator for j in arm.joints] == ["K-75+"] * 3 + ["K-58"] * 3
    assert arm.bus_addresses == (0x10, 0x11, 0x12, 0x13, 0x14, 0x15) and arm.robot_type == 7
    # straight up at 180° everywhere (the MoveIt config's "Vertical"): the shoulder plus the reach
    R, p = PinArm(arm).pose(arm.physical_deg_to_model([180.0] * 6))
    assert p == pytest.approx([0.0, 0.0098, 0.2755 + arm.reach], abs=1e-9)
    # the home is mfvs's choice: the end effector where the j2s7s300's home puts it, the same frame
    seven = load_arm("j2s7s300")
    T, T7 = arm.dh_forward_kinematics(arm.home), seven.dh_forward_kinematics(seven.home)
    assert np.abs(T - T7).max() < 1e-9


# ------------------------------------------------------------------------------------------------ bad files
def test_a_description_file_that_is_not_valid_is_refused(tmp_path):
    good = load_arm("j2n6s300").path.read_text()
    cases = {
        "other_name": good.replace("name: j2n6s300", "name: j2x6s300"),
        "too_few_links": good.replace("  - {mass_kg: 0.727 + 0.34141 + 0.007}\n", ""),
        "unknown_length": good.replace("d: -e2", "d: -e3"),
        "code_in_a_number": good.replace("d: -e2", "d: __import__('os').getcwd()"),
        "home_out_of_range": good.replace("home_deg: [275.29, 167.58,", "home_deg: [275.29, 20.0,"),
        "sign_of_two": good.replace("sign: -1", "sign: -2"),
    }
    for stem, text in cases.items():
        path = tmp_path / f"{stem}.yaml"
        path.write_text(text)
        with pytest.raises(ArmError):
            read_description(path)


def test_expressions_are_arithmetic_only():
    assert evaluate("-(D3 + D4 * sin(aa) / sin(2 * aa))", {"D3": 0.2, "D4": 0.1, "aa": math.pi / 6}) == \
        pytest.approx(-(0.2 + 0.1 / math.sqrt(3)))
    assert evaluate("pi/2", {}) == math.pi / 2 and evaluate(3, {}) == 3.0
    for bad in ("__import__('os')", "D1.real", "[1][0]", "1 if 1 else 2", "open('x')", "2 ** 10000", "1/0"):
        with pytest.raises((ArmError, ZeroDivisionError)):
            evaluate(bad, {"D1": 1.0})


def test_mujoco_warnings_go_to_the_log_not_to_a_file_in_the_working_directory(tmp_path, monkeypatch, caplog):
    """MuJoCo's own warning handler writes MUJOCO_LOG.TXT wherever the process runs; ours logs instead."""
    import logging

    mj = mujoco_module()
    monkeypatch.chdir(tmp_path)
    model = mj.MjModel.from_xml_string('<mujoco><worldbody><body><joint/><geom size="0.1"/></body>'
                                       '</worldbody></mujoco>')
    data = mj.MjData(model)
    data.qpos[0] = float("nan")
    with caplog.at_level(logging.WARNING, logger="mujoco"):
        mj.mj_step(model, data)
    assert not (tmp_path / "MUJOCO_LOG.TXT").exists()
    assert any("Nan, Inf or huge value" in r.getMessage() for r in caplog.records)
