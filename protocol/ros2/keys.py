"""The zenoh key expressions and liveliness tokens of rmw_zenoh, built from explicit inputs.

Sources (docs/ros2.md, "The wire", quotes them): rmw_zenoh's design document (docs/design.md at ros2/rmw_zenoh
99a6a2bd, sections "Topic and Service name mapping to Zenoh key expressions" and "Graph Cache") and the code it
documents, liveliness_utils.cpp and qos.cpp of each distro's release (ros2-gbp/rmw_zenoh-release, branches
release/<distro>/rmw_zenoh_cpp: humble 0.1.9, jazzy 0.2.10, kilted 0.6.7, lyrical 0.10.5).

A data key (a publisher's put, a service's queryable)::

    <domain_id>/<fully qualified name without its leading '/'>/<DDS type name>/<type hash>
    0/robot1/chatter/std_msgs::msg::dds_::String_/RIHS01_df668c74...

The name keeps its slashes: they are the key's chunks. A liveliness token, one per node and per endpoint::

    @ros2_lv/<domain_id>/<zenoh id>/<node id>/<node id>/NN/<enclave>/<namespace>/<node name>
    @ros2_lv/<domain_id>/<zenoh id>/<node id>/<entity id>/<MP|MS|SS|SC>/<enclave>/<namespace>/<node name>/
        <fully qualified name>/<DDS type name>/<type hash>/<qos>

where enclave, namespace, node name, name, type and hash are "mangled": every '/' becomes '%' (so "/" is "%",
"/robot1" is "%robot1", "/chatter" is "%chatter"), and the QoS is ``qos_to_keyexpr``'s compact form.

What differs by distro: Humble has no type hashes, its rmw_zenoh writes the constant "TypeHashNotSupported" where
the hash goes (rmw_publisher_data.cpp of release/humble); Jazzy, Kilted and Lyrical write the type's RIHS01 hash
(REP-2011). The tokens' layout is the same in all four; Lyrical may append one more chunk, ``backends:...``, to
tokens of its Buffer message types only (none of the types mfvs publishes). The QoS defaults the compact form leaves
out changed once: durability became VOLATILE in Jazzy 0.2.3 and Humble 0.1.2 (TRANSIENT_LOCAL before:
``RMW_ZENOH_DEFAULT_QOS_BEFORE_VOLATILE``).
"""
from __future__ import annotations

import re
from dataclasses import dataclass, replace
from enum import Enum, IntEnum

#: the admin space of every rmw_zenoh liveliness token, a hermetic zenoh namespace (liveliness_utils.cpp
#: ADMIN_SPACE; design.md "Graph Cache")
ADMIN_SPACE = "@ros2_lv"
#: what Humble's rmw_zenoh writes where later distros write the type hash (release/humble/rmw_zenoh_cpp
#: src/detail/rmw_publisher_data.cpp: ``type_hash_c_str = "TypeHashNotSupported"``)
HUMBLE_TYPE_HASH = "TypeHashNotSupported"
#: the character standing for '/' in a token's names (liveliness_utils.cpp SLASH_REPLACEMENT)
SLASH_REPLACEMENT = "%"


class Distro(Enum):
    """The ROS 2 distribution whose rmw_zenoh the keys are for."""
    HUMBLE = "humble"    # no type hashes: HUMBLE_TYPE_HASH in keys and tokens
    JAZZY = "jazzy"      # RIHS01 hashes; from rmw_zenoh 0.2.4 on the positional attachment (attachment.py)
    KILTED = "kilted"    # as Jazzy 0.2.4+ (liveliness_utils.cpp and qos.cpp identical to jazzy 0.2.10's)
    LYRICAL = "lyrical"  # as Kilted, plus the optional ``backends:`` chunk for Buffer message types

    @property
    def has_type_hashes(self) -> bool:
        return self is not Distro.HUMBLE


