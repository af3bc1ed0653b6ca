"""The hot paths' NumPy helpers give what the plain NumPy expressions give, to the bit (services.runtime.arrays): the
emulated arm's lockstep runs must not change with them (issue 35)."""
import numpy as np
import pytest

from services.runtime.arrays import clip, constant

SPECIAL = [0.0, -0.0, 1e-320, -1e-320, 1e308, -1e308, np.inf, -np.inf, np.nan]


def operands(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    values = rng.normal(0.0, 10.0, 64) * 10.0 ** rng.integers(-12, 12, 64)
    return np.concatenate([values, SPECIAL])


def same(a: np.ndarray, b: np.ndarray) -> bool:
    """Equal bit for bit (NaN where NaN, the sign of every zero)."""
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


@pytest.mark.parametrize("scalar", [0.0, -0.0, 2.0, 0.01, 22500.0, -120.0, np.pi / 180.0, 1e-9, np.inf])
def test_a_0d_constant_operand_computes_what_the_python_float_does(scalar):
    a = operands(1)
    k = constant(scalar)
    with np.errstate(all="ignore"):  # overflow, 0/0 and inf-inf among the operands, on purpose
        for op in (np.add, np.subtract, np.multiply, np.divide, np.maximum, np.minimum, np.greater, np.less):
            assert same(op(a, k), op(a, scalar)), op.__name__
            assert same(op(k, a), op(scalar, a)), op.__name__


def test_the_clip_ufunc_is_np_clip():
    a = operands(2)
    low, high = operands(3), operands(4)
    assert same(clip(a, low, high), np.clip(a, low, high))
    assert same(clip(a, constant(-1.5), constant(2.5)), np.clip(a, -1.5, 2.5))
