"""`mfvs ros2` and `mfvs up --ros2`: the bridge's command line, its domain from $ROS_DOMAIN_ID as ROS reads it,
and the bridge as one more service of a profile (run as the operator behind authority). No stack is started."""
import subprocess
import sys

import pytest

from services.ros2_bridge.cli import default_domain
from services.ros2_bridge.service import Ros2BridgeConfig
from services.runtime.authority import write_deployment
from services.stack.launcher import behind_authority, load_profile, service_command, with_ros2
from tests.helpers import REPO


def test_the_domain_is_ros_domain_id_as_ros_reads_it(monkeypatch):
    monkeypatch.delenv("ROS_DOMAIN_ID", raising=False)
    assert default_domain() == 0
    monkeypatch.setenv("ROS_DOMAIN_ID", " 42 ")
    assert default_domain() == 42
    monkeypatch.setenv("ROS_DOMAIN_ID", "")
    assert default_domain() == 0
    monkeypatch.setenv("ROS_DOMAIN_ID", "-1")
    with pytest.raises(ValueError, match="not a domain id"):
        default_domain()


@pytest.mark.parametrize("settings, problem", [
    ({"namespace": "robot1"}, "namespace"), ({"namespace": "/1robot"}, "namespace"),
    ({"node_name": "my/node"}, "node name"), ({"domain_id": -3}, "domain_id"),
    ({"goal_min_distance_m": 3.0}, "goal distances"), ({"operator": ""}, "operator"),
])
def test_a_bridge_setting_ros_would_refuse_is_refused_before_it_starts(settings, problem):
    with pytest.raises(ValueError, match=problem):
        Ros2BridgeConfig(**settings)


def test_up_ros2_adds_the_bridge_to_any_profile_once_and_it_runs_as_the_operator(tmp_path):
    sim = with_ros2(load_profile("sim", 7447), 3)
    (bridge,) = [s for s in sim.services if s.name == "ros2_bridge"]
    command = service_command(bridge, "tcp/127.0.0.1:7447", "jaco")
    assert command[1:3] == ["-m", "services.ros2_bridge"] and command[-2:] == ["--set", "domain_id=3"]
    assert with_ros2(sim, 5) == sim  # a profile that has one keeps its own
    across = with_ros2(load_profile(str(REPO / "deploy" / "profiles" / "multi-host.yaml"), 7447), 0)
    assert [s.host for s in across.services if s.name == "ros2_bridge"] == [across.router.host]
    deployment = write_deployment(tmp_path / "secrets", services=["safety", "vision", "controller", "robot_sim",
                                                                  "operator"])
    guarded = behind_authority(sim, deployment)
    (bridge,) = [s for s in guarded.services if s.name == "ros2_bridge"]
    assert bridge.zenoh_config == str(deployment.client_configs["operator"])


def test_mfvs_up_refuses_a_ros_domain_id_that_is_none_before_anything_starts(tmp_path):
    out = subprocess.run([sys.executable, "-m", "services.cli", "up", "--ros2"], cwd=REPO, capture_output=True,
                         text=True, timeout=60, env={"PATH": "/usr/bin:/bin", "ROS_DOMAIN_ID": "seven",
                                                     "MFVS_RUN_DIR": str(tmp_path)})
    assert out.returncode == 2 and "ROS_DOMAIN_ID='seven' is not a domain id" in out.stderr, out
    assert not (tmp_path / "stack.json").exists()


def test_mfvs_ros2_says_plainly_what_is_wrong_with_its_options():
    out = subprocess.run([sys.executable, "-m", "services.cli", "ros2", "--namespace", "jaco", "--connect",
                          "tcp/127.0.0.1:1"], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert out.returncode == 2 and out.stderr.startswith("mfvs ros2: namespace 'jaco'"), out
