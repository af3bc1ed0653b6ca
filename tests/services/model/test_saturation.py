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


@given(vectors, positive)
def test_limit_norm_keeps_the_direction_and_meets_the_limit(v, limit):
    out, size = saturation.limit_norm(v, limit)
    assert size == pytest.approx(np.linalg.norm(v))
    if size > limit:
        assert np.linalg.norm(out) == pytest.approx(limit)
        assert np.allclose(out * size / limit, v)  # along v
    else:
        assert out is v


@given(vectors, vectors, positive)
def test_limit_norm_change_cuts_the_change_along_itself(previous, v, max_change):
    out, cut = saturation.limit_norm_change(previous, v, max_change)
    change = np.linalg.norm(v - previous)
    assert cut == (change > max_change)
    assert np.linalg.norm(out - previous) <= max_change * (1 + 1e-9) or not cut
    if cut:
        assert np.allclose((out - previous) * change / max_change, v - previous)
    else:
        assert out is v


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