class EntityKind(Enum):
    """The entity kinds of a token (liveliness_utils.cpp NODE_STR, PUB_STR, SUB_STR, SRV_STR, CLI_STR)."""
    NODE = "NN"
    PUBLISHER = "MP"
    SUBSCRIPTION = "MS"
    SERVICE_SERVER = "SS"
    SERVICE_CLIENT = "SC"


# The QoS policies, with rmw's numbering (rmw/types.h of rmw 7.3.2, Jazzy: the enums count from 0 in this order;
# the token writes these numbers).
class Reliability(IntEnum):
    SYSTEM_DEFAULT = 0
    RELIABLE = 1
    BEST_EFFORT = 2
    UNKNOWN = 3
    BEST_AVAILABLE = 4


class Durability(IntEnum):
    SYSTEM_DEFAULT = 0
    TRANSIENT_LOCAL = 1
    VOLATILE = 2
    UNKNOWN = 3
    BEST_AVAILABLE = 4


class History(IntEnum):
    SYSTEM_DEFAULT = 0
    KEEP_LAST = 1
    KEEP_ALL = 2
    UNKNOWN = 3


class Liveliness(IntEnum):
    SYSTEM_DEFAULT = 0
    AUTOMATIC = 1
    MANUAL_BY_NODE = 2  # deprecated in rmw, kept for its number
    MANUAL_BY_TOPIC = 3
    UNKNOWN = 4
    BEST_AVAILABLE = 5


#: rmw's infinite duration, (seconds, nanoseconds) (rmw/time.h RMW_DURATION_INFINITE)
DURATION_INFINITE = (9223372036, 854775807)
#: rmw's "unspecified" duration, the default of deadline, lifespan and lease (rmw/time.h RMW_DURATION_UNSPECIFIED)
DURATION_UNSPECIFIED = (0, 0)
#: the depth rmw_zenoh substitutes for 0 (qos.cpp RMW_ZENOH_DEFAULT_HISTORY_DEPTH: "a popular magic number")
RMW_ZENOH_DEFAULT_DEPTH = 42


@dataclass(frozen=True)
class Qos:
    """An endpoint's QoS as rmw_zenoh writes it in a token. The defaults are rmw_zenoh's (qos.cpp, every distro
    since Jazzy 0.2.3 and Humble 0.1.2): what equals them is left out of the token's text."""
    reliability: Reliability = Reliability.RELIABLE
    durability: Durability = Durability.VOLATILE
    history: History = History.KEEP_LAST
    depth: int = RMW_ZENOH_DEFAULT_DEPTH
    deadline: tuple[int, int] = DURATION_INFINITE
    lifespan: tuple[int, int] = DURATION_INFINITE
    liveliness: Liveliness = Liveliness.AUTOMATIC
    liveliness_lease_duration: tuple[int, int] = DURATION_INFINITE

    def adapted(self, defaults: "Qos | None" = None) -> "Qos":
        """The profile rmw_zenoh puts in the token (QoS::best_available_qos, run on every endpoint it creates):
        SYSTEM_DEFAULT policies take rmw_zenoh's default, a depth of 0 takes 42, an unspecified
        duration (0, 0) is infinite. BEST_AVAILABLE stays as it is, as rmw_zenoh leaves it. An UNKNOWN policy is
        refused, as rmw_zenoh refuses to create the endpoint (QoS::is_supported)."""
        defaults = defaults or RMW_ZENOH_DEFAULT_QOS
        if self.reliability is Reliability.UNKNOWN or self.durability is Durability.UNKNOWN or \
                self.history is History.UNKNOWN or self.liveliness is Liveliness.UNKNOWN:
            raise InvalidName(f"{self}: rmw_zenoh creates no endpoint with an UNKNOWN policy")
        unset = (0,)  # SYSTEM_DEFAULT in every policy
        return replace(
            self,
            reliability=defaults.reliability if self.reliability in unset else self.reliability,
            durability=defaults.durability if self.durability in unset else self.durability,
            history=defaults.history if self.history in unset else self.history,
            depth=defaults.depth if self.depth == 0 else self.depth,
            deadline=defaults.deadline if self.deadline == DURATION_UNSPECIFIED else self.deadline,
            lifespan=defaults.lifespan if self.lifespan == DURATION_UNSPECIFIED else self.lifespan,
            liveliness=defaults.liveliness if self.liveliness in unset else self.liveliness,
            liveliness_lease_duration=(defaults.liveliness_lease_duration
                                       if self.liveliness_lease_duration == DURATION_UNSPECIFIED
                                       else self.liveliness_lease_duration))


