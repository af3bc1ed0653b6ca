"""Who may command the arm through safety, and which of them does now: the command sources (ros2_control's exclusive
claim on a command interface, as a pure rule).

Every desired command names its source (``Twist.source``, ``JointVelocity.source``): a declared source's name, and
after a slash what it is doing (``controller/servo``, ``controller/probe``). Safety's configuration declares each
source once (:class:`CommandSource`): the keys its commands arrive on, what they may drive, its priority (the person
first) and how their freshness is judged. A command from a source that is not declared for the key it came on, or
that drives what its source may not, is refused before any other check (:meth:`SourceRegistry.admit`).

One source is in control at a time (:class:`Claim`): the one whose command safety holds. Another source takes over
only with a higher priority, or once the holder has let go (its command refused, stale or stopped: safety holds
nothing of it any more); each change is counted and said in ``SafetyStatus.in_control``. A lower or equal priority
source's command while another holds is refused, naming the holder: it is not a stop of the holder's motion.
A source that was displaced by a higher priority (the servo, by the person's stick) takes control again only with a
command at rest: the person letting go of the stick never hands the arm back to a motion they interrupted; the
controller pauses its task when it hears that another source is in control, and only a resume moves it on.
"""
from __future__ import annotations

import enum
import re
from typing import Optional

from protocol.messages import declared_source as declared_name
from services.runtime.config import ConfigStruct


class Drives(str, enum.Enum):
    """What a source's commands may drive."""

    #: the end effector, by a mixed-frame twist (``desired_twist``)
    TWIST = "twist"
    #: the joints, by joint velocities (``desired_joint_velocity``)
    JOINT_VELOCITY = "joint_velocity"
    #: the hand's fingers, by the ``fingers`` part of either command (a task's grasp and release)
    FINGERS = "fingers"


class Freshness(str, enum.Enum):
    """How a source's commands are judged fresh (``SafetyCore.input_problem``).

    ``image``: derived from a camera image, whose capture stamp the command carries (``source_stamp_ns``): the
    command and its image within their budgets, the services on the image's path (safety's ``upstream``) alive.
    ``device``: made from a person's input device (a joystick): the command within its budget, the device heard
    within its own (``source_stamp_ns``: when the source last had proof that the device is there, docs/contracts.md),
    each command's sequence number above the last; no service upstream is needed, and none of the image path's
    losses stops it. A person's device runs on wall time: never in a lockstep run."""

    IMAGE = "image"
    DEVICE = "device"


class NearSingularity(str, enum.Enum):
    """What safety does with a source's twist toward a singularity (services/model/singularity.py).

    ``stop``: slowed from ``limits.singularity.slow_from`` and stopped before ``stop_at``, no faster than the arm
    can still brake from (MoveIt Servo's rule, and ours): for a person's stick, open loop, who drives into a
    singularity and then away from it. ``robot``: left to the robot's own handling, as the seed papers' JACO-2 ran
    (its DSP's damped least squares, services/robot/dsp.py): for a closed loop such as the visual servo, whose
    command does not change while the arm stands, so that a stop would hold it at the bound for good. Measured on
    seed 000's markerless random starts (seed 7, the cup, 26 starts): with ``stop`` the servo stood at the bound on
    2 of the 26 and the tag's servo on 2 others, each for its 1000 iterations; with ``robot`` all 26 converge."""

    STOP = "stop"
    ROBOT = "robot"


#: a source's name, as commands give it before the slash
SOURCE_NAME = re.compile(r"^[a-z][a-z0-9_\-]{0,31}$")


class CommandSource(ConfigStruct):
    """One source of robot motion that safety takes commands from."""

    name: str
    #: the keys its commands arrive on (protocol.keys.Keys attributes: desired_twist, desired_joint_velocity)
    keys: list[str]
    drives: list[Drives]
    #: a higher priority takes control from a lower one (the person's joystick above the servo)
    priority: int = 0
    freshness: Freshness = Freshness.IMAGE
    #: its twists toward a singularity: stopped before it by safety, or left to the robot (:class:`NearSingularity`)
    singularity: NearSingularity = NearSingularity.STOP
    #: the identity the deployment's access control lets publish on its keys (docs/security.md); said here so that
    #: `mfvs status` shows who a source is; the router enforces it
    identity: Optional[str] = None

    def __post_init__(self) -> None:
        if not SOURCE_NAME.match(self.name):
            raise ValueError(f"command source name {self.name!r} must be 1-32 of a-z, 0-9, _ and -, starting with "
                             "a letter")
        self.freshness = Freshness(self.freshness)  # compared by identity; a config file's string made the enum
        self.singularity = NearSingularity(self.singularity)
        if not self.keys or not self.drives:
            raise ValueError(f"command source {self.name!r} needs the keys its commands come on and what they drive")


