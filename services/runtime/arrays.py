"""NumPy on the paths that run every bus cycle or physics step (the emulated actuators, the robot node's targets):
the same operations and the same float64 results, without the per-call costs that dominate at six or seven
elements (an operation on 7 joints takes ~0.2 µs; what NumPy adds around it can take as long again).

- :func:`clip`: ``np.clip``'s own ufunc, without its Python wrappers (~1.4 µs a call less).
- :func:`constant`: a Python float as a 0-d float64 array. NumPy 2 converts a Python float operand afresh at
  every operation (~0.37 µs an operation on 7 joints against ~0.2 µs with a 0-d array operand); the arithmetic is
  the same float64 arithmetic either way.
"""
from __future__ import annotations

import numpy as np

try:
    from numpy._core.umath import clip
except ImportError:  # NumPy 1.x
    clip = np.clip


def constant(value: float) -> np.ndarray:
    """``value`` as a 0-d float64 array, an operand for hot-path arithmetic (module docstring)."""
    return np.array(float(value), dtype=np.float64)
