"""The one saturation (services/model/saturation.py) the controller, safety and the DSP share."""
import numpy as np
import pytest
from hypothesis import given, strategies as st
from hypothesis.extra.numpy import arrays

from services.model import saturation
from tests.helpers import REPO

finite = st.floats(-10.0, 10.0, allow_nan=False)
vectors = arrays(np.float64, 3, elements=finite)
joints = arrays(np.float64, 7, elements=finite)
positive = st.floats(0.01, 5.0)


twists = arrays(np.float64, 6, elements=finite)


def parallel(a, b) -> bool:
    """``a`` is ``b`` times a positive factor."""
    scale = np.dot(a, b) / max(np.dot(b, b), 1e-300)
    return scale > 0 and np.allclose(a, scale * b, atol=1e-12)


@given(twists, positive, positive)
def test_limit_twist_scales_the_whole_twist_by_one_factor(twist, linear_limit, angular_limit):
    out, ratio = saturation.limit_twist(twist, linear_limit, angular_limit)
    assert ratio.linear == pytest.approx(np.linalg.norm(twist[:3]) / linear_limit)
    assert ratio.angular == pytest.approx(np.linalg.norm(twist[3:]) / angular_limit)
    assert np.linalg.norm(out[:3]) <= linear_limit * (1 + 1e-9)
    assert np.linalg.norm(out[3:]) <= angular_limit * (1 + 1e-9)
    if ratio.over > 1.0:
        assert np.allclose(out * ratio.over, twist)  # one factor: the direction of the whole twist kept
        assert max(np.linalg.norm(out[:3]) / linear_limit, np.linalg.norm(out[3:]) / angular_limit) == \
            pytest.approx(1.0)  # and no more than needed
    else:
        assert out is twist


def test_a_twist_over_one_limit_slows_its_other_part_too():
    """The linear part at twice its limit halves the angular part as well: the step stays on its line."""
    out, ratio = saturation.limit_twist(np.array([0.4, 0.0, 0.0, 0.0, 0.0, 0.5]), 0.2, 1.0)
    assert ratio == (2.0, 0.5)
    assert np.allclose(out, [0.2, 0.0, 0.0, 0.0, 0.0, 0.25])


def test_limit_twist_judged_on_another_measure_of_the_same_motion():
    """Rates whose ω is twice as large: the factor comes from ω, and scales the rates."""
    rates = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.5])
    out, ratio = saturation.limit_twist(rates, 0.2, 0.5, judged_on=np.array([0.0, 0.0, 0.0, 0.0, 0.0, 1.0]))
    assert ratio.over == pytest.approx(2.0)
    assert np.allclose(out, rates / 2.0)


@given(twists, twists, positive, positive)
def test_limit_twist_change_cuts_the_change_by_one_factor(previous, twist, max_linear, max_angular):
    out, cut = saturation.limit_twist_change(previous, twist, max_linear, max_angular)
    change = twist - previous
    ratio = max(np.linalg.norm(change[:3]) / max_linear, np.linalg.norm(change[3:]) / max_angular)
    assert cut == (ratio > 1.0)
    assert np.linalg.norm(out[:3] - previous[:3]) <= max_linear * (1 + 1e-9)
    assert np.linalg.norm(out[3:] - previous[3:]) <= max_angular * (1 + 1e-9)
    if cut:
        assert np.allclose((out - previous) * ratio, change)
    else:
        assert out is twist


@given(joints, arrays(np.float64, 7, elements=positive))
def test_limit_uniformly_brings_every_element_within_by_one_factor(v, limits):
    out, ratio = saturation.limit_uniformly(v, limits)
    assert ratio == pytest.approx(np.max(np.abs(v) / limits))
    assert np.all(np.abs(out) <= limits * (1 + 1e-9))
    if ratio > 1.0:
        assert np.allclose(out * ratio, v)
    else:
        assert out is v


@given(joints, joints, positive)
def test_limit_change_uniformly_meets_every_element_s_change_limit(previous, v, max_change):
    out, cut = saturation.limit_change_uniformly(previous, v, max_change)
    assert cut == bool(np.max(np.abs(v - previous)) > max_change)
    assert np.all(np.abs(out - previous) <= max_change * (1 + 1e-9))


def test_the_controller_safety_and_the_dsp_saturate_through_it():
    """One saturation: no other module scales a velocity to a limit by hand."""
    root = REPO / "services"
    for path in ("controller/core.py", "safety/checks.py", "robot/dsp.py"):
        text = (root / path).read_text()
        assert "saturation." in text, path
        assert "*= vmax / speed" not in text and "step / step_ratio" not in text, path
        # a twist is limited as a whole, never its linear and angular parts apart
        assert "[part], speed" not in text and "[:3], linear" not in text and "[part], cut" not in text, path