#: rmw_zenoh's default profile (qos.cpp of humble 0.1.9, jazzy 0.2.10, kilted 0.6.7, lyrical 0.10.5)
RMW_ZENOH_DEFAULT_QOS = Qos()
#: the defaults of Humble 0.1.0-0.1.1 and Jazzy 0.2.0-0.2.2, whose durability default was TRANSIENT_LOCAL
#: ("Switch default durability to volatile", rmw_zenoh #530, released in Jazzy 0.2.3): to read their tokens
RMW_ZENOH_DEFAULT_QOS_BEFORE_VOLATILE = replace(RMW_ZENOH_DEFAULT_QOS, durability=Durability.TRANSIENT_LOCAL)


class InvalidName(ValueError):
    """A ROS name, id or type that rmw_zenoh would not put in a key."""


def _unless_default(value, default) -> str:
    return "" if value == default else str(int(value))


def qos_to_keyexpr(qos: Qos, defaults: Qos = RMW_ZENOH_DEFAULT_QOS) -> str:
    """The QoS chunk of a token (liveliness_utils.cpp qos_to_keyexpr), each part empty when it equals the default::

        <reliability>:<durability>:<history>,<depth>:<deadline s>,<ns>:<lifespan s>,<ns>:<liveliness>,<lease s>,<ns>

    ``::,7:,:,:,,`` is a depth of 7 with everything else default (design.md's talker)."""
    parts = [
        _unless_default(qos.reliability, defaults.reliability),
        _unless_default(qos.durability, defaults.durability),
        f"{_unless_default(qos.history, defaults.history)},{_unless_default(qos.depth, defaults.depth)}",
    ]
    for duration, default in ((qos.deadline, defaults.deadline), (qos.lifespan, defaults.lifespan)):
        parts.append(f"{_unless_default(duration[0], default[0])},{_unless_default(duration[1], default[1])}")
    lease, default_lease = qos.liveliness_lease_duration, defaults.liveliness_lease_duration
    parts.append(f"{_unless_default(qos.liveliness, defaults.liveliness)},"
                 f"{_unless_default(lease[0], default_lease[0])},{_unless_default(lease[1], default_lease[1])}")
    return ":".join(parts)


def qos_from_keyexpr(text: str, defaults: Qos = RMW_ZENOH_DEFAULT_QOS) -> Qos:
    """The profile a token's QoS chunk states (liveliness_utils.cpp keyexpr_to_qos: an empty part is the
    default; a number not of its policy, a negative or non-numeric value is refused)."""
    parts = text.split(":")
    if len(parts) != 6:
        raise InvalidName(f"QoS chunk {text!r}: 6 ':'-separated parts are needed, got {len(parts)}")
    history, deadline, lifespan, liveliness = (part.split(",") for part in parts[2:])
    if (len(history), len(deadline), len(lifespan), len(liveliness)) != (2, 2, 2, 3):
        raise InvalidName(f"QoS chunk {text!r}: history, deadline and lifespan take 2 ','-parts, liveliness 3")

    def number(part: str, default: int) -> int:
        if part == "":
            return default
        if not part.isdigit():
            raise InvalidName(f"QoS chunk {text!r}: {part!r} is not a non-negative decimal number")
        return int(part)

    def policy(enum, part: str, default):
        value = number(part, default)
        try:
            return enum(value)
        except ValueError:
            raise InvalidName(f"QoS chunk {text!r}: {part!r} is no {enum.__name__} policy") from None

    return Qos(
        reliability=policy(Reliability, parts[0], defaults.reliability),
        durability=policy(Durability, parts[1], defaults.durability),
        history=policy(History, history[0], defaults.history),
        depth=number(history[1], defaults.depth),
        deadline=(number(deadline[0], defaults.deadline[0]), number(deadline[1], defaults.deadline[1])),
        lifespan=(number(lifespan[0], defaults.lifespan[0]), number(lifespan[1], defaults.lifespan[1])),
        liveliness=policy(Liveliness, liveliness[0], defaults.liveliness),
        liveliness_lease_duration=(number(liveliness[1], defaults.liveliness_lease_duration[0]),
                                   number(liveliness[2], defaults.liveliness_lease_duration[1])))


