"""Point features' error, as vision measures it and the controller judges it: one function each, shared, so that the
two never disagree on when a task has converged."""
from __future__ import annotations

import numpy as np


def feature_error(points, goal) -> tuple[np.ndarray, float]:
    """e = s − s* stacked (x0, y0, x1, y1, ...) and its Euclidean norm."""
    e = (np.asarray(points, dtype=float) - np.asarray(goal, dtype=float)).reshape(-1)
    return e, float(np.linalg.norm(e))


def per_point_rms(error, weights) -> float:
    """The weighted per-point RMS of a stacked error, √(Σ wᵢ‖eᵢ‖² / Σ wᵢ): what convergence is judged on. It does not
    grow with the number of points, so one threshold serves a tag's four and a keypoint target's hundreds; with
    every weight 1 it is ‖e‖/√n (a tag's ‖e‖/2, to the bit, so Sensors 2022's ‖e‖ < 5e-5 is error_rms < 2.5e-5)."""
    e = np.asarray(error, dtype=float)
    w = np.asarray(weights, dtype=float)
    if len(e) != 2 * len(w) or len(w) == 0:
        raise ValueError(f"an error of {len(e)} values for {len(w)} weights: two values per point")
    if np.all(w == 1.0):
        return float(np.linalg.norm(e)) / float(np.sqrt(len(w)))
    if not (np.all(w >= 0.0) and np.sum(w) > 0.0):
        raise ValueError("weights must be non-negative with a positive sum")
    return float(np.sqrt(np.dot(w, np.sum(e.reshape(-1, 2) ** 2, axis=1)) / np.sum(w)))
