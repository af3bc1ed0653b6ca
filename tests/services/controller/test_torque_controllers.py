"""The JACO thesis's chapter-5 controllers (services/controller/torque_controllers.py) without a robot: their starts,
references and gains, and what they refuse."""
import math

import numpy as np
import pytest

from services.controller import torque_laws as laws
from services.controller.torque_controllers import CONTROLLERS, ControllerOptions, make_controller
from services.model.arm import load_arm

ARM6 = load_arm("j2n6s300")
ARM7 = load_arm("j2s7s300")


def test_the_thesis_arm_goes_to_eq_5_2s_xf_another_arm_moves_as_far():
    x0 = laws.THESIS_X0 + 0.001  # the arm's report, a little off the thesis's reading
    start = make_controller("jt-pid", ARM6).begin(ARM6.home, x0)
    assert start.target == "thesis" and start.xf == pytest.approx(laws.THESIS_XF) and start.x0 == pytest.approx(x0)
    seven = make_controller("null-space", ARM7).begin(ARM7.home)
    assert seven.target == "displacement"
    assert seven.xf - seven.x0 == pytest.approx(laws.THESIS_DISPLACEMENT)
    short = make_controller("jt-pid", ARM6, ControllerOptions(displacement_scale=0.25)).begin(ARM6.home, x0)
    assert short.xf == pytest.approx(x0 + 0.25 * (laws.THESIS_XF - x0))


def test_a_task_controller_at_its_reference_commands_only_gravity():
    """At X0 at rest, with the errors zero, (a)-(c) give ĝ(q) (task_gravity) or nothing, and (e) ĝ(q)."""
    model = laws.DynamicsModel(ARM6)
    for name in ("jt-pid", "null-space", "null-space-mass", "joint-velocity"):
        controller = make_controller(name, ARM6)
        controller.begin(ARM6.home)
        step = controller.step(0.0, 0.002, ARM6.home, np.zeros(6))
        assert step.tau == pytest.approx(model.gravity(ARM6.home), abs=1e-9), name
        assert step.position_error_m == pytest.approx(0.0, abs=1e-12) and not step.abort
    literal = make_controller("jt-pid", ARM6, ControllerOptions(task_gravity=False))
    literal.begin(ARM6.home)
    assert literal.step(0.0, 0.002, ARM6.home, np.zeros(6)).tau == pytest.approx(np.zeros(6), abs=1e-9)


def test_joint_pd_uses_table_5_3_mapped_onto_the_arm():
    controller = make_controller("joint-pd", ARM7)
    controller.begin(ARM7.home)
    assert controller.kp == pytest.approx([32.5, 40.5, 55, 55, 65, 70, 850])
    assert controller.duration_s == 2 * laws.SINUSOID_PERIOD_S
    step = controller.step(2.0, 0.002, ARM7.home, np.zeros(7))  # the crest, 20° ahead of every joint
    assert step.joint_error_deg == pytest.approx(20.0)
    model = laws.DynamicsModel(ARM7)
    expected = model.mass(ARM7.home) @ (controller.kp * math.radians(20.0)) + model.gravity(ARM7.home)
    assert step.tau == pytest.approx(expected)


def test_the_controller_gives_up_beyond_its_thresholds():
    controller = make_controller("null-space", ARM6, ControllerOptions(abort_position_m=0.01))
    controller.begin(ARM6.home)
    assert "position error" in controller.step(8.0, 0.002, ARM6.home, np.zeros(6)).abort


def test_unknown_names_and_bad_options_are_refused():
    with pytest.raises(ValueError, match="unknown controller 'pid'; known: " + ", ".join(CONTROLLERS)):
        make_controller("pid", ARM6)
    for bad in ({"tf_s": 0.0}, {"displacement_scale": 1.5}, {"amplitude_deg": 60.0}, {"kp": [1.0, -1.0]},
                {"abort_joint_deg": 0.0}):
        with pytest.raises(ValueError):
            ControllerOptions(**bad)
    with pytest.raises(ValueError, match="onto 6 joints"):
        make_controller("joint-pd", ARM6, ControllerOptions(kp=[1.0] * 7)).begin(ARM6.home)
