"""The ``lightning-vtr`` command line: one sub-command per job (``build-dataset``, ``dataset-info``, ...).

Each sub-command is a module of this package with a ``HELP`` line, ``add_arguments(parser)`` and
``run(args) -> exit status``, registered in :data:`COMMANDS`; adding a command is adding a module and one
entry. ``fit`` / ``validate`` / ``test`` go to Lightning's ``LightningCLI``
(:mod:`lightning_vtr.cli.lightning`). Errors a user can fix (a bad path, ``--shard 3/2``) print one line to
stderr and exit with status 2; argparse's own usage errors exit with 2 as well.
"""

from __future__ import annotations

import argparse
import shlex
import sys
from collections.abc import Callable, Sequence

from lightning_vtr.cli import build_dataset, dataset_info, report
from lightning_vtr.cli.lightning import LIGHTNING_SUBCOMMANDS, run_lightning_cli

__all__ = ["COMMANDS", "build_parser", "main"]

#: name -> (help, add_arguments(parser), run(args) -> exit status).
COMMANDS: dict[str, tuple[str, Callable[[argparse.ArgumentParser], None], Callable[[argparse.Namespace], int]]] = {
    "build-dataset": (build_dataset.HELP, build_dataset.add_arguments, build_dataset.run),
    "dataset-info": (dataset_info.HELP, dataset_info.add_arguments, dataset_info.run),
    "report": (report.HELP, report.add_arguments, report.run),
}


def build_parser() -> argparse.ArgumentParser:
    """The parser of every sub-command of :data:`COMMANDS` (not of the LightningCLI ones)."""
    parser = argparse.ArgumentParser(
        prog="lightning-vtr", description="View transformation robustness for multi-view 3D reconstruction."
    )
    parser.epilog = (
        f"Training and testing: `lightning-vtr {'|'.join(LIGHTNING_SUBCOMMANDS)} --config CONFIG.yaml` "
        "(LightningCLI; --help there)."
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, (help_text, add_arguments, run) in COMMANDS.items():
        command = sub.add_parser(name, help=help_text)
        add_arguments(command)
        command.set_defaults(run=run)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``lightning-vtr`` with ``argv`` (default ``sys.argv[1:]``); returns the exit status."""
    words = list(sys.argv[1:] if argv is None else argv)
    if words and words[0] in LIGHTNING_SUBCOMMANDS:
        return run_lightning_cli(None if argv is None else words)
    args = build_parser().parse_args(words)
    args.command_line = shlex.join(["lightning-vtr", *words])  # shown in reports
    try:
        return int(args.run(args))
    except (ValueError, FileNotFoundError, RuntimeError) as err:
        # Errors a user can fix get one line, not a traceback.
        print(f"lightning-vtr {args.command}: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
