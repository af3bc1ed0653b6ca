"""`mfvs jog`'s configuration (services/jog/jog.yaml: every key shown with its default)."""
from __future__ import annotations

import math

import msgspec

from protocol.messages import JOG_SOURCE, JOG_SPEED_LEVELS, SourceName
from services.jog.evdev_input import GamepadMap
from services.jog.mapping import JogMapping
from services.runtime.config import ConfigStruct


def check_stream(source: str, rate_hz: float, where: str = "") -> None:
    """A stick's stream's source and rate, or ValueError (``where``: the keys' prefix, e.g. ``jog.``)."""
    if not source.startswith("jog/"):
        raise ValueError(f"{where}source {source!r}: a jog's source is jog/<device>")
    if not (math.isfinite(rate_hz) and 10.0 <= rate_hz <= 200.0):
        raise ValueError(f"{where}rate_hz must be within 10..200 (safety stops a jog unheard for 100 ms)")


class JogConfig(ConfigStruct):
    #: the commands' source: jog/<device> (safety's sources declare jog; each device counts its own sequence)
    source: SourceName = JOG_SOURCE
    #: how often a device is read and a request sent (Hz): 50, twice safety's need (its command budget is 100 ms,
    #: so four requests in a row may be lost before it stops the arm): our choice
    rate_hz: float = 50.0
    #: the speed level a device starts at (1..3: Kinova's ÷2 per level below the top): the slowest, our choice, for
    #: a person's first touch
    speed_level: int = JOG_SPEED_LEVELS[0]
    mapping: JogMapping = msgspec.field(default_factory=JogMapping)
    gamepad: GamepadMap = msgspec.field(default_factory=GamepadMap)

    def __post_init__(self) -> None:
        check_stream(self.source, self.rate_hz)
        if self.speed_level not in JOG_SPEED_LEVELS:
            raise ValueError(f"speed_level must be one of {JOG_SPEED_LEVELS}")
