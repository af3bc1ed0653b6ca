import pytest

from protocol.keys import InvalidKeyChunk, Keys
from protocol.kinova import API_FUNCTIONS


def test_every_key_is_under_the_robot_prefix():
    keys = Keys("jaco-1")
    names = [n for n in dir(Keys) if isinstance(getattr(Keys, n), property) and n != "prefix"]
    values = [getattr(keys, n) for n in names]
    values += [keys.robot_api(f) for f in API_FUNCTIONS]
    values += [keys.health("vision"), keys.liveliness("safety"), keys.vision_api("teach")]
    assert all(v.startswith("mfvs/jaco-1/") for v in values)
    assert len(set(values)) == len(values)


def test_api_keys_use_kinova_names():
    assert Keys().robot_api("SendBasicTrajectory") == "mfvs/jaco/robot/api/SendBasicTrajectory"


@pytest.mark.parametrize("bad", ["", "a/b", "*", "jaco**", "x$y", "a?b", "a#b", "x" * 65])
def test_invalid_robot_ids_are_refused(bad):
    with pytest.raises(InvalidKeyChunk):
        Keys(bad)


def test_invalid_service_name_is_refused():
    with pytest.raises(InvalidKeyChunk):
        Keys().health("vision/**")


def test_all_robots_is_a_wildcard_over_robot_ids():
    assert Keys.all_robots().robot_command == "mfvs/*/robot/command"
