"""Saturation: the one way a velocity is brought within a speed or acceleration limit, for the controller (its
output), safety (what it forwards) and the emulated DSP (what it executes).

Every function scales along the vector, so a limited motion keeps its direction: a twist's linear and angular
parts each within their speed, joint velocities all by one factor (a Cartesian motion stays on its line), and a
change of velocity cut short along itself (an acceleration limit, ``max_change = a_max·dt``). Pure: no state, no
counters; each returns what it measured so the caller can refuse instead, flag or count.
"""
from __future__ import annotations

import numpy as np

#: the parts of a 6-vector twist [v; ω] and the names their limits go by
TWIST_PARTS = ((slice(0, 3), "linear"), (slice(3, 6), "angular"))


def limit_norm(v: np.ndarray, limit: float) -> tuple[np.ndarray, float]:
    """``v`` scaled down along itself to norm ``limit`` when it is longer, and its norm before (over ``limit``:
    it was scaled)."""
    size = float(np.linalg.norm(v))
    if size > limit:
        return v * (limit / size), size
    return v, size


def limit_norm_change(previous: np.ndarray, v: np.ndarray, max_change: float) -> tuple[np.ndarray, bool]:
    """``v``, its change from ``previous`` cut to norm ``max_change`` along itself; whether it was cut."""
    change = v - previous
    size = float(np.linalg.norm(change))
    if size > max_change:
        return previous + change * (max_change / size), True
    return v, False


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
