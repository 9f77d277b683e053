"""Argument checks shared by every public entry point, with one message form.

Every check raises with ``"`name` must be <what>, got <value>"``: :class:`TypeError` when the value has
the wrong type, :class:`ValueError` when it has the right type and a wrong value. Each returns the value
normalised (e.g. a float), so a constructor reads ``self.k = check_int("k", k, minimum=1)``.
"""

from __future__ import annotations

import math
from collections.abc import Collection
from typing import Any

import numpy as np
import torch

__all__ = [
    "check_choice",
    "check_float",
    "check_int",
    "check_probabilities",
    "check_range",
    "check_type",
]


def _is_int(value: Any) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))


def _is_real(value: Any) -> bool:
    return _is_int(value) or isinstance(value, (float, np.floating))


def check_type(name: str, value: Any, types: type | tuple[type, ...], what: str | None = None) -> Any:
    """``value`` if it is an instance of ``types``; else ``TypeError`` naming ``what`` (default: the type names)."""
    if not isinstance(value, types):
        if what is None:
            names = [t.__name__ for t in (types if isinstance(types, tuple) else (types,))]
            what = " or ".join(names)
        raise TypeError(f"`{name}` must be {_article(what)}, got {type(value).__name__} {value!r}")
    return value


def check_int(name: str, value: Any, *, minimum: int | None = None, maximum: int | None = None) -> int:
    """``int(value)`` for an integer (not a bool) in ``[minimum, maximum]``."""
    if not _is_int(value):
        raise TypeError(f"`{name}` must be an int, got {type(value).__name__} {value!r}")
    value = int(value)
    _check_bounds(name, value, minimum, maximum, "an int")
    return value


def check_float(
    name: str,
    value: Any,
    *,
    minimum: float | None = None,
    maximum: float | None = None,
    min_open: bool = False,
    max_open: bool = False,
) -> float:
    """``float(value)`` for a finite real number (not a bool) in the given, by default closed, interval."""
    if not _is_real(value):
        raise TypeError(f"`{name}` must be a number, got {type(value).__name__} {value!r}")
    value = float(value)
    if not math.isfinite(value):
        raise ValueError(f"`{name}` must be a finite number, got {value!r}")
    _check_bounds(name, value, minimum, maximum, "a number", min_open, max_open)
    return value


def check_choice(name: str, value: Any, choices: Collection[Any]) -> Any:
    """``value`` if it is one of ``choices``; else ``ValueError`` listing them."""
    try:
        ok = value in choices
    except TypeError:  # unhashable value against a set
        ok = False
    if not ok:
        options = ", ".join(repr(c) for c in choices)
        raise ValueError(f"`{name}` must be one of {options}, got {value!r}")
    return value


def check_range(name: str, value: Any, low: float, high: float, unit: str = "") -> tuple[float, float]:
    """A pair ``(lo, hi)`` of numbers with ``low <= lo <= hi <= high``, as floats."""
    suffix = f" ({unit})" if unit else ""
    try:
        lo, hi = value
    except (TypeError, ValueError):
        raise TypeError(f"`{name}` must be a pair (low, high){suffix}, got {value!r}") from None
    if not (_is_real(lo) and _is_real(hi)):
        raise TypeError(f"`{name}` must be a pair of numbers{suffix}, got {value!r}")
    lo, hi = float(lo), float(hi)
    if not (low <= lo <= hi <= high):
        raise ValueError(f"`{name}` must satisfy {low:g} <= low <= high <= {high:g}{suffix}, got {value!r}")
    return lo, hi


def check_probabilities(name: str, values: torch.Tensor, hint: str = "") -> torch.Tensor:
    """``values`` if every element is a finite number in ``[0, 1]``; else ``ValueError`` naming ``name``, the
    observed range of the finite values and the count of non-finite ones, followed by ``hint``.

    Example::

        >>> check_probabilities("predict_voxels", torch.tensor([0.2, 1.7]))
        Traceback (most recent call last):
        ...
        ValueError: `predict_voxels` must return probabilities in [0, 1], got values in [0.2, 1.7] (0 non-finite of 2)
    """
    values = check_type(name, values, torch.Tensor, "torch.Tensor")
    finite = torch.isfinite(values)
    bad = int(values.numel() - finite.sum().item())
    kept = values[finite]
    if bad == 0 and (kept.numel() == 0 or (kept.min() >= 0 and kept.max() <= 1)):
        return values
    seen = f"values in [{kept.min().item():.4g}, {kept.max().item():.4g}]" if kept.numel() else "no finite values"
    message = f"`{name}` must return probabilities in [0, 1], got {seen} ({bad} non-finite of {values.numel()})"
    raise ValueError(f"{message}{'; ' + hint if hint else ''}")


def _check_bounds(
    name: str,
    value: float,
    minimum: float | None,
    maximum: float | None,
    what: str,
    min_open: bool = False,
    max_open: bool = False,
) -> None:
    below = minimum is not None and (value <= minimum if min_open else value < minimum)
    above = maximum is not None and (value >= maximum if max_open else value > maximum)
    if not (below or above):
        return
    if minimum is not None and maximum is not None:
        left, right = "(" if min_open else "[", ")" if max_open else "]"
        bound = f"in {left}{minimum:g}, {maximum:g}{right}"
    elif minimum is not None:
        bound = f"> {minimum:g}" if min_open else f">= {minimum:g}"
    else:
        bound = f"< {maximum:g}" if max_open else f"<= {maximum:g}"
    raise ValueError(f"`{name}` must be {what} {bound}, got {value!r}")


def _article(what: str) -> str:
    return what if what.split()[0] in ("a", "an", "the") else f"{'an' if what[0].lower() in 'aeiou' else 'a'} {what}"
