"""JSON coercion, once for the whole project: numpy scalars and arrays become Python
numbers and lists, and a non-finite number becomes ``null`` (JSON has no NaN)."""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["json_number", "to_jsonable"]


def json_number(x: Any) -> float | int | bool | str | None:
    """One JSON-safe scalar: numpy -> Python, non-finite or non-numeric -> ``None``."""
    if isinstance(x, np.generic):
        x = x.item()
    if x is None or isinstance(x, (bool, int, str)):
        return x
    try:
        f = float(x)
    except (TypeError, ValueError):
        return None
    return f if math.isfinite(f) else None


def to_jsonable(obj: Any) -> Any:
    """``obj`` with every mapping, sequence and array converted for ``json.dumps(allow_nan=False)``."""
    if isinstance(obj, Mapping):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, np.ndarray):
        return [to_jsonable(v) for v in obj.tolist()]
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, Path):
        return str(obj)
    return json_number(obj)
