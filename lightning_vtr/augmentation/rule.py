"""The callback's pool argument and its stored rule: building the pool, describing a rule and telling two apart."""

from __future__ import annotations

import json
from collections.abc import Mapping
from typing import Any

from lightning_vtr.selection.base import ViewSelector
from lightning_vtr.selection.pool import ViewpointPool
from lightning_vtr.utils.validation import check_type

__all__ = ["describe_rule", "make_pool", "rule_differences", "rule_mismatch"]

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
    selector = ", ".join(f"{k}={v!r}" for k, v in dict(rule.get("selector_settings") or {}).items())
    rest = ", ".join(f"{k}={v!r}" for k, v in rule.items() if k not in ("selector", "selector_settings"))
    return f"{rule.get('selector')}({selector}) with {rest}"


def rule_differences(old: Mapping[str, Any], new: Mapping[str, Any], prefix: str = "") -> list[str]:
    """Every setting whose value differs between two rules.

    Args:
        old: the checkpoint's rule.
        new: the running callback's rule.
        prefix: put before every key (nested keys are joined by ``.``).

    Returns:
        One ``"<key> (<old> in the checkpoint, <new> now)"`` per differing setting, in ``old``'s key order, then
        the keys only ``new`` has.

    Example:
        >>> rule_differences({"fraction": 0.05, "pool": {"refresh": True}}, {"fraction": 0.05, "pool": {"refresh": False}})
        ['pool.refresh (True in the checkpoint, False now)']
    """
    out = []
    for key in [*old, *(k for k in new if k not in old)]:
        a, b = old.get(key), new.get(key)
        if isinstance(a, Mapping) and isinstance(b, Mapping):
            out += rule_differences(a, b, f"{prefix}{key}.")
        elif json.dumps(a, sort_keys=True) != json.dumps(b, sort_keys=True):
            out.append(f"{prefix}{key} ({a!r} in the checkpoint, {b!r} now)")
    return out


def rule_mismatch(saved: Mapping[str, Any], current: Mapping[str, Any]) -> str | None:
    """The warning for a checkpoint whose state belongs to another rule, or ``None`` when the rules agree.

    Args:
        saved: the rule stored with the checkpoint's state.
        current: the running callback's rule.

    Returns:
        A message naming both rules and every setting that differs, or ``None``.

    Example:
        >>> rule_mismatch({"fraction": 0.05}, {"fraction": 0.05}) is None
        True
    """
    differences = rule_differences(saved, current)
    if not differences:
        return None
    return (
        f"ErrorGuidedViewAugmentation: the checkpoint's state belongs to the rule {describe_rule(saved)}; "
        f"this callback runs {describe_rule(current)}. They differ in {'; '.join(differences)}. Starting "
        "this callback's state fresh (empty pool, no history); the datamodule keeps serving the samples "
        "the checkpoint lists. Resume with the checkpoint's rule to continue its state."
    )
