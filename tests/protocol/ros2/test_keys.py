"""Keys and liveliness tokens equal, character for character, the examples of rmw_zenoh's design document and the
tokens a real talker declared, as captured in rmw_zenoh's issue tracker."""
import json
from dataclasses import replace
from pathlib import Path

import pytest
from hypothesis import given, strategies as st

from protocol.ros2 import keys as k
from protocol.ros2 import types

STRING = types.STRING.rihs01
ADD_TWO_INTS = "RIHS01_e118de6bf5eeb66a2491b5bda11202e7b68f198d6f67922cf30364858239c81a"
HASHES = json.loads((Path(__file__).parent / "fixtures" / "fixtures.json").read_text())["type_hashes"]
LOG = HASHES["rcl_interfaces/msg/Log"]["jazzy_package"]
PARAMETER_EVENT = HASHES["rcl_interfaces/msg/ParameterEvent"]["jazzy_package"]

# rmw_zenoh's docs/design.md at commit 99a6a2bd10b949052f4f12c5854825dc005e95a5
# (https://github.com/ros2/rmw_zenoh/blob/99a6a2bd10b949052f4f12c5854825dc005e95a5/docs/design.md), verbatim
DESIGN_CHATTER_KEY = "0/chatter/std_msgs::msg::dds_::String_/" \
    "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
DESIGN_NAMESPACED_CHATTER_KEY = "0/robot1/chatter/std_msgs::msg::dds_::String_/" \
    "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
DESIGN_SERVICE_KEY = "2/add_two_ints/example_interfaces::srv::dds_::AddTwoInts_/" \
    "RIHS01_e118de6bf5eeb66a2491b5bda11202e7b68f198d6f67922cf30364858239c81a"
DESIGN_LISTENER_NODE = "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/0/NN/%/%/listener"
DESIGN_LISTENER_SUBSCRIPTION = "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/10/MS/%/%/listener/%chatter/" \
    "std_msgs::msg::dds_::String_/RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18/" \
    "::,10:,:,:,,"
DESIGN_TALKER_PUBLISHER = "@ros2_lv/2/8b20917502ee955ac4476e0266340d5c/0/10/MP/%/%/talker/%chatter/" \
    "std_msgs::msg::dds_::String_/RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18/" \
    "::,7:,:,:,,"
DESIGN_SERVICE_SERVER = "@ros2_lv/2/f9980ee0495eaafb3e38f0d19e2eae12/0/10/SS/%/%/add_two_ints_server/" \
    "%add_two_ints/example_interfaces::srv::dds_::AddTwoInts_/" \
    "RIHS01_e118de6bf5eeb66a2491b5bda11202e7b68f198d6f67922cf30364858239c81a/::,10:,:,:,,"
DESIGN_SERVICE_CLIENT = "@ros2_lv/2/e1dc8d1b45ae8717fce78689cc655685/0/10/SC/%/%/add_two_ints_client/" \
    "%add_two_ints/example_interfaces::srv::dds_::AddTwoInts_/" \
    "RIHS01_e118de6bf5eeb66a2491b5bda11202e7b68f198d6f67922cf30364858239c81a/::,10:,:,:,,"

# Captured from `ros2 run demo_nodes_cpp talker --ros-args --remap __ns:=/robot1` on Jazzy or later, posted in
# https://github.com/ros2/rmw_zenoh/issues/643 ("Key Expression Polishment", 2025-05-19), verbatim
CAPTURED_ZID = "999bf91283606d2068c7524e5badfa6c"
CAPTURED_ROSOUT_KEY = "0/rosout/rcl_interfaces::msg::dds_::Log_/" \
    "RIHS01_e28ce254ca8abc06abf92773b74602cdbf116ed34fbaf294fb9f81da9f318eac"
CAPTURED_ROSOUT_PUBLISHER = "@ros2_lv/0/999bf91283606d2068c7524e5badfa6c/0/1/MP/%/%robot1/talker/%rosout/" \
    "rcl_interfaces::msg::dds_::Log_/RIHS01_e28ce254ca8abc06abf92773b74602cdbf116ed34fbaf294fb9f81da9f318eac/" \
    ":1:,1000:,:10,0:,,"
CAPTURED_PARAMETER_EVENTS_KEY = "0/parameter_events/rcl_interfaces::msg::dds_::ParameterEvent_/" \
    "RIHS01_043e627780fcad87a22d225bc2a037361dba713fca6a6b9f4b869a5aa0393204"