# ROS 2 names (design.ros2.org, "Topic and Service name mapping"; rcl's validation): tokens of letters, digits and
# '_', not starting with a digit, separated by single '/'. The fully qualified form starts with '/'.
_TOKEN = r"[A-Za-z_][A-Za-z0-9_]*"
_FULLY_QUALIFIED = re.compile(rf"^(/{_TOKEN})+$")
_NODE_NAME = re.compile(rf"^{_TOKEN}$")
_ROS_TYPE = re.compile(rf"^({_TOKEN})/(msg|srv)/({_TOKEN})$")
# a zenoh id as zenoh prints it (and rmw_zenoh writes it): lowercase hex, at most 16 bytes, no leading zeros
_ZENOH_ID = re.compile(r"^[1-9a-f][0-9a-f]{0,31}$")
_RIHS01 = re.compile(r"^RIHS01_[0-9a-f]{64}$")


def mangle(name: str) -> str:
    """A name as a single token chunk: every '/' becomes '%' (liveliness_utils.cpp mangle_name)."""
    return name.replace("/", SLASH_REPLACEMENT)


def demangle(chunk: str) -> str:
    """The name a chunk stands for (liveliness_utils.cpp demangle_name)."""
    return chunk.replace(SLASH_REPLACEMENT, "/")


def check_namespace(namespace: str) -> str:
    """A node namespace: "/" or a fully qualified name ("/robot1")."""
    if namespace != "/" and not _FULLY_QUALIFIED.match(namespace):
        raise InvalidName(f"namespace {namespace!r}: '/' or '/'-separated tokens of [A-Za-z0-9_] (no digit first)")
    return namespace


def check_node_name(name: str) -> str:
    if not _NODE_NAME.match(name):
        raise InvalidName(f"node name {name!r}: one token of [A-Za-z0-9_], not starting with a digit")
    return name


def fully_qualified_name(namespace: str, name: str, node_name: str | None = None) -> str:
    """The name a topic or service of a node in ``namespace`` resolves to (rcl's expansion): an absolute name
    ("/rosout") stays, a relative one ("chatter") goes under the namespace, a private one ("~/state") under the
    node. Substitutions ({node}) are not handled: mfvs's names have none."""
    check_namespace(namespace)
    if name.startswith("~"):
        if node_name is None:
            raise InvalidName(f"private name {name!r} needs the node's name")
        base = namespace.rstrip("/") + "/" + check_node_name(node_name)
        if name != "~" and not name.startswith("~/"):
            raise InvalidName(f"private name {name!r}: '~' or '~/' and a relative name")
        name = base + name[1:]
    elif not name.startswith("/"):
        name = namespace.rstrip("/") + "/" + name
    if not _FULLY_QUALIFIED.match(name):
        raise InvalidName(f"topic or service name {name!r}: '/'-separated tokens of [A-Za-z0-9_] (no digit first)")
    return name


def dds_type_name(ros_type: str) -> str:
    """The DDS name rmw_zenoh uses for a ROS type: ``sensor_msgs/msg/Image`` is ``sensor_msgs::msg::dds_::Image_``
    (type_support_common.cpp _create_type_name). A service's (``std_srvs/srv/Trigger``) is its response type's
    name less ``Response_``: ``std_srvs::srv::dds_::Trigger_`` (rmw_service_data.cpp)."""
    match = _ROS_TYPE.match(ros_type)
    if not match:
        raise InvalidName(f"ROS type {ros_type!r}: '<package>/msg/<Name>' or '<package>/srv/<Name>'")
    package, kind, name = match.groups()
    return f"{package}::{kind}::dds_::{name}_"


