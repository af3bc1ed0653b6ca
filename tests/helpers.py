"""Shared test helpers: random configurations and reference kinematics through Pinocchio."""
import numpy as np

from services.model import jaco2
from services.model.kinematics import ArmKinematics


def random_q(rng, margin_deg: float = 2.0) -> np.ndarray:
    """Model angles: limited joints uniformly inside their limits, continuous joints over ±2 turns."""
    lower, upper = jaco2.model_limits()
    q = rng.uniform(-4 * np.pi, 4 * np.pi, jaco2.N_JOINTS)
    limited = np.isfinite(lower)
    m = np.radians(margin_deg)
    q[limited] = rng.uniform(lower[limited] + m, upper[limited] - m)
    return q


class PinArm(ArmKinematics):
    """Reference kinematics for tests: the product's Pinocchio wrapper (checked against MuJoCo and the DH table
    in test_jaco2_model)."""


class CpuLoad:
    """Keeps every core busy (one spinning process per core, at normal priority), as another program on a shared
    machine would: a context manager. What runs beside it must stay correct: late, counted, never faster. (Plain
    processes, not multiprocessing's: those would re-import the caller's main module.)"""

    def __init__(self, processes: int | None = None) -> None:
        import os

        self.count = processes if processes is not None else (os.cpu_count() or 1)
        self._procs = []

    def __enter__(self) -> "CpuLoad":
        import subprocess
        import sys

        for _ in range(self.count):
            self._procs.append(subprocess.Popen([sys.executable, "-c", "while True: pass"]))
        return self

    def __exit__(self, *exc) -> None:
        for process in self._procs:
            process.kill()
            process.wait(timeout=5)
        self._procs.clear()
