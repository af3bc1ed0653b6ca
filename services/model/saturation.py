"""Saturation: the one way a velocity is brought within a speed or acceleration limit, for the controller (its
output), safety (what it forwards) and the emulated DSP (what it executes).

Every function scales the whole vector by one factor, so a limited motion keeps the direction its law asked for:
a twist [v; ω] by the larger of its linear and angular speeds over their limits (scaling the parts apart turns an
IBVS step off its line in feature space: Sensors 2022's mixed law lost a third of its lead on a start where the linear
part was cut and the angular was not), joint velocities by the joint furthest over its speed (a Cartesian motion
stays on its line), and a change of velocity cut short along itself (an acceleration limit, ``max_change =
a_max·dt``). Pure: no state, no counters; each returns what it measured so the caller can refuse instead, flag or
count.
"""
from __future__ import annotations

from typing import NamedTuple, Optional

import numpy as np

#: the parts of a 6-vector twist [v; ω] and the names their limits go by
TWIST_PARTS = ((slice(0, 3), "linear"), (slice(3, 6), "angular"))


class TwistRatio(NamedTuple):
    """A twist's linear and angular speeds (or changes), each as a fraction of its limit."""

    linear: float
    angular: float

    @property
    def over(self) -> float:
        """The factor the whole twist is divided by to bring both parts within their limits (≤ 1: none over)."""
        return max(self.linear, self.angular)


def twist_ratio(twist: np.ndarray, linear_limit: float, angular_limit: float) -> TwistRatio:
    """How many times its limit each part of the twist [v; ω] is (by their norms)."""
    return TwistRatio(float(np.linalg.norm(twist[:3])) / linear_limit,
                      float(np.linalg.norm(twist[3:])) / angular_limit)


def limit_twist(twist: np.ndarray, linear_limit: float, angular_limit: float,
                judged_on: Optional[np.ndarray] = None) -> tuple[np.ndarray, TwistRatio]:
    """``twist`` divided by one factor (:attr:`TwistRatio.over`) when either part is over its limit: both parts
    within their limits, the twist's direction kept. ``judged_on``: the end effector's [v; ω] when the twist's
    angular part is not ω itself (Euler-angle rates, linear in ω: the same factor scales both)."""
    ratio = twist_ratio(twist if judged_on is None else judged_on, linear_limit, angular_limit)
    if ratio.over > 1.0:
        return twist / ratio.over, ratio
    return twist, ratio


def limit_twist_change(previous: np.ndarray, twist: np.ndarray, max_linear_change: float,
                       max_angular_change: float) -> tuple[np.ndarray, bool]:
    """``twist``, its change from ``previous`` divided by one factor so neither part's change is over its limit
    (the linear and angular accelerations); whether it was."""
    change = twist - previous
    ratio = twist_ratio(change, max_linear_change, max_angular_change).over
    if ratio > 1.0:
        return previous + change / ratio, True
    return twist, False


def over_limit_ratio(v: np.ndarray, limits) -> float:
    """How many times its limit the element of ``v`` furthest over it is (≤ 1: none is over)."""
    return float(np.max(np.abs(v) / limits))


def limit_uniformly(v: np.ndarray, limits) -> tuple[np.ndarray, float]:
    """``v`` divided by :func:`over_limit_ratio` when that is over 1 (every element within its limit, the
    direction kept), and the ratio."""
    ratio = over_limit_ratio(v, limits)
    if ratio > 1.0:
        return v / ratio, ratio
    return v, ratio


def limit_change_uniformly(previous: np.ndarray, v: np.ndarray, max_changes) -> tuple[np.ndarray, bool]:
    """``v``, its change from ``previous`` divided by one factor so no element changes by more than its
    ``max_changes`` (joint accelerations); whether it was."""
    change = v - previous
    ratio = over_limit_ratio(change, max_changes)
    if ratio > 1.0:
        return previous + change / ratio, True
    return v, False
