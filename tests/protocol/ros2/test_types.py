"""The type hashes mfvs puts in its keys equal the ones ROS 2's own packages ship, and the codec's types are the
ones hashed."""
import json
import re
from pathlib import Path

import pytest

from protocol.ros2 import cdr, types

HASHES = json.loads((Path(__file__).parent / "fixtures" / "fixtures.json").read_text())["type_hashes"]
CONSTANTS = sorted(types.BY_NAME.values(), key=lambda ros_type: ros_type.name)


def test_every_constant_is_a_rihs01_hash_and_has_a_fixture():
    assert len(CONSTANTS) == 22
    for ros_type in CONSTANTS:
        assert re.fullmatch(r"RIHS01_[0-9a-f]{64}", ros_type.rihs01), ros_type
        assert ros_type.name in HASHES, ros_type.name


@pytest.mark.parametrize("ros_type", CONSTANTS, ids=lambda ros_type: ros_type.name)
def test_hashes_equal_the_jazzy_packages_and_rosbags(ros_type):
    sources = HASHES[ros_type.name]
    if sources["jazzy_package"] is not None:
        assert ros_type.rihs01 == sources["jazzy_package"]
    # rosbags: a second implementation, and the only one for Kilted and Lyrical; it has no services (types.py)
    if ros_type.name != "std_srvs/srv/Trigger":
        assert ros_type.rihs01 == sources["rosbags_jazzy"] == sources["rosbags_kilted"] == sources["rosbags_lyrical"]


def test_only_tf2_msgs_rests_on_rosbags_alone_and_only_trigger_on_the_package_alone():
    package_missing = {name for name, sources in HASHES.items() if sources["jazzy_package"] is None}
    rosbags_missing = {name for name, sources in HASHES.items() if sources["rosbags_jazzy"] is None}
    assert package_missing == {"tf2_msgs/msg/TFMessage"} and rosbags_missing == {"std_srvs/srv/Trigger"}


def test_every_message_type_of_the_codec_has_its_hash_here():
    service_parts = {"std_srvs/srv/Trigger_Request", "std_srvs/srv/Trigger_Response"}  # hashed as std_srvs/srv/Trigger
    assert set(cdr.MESSAGE_TYPES) - service_parts == set(types.BY_NAME) - {"std_srvs/srv/Trigger"}
