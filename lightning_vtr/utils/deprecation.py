"""Aliases that keep a moved module importable under its old name for one release."""

from __future__ import annotations

import importlib
import sys
import warnings
from typing import Any

__all__ = ["alias_module", "renamed_argument"]


def alias_module(old: str, new: str, removed_in: str = "0.3") -> None:
    """Make ``import old`` return module ``new``, with a :class:`DeprecationWarning`.

    Call it from the old module's file; the old name then *is* the new module (same objects, so
    ``monkeypatch`` and ``isinstance`` keep working), and importing it warns once per process.
    """
    warnings.warn(
        f"`{old}` moved to `{new}`; the old path is deprecated and will be removed in {removed_in}.",
        DeprecationWarning,
        stacklevel=3,
    )
    sys.modules[old] = importlib.import_module(new)


def renamed_argument(old: str, old_value: Any, new: str, new_value: Any, removed_in: str = "0.3") -> Any:
    """The value of an argument renamed from ``old`` to ``new``; ``old_value`` is ``None`` unless given.

    Giving the old name warns (:class:`DeprecationWarning`) and its value wins over the new name's
    default.

    Example::

        def __init__(self, num_views: int = 3, n_views: int | None = None):
            num_views = renamed_argument("n_views", n_views, "num_views", num_views)
    """
    if old_value is None:
        return new_value
    warnings.warn(
        f"`{old}` was renamed `{new}`; the old name is deprecated and will be removed in {removed_in}.",
        DeprecationWarning,
        stacklevel=3,
    )
    return old_value
