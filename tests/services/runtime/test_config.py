"""Service and scenario configs: a mistyped key is named, with the closest known key."""
import pytest

from services.runtime.config import ConfigError, config_from_text
from services.servo.scenario import Scenario


def test_a_mistyped_key_gets_the_closest_known_one_at_its_place():
    with pytest.raises(ConfigError, match=r"convergence\.max_iteration.*did you mean `max_iterations`"):
        config_from_text("convergence: {max_iteration: 10}", Scenario)
    with pytest.raises(ConfigError, match=r"did you mean `pose_in_camera`"):
        config_from_text("target: {pose_in_camra: {xyz: [0, 0, 0.5]}}", Scenario)
    with pytest.raises(ConfigError) as refused:
        config_from_text("zzzz: 1", Scenario)
    assert "did you mean" not in str(refused.value)