def wire_type_hash(type_hash: str | None, distro: Distro) -> str:
    """What goes where a key has the type hash: the RIHS01 hash from Jazzy on, HUMBLE_TYPE_HASH on Humble."""
    if not distro.has_type_hashes:
        return HUMBLE_TYPE_HASH
    if type_hash is None or not _RIHS01.match(type_hash):
        raise InvalidName(f"{distro.value} needs the type's RIHS01 hash ('RIHS01_' and 64 hex digits), "
                          f"got {type_hash!r}")
    return type_hash


def _check_domain(domain_id: int) -> int:
    # ROS_DOMAIN_ID: rmw_zenoh writes any size_t; ROS documents 0-232 (DDS's port arithmetic), but rmw_zenoh has no
    # ports to compute, and issue ros2/rmw_zenoh#693 shows a domain of 200 in use: any non-negative int is taken
    if isinstance(domain_id, bool) or not isinstance(domain_id, int) or domain_id < 0:
        raise InvalidName(f"domain id {domain_id!r}: a non-negative integer")
    return domain_id


def data_key(domain_id: int, name: str, ros_type: str, type_hash: str | None, distro: Distro) -> str:
    """The key a topic's samples are put on, or a service's queries sent to (liveliness_utils.cpp TopicInfo:
    strip_slashes takes the fully qualified name's leading '/')::

        data_key(0, "/robot1/chatter", "std_msgs/msg/String", STRING_HASH, Distro.JAZZY)
        == "0/robot1/chatter/std_msgs::msg::dds_::String_/RIHS01_df668c74..."
    """
    if not _FULLY_QUALIFIED.match(name):
        raise InvalidName(f"{name!r} is not a fully qualified name (fully_qualified_name() makes one)")
    return f"{_check_domain(domain_id)}/{name[1:]}/{dds_type_name(ros_type)}/{wire_type_hash(type_hash, distro)}"


def liveliness_subscription_key(domain_id: int) -> str:
    """What a graph watcher subscribes to: every token of a domain (liveliness_utils.cpp subscription_token)."""
    return f"{ADMIN_SPACE}/{_check_domain(domain_id)}/**"


def _check_ids(zenoh_id: str, *ids: int) -> None:
    if not isinstance(zenoh_id, str) or not _ZENOH_ID.match(zenoh_id):
        raise InvalidName(f"zenoh id {zenoh_id!r}: lowercase hex as zenoh prints it, at most 32 digits")
    for value in ids:
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            raise InvalidName(f"node and entity ids are non-negative integers, got {value!r}")


def _node_part(domain_id: int, zenoh_id: str, node_id: int, entity_id: int, kind: EntityKind, enclave: str,
               namespace: str, node_name: str) -> str:
    _check_ids(zenoh_id, node_id, entity_id)
    if enclave != "/" and not _FULLY_QUALIFIED.match(enclave):
        raise InvalidName(f"enclave {enclave!r}: '/' or a fully qualified name")
    return "/".join((ADMIN_SPACE, str(_check_domain(domain_id)), zenoh_id, str(node_id), str(entity_id), kind.value,
                     mangle(enclave), mangle(check_namespace(namespace)), mangle(check_node_name(node_name))))


def node_token(domain_id: int, zenoh_id: str, node_id: int, namespace: str, node_name: str,
               enclave: str = "/") -> str:
    """A node's liveliness token; its id stands twice, as node and as entity (rmw_node_data.cpp)::

        @ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/0/NN/%/%/listener

    The enclave is SROS's, "/" (mangled "%") when security is off (design.md: "just % if not set")."""
    return _node_part(domain_id, zenoh_id, node_id, node_id, EntityKind.NODE, enclave, namespace, node_name)


