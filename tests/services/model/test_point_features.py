import math

import numpy as np
import pytest

from services.model.point_features import feature_error, per_point_rms


def test_a_tags_rms_is_its_norm_over_two_to_the_bit(rng):
    for _ in range(200):
        e = rng.normal(0.0, 10.0 ** rng.uniform(-6, -1), 8)
        norm = float(np.linalg.norm(e))
        assert per_point_rms(e, [1.0] * 4) == norm / 2.0
        assert (per_point_rms(e, [1.0] * 4) < 2.5e-5) == (norm < 5e-5)  # Sensors 2022's threshold, restated


def test_the_rms_is_per_point_and_weighted():
    e = np.array([3.0, 4.0, 0.0, 0.0])  # point 0 off by 5, point 1 on its goal
    assert per_point_rms(e, [1.0, 1.0]) == pytest.approx(5.0 / math.sqrt(2.0))
    assert per_point_rms(e, [1.0, 0.0]) == pytest.approx(5.0)  # the second point faded out entirely
    assert per_point_rms(e, [0.0, 1.0]) == pytest.approx(0.0)
    # the same error per point over many points: the same RMS (a norm would grow with their number)
    assert per_point_rms(np.tile([3.0, 4.0], 300), [1.0] * 300) == pytest.approx(5.0)


def test_weights_and_errors_must_agree():
    with pytest.raises(ValueError, match="two values per point"):
        per_point_rms([0.0] * 6, [1.0, 1.0])
    with pytest.raises(ValueError, match="positive sum"):
        per_point_rms([0.0] * 4, [0.0, 0.0])
    with pytest.raises(ValueError, match="non-negative"):
        per_point_rms([0.0] * 4, [1.5, -0.5])


def test_feature_error_is_stacked_per_point():
    e, norm = feature_error([[1.0, 2.0], [3.0, 4.0]], [[0.0, 0.0], [3.0, 3.0]])
    assert e.tolist() == [1.0, 2.0, 0.0, 1.0] and norm == pytest.approx(math.sqrt(6.0))
