"""The bounds a core configuration states on its fields, checked where they are stated.

A field of a config dataclass annotated ``Annotated[float, Ge(0)]`` (annotated_types'
``Gt``, ``Ge``, ``Lt``, ``Le``, ``Interval``), or a tuple of such numbers, must be a finite
number within those bounds.  The same annotations are what the service's configuration
validates against (``service/config.py`` builds its models from the dataclasses) and what
``deploy/config.example.toml`` lists, so each bound is written once: on the field.
:func:`check_bounds` is what a config's ``__post_init__`` calls, so a core config made in
code (the offline commands, the scripts) is held to the same bounds as the service's.
Pure Python, no I/O.
"""

from __future__ import annotations

import dataclasses
import math
import typing
from functools import cache
from typing import Any

__all__ = ["check_bounds"]

#: annotated_types' attribute -> (the bound's sign, its test)
_OPS = {"gt": (">", lambda v, b: v > b), "ge": (">=", lambda v, b: v >= b),
        "lt": ("<", lambda v, b: v < b), "le": ("<=", lambda v, b: v <= b)}


def _limits(annotation: Any) -> tuple[tuple[str, float], ...]:
    """``((attr, bound), ...)`` of an ``Annotated`` type's annotated_types metadata."""
    out = []
    for meta in getattr(annotation, "__metadata__", ()):
        for attr in _OPS:
            bound = getattr(meta, attr, None)
            if bound is not None:
                out.append((attr, bound))
    return tuple(out)


@cache
def _bounded_fields(cls: type) -> tuple[tuple[str, tuple, bool], ...]:
    """``(name, limits, is_tuple)`` of every field of ``cls`` that states bounds."""
    hints = typing.get_type_hints(cls, include_extras=True)
    out = []
    for f in dataclasses.fields(cls):
        hint = hints[f.name]
        limits = _limits(hint)
        if limits:
            out.append((f.name, limits, False))
        elif typing.get_origin(hint) is tuple:
            args = [a for a in typing.get_args(hint) if a is not Ellipsis]
            limits = _limits(args[0]) if args else ()
            if limits and all(_limits(a) == limits for a in args):
                out.append((f.name, limits, True))
    return tuple(out)


def _within(value: Any, limits: tuple) -> bool:
    try:
        return math.isfinite(value) and all(_OPS[attr][1](value, bound) for attr, bound in limits)
    except TypeError:  # not a number
        return False


def check_bounds(config: Any) -> None:
    """Raise ``ValueError`` naming the first field of ``config`` outside its annotated bounds."""
    for name, limits, is_tuple in _bounded_fields(type(config)):
        value = getattr(config, name)
        values = value if is_tuple else (value,)
        if not all(_within(v, limits) for v in values):
            bounds = " and ".join(f"{_OPS[attr][0]} {bound:g}" for attr, bound in limits)
            what = "finite numbers" if is_tuple else "a finite number"
            raise ValueError(f"{name} must be {what} {bounds}, got {value!r}")
