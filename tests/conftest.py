import os

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np
import pytest

from services.runtime.transport import Router


@pytest.fixture
def rng():
    return np.random.default_rng(20261122)


@pytest.fixture
def router():
    """A real zenoh router on a free loopback port, in this process."""
    with Router(port=0) as r:
        yield r