#: what each command key carries
KEY_DRIVES = {"desired_twist": Drives.TWIST, "desired_joint_velocity": Drives.JOINT_VELOCITY,
              "desired_jog": Drives.TWIST}


def default_sources() -> list[CommandSource]:
    """The controller: the visual servo and its task's phases (a grasp's fingers among them), from images; the
    person's stick (services/jog): the hand and the fingers, from a device, above the servo."""
    return [CommandSource(name="controller", keys=["desired_twist", "desired_joint_velocity"],
                          drives=[Drives.TWIST, Drives.JOINT_VELOCITY, Drives.FINGERS], priority=10,
                          freshness=Freshness.IMAGE, singularity=NearSingularity.ROBOT, identity="controller"),
            CommandSource(name="jog", keys=["desired_jog"], drives=[Drives.TWIST, Drives.FINGERS], priority=20,
                          freshness=Freshness.DEVICE, identity="jog")]


class SourceRegistry:
    def __init__(self, sources: list[CommandSource]) -> None:
        names = [s.name for s in sources]
        if len(set(names)) != len(names):
            raise ValueError(f"command sources declared twice: {sorted({n for n in names if names.count(n) > 1})}")
        for source in sources:
            unknown = [key for key in source.keys if key not in KEY_DRIVES]
            if unknown:
                raise ValueError(f"command source {source.name!r}: unknown keys {unknown}; known: {sorted(KEY_DRIVES)}")
        self.sources = {s.name: s for s in sources}

    def freshness(self, source: str) -> Freshness:
        """The freshness rule of the declared source a command names (image for an undeclared one: it is refused
        before its freshness matters)."""
        declared = self.sources.get(declared_name(source))
        return Freshness.IMAGE if declared is None else declared.freshness

    def stops_near_singularity(self, source: str) -> bool:
        """Whether safety slows and stops the declared source's twists toward a singularity (:class:`NearSingularity`;
        an undeclared one is refused before it matters)."""
        declared = self.sources.get(declared_name(source))
        return declared is None or declared.singularity is NearSingularity.STOP

    def admit(self, source: str, key: str, fingers: bool = False) -> tuple[Optional[CommandSource], str]:
        """(the declared source, "") for a command naming ``source`` on ``key`` (``fingers``: carrying a finger
        part), or (None, why not)."""
        declared = self.sources.get(declared_name(source))
        if declared is None:
            return None, f"source: {source!r} is not a declared command source ({', '.join(self.sources)})"
        if key not in declared.keys:
            return None, f"source: {declared.name} may not command on {key}"
        if KEY_DRIVES[key] not in declared.drives:
            return None, f"source: {declared.name} may not drive {KEY_DRIVES[key].value}"
        if fingers and Drives.FINGERS not in declared.drives:
            return None, f"source: {declared.name} may not drive {Drives.FINGERS.value}"
        return declared, ""


class Claim:
    """Which source is in control. Pure: the core tells it what it holds."""

    def __init__(self) -> None:
        #: the source in control (its full name, e.g. controller/servo), or "" when safety holds nothing
        self.holder = ""
        self._priority = 0
        #: how many times control changed hands (not counting a source letting go)
        self.switches = 0
        #: declared sources a higher priority took control from, and who: each retakes control only at rest
        self.displaced: dict[str, str] = {}

    def refusal(self, candidate: CommandSource, source: str, holding: bool, at_rest: bool = False) -> Optional[str]:
        """Why ``source`` (of ``candidate``) may not take control now, or None. ``holding``: safety holds the
        holder's command (a holder that let go holds nothing); ``at_rest``: the command asks for no motion."""
        if holding and self.holder and declared_name(self.holder) != candidate.name \
                and candidate.priority <= self._priority:
            return f"claim: {self.holder} is in control (priority {self._priority} ≥ {candidate.priority})"
        if candidate.name in self.displaced and not at_rest and declared_name(self.holder) != candidate.name:
            return (f"claim: {candidate.name} was displaced by {self.displaced[candidate.name]} and takes control "
                    "again only from rest (its task pauses)")
        return None

    def take(self, candidate: CommandSource, source: str) -> bool:
        """``source`` is in control now; whether control changed hands."""
        changed = bool(self.holder) and declared_name(self.holder) != candidate.name
        if changed and candidate.priority > self._priority:
            self.displaced[declared_name(self.holder)] = source
        self.displaced.pop(candidate.name, None)
        self.switches += changed
        self.holder, self._priority = source, candidate.priority
        return changed

    def let_go(self) -> None:
        self.holder, self._priority = "", 0

