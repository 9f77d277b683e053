"""The callback's pool argument and its stored rule: building the pool, describing a rule and telling two apart."""

from __future__ import annotations

import json
from collections.abc import Mapping
from typing import Any

from lightning_vtr.selection.base import ViewSelector
from lightning_vtr.selection.pool import ViewpointPool
from lightning_vtr.utils.validation import check_type

__all__ = ["describe_rule", "describe_selector", "make_pool", "rule_differences", "rule_mismatch"]

_POOL_ARGUMENTS = {"capacity", "prefer_others", "refresh", "fallback", "num_views"}


def make_pool(pool: ViewpointPool | Mapping[str, Any] | None, selector: ViewSelector) -> ViewpointPool | None:
    """The pool a callback with ``selector`` draws from.

    Args:
        pool: a :class:`~lightning_vtr.selection.pool.ViewpointPool` (used as is), a mapping of its arguments
            (``num_views`` defaults to the selector's), or ``None`` (no pool).
        selector: the callback's selector.

    Returns:
        The pool, or ``None``.

    Raises:
        ValueError: a pool with a selector that draws each object's views itself (``uses_pool=False``), or a pool
            whose ``num_views`` is not the selector's.
        TypeError: a mapping with keys ``ViewpointPool`` does not take, or another type.

    Example:
        >>> from lightning_vtr.selection.error_guided import ErrorGuidedSelector
        >>> make_pool({"refresh": False}, ErrorGuidedSelector()).refresh
        False
    """
    if pool is None:
        return None
    if not selector.uses_pool:
        raise ValueError(
            f"`pool` must be None with {type(selector).__name__}, which draws each object's views itself "
            f"(uses_pool=False), got {pool!r}: pass pool=None"
        )
    if isinstance(pool, Mapping):
        unknown = sorted(set(pool) - _POOL_ARGUMENTS)
        if unknown:
            raise TypeError(
                f"`pool` as a mapping takes ViewpointPool's arguments (capacity, prefer_others, refresh, fallback), "
                f"got unknown keys {unknown}"
            )
        pool = ViewpointPool(**{"num_views": selector.num_views, **pool})
    check_type("pool", pool, ViewpointPool, "ViewpointPool, a mapping of its arguments or None")
    if pool.num_views != selector.num_views:
        raise ValueError(
            f"`pool` holds view sets of {pool.num_views} views but the selector {type(selector).__name__} returns "
            f"{selector.num_views}: pass ViewpointPool(num_views={selector.num_views}, ...)"
        )
    return pool


def describe_rule(rule: Mapping[str, Any]) -> str:
    """One line for a rule.

    Args:
        rule: an ``ErrorGuidedViewAugmentation.rule()``.

    Returns:
        ``"<selector>(<its settings>) with <the other settings>"``.

    Example:
        >>> describe_rule({"selector": "RandomSelector", "selector_settings": {"num_views": 3}, "fraction": 0.05})
        'RandomSelector(num_views=3) with fraction=0.05'
    """
    rest = ", ".join(f"{k}={v!r}" for k, v in rule.items() if k not in ("selector", "selector_settings"))
    return f"{describe_selector(rule)} with {rest}"


_ABSENT = object()
"""A setting one of two rules does not have (a setting of another score, or of an older version)."""


def _effective(value: Any, one_sided: bool) -> Any:
    """``value`` as a comparison sees it: ``None`` and ``"none"`` both mean "none"; beside a setting the other rule
    does not have, so do the values that switch a setting off (``False``, ``0``, an empty list or mapping)."""
    if value is _ABSENT or value is None or (isinstance(value, str) and value.lower() == "none"):
        return None
    if one_sided and (value is False or (isinstance(value, (int, float)) and value == 0) or value in ([], {})):
        return None
    return value


def _shown(value: Any) -> str:
    return "not set" if value is _ABSENT else repr(value)