CAPTURED_PARAMETER_EVENTS_PUBLISHER = "@ros2_lv/0/999bf91283606d2068c7524e5badfa6c/0/8/MP/%/%robot1/talker/" \
    "%parameter_events/rcl_interfaces::msg::dds_::ParameterEvent_/" \
    "RIHS01_043e627780fcad87a22d225bc2a037361dba713fca6a6b9f4b869a5aa0393204/::,1000:,:,:,,"
CAPTURED_PARAMETER_EVENTS_SUBSCRIPTION = "@ros2_lv/0/999bf91283606d2068c7524e5badfa6c/0/9/MS/%/%robot1/talker/" \
    "%parameter_events/rcl_interfaces::msg::dds_::ParameterEvent_/" \
    "RIHS01_043e627780fcad87a22d225bc2a037361dba713fca6a6b9f4b869a5aa0393204/::,1000:,:,:,,"
# A Humble service's data key and its QoS chunk, from a log of rmw_zenoh 0.1.1 on Humble (whose default durability
# was still TRANSIENT_LOCAL), https://github.com/ros2/rmw_zenoh/issues/693, verbatim
CAPTURED_HUMBLE_SERVICE_KEY = "200/peripherals/environmental_sensors/get_data/" \
    "mk4_interfaces::srv::dds_::GetEnvironmentData_/TypeHashNotSupported"
CAPTURED_HUMBLE_SERVICE_QOS = ":2:,10:,:,:,,"

# rclcpp's profiles as the tokens above were made from them (rmw/qos_profiles.h: the default and services'
# profiles are RELIABLE, VOLATILE, KEEP_LAST 10; the talker asks for depth 7; /rosout is TRANSIENT_LOCAL, depth
# 1000, lifespan 10 s, rcl/logging_rosout.c; parameter events depth 1000, rmw_qos_profile_parameter_events), with
# the unspecified durations rmw_zenoh reads as infinite
UNSPECIFIED = k.DURATION_UNSPECIFIED
RCLCPP_DEFAULT = k.Qos(k.Reliability.RELIABLE, k.Durability.VOLATILE, k.History.KEEP_LAST, 10, UNSPECIFIED,
                       UNSPECIFIED, k.Liveliness.SYSTEM_DEFAULT, UNSPECIFIED)
ROSOUT = replace(RCLCPP_DEFAULT, durability=k.Durability.TRANSIENT_LOCAL, depth=1000, lifespan=(10, 0))
PARAMETER_EVENTS = replace(RCLCPP_DEFAULT, depth=1000)


def test_data_keys_equal_the_design_documents():
    assert k.data_key(0, "/chatter", "std_msgs/msg/String", STRING, k.Distro.JAZZY) == DESIGN_CHATTER_KEY
    assert k.data_key(0, k.fully_qualified_name("/robot1", "chatter"), "std_msgs/msg/String", STRING,
                      k.Distro.KILTED) == DESIGN_NAMESPACED_CHATTER_KEY
    assert k.data_key(2, "/add_two_ints", "example_interfaces/srv/AddTwoInts", ADD_TWO_INTS,
                      k.Distro.LYRICAL) == DESIGN_SERVICE_KEY


def test_data_keys_equal_the_captured_ones():
    # the talker was namespaced /robot1, /rosout and /parameter_events are absolute names: no namespace in the key
    assert k.data_key(0, k.fully_qualified_name("/robot1", "/rosout"), "rcl_interfaces/msg/Log", LOG,
                      k.Distro.JAZZY) == CAPTURED_ROSOUT_KEY
    assert k.data_key(0, "/parameter_events", "rcl_interfaces/msg/ParameterEvent", PARAMETER_EVENT,
                      k.Distro.JAZZY) == CAPTURED_PARAMETER_EVENTS_KEY
    # Humble: the constant in place of the hash, whatever hash is given
    assert k.data_key(200, "/peripherals/environmental_sensors/get_data", "mk4_interfaces/srv/GetEnvironmentData",
                      None, k.Distro.HUMBLE) == CAPTURED_HUMBLE_SERVICE_KEY
    assert k.data_key(0, "/chatter", "std_msgs/msg/String", STRING, k.Distro.HUMBLE).endswith(
        "::String_/TypeHashNotSupported")


def test_node_token_equals_the_design_documents():
    assert k.node_token(2, "aac3178e146ba6f1fc6e6a4085e77f21", 0, "/", "listener") == DESIGN_LISTENER_NODE


