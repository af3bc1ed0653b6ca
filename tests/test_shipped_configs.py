"""Each service's shipped YAML is its documentation: it must load to exactly the code's defaults and show every
key (a key missing from the file would be an undocumented setting)."""

import msgspec
import pytest

from services.runtime.config import load_config, read_yaml
from services.camera.service import CameraConfig
from services.controller.service import ControllerConfig
from services.jog.config import JogConfig
from services.robot_gateway.service import GatewayConfig
from services.robot_sim.service import RobotSimConfig
from services.ros2_bridge.service import Ros2BridgeConfig
from services.safety.service import SafetyConfig
from services.vision.service import VisionConfig
from tests.helpers import REPO

SHIPPED = {
    "robot_sim": RobotSimConfig, "vision": VisionConfig, "controller": ControllerConfig, "safety": SafetyConfig,
    "robot_gateway": GatewayConfig, "camera": CameraConfig, "ros2_bridge": Ros2BridgeConfig, "jog": JogConfig,
}


def key_paths(node, prefix=""):
    """Dotted paths of every mapping key (lists are values: their items are not walked)."""
    if not isinstance(node, dict):
        return set()
    paths = set()
    for key, value in node.items():
        path = f"{prefix}{key}"
        paths.add(path)
        paths |= key_paths(value, f"{path}.")
    return paths


@pytest.mark.parametrize("service", sorted(SHIPPED))
def test_shipped_config_is_the_defaults_with_every_key(service):
    config_type = SHIPPED[service]
    shipped = REPO / "services" / service / f"{service}.yaml"
    assert load_config(shipped, config_type) == config_type()
    missing = key_paths(msgspec.to_builtins(config_type())) - key_paths(read_yaml(shipped))
    assert not missing, f"{shipped.name} does not show {sorted(missing)}"


def test_the_visual_path_shares_one_image_budget():
    from protocol.conventions import IMAGE_AGE_BUDGET_S
    from services.controller.service import ControllerConfig
    from services.safety.checks import SafetyLimits
    from services.vision.service import VisionConfig

    assert VisionConfig().max_image_age_s == ControllerConfig().max_input_age_s == SafetyLimits().image_budget_s \
        == IMAGE_AGE_BUDGET_S


@pytest.mark.parametrize("path", sorted((REPO / "examples" / "scenarios").glob("*.yaml")), ids=lambda p: p.name)
def test_every_example_scenario_loads_with_what_the_services_check_of_it(path):
    from services.servo.scenario import load_scenario

    load_scenario(path)
