"""The ``lightning-vtr`` command line: one module per sub-command, dispatched by :func:`main`."""

from __future__ import annotations

from typing import TYPE_CHECKING

from lightning_vtr.utils.exports import lazy_exports

if TYPE_CHECKING:  # what type checkers, IDEs and the API reference read
    from lightning_vtr.cli.dispatch import COMMANDS, build_parser, main
else:  # at run time each name is imported from its module on first use
    __getattr__, __dir__ = lazy_exports(
        __name__,
        {
            "lightning_vtr.cli.dispatch": ["COMMANDS", "build_parser", "main"],
        },
    )

__all__ = [
    "COMMANDS",
    "build_parser",
    "main",
]
