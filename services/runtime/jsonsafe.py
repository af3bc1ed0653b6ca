"""JSON has no NaN or Infinity: a figure that is missing or not finite is written as null."""
from __future__ import annotations

import math


def json_safe(value):
    """``value`` with every non-finite float as None, through dicts, lists and tuples; bytes as their length."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if isinstance(value, (bytes, bytearray, memoryview)):
        return {"bytes": len(value)}
    return value
