"""Aliases that keep a moved module importable under its old name for one release."""

from __future__ import annotations

import importlib
import sys
import warnings

__all__ = ["alias_module"]


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