def test_endpoint_tokens_equal_the_design_documents():
    common = dict(node_id=0, entity_id=10, namespace="/", distro=k.Distro.JAZZY)
    assert k.endpoint_token(k.EntityKind.SUBSCRIPTION, 2, "aac3178e146ba6f1fc6e6a4085e77f21", node_name="listener",
                            name="/chatter", ros_type="std_msgs/msg/String", type_hash=STRING, qos=RCLCPP_DEFAULT,
                            **common) == DESIGN_LISTENER_SUBSCRIPTION
    assert k.endpoint_token(k.EntityKind.PUBLISHER, 2, "8b20917502ee955ac4476e0266340d5c", node_name="talker",
                            name="/chatter", ros_type="std_msgs/msg/String", type_hash=STRING,
                            qos=replace(RCLCPP_DEFAULT, depth=7), **common) == DESIGN_TALKER_PUBLISHER
    for kind, zid, node, token in ((k.EntityKind.SERVICE_SERVER, "f9980ee0495eaafb3e38f0d19e2eae12",
                                    "add_two_ints_server", DESIGN_SERVICE_SERVER),
                                   (k.EntityKind.SERVICE_CLIENT, "e1dc8d1b45ae8717fce78689cc655685",
                                    "add_two_ints_client", DESIGN_SERVICE_CLIENT)):
        assert k.endpoint_token(kind, 2, zid, node_name=node, name="/add_two_ints",
                                ros_type="example_interfaces/srv/AddTwoInts", type_hash=ADD_TWO_INTS,
                                qos=RCLCPP_DEFAULT, **common) == token


def test_endpoint_tokens_equal_the_captured_talkers():
    common = dict(domain_id=0, zenoh_id=CAPTURED_ZID, node_id=0, namespace="/robot1", node_name="talker",
                  distro=k.Distro.JAZZY)
    assert k.endpoint_token(k.EntityKind.PUBLISHER, entity_id=1, name="/rosout", ros_type="rcl_interfaces/msg/Log",
                            type_hash=LOG, qos=ROSOUT, **common) == CAPTURED_ROSOUT_PUBLISHER
    assert k.endpoint_token(k.EntityKind.PUBLISHER, entity_id=8, name="/parameter_events",
                            ros_type="rcl_interfaces/msg/ParameterEvent", type_hash=PARAMETER_EVENT,
                            qos=PARAMETER_EVENTS, **common) == CAPTURED_PARAMETER_EVENTS_PUBLISHER
    assert k.endpoint_token(k.EntityKind.SUBSCRIPTION, entity_id=9, name="/parameter_events",
                            ros_type="rcl_interfaces/msg/ParameterEvent", type_hash=PARAMETER_EVENT,
                            qos=PARAMETER_EVENTS, **common) == CAPTURED_PARAMETER_EVENTS_SUBSCRIPTION


def test_the_captured_humble_qos_chunk_is_read_with_the_old_defaults():
    # Humble 0.1.1 defaulted to TRANSIENT_LOCAL, so a VOLATILE service wrote its durability, 2
    services = replace(RCLCPP_DEFAULT).adapted(k.RMW_ZENOH_DEFAULT_QOS_BEFORE_VOLATILE)
    assert k.qos_to_keyexpr(services, k.RMW_ZENOH_DEFAULT_QOS_BEFORE_VOLATILE) == CAPTURED_HUMBLE_SERVICE_QOS
    assert k.qos_from_keyexpr(CAPTURED_HUMBLE_SERVICE_QOS, k.RMW_ZENOH_DEFAULT_QOS_BEFORE_VOLATILE) == services
    assert k.qos_to_keyexpr(services) == "::,10:,:,:,,"  # the same profile under today's defaults


@pytest.mark.parametrize("token", [DESIGN_LISTENER_NODE, DESIGN_LISTENER_SUBSCRIPTION, DESIGN_TALKER_PUBLISHER,
                                   DESIGN_SERVICE_SERVER, DESIGN_SERVICE_CLIENT, CAPTURED_ROSOUT_PUBLISHER,
                                   CAPTURED_PARAMETER_EVENTS_PUBLISHER, CAPTURED_PARAMETER_EVENTS_SUBSCRIPTION])
def test_parsing_a_token_and_building_it_again_gives_the_same_text(token):
    parts = k.parse_token(token)
    if parts.kind is k.EntityKind.NODE:
        rebuilt = k.node_token(parts.domain_id, parts.zenoh_id, parts.node_id, parts.namespace, parts.node_name,
                               parts.enclave)
    else:
        package, kind, name = parts.dds_type.split("::", 2)
        ros_type = f"{package}/{kind}/{name.removeprefix('dds_::').removesuffix('_')}"
        rebuilt = k.endpoint_token(parts.kind, parts.domain_id, parts.zenoh_id, parts.node_id, parts.entity_id,
                                   parts.namespace, parts.node_name, parts.name, ros_type, parts.type_hash,
                                   parts.qos, k.Distro.JAZZY, parts.enclave)
    assert rebuilt == token


