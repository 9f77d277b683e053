"""Lazy re-exports: the package's ``__init__`` modules import each public name from its module on first use.

Every package of :mod:`lightning_vtr` re-exports its public names this way, so importing one module of a
package (``lightning_vtr.synthesis.pose``) costs that module alone, not every dependency of its siblings
(Lightning, diffusers, matplotlib). An ``__init__.py`` lists the names three times: under ``if TYPE_CHECKING:``
as ordinary imports (what type checkers, IDEs and the API reference read), in the mapping given to
:func:`lazy_exports` in that block's ``else:`` branch (so type checkers do not see a module ``__getattr__`` and
still report unknown names), and in ``__all__``; ``tests/utils/test_exports.py`` checks that the three agree.
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Callable, Mapping, Sequence
from typing import Any

__all__ = ["lazy_exports"]


def lazy_exports(
    package: str, exports: Mapping[str, Sequence[str]]
) -> tuple[Callable[[str], Any], Callable[[], list[str]]]:
    """The module-level ``__getattr__`` and ``__dir__`` (PEP 562) of a package that re-exports names lazily.

    ``__getattr__(name)`` imports the module that defines ``name`` on first use and stores the value in the
    package, so later lookups do not call it again; ``__dir__()`` lists the package's globals and every
    exported name, imported or not.

    Args:
        package: the package's ``__name__`` (its module must be in ``sys.modules`` when a name is looked up).
        exports: the defining module (absolute name) -> the names re-exported from it.

    Returns:
        ``(__getattr__, __dir__)``, to be assigned at the package's module level.

    Raises:
        ValueError: a name is listed under two modules.

    Example:
        >>> getattr_, dir_ = lazy_exports("json", {"json.decoder": ["JSONDecodeError"]})
        >>> getattr_("JSONDecodeError").__name__
        'JSONDecodeError'
        >>> getattr_("nothing")
        Traceback (most recent call last):
            ...
        AttributeError: module 'json' has no attribute 'nothing'
    """
    owner: dict[str, str] = {}
    for module, names in exports.items():
        for name in names:
            if name in owner:
                raise ValueError(
                    f"`exports` of {package!r} must list each name once, got {name!r} under {owner[name]!r} "
                    f"and {module!r}"
                )
            owner[name] = module

    def __getattr__(name: str) -> Any:
        module = owner.get(name)
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(module), name)
        setattr(sys.modules[package], name, value)
        return value

    def __dir__() -> list[str]:
        return sorted({*vars(sys.modules[package]), *owner})

    return __getattr__, __dir__
