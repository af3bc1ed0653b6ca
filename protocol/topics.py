"""What is published on each key: the one table of the stack's topics and their message types, for the tools that
see the stack from outside (``mfvs echo``, ``hz``, ``keys``, ``record``, ``replay``, ``view``).

A topic is a published key (put/subscribe); queries (``*/api/*``, health, the arm check) are not topics. The keys
themselves are spelled in :mod:`protocol.keys` only; here each one gets its type.
"""
from __future__ import annotations

import difflib
import re
from dataclasses import dataclass

from protocol import messages as m
from protocol.keys import ROOT, Keys


@dataclass(frozen=True)
class Topic:
    key: str
    message_type: type
    #: who publishes it, as the architecture's contracts say
    publisher: str
    #: on the path from a frame to the arm's motion, or its stop: sent at once and ahead of the rest (images, status)
    #: in every queue on the way (services.runtime.transport.publisher_options)
    control_path: bool = False


def topics(keys: Keys) -> list[Topic]:
    """Every topic of one robot's stack (``Keys.all_robots()`` for every robot's)."""
    return [
        Topic(keys.camera_image, m.Image, "robot_sim or camera"),
        Topic(keys.camera_info, m.CameraInfo, "robot_sim or camera"),
        Topic(keys.features, m.Features, "vision", control_path=True),
        Topic(keys.vision_goal, m.VisionGoal, "operator"),
        Topic(keys.desired_twist, m.Twist, "controller", control_path=True),
        Topic(keys.desired_joint_velocity, m.JointVelocity, "controller", control_path=True),
        Topic(keys.desired_jog, m.Jog, "jog (a person's stick: mfvs jog, the console's stick as the jog identity, or a "
              "ROS 2 one relayed by ros2_bridge)", control_path=True),
        Topic(keys.controller_status, m.ControllerStatus, "controller"),
        Topic(keys.robot_command, m.RobotCommand, "safety", control_path=True),
        Topic(keys.safety_status, m.SafetyStatus, "safety"),
        Topic(keys.estop, m.EStop, "operator", control_path=True),
        Topic(keys.robot_state, m.RobotState, "robot_sim or robot_gateway", control_path=True),
        Topic(keys.lowlevel_command, m.TorqueCommand, "a low-level client (torque_controller)", control_path=True),
        Topic(keys.lowlevel_state, m.LowLevelState, "robot_sim or robot_gateway", control_path=True),
        Topic(keys.clock, m.SimClock, "robot_sim"),
        Topic(keys.sim_objects, m.SimObjects, "robot_sim, where its scene has free objects"),
        # one key per service (a wildcard here); each service also answers a query on its own
        Topic(keys.health_all, m.ServiceHealth, "every service, 1 Hz"),
    ]


class UnknownTopic(ValueError):
    """A key that is no topic of the stack (a typo, a query's key, another program's key)."""


def _suffix(key: str) -> tuple[str, str]:
    """(robot id, the key after ``mfvs/<robot id>/``); raises UnknownTopic for a key outside the stack."""
    parts = key.strip("/").split("/", 2)
    if len(parts) < 3 or parts[0] != ROOT:
        raise UnknownTopic(f"{key!r} is not an mfvs key: they read {ROOT}/<robot id>/<topic>, e.g. "
                           f"{Keys().robot_state}")
    return parts[1], parts[2]


def topic_of(key: str) -> Topic:
    """The topic a concrete key (``mfvs/jaco/robot/state``) names; UnknownTopic, with the closest topic when
    there is one, otherwise."""
    robot_id, suffix = _suffix(key)
    table = {_suffix(t.key)[1]: t for t in topics(Keys.all_robots())}
    found = table.get(suffix) or next((t for pattern, t in table.items()
                                       if "*" in pattern and key_pattern(pattern).match(suffix)), None)
    if found is not None:
        return Topic(key if "*" not in robot_id else found.key, found.message_type, found.publisher,
                     found.control_path)
    close = difflib.get_close_matches(suffix, list(table), n=1)
    hint = f"; did you mean {ROOT}/{robot_id}/{close[0]}?" if close else f"; the topics: {', '.join(sorted(table))}"
    raise UnknownTopic(f"{key!r} is no topic of the stack{hint}")


def key_pattern(pattern: str) -> "re.Pattern[str]":
    """A zenoh key pattern as a regular expression over keys: ``*`` one chunk, ``**`` any number of chunks."""
    chunks = []
    for chunk in pattern.strip("/").split("/"):
        chunks.append({"**": "(?:[^/]+(?:/[^/]+)*)?", "*": "[^/]+"}.get(chunk, re.escape(chunk)))
    return re.compile("/".join(chunks).replace("/(?:[^/]+(?:/[^/]+)*)?", "(?:/[^/]+)*") + "$")


def resolve(pattern: str, keys: Keys) -> str:
    """A key or pattern as given on a command line: whole (``mfvs/jaco/robot/state``) or below the robot's prefix
    (``robot/state``, ``**``)."""
    pattern = pattern.strip().strip("/")
    if not pattern:
        raise UnknownTopic("an empty key")
    return pattern if pattern.split("/", 1)[0] == ROOT else f"{keys.prefix}/{pattern}"


def matching(pattern: str, keys: Keys) -> list[Topic]:
    """The topics of ``keys`` a key pattern selects (see :func:`resolve`): a topic's key, or a zenoh wildcard
    pattern (``*`` one chunk, ``**`` any); UnknownTopic when it selects none."""
    pattern = resolve(pattern, keys)
    expression = key_pattern(pattern)
    chosen = [t for t in topics(keys) if expression.match(t.key)]
    if not chosen:
        if "*" not in pattern:
            topic_of(pattern)  # says what is wrong with it
        raise UnknownTopic(f"{pattern!r} selects none of the stack's topics for robot {keys.robot_id!r}")
    return chosen