def endpoint_token(kind: EntityKind, domain_id: int, zenoh_id: str, node_id: int, entity_id: int,
                   namespace: str, node_name: str, name: str, ros_type: str, type_hash: str | None, qos: Qos,
                   distro: Distro, enclave: str = "/") -> str:
    """A publisher's, subscription's, service server's or client's liveliness token (liveliness_utils.cpp
    Entity::Entity; design.md "Graph Cache")::

        @ros2_lv/2/8b20917502ee955ac4476e0266340d5c/0/10/MP/%/%/talker/%chatter/std_msgs::msg::dds_::String_/
            RIHS01_df668c74.../::,7:,:,:,,

    ``name`` is the fully qualified topic or service name, ``ros_type`` the message or service type, ``qos`` as
    the endpoint was asked for: the token states ``qos.adapted()``, as rmw_zenoh does."""
    if kind is EntityKind.NODE:
        raise InvalidName("a node's token is node_token()")
    if not _FULLY_QUALIFIED.match(name):
        raise InvalidName(f"{name!r} is not a fully qualified name (fully_qualified_name() makes one)")
    is_service_type = dds_type_name(ros_type).split("::")[1] == "srv"
    if is_service_type != (kind in (EntityKind.SERVICE_SERVER, EntityKind.SERVICE_CLIENT)):
        raise InvalidName(f"a {kind.name.lower()} does not carry a {'service' if is_service_type else 'message'} "
                          f"type ({ros_type})")
    head = _node_part(domain_id, zenoh_id, node_id, entity_id, kind, enclave, namespace, node_name)
    return "/".join((head, mangle(name), mangle(dds_type_name(ros_type)), mangle(wire_type_hash(type_hash, distro)),
                     qos_to_keyexpr(qos.adapted())))


@dataclass(frozen=True)
class Token:
    """A liveliness token's parts, as a graph watcher reads them (liveliness_utils.cpp Entity::make)."""
    domain_id: int
    zenoh_id: str
    node_id: int
    entity_id: int
    kind: EntityKind
    enclave: str
    namespace: str
    node_name: str
    name: str | None = None
    dds_type: str | None = None
    type_hash: str | None = None
    qos: Qos | None = None


def parse_token(token: str, defaults: Qos = RMW_ZENOH_DEFAULT_QOS) -> Token:
    """The parts of a liveliness token (an optional trailing ``backends:`` chunk, Lyrical's, is ignored)."""
    parts = token.split("/")
    if len(parts) < 9 or parts[0] != ADMIN_SPACE or any(part == "" for part in parts):
        raise InvalidName(f"token {token!r}: '{ADMIN_SPACE}/' and at least 8 non-empty chunks are needed")
    try:
        kind = EntityKind(parts[5])
    except ValueError:
        raise InvalidName(f"token {token!r}: entity kind {parts[5]!r} is none of NN, MP, MS, SS, SC") from None
    if not all(part.isdigit() for part in parts[1:2] + parts[3:5]):
        raise InvalidName(f"token {token!r}: domain, node and entity ids must be decimal numbers")
    common = dict(domain_id=int(parts[1]), zenoh_id=parts[2], node_id=int(parts[3]), entity_id=int(parts[4]),
                  kind=kind, enclave=demangle(parts[6]), namespace=demangle(parts[7]), node_name=demangle(parts[8]))
    if kind is EntityKind.NODE:
        if len(parts) != 9:
            raise InvalidName(f"node token {token!r}: 9 chunks, got {len(parts)}")
        return Token(**common)
    if len(parts) not in (13, 14) or (len(parts) == 14 and not parts[13].startswith("backends:")):
        raise InvalidName(f"{kind.name.lower()} token {token!r}: 13 chunks (a 14th only 'backends:...'), "
                          f"got {len(parts)}")
    return Token(**common, name=demangle(parts[9]), dds_type=demangle(parts[10]), type_hash=demangle(parts[11]),
                 qos=qos_from_keyexpr(parts[12], defaults))