def test_parse_reads_the_parts_and_ignores_lyricals_backends_chunk():
    parts = k.parse_token(CAPTURED_ROSOUT_PUBLISHER + "/backends:cpu:")
    assert (parts.namespace, parts.node_name, parts.name, parts.entity_id) == ("/robot1", "talker", "/rosout", 1)
    assert parts.qos.lifespan == (10, 0) and parts.qos.durability is k.Durability.TRANSIENT_LOCAL
    assert parts.qos.deadline == k.DURATION_INFINITE and parts.qos.depth == 1000


def test_the_bridge_s_own_tokens_for_a_namespace_and_humble():
    token = k.endpoint_token(k.EntityKind.PUBLISHER, 7, "1f", 0, 3, "/lab/jaco", "mfvs", "/lab/jaco/camera/image_raw",
                             types.IMAGE.name, types.IMAGE.rihs01, k.Qos(reliability=k.Reliability.BEST_EFFORT,
                                                                         depth=1), k.Distro.HUMBLE)
    assert token == "@ros2_lv/7/1f/0/3/MP/%/%lab%jaco/mfvs/%lab%jaco%camera%image_raw/" \
                    "sensor_msgs::msg::dds_::Image_/TypeHashNotSupported/2::,1:,:,:,,"
    transient = k.Qos(durability=k.Durability.TRANSIENT_LOCAL, depth=1)
    assert k.qos_to_keyexpr(transient) == ":1:,1:,:,:,,"
    assert k.data_key(7, "/lab/jaco/tf_static", types.TF_MESSAGE.name, types.TF_MESSAGE.rihs01, k.Distro.JAZZY) == \
        "7/lab/jaco/tf_static/tf2_msgs::msg::dds_::TFMessage_/" + types.TF_MESSAGE.rihs01
    assert k.liveliness_subscription_key(7) == "@ros2_lv/7/**"


def test_names_resolve_as_rcl_resolves_them():
    assert k.fully_qualified_name("/", "chatter") == "/chatter"
    assert k.fully_qualified_name("/robot1", "chatter") == "/robot1/chatter"
    assert k.fully_qualified_name("/robot1", "/tf") == "/tf"
    assert k.fully_qualified_name("/robot1", "~/state", "mfvs") == "/robot1/mfvs/state"
    assert k.fully_qualified_name("/", "~", "mfvs") == "/mfvs"
    assert k.dds_type_name("std_srvs/srv/Trigger") == "std_srvs::srv::dds_::Trigger_"


def test_adapted_qos_is_what_rmw_zenoh_states():
    asked = k.Qos(k.Reliability.SYSTEM_DEFAULT, k.Durability.SYSTEM_DEFAULT, k.History.SYSTEM_DEFAULT, 0,
                  UNSPECIFIED, UNSPECIFIED, k.Liveliness.SYSTEM_DEFAULT, UNSPECIFIED)
    assert asked.adapted() == k.RMW_ZENOH_DEFAULT_QOS and k.qos_to_keyexpr(asked.adapted()) == "::,:,:,:,,"
    best = k.Qos(reliability=k.Reliability.BEST_AVAILABLE)
    assert best.adapted() == best and k.qos_to_keyexpr(best) == "4::,:,:,:,,"
    with pytest.raises(k.InvalidName, match="UNKNOWN"):
        k.Qos(durability=k.Durability.UNKNOWN).adapted()


qos_profiles = st.builds(
    k.Qos, st.sampled_from(list(k.Reliability)), st.sampled_from(list(k.Durability)),
    st.sampled_from(list(k.History)), st.integers(0, 2**32),
    *(st.tuples(st.integers(0, 2**63), st.integers(0, 999999999)) for _ in range(2)),
    st.sampled_from(list(k.Liveliness)), st.tuples(st.integers(0, 2**63), st.integers(0, 999999999)))


@given(qos_profiles, st.sampled_from([k.RMW_ZENOH_DEFAULT_QOS, k.RMW_ZENOH_DEFAULT_QOS_BEFORE_VOLATILE]))
def test_every_qos_survives_its_text(qos, defaults):
    text = k.qos_to_keyexpr(qos, defaults)
    assert "/" not in text and k.qos_from_keyexpr(text, defaults) == qos


