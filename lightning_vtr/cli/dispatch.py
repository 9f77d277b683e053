"""The ``lightning-vtr`` command line: one sub-command per job (``build-dataset``, ``dataset-info``, ...).

Each sub-command is a module of this package with a ``HELP`` line, ``add_arguments(parser)`` and
``run(args) -> exit status``, registered in :data:`COMMANDS`; adding a command is adding a module and one
entry. ``fit`` / ``validate`` / ``test`` go to Lightning's ``LightningCLI``
(:mod:`lightning_vtr.cli.lightning`); ``predict`` is the package's command (:mod:`lightning_vtr.cli.predict`)
unless its words use LightningCLI's options (``--config``, ``--ckpt_path``, ``--trainer.*``, ...), then it goes
to LightningCLI too. Errors a user can fix print one line to stderr naming the thing, what was expected and
what was found, never a traceback: exit status 2 for usage errors (a missing path, ``--shard 3/2``, an output
folder holding other files, an option argparse rejects), 1 for data errors (a truncated checkpoint, a file that
is not a picture, a full disk); see :mod:`lightning_vtr.errors` and ``docs/bad_input.md``.
"""

from __future__ import annotations

import argparse
import re
import shlex
import sys
from collections.abc import Callable, Sequence
from typing import NoReturn

from lightning_vtr.cli import build_dataset, dataset_info, pix3d, predict, report, robustness
from lightning_vtr.cli.lightning import LIGHTNING_SUBCOMMANDS, run_lightning_cli
from lightning_vtr.errors import EXPECTED_ERRORS, UsageError, exit_status, one_line
from lightning_vtr.utils.memory import retain_freed_memory

__all__ = ["COMMANDS", "build_parser", "goes_to_lightning", "main"]

#: name -> (help, add_arguments(parser), run(args) -> exit status).
COMMANDS: dict[str, tuple[str, Callable[[argparse.ArgumentParser], None], Callable[[argparse.Namespace], int]]] = {
    "build-dataset": (build_dataset.HELP, build_dataset.add_arguments, build_dataset.run),
    "dataset-info": (dataset_info.HELP, dataset_info.add_arguments, dataset_info.run),
    "report": (report.HELP, report.add_arguments, report.run),
    "predict": (predict.HELP, predict.add_arguments, predict.run),
    "pix3d": (pix3d.HELP, pix3d.add_arguments, pix3d.run),
    "evaluate-folder": (pix3d.FOLDER_HELP, pix3d.add_folder_arguments, pix3d.run_folder),
    "robustness": (robustness.HELP, robustness.add_arguments, robustness.run),
}
#: A word that only a LightningCLI command line has: a config, its own options, or a dotted class argument.
_LIGHTNING_WORD = re.compile(
    r"^(-c$|--(config|print_config|ckpt_path|seed_everything|return_predictions|optimizer|lr_scheduler)([=.]|$)"
    r"|--(trainer|model|data)\.)"
)


def goes_to_lightning(words: Sequence[str]) -> bool:
    """Whether ``lightning-vtr <words>`` is a LightningCLI command line: ``fit`` / ``validate`` / ``test``
    always; a sub-command that is also the package's own (``predict``) when a word is LightningCLI's
    (``--config``, ``--print_config``, ``--ckpt_path``, ``--trainer.*``, ``--model.*``, ``--data.*``, ...)."""
    if not words or words[0] not in LIGHTNING_SUBCOMMANDS:
        return False
    return words[0] not in COMMANDS or any(_LIGHTNING_WORD.match(word) for word in words[1:])


class _ParseError(UsageError):
    """An option argparse rejected, with the program (``lightning-vtr COMMAND``) whose parser rejected it."""

    def __init__(self, prog: str, message: str) -> None:
        super().__init__(f"{message} (`{prog} --help` lists the options)")
        self.prog = prog


class _Parser(argparse.ArgumentParser):
    """An ``ArgumentParser`` whose errors are raised as :class:`_ParseError` (one line from :func:`main`)
    instead of printing the usage and exiting."""

    def error(self, message: str) -> NoReturn:
        raise _ParseError(self.prog, message)


def build_parser() -> argparse.ArgumentParser:
    """The parser of every sub-command of :data:`COMMANDS` (not of the LightningCLI ones).

    Its errors (an unknown option, a value a type check rejects, a missing required option) raise
    :class:`~lightning_vtr.errors.UsageError` rather than exiting; ``--help`` still prints and exits.
    """
    parser = _Parser(
        prog="lightning-vtr", description="View transformation robustness for multi-view 3D reconstruction."
    )
    parser.epilog = (
        f"Training and testing: `lightning-vtr {'|'.join(LIGHTNING_SUBCOMMANDS)} --config CONFIG.yaml` "
        "(LightningCLI; --help there). `lightning-vtr predict --ckpt CKPT ...` is the package's own command."
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
    retain_freed_memory()  # this process trains: freed CPU memory is reused, not faulted in again every step
    if goes_to_lightning(words):
        command, run = words[0], lambda: run_lightning_cli(None if argv is None else words)
    else:
        try:
            args = build_parser().parse_args(words)
        except _ParseError as err:
            print(f"{err.prog}: error: {one_line(err)}", file=sys.stderr)
            return exit_status(err)
        args.command_line = shlex.join(["lightning-vtr", *words])  # shown in reports
        command, run = args.command, lambda: args.run(args)
    try:
        return int(run())
    except EXPECTED_ERRORS as err:
        # Errors a user can fix get one line, not a traceback: 2 for the command line, 1 for the data.
        print(f"lightning-vtr {command}: error: {one_line(err)}", file=sys.stderr)
        return exit_status(err)


if __name__ == "__main__":
    sys.exit(main())
