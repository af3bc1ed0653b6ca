"""A stick's axes and buttons as a person's jog request (protocol.messages.Jog), the way Kinova's joystick maps them.
Pure: no device, no zenoh, no clock of its own (each call is given the time).

Kinova's joystick (KinovaTypes.h ``JoystickCommand``: six axes, sixteen buttons, mode lists A and B) moves the hand
in the mixed frame: in translation mode along the base's X, Y, Z, in wrist mode about the hand's own axes, in
finger mode the fingers together; its speed buttons double or halve the speed. The steps, each one named function:

1. :func:`apply_dead_band`: an axis inside the dead band is zero, the rest rescaled to start from zero at its edge
   (the ROS ``joy`` node's ``deadzone`` does the same, so a stick resting off-centre does not creep);
2. :func:`lock_diagonals` (when asked): only the axis pushed furthest moves, as a person with a tremor asks;
3. :class:`SpasmFilter`: a deflection grows no faster than a ramp of ``rise_s`` with its rate changing no faster
   than over ``jerk_s`` (a sudden full push, a spasm, becomes a short ramp); a deflection that shrinks, and a release,
   pass at once (letting go must never be slowed);
4. :func:`speed_factor` and the mode's full speeds (:class:`JogSpeeds`): the request in m/s, rad/s.

Kinova's ``SetSpasmFilterValues`` takes one value and an activation flag (SPASM_FILTER_COUNT is 1 in its headers);
what the value means is not documented, so the filter here and its parameters are ours (docs/jog.md).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import msgspec
import numpy as np

from protocol.messages import JOG_SPEED_LEVELS, MAX_JOG_SPEED, JogMode
from services.runtime.config import ConfigStruct

#: the modes a mode button cycles through, in order (Kinova's mode list A: translation, wrist, fingers)
MODE_CYCLE = (JogMode.TRANSLATION, JogMode.WRIST, JogMode.FINGERS)


class JogSpeeds(ConfigStruct):
    """The full speed of each mode at the top speed level (the others: halved per level below, as Kinova's ÷2)."""

    #: m/s: the JACO-2's product sheet gives 20 cm/s as its top linear speed (../shared/reference/kinova.md)
    linear_mps: float = 0.2
    #: rad/s about the hand's axes: 0.6 (34°/s), under the wrist joints' 48°/s and the shoulder's 36°/s
    #: (kinova.md), so a turn at full stick stays within what the joints can give: our choice
    angular_rps: float = 0.6
    #: rad/s of every finger: 1.0, our choice, below the KG-3's full travel over its closing time (its max_speed)
    finger_rps: float = 1.0

    def __post_init__(self) -> None:
        for name in ("linear_mps", "angular_rps", "finger_rps"):
            value = getattr(self, name)
            if not (math.isfinite(value) and 0.0 < value <= MAX_JOG_SPEED):
                raise ValueError(f"speeds.{name} must be within 0..{MAX_JOG_SPEED}")


class SpasmFilterConfig(ConfigStruct):
    """Our parameters (the module's docstring): a full push takes about ``rise_s + jerk_s`` to reach full speed."""

    enabled: bool = True
    #: the fastest a deflection grows: from rest to full in this long (s)
    rise_s: float = 0.25
    #: how long the growth rate takes to reach its fastest (s): no step in the rate either
    jerk_s: float = 0.1

    def __post_init__(self) -> None:
        if not (0.0 < self.rise_s <= 5.0 and 0.0 < self.jerk_s <= 5.0):
            raise ValueError("spasm_filter.rise_s and jerk_s must be within 0..5 s")


class JogMapping(ConfigStruct):
    """How a stick's axes become a jog request (services/jog/jog.yaml)."""

    speeds: JogSpeeds = msgspec.field(default_factory=JogSpeeds)
    #: an axis within this of its centre is zero (the rest rescaled): 0.1, our choice, above the 5 % the ROS joy
    #: node sets by default, for a worn stick and a hand that trembles
    dead_band: float = 0.1
    #: only the axis pushed furthest moves
    lock_diagonals: bool = False
    spasm_filter: SpasmFilterConfig = msgspec.field(default_factory=SpasmFilterConfig)

    def __post_init__(self) -> None:
        if not 0.0 <= self.dead_band < 0.5:
            raise ValueError("dead_band must be within 0..0.5")


@dataclass
class StickInput:
    """What a stick says at one moment: its three axes in [-1, 1] (for the mode: translation X, Y, Z of the base;
    wrist about the hand's x, y, z; fingers: the first axis), the mode, the speed level and the dead-man."""

    axes: tuple[float, float, float]
    mode: JogMode
    speed_level: int
    deadman: bool


def apply_dead_band(axes: np.ndarray, dead_band: float) -> np.ndarray:
    """Each axis: 0 within ``dead_band`` of the centre, else rescaled so it rises from 0 at the band's edge to ±1."""
    axes = np.clip(np.asarray(axes, dtype=float), -1.0, 1.0)
    magnitude = np.abs(axes)
    out = np.where(magnitude <= dead_band, 0.0, (magnitude - dead_band) / (1.0 - dead_band))
    return np.sign(axes) * out


def lock_diagonals(axes: np.ndarray) -> np.ndarray:
    """Only the axis pushed furthest (the first of equals), the others zero."""
    axes = np.asarray(axes, dtype=float)
    out = np.zeros_like(axes)
    if np.any(axes):
        strongest = int(np.argmax(np.abs(axes)))
        out[strongest] = axes[strongest]
    return out


def speed_factor(level: int) -> float:
    """The fraction of the full speed at a speed level: the top level 1, each below it half (Kinova's ÷2)."""
    if level not in JOG_SPEED_LEVELS:
        raise ValueError(f"speed level {level} is not one of {JOG_SPEED_LEVELS}")
    return 0.5 ** (JOG_SPEED_LEVELS[-1] - level)


class SpasmFilter:
    """Each axis's growth limited in rate (1/rise_s) and in the rate's change (1/(rise_s·jerk_s)); a shrink passes
    at once. Stateful: one per stick, :meth:`reset` on a mode change or a release."""

    def __init__(self, config: SpasmFilterConfig, n: int = 3) -> None:
        self.config = config
        self.value = np.zeros(n)
        self.rate = np.zeros(n)
        self._t: Optional[float] = None

    def reset(self) -> None:
        self.value[:] = 0.0
        self.rate[:] = 0.0
        self._t = None

    def __call__(self, target: np.ndarray, t_s: float) -> np.ndarray:
        target = np.asarray(target, dtype=float)
        cfg = self.config
        if not cfg.enabled:
            self.value = target.copy()
            return self.value.copy()
        dt = 0.0 if self._t is None else max(0.0, t_s - self._t)
        self._t = t_s
        max_rate = 1.0 / cfg.rise_s
        max_rate_change = max_rate / cfg.jerk_s * dt
        for i, (value, wanted) in enumerate(zip(self.value, target)):
            shrinking = abs(wanted) <= abs(value) or (value != 0.0 and np.sign(wanted) != np.sign(value))
            if shrinking:  # toward the centre, or across it: at once (a release is never slowed)
                self.value[i] = wanted if np.sign(wanted) == np.sign(value) or value == 0.0 else 0.0
                self.rate[i] = 0.0
                continue
            direction = np.sign(wanted)
            rate = min(abs(self.rate[i]) + max_rate_change, max_rate)
            step = min(rate * dt, abs(wanted - value))
            self.value[i] = value + direction * step
            self.rate[i] = direction * rate
        return self.value.copy()


@dataclass
class JogMotion:
    """The request for one moment: what a Jog message carries beside its header."""

    mode: JogMode
    speed_level: int
    deadman: bool
    linear: tuple[float, float, float] = (0.0, 0.0, 0.0)
    angular: tuple[float, float, float] = (0.0, 0.0, 0.0)
    finger_rate: float = 0.0


class StickMapper:
    """A stick's inputs over time as jog requests: dead band, diagonal lock, spasm filter, the mode's speeds."""

    def __init__(self, mapping: JogMapping) -> None:
        self.mapping = mapping
        self.filter = SpasmFilter(mapping.spasm_filter)
        self._mode: Optional[JogMode] = None

    def __call__(self, stick: StickInput, t_s: float) -> JogMotion:
        cfg = self.mapping
        if stick.mode is not self._mode or not stick.deadman:
            self.filter.reset()  # a new mode, or a release, starts from rest
            self._mode = stick.mode
        axes = apply_dead_band(stick.axes, cfg.dead_band)
        if cfg.lock_diagonals:
            axes = lock_diagonals(axes)
        if not stick.deadman:
            return JogMotion(stick.mode, stick.speed_level, False)
        axes = self.filter(axes, t_s)
        scale = speed_factor(stick.speed_level)
        speeds = cfg.speeds
        motion = JogMotion(stick.mode, stick.speed_level, True)
        if stick.mode is JogMode.TRANSLATION:
            motion.linear = tuple(float(a) for a in axes * speeds.linear_mps * scale)
        elif stick.mode is JogMode.WRIST:
            motion.angular = tuple(float(a) for a in axes * speeds.angular_rps * scale)
        else:
            motion.finger_rate = float(axes[0] * speeds.finger_rps * scale)
        return motion
