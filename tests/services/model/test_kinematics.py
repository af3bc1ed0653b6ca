"""The singularity measure (services/model/kinematics.py): one unit for translation and rotation, so an arm scaled in
size is as near a singularity at the same angles, and 0 exactly where the arm is singular."""
import math

import numpy as np
import pinocchio as pin
import pytest

from services.model.kinematics import ArmKinematics, manipulability, normalized_jacobian, singularity_measure
from services.model.arm import EE_LINK, load_arm

ARM = load_arm("j2s7s300")

KIN = ArmKinematics(ARM)
RNG = np.random.default_rng(34)


def scaled_jacobian(q, scale: float) -> np.ndarray:
    """The base Jacobian of the arm with every length multiplied by ``scale`` (Pinocchio's own model, its joint
    placements moved): the real kinematics of a bigger or smaller arm of the same shape."""
    model = ARM.load_pinocchio().model.copy()
    for i in range(len(model.jointPlacements)):
        model.jointPlacements[i] = pin.SE3(model.jointPlacements[i].rotation,
                                           model.jointPlacements[i].translation * scale)
    for frame in model.frames:
        frame.placement = pin.SE3(frame.placement.rotation, frame.placement.translation * scale)
    data = model.createData()
    pin.computeJointJacobians(model, data, q)
    pin.updateFramePlacements(model, data)
    return pin.getFrameJacobian(model, data, model.getFrameId(EE_LINK), pin.LOCAL_WORLD_ALIGNED)


@pytest.mark.parametrize("scale", [0.5, 2.0, 3.7])
def test_an_arm_scaled_in_size_is_as_near_a_singularity_at_the_same_angles(scale):
    length = KIN.characteristic_length_m
    for _ in range(20):
        q = ARM.home + RNG.uniform(-1.0, 1.0, ARM.n_joints)
        J, Js = scaled_jacobian(q, 1.0), scaled_jacobian(q, scale)
        assert np.allclose(Js[:3], J[:3] * scale) and np.allclose(Js[3:], J[3:])  # lengths scale translation only
        assert singularity_measure(Js, length * scale) == pytest.approx(singularity_measure(J, length), rel=1e-9)
        # Yoshikawa's manipulability, with its rows in m/s and rad/s, does not: it moves with the arm's size
        assert manipulability(Js) != pytest.approx(manipulability(J), rel=1e-3)


def test_zero_where_the_arm_is_singular_and_far_from_zero_at_home():
    stretched = ARM.physical_deg_to_model([0.0, 180.0, 0.0, 180.0, 0.0, 180.0, 0.0])  # straight up
    assert singularity_measure(KIN.jacobian_base(stretched), KIN.characteristic_length_m) < 1e-9
    home = singularity_measure(KIN.jacobian_base(ARM.home), KIN.characteristic_length_m)
    assert 0.1 < home < 0.2
    # the elbow straightening: the measure falls to 0 as joint 4 reaches 180°
    values = [singularity_measure(KIN.jacobian_base(ARM.physical_deg_to_model([270.0, 180 + a, 0.0, a, 0.0,
                                                                                 220.0, 0.0])),
                                  KIN.characteristic_length_m) for a in (150.0, 160.0, 170.0, 179.0)]
    assert values == sorted(values, reverse=True) and values[-1] < 0.005


def test_normalized_jacobian_moves_the_same_joints_as_the_jacobian():
    """Rows in one unit change the measure, not the motion: the pseudo-inverse solution is the same."""
    J = KIN.jacobian_base(ARM.home)
    twist = np.array([0.05, -0.02, 0.03, 0.1, 0.2, -0.1])
    length = KIN.characteristic_length_m
    twist_n = twist.copy()
    twist_n[:3] /= length
    assert np.allclose(np.linalg.pinv(normalized_jacobian(J, length)) @ twist_n, np.linalg.pinv(J) @ twist)
    assert math.isclose(KIN.characteristic_length_m, ARM.reach)
