"""The ``lightning-vtr`` command line: one module per sub-command, dispatched by :func:`main`."""

from __future__ import annotations

from lightning_vtr.cli.dispatch import COMMANDS, build_parser, main

__all__ = ["COMMANDS", "build_parser", "main"]
