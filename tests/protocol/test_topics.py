"""The topic table: every published key has its type, and a key on a command line is resolved or refused with
what it might have been."""
import pytest
import zenoh

from protocol import messages as m
from protocol.keys import Keys
from protocol.topics import UnknownTopic, matching, resolve, topic_of, topics


def test_every_topic_is_a_key_of_the_stack_with_a_message_type():
    keys = Keys("arm-2")
    table = topics(keys)
    assert len({t.key for t in table}) == len(table)
    for topic in table:
        assert topic.key.startswith("mfvs/arm-2/")
        assert issubclass(topic.message_type, m.Message)
        if "*" not in topic.key:
            assert topic_of(topic.key) == topic
    assert topic_of(keys.robot_state).message_type is m.RobotState
    assert topic_of(keys.camera_image).message_type is m.Image
    # each service's health on a key of its own: one topic, a wildcard
    assert topic_of(keys.health("vision")).message_type is m.ServiceHealth
    assert topic_of(keys.health("vision")).key == keys.health("vision")


def test_a_key_below_the_robot_or_a_pattern_selects_topics():
    keys = Keys("jaco")
    assert resolve("robot/state", keys) == "mfvs/jaco/robot/state"
    assert resolve("mfvs/other/robot/state", keys) == "mfvs/other/robot/state"
    assert [t.key for t in matching("robot/state", keys)] == [keys.robot_state]
    assert {t.key for t in matching("robot/*", keys)} == {keys.robot_state, keys.robot_command}
    assert {t.key for t in matching("robot/**", keys)} == {keys.robot_state, keys.robot_command,
                                                          keys.lowlevel_state, keys.lowlevel_command}
    assert len(matching("**", keys)) == len(topics(keys))
    assert [t.key for t in matching("mfvs/*/vision/features", keys)] == [keys.features]


@pytest.mark.parametrize("key, says", [
    ("robot/stat", "did you mean mfvs/jaco/robot/state"),
    ("mfvs/jaco/vision/featurs", "did you mean mfvs/jaco/vision/features"),
    ("mfvs/jaco/robot/api/GetAngularPosition", "is no topic"),  # a query's key, not a topic
    ("ros/camera", "is no topic"),
    ("", "empty key"),
])
def test_a_key_that_is_no_topic_says_what_it_might_have_been(key, says):
    with pytest.raises(UnknownTopic, match=says):
        matching(key, Keys("jaco"))


def test_a_pattern_that_selects_nothing_says_so():
    with pytest.raises(UnknownTopic, match="selects none"):
        matching("mfvs/other/**", Keys("jaco"))
    with pytest.raises(UnknownTopic, match="not an mfvs key"):
        topic_of("foo/bar")


def test_the_control_path_goes_out_at_once_and_ahead_of_the_images():
    from services.runtime.transport import publisher_options

    keys = Keys()
    for key in (keys.features, keys.desired_twist, keys.desired_joint_velocity, keys.robot_command, keys.estop,
                keys.robot_state, keys.lowlevel_command, keys.lowlevel_state):
        options = publisher_options(key)
        assert options["express"] is True and options["priority"] == zenoh.Priority.INTERACTIVE_HIGH, key
    for key in (keys.camera_image, keys.camera_info, keys.controller_status, keys.health("vision")):
        assert publisher_options(key) == {}, key
    assert publisher_options("somebody/else") == {}