def rule_differences(old: Mapping[str, Any], new: Mapping[str, Any], prefix: str = "") -> list[str]:
    """Every setting whose effective value differs between two rules.

    Values that mean the same are equal: ``None`` and ``"none"``, and a setting only one rule has (an option of
    another score, or a setting an older version did not store) when its value is ``None``, ``"none"``, ``False``,
    ``0`` or empty. When the selectors' classes differ, the selector is one difference (both with their
    settings), not each of its settings.

    Args:
        old: the checkpoint's rule.
        new: the running callback's rule.
        prefix: put before every key (nested keys are joined by ``.``).

    Returns:
        One ``"<key>: <old> in the checkpoint, <new> now"`` per differing setting, in ``old``'s key order, then
        the keys only ``new`` has; a selector's settings are keyed ``<SelectorClass>.<setting>``.

    Example:
        >>> rule_differences({"fraction": 0.05, "pool": {"refresh": True}}, {"fraction": 0.05, "pool": {"refresh": False}})
        ['pool.refresh: True in the checkpoint, False now']
        >>> rule_differences({"selector_settings": {"mask": None}}, {"selector_settings": {"mask": "none", "eps": 0.0}})
        []
    """
    out = []
    same_selector = old.get("selector") == new.get("selector")
    for key in [*old, *(k for k in new if k not in old)]:
        a, b = old.get(key, _ABSENT), new.get(key, _ABSENT)
        if not prefix and key == "selector" and a != b:
            out.append(f"selector: {describe_selector(old)} in the checkpoint, {describe_selector(new)} now")
            continue
        if not prefix and key == "selector_settings":
            if same_selector and isinstance(a, Mapping) and isinstance(b, Mapping):
                out += rule_differences(a, b, f"{new.get('selector')}.")
            continue
        if isinstance(a, Mapping) and isinstance(b, Mapping):
            out += rule_differences(a, b, f"{prefix}{key}.")
            continue
        one_sided = a is _ABSENT or b is _ABSENT
        if json.dumps(_effective(a, one_sided), sort_keys=True) != json.dumps(_effective(b, one_sided), sort_keys=True):
            out.append(f"{prefix}{key}: {_shown(a)} in the checkpoint, {_shown(b)} now")
    return out


def describe_selector(rule: Mapping[str, Any]) -> str:
    """``"<selector>(<its settings>)"`` of a rule.

    Args:
        rule: an ``ErrorGuidedViewAugmentation.rule()``.

    Returns:
        The selector's class name with its settings.

    Example:
        >>> describe_selector({"selector": "RandomSelector", "selector_settings": {"num_views": 3}})
        'RandomSelector(num_views=3)'
    """
    settings = ", ".join(f"{k}={v!r}" for k, v in dict(rule.get("selector_settings") or {}).items())
    return f"{rule.get('selector')}({settings})"


def rule_mismatch(saved: Mapping[str, Any], current: Mapping[str, Any]) -> str | None:
    """The warning for a checkpoint whose state belongs to another rule, or ``None`` when the rules agree.

    Args:
        saved: the rule stored with the checkpoint's state.
        current: the running callback's rule.

    Returns:
        A message whose first line says what the callback does and whose other lines list each setting that
        differs (:func:`rule_differences`), one per line; ``None`` when no effective setting differs.

    Example:
        >>> rule_mismatch({"fraction": 0.05}, {"fraction": 0.05}) is None
        True
        >>> print(rule_mismatch({"fraction": 0.05, "seed": 0}, {"fraction": 0.1, "seed": 0}))
        ErrorGuidedViewAugmentation: the checkpoint's state belongs to another rule, which differs in:
          fraction: 0.05 in the checkpoint, 0.1 now
        Starting this callback's state fresh (empty pool, no history); the datamodule keeps serving the samples
        the checkpoint lists. Resume with the checkpoint's rule to continue its state.
    """
    differences = rule_differences(saved, current)
    if not differences:
        return None
    return "\n".join(
        [
            "ErrorGuidedViewAugmentation: the checkpoint's state belongs to another rule, which differs in:",
            *(f"  {line}" for line in differences),
            "Starting this callback's state fresh (empty pool, no history); the datamodule keeps serving the samples",
            "the checkpoint lists. Resume with the checkpoint's rule to continue its state.",
        ]
    )
