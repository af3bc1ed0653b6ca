"""A scripted stick (``mfvs jog --script FILE``): what a device would send, step by step, for tests, demos and bug
reports. The file is YAML::

    rate_hz: 50                   # how often the stick is read and a request sent (1..200)
    speed_level: 2                # the speed level the steps use unless they say (1..3; default 3, the top)
    steps:
      - {for_s: 1.5, mode: translation, axes: [0.5, 0, 0], deadman: true}
      - {for_s: 0.5, mode: translation, axes: [0, 0, 0], deadman: false}
      - {for_s: 1.0, mode: wrist, axes: [0, 0, 0.4], deadman: true, speed_level: 1}
      - {for_s: 0.5, deadman: true, device: frozen}   # the device stops being heard: safety stops the arm
      - {for_s: 0.5, deadman: true, device: silent}   # nothing is sent at all (a stale stream)
      - {for_s: 0.1, resume: true}                    # the resume button: a paused task goes on

Axes are the stick's three, each in [-1, 1] (translation: the hand along the base's X, Y, Z; wrist: about the
hand's own axes; fingers: the first axis, positive closes), scaled by the speed level, through the same mapping as a
device's (services/jog/mapping.py). A step's ``mode`` defaults to the previous step's (translation first).
"""
from __future__ import annotations

import enum
import math
from typing import Optional

from protocol.messages import JOG_SPEED_LEVELS, JogMode
from services.runtime.config import ConfigStruct, config_from_mapping, read_yaml

#: the longest a script may run (s): a test or a demo, not a session
MAX_SCRIPT_S = 600.0


class DeviceCondition(str, enum.Enum):
    #: read and sent as a device would be
    OK = "ok"
    #: the requests go on, but the device is no longer heard (a frozen gamepad, an unplugged one whose reader hangs)
    FROZEN = "frozen"
    #: nothing is sent (the stick's program stopped, the network between dropped it)
    SILENT = "silent"


class ScriptStep(ConfigStruct):
    for_s: float
    mode: Optional[JogMode] = None
    axes: tuple[float, float, float] = (0.0, 0.0, 0.0)
    deadman: bool = False
    speed_level: Optional[int] = None
    device: DeviceCondition = DeviceCondition.OK
    #: press the resume button at the step's start (a paused task goes on)
    resume: bool = False

    def __post_init__(self) -> None:
        if not (math.isfinite(self.for_s) and 0.0 < self.for_s <= MAX_SCRIPT_S):
            raise ValueError(f"for_s must be within 0..{MAX_SCRIPT_S:.0f} s")
        if not all(math.isfinite(a) and -1.0 <= a <= 1.0 for a in self.axes):
            raise ValueError("axes must each be within -1..1 (the stick's deflection)")
        if self.speed_level is not None and self.speed_level not in JOG_SPEED_LEVELS:
            raise ValueError(f"speed_level must be one of {JOG_SPEED_LEVELS}")


class JogScript(ConfigStruct):
    steps: list[ScriptStep]
    rate_hz: float = 50.0
    speed_level: int = JOG_SPEED_LEVELS[-1]

    def __post_init__(self) -> None:
        if not (math.isfinite(self.rate_hz) and 1.0 <= self.rate_hz <= 200.0):
            raise ValueError("rate_hz must be within 1..200")
        if self.speed_level not in JOG_SPEED_LEVELS:
            raise ValueError(f"speed_level must be one of {JOG_SPEED_LEVELS}")
        if not self.steps:
            raise ValueError("steps: a script needs at least one step")
        if self.duration_s > MAX_SCRIPT_S:
            raise ValueError(f"the steps last {self.duration_s:.0f} s, more than {MAX_SCRIPT_S:.0f} s")
        mode = JogMode.TRANSLATION
        for step in self.steps:  # each step's mode and level said, the previous step's where it is not
            mode = step.mode = step.mode or mode
            step.speed_level = step.speed_level or self.speed_level

    @property
    def duration_s(self) -> float:
        return sum(step.for_s for step in self.steps)


def load_script(path) -> JogScript:
    """A script file, or a ConfigError naming what is wrong and where."""
    return config_from_mapping(read_yaml(path), JogScript, str(path))


def script_from_mapping(data, name: str = "<script>") -> JogScript:
    return config_from_mapping(data, JogScript, name)


def step_at(script: JogScript, t_s: float) -> Optional[tuple[int, ScriptStep]]:
    """The step (its index and itself) running ``t_s`` after the script's start, or None once it is over."""
    start = 0.0
    for index, step in enumerate(script.steps):
        if t_s < start + step.for_s:
            return index, step
        start += step.for_s
    return None