tokens = st.from_regex(r"[A-Za-z_][A-Za-z0-9_]{0,8}", fullmatch=True)


@given(st.integers(0, 232), st.from_regex(r"[1-9a-f][0-9a-f]{0,31}", fullmatch=True), st.integers(0, 99),
       st.integers(0, 99), st.lists(tokens, max_size=3), tokens, st.lists(tokens, min_size=1, max_size=4),
       st.sampled_from([k.EntityKind.PUBLISHER, k.EntityKind.SUBSCRIPTION]), qos_profiles.filter(
           lambda q: k.Reliability.UNKNOWN != q.reliability and q.durability != k.Durability.UNKNOWN
           and q.history != k.History.UNKNOWN and q.liveliness != k.Liveliness.UNKNOWN))
def test_every_endpoint_token_parses_back_to_its_inputs(domain, zid, node_id, entity_id, namespace_parts, node,
                                                        topic_parts, kind, qos):
    namespace = "/" + "/".join(namespace_parts)
    topic = "/" + "/".join(topic_parts)
    token = k.endpoint_token(kind, domain, zid, node_id, entity_id, namespace, node, topic, types.IMAGE.name,
                             types.IMAGE.rihs01, qos, k.Distro.JAZZY)
    parts = k.parse_token(token)
    assert (parts.domain_id, parts.zenoh_id, parts.node_id, parts.entity_id, parts.kind) == \
        (domain, zid, node_id, entity_id, kind)
    assert (parts.namespace, parts.node_name, parts.name, parts.qos) == (namespace, node, topic, qos.adapted())
    assert token.count("/") == 12  # every name's slashes are mangled: the chunks stay where a reader counts them


@pytest.mark.parametrize("call, match", [
    (lambda: k.data_key(0, "chatter", "std_msgs/msg/String", STRING, k.Distro.JAZZY), "fully qualified"),
    (lambda: k.data_key(0, "/chatter", "std_msgs/String", STRING, k.Distro.JAZZY), "ROS type"),
    (lambda: k.data_key(0, "/chatter", "std_msgs/msg/String", None, k.Distro.JAZZY), "RIHS01"),
    (lambda: k.data_key(0, "/chatter", "std_msgs/msg/String", "RIHS01_abc", k.Distro.KILTED), "RIHS01"),
    (lambda: k.data_key(-1, "/chatter", "std_msgs/msg/String", STRING, k.Distro.JAZZY), "domain id"),
    (lambda: k.data_key(0, "/chat*ter", "std_msgs/msg/String", STRING, k.Distro.JAZZY), "fully qualified"),
    (lambda: k.node_token(0, "ABC", 0, "/", "n"), "zenoh id"),
    (lambda: k.node_token(0, "1f", 0, "robot1", "n"), "namespace"),
    (lambda: k.node_token(0, "1f", 0, "/", "a/b"), "node name"),
    (lambda: k.node_token(0, "1f", -1, "/", "n"), "ids"),
    (lambda: k.fully_qualified_name("/", "a//b"), "topic or service name"),
    (lambda: k.fully_qualified_name("/", "~x", "n"), "private name"),
    (lambda: k.endpoint_token(k.EntityKind.PUBLISHER, 0, "1f", 0, 1, "/", "n", "/s", "std_srvs/srv/Trigger",
                              types.TRIGGER.rihs01, k.Qos(), k.Distro.JAZZY), "service"),
    (lambda: k.endpoint_token(k.EntityKind.SERVICE_SERVER, 0, "1f", 0, 1, "/", "n", "/s", "std_msgs/msg/String",
                              STRING, k.Qos(), k.Distro.JAZZY), "message"),
    (lambda: k.parse_token("@ros2_lv/0/1f/0/0/XX/%/%/n"), "entity kind"),
    (lambda: k.parse_token("@ros2_lv/0/1f/0/0/NN/%/%"), "at least 8"),
    (lambda: k.parse_token(DESIGN_TALKER_PUBLISHER.rsplit("/", 1)[0]), "13 chunks"),
    (lambda: k.qos_from_keyexpr("::,7:,:,:,"), "liveliness 3"),
    (lambda: k.qos_from_keyexpr("9::,7:,:,:,,"), "Reliability"),
    (lambda: k.qos_from_keyexpr(":-1:,7:,:,:,,"), "non-negative"),
    (lambda: k.qos_from_keyexpr("::,7:,:,:,,:"), "6"),
])
def test_inputs_rmw_zenoh_would_not_accept_are_refused(call, match):
    with pytest.raises(k.InvalidName, match=match):
        call()
