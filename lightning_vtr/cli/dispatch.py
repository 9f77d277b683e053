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

``lightning-vtr fit|validate|test --help`` (exactly those words) prints a help text shipped in
``lightning_vtr/cli/help/`` instead of importing Lightning to build the parser (seconds): the live parser's text,
written by ``python -m lightning_vtr.cli.gen_help`` and wrapped at 80 columns. It is printed only when Python and
the libraries the text depends on have the versions it was written with (:func:`shipped_help`); any other
command line, such as ``fit --config CONFIG.yaml --help`` or ``fit --model module.Class --help``, gets the live
parser's help.
"""

from __future__ import annotations

import argparse
import os
import re
import shlex
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, NoReturn

from lightning_vtr.errors import EXPECTED_ERRORS, UsageError, exit_status, one_line
from lightning_vtr.utils.memory import retain_freed_memory
from lightning_vtr.utils.paths import printable

__all__ = [
    "COMMANDS",
    "HELP_DIR",
    "HELP_DISTRIBUTIONS",
    "HELP_ENVIRONMENT_FILE",
    "LIGHTNING_COMMANDS",
    "Command",
    "build_parser",
    "goes_to_lightning",
    "help_environment",
    "main",
    "shipped_help",
]

#: The ``LightningCLI`` sub-commands (as :data:`lightning_vtr.cli.lightning.LIGHTNING_SUBCOMMANDS`, kept here so
#: that ``lightning-vtr --help`` imports no Lightning), with their help lines.
LIGHTNING_COMMANDS: dict[str, str] = {
    "fit": "train any LightningModule with predict_voxels (LightningCLI: --config, --model module.Class, ...)",
    "validate": "validate a model on the validation split (LightningCLI: --config, --ckpt_path, ...)",
    "test": "test a model on every view set's test split (LightningCLI: --config, --ckpt_path, ...)",
}
LIGHTNING_SUBCOMMANDS = (*LIGHTNING_COMMANDS, "predict")
#: The folder of the shipped help texts of :data:`LIGHTNING_COMMANDS` (``fit.txt``, ...) and of the environment
#: they were written in (:data:`HELP_ENVIRONMENT_FILE`); ``python -m lightning_vtr.cli.gen_help`` writes them.
HELP_DIR = Path(__file__).with_name("help")
#: The file of :data:`HELP_DIR` holding :func:`help_environment` as it was when the texts were written (JSON).
HELP_ENVIRONMENT_FILE = "environment.json"
#: The distributions whose versions the LightningCLI help texts depend on (options, types, docstring parsing).
HELP_DISTRIBUTIONS = ("lightning", "jsonargparse", "docstring-parser", "typeshed-client")


class Command:
    """A sub-command: its help line and the module (imported only when the command runs or shows its help)
    holding ``add_arguments(parser)`` and ``run(args) -> exit status``.

    Args:
        help: the one-line help of ``lightning-vtr --help``.
        module: the module's import path.
        add: the name of its ``add_arguments`` function.
        run: the name of its ``run`` function.
    """

    def __init__(self, help: str, module: str, add: str = "add_arguments", run: str = "run") -> None:
        self.help, self.module, self._add, self._run = help, module, add, run

    def _function(self, name: str) -> Callable[..., Any]:
        import importlib

        return getattr(importlib.import_module(self.module), name)

    def add_arguments(self, parser: argparse.ArgumentParser) -> None:
        """Add the command's options to ``parser`` (imports its module)."""
        self._function(self._add)(parser)

    def run(self, args: argparse.Namespace) -> int:
        """Run the command on parsed arguments; returns the exit status."""
        return int(self._function(self._run)(args))


#: name -> :class:`Command`, in the order of ``lightning-vtr --help``.
COMMANDS: dict[str, Command] = {
    "build-dataset": Command(
        "build a ShapeNet-VTR dataset (procedural, ShapeNetCore or a mesh folder)", "lightning_vtr.cli.build_dataset"
    ),
    "dataset-info": Command(
        "summarise a ShapeNet-VTR dataset (--verify: read every file and list problems)",
        "lightning_vtr.cli.dataset_info",
    ),
    "report": Command(
        "compare view strategies (yours too) over seeds for any model; write Table 1 with CIs, paired differences",
        "lightning_vtr.cli.report",
    ),
    "predict": Command(
        "run a trained model on image folders or a dataset split; write binvox, meshes, sheets and index.html",
        "lightning_vtr.cli.predict",
    ),
    "pix3d": Command(
        "evaluate checkpoints on Pix3D photographs; write the paper's Table 5 (mIoU, F-score) as markdown and CSV",
        "lightning_vtr.cli.pix3d",
    ),
    "evaluate-folder": Command(
        "evaluate checkpoints on a folder test set (<set>/<taxonomy>/<model>/NN.png + ShapeNetVox32)",
        "lightning_vtr.cli.pix3d",
        "add_folder_arguments",
        "run_folder",
    ),
    "robustness": Command(
        "measure checkpoints' IoU around every viewpoint bin; write bins.csv, equal-area maps and index.html",
        "lightning_vtr.cli.robustness",
    ),
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


def help_environment() -> dict[str, Any]:
    """What the LightningCLI help texts depend on besides this package's code: the Python version
    (``"3.11"``, argparse's layout) and the version of each of :data:`HELP_DISTRIBUTIONS` (``None`` when it is
    not installed), as ``{"python": ..., "distributions": {name: version}}``."""
    from importlib.metadata import PackageNotFoundError, version

    def installed(name: str) -> str | None:
        try:
            return version(name)
        except PackageNotFoundError:
            return None

    return {
        "python": f"{sys.version_info.major}.{sys.version_info.minor}",
        "distributions": {name: installed(name) for name in HELP_DISTRIBUTIONS},
    }


def shipped_help(words: Sequence[str]) -> str | None:
    """The shipped text ``lightning-vtr <words>`` prints, for ``words`` exactly ``[COMMAND, "--help"]`` or
    ``[COMMAND, "-h"]`` with ``COMMAND`` one of :data:`LIGHTNING_COMMANDS`; ``None`` (the live parser's help)
    for any other words, when the text is not in :data:`HELP_DIR`, when :func:`help_environment` differs from
    the one it was written in, or when a ``JSONARGPARSE_*`` variable (which can change the help) is set."""
    import json

    if len(words) != 2 or words[0] not in LIGHTNING_COMMANDS or words[1] not in ("--help", "-h"):
        return None
    if any(name.startswith("JSONARGPARSE_") for name in os.environ):
        return None
    try:
        text = (HELP_DIR / f"{words[0]}.txt").read_text(encoding="utf-8")
        written_in = json.loads((HELP_DIR / HELP_ENVIRONMENT_FILE).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return text if written_in == help_environment() else None


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


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """The parser of the sub-commands of :data:`COMMANDS`; the LightningCLI ones are listed in its help (and
    accepted as choices) but go to :func:`~lightning_vtr.cli.lightning.run_lightning_cli` before it parses.

    Args:
        only: the one command whose options are added (its module is imported); ``None``: every command's.

    Its errors (an unknown option, a value a type check rejects, a missing required option) raise
    :class:`~lightning_vtr.errors.UsageError` rather than exiting; ``--help`` still prints and exits.
    """
    parser = _Parser(
        prog="lightning-vtr", description="View transformation robustness for multi-view 3D reconstruction."
    )
    parser.epilog = (
        f"Training and testing: `lightning-vtr {'|'.join(LIGHTNING_SUBCOMMANDS)} --config CONFIG.yaml` "
        "(LightningCLI; --help there). `lightning-vtr predict --ckpt CKPT ...` is the package's own command. "
        "A model of your own: --model module.Class (run from the folder holding module.py)."
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, help_text in LIGHTNING_COMMANDS.items():
        sub.add_parser(name, help=help_text, add_help=False)
    for name, command in COMMANDS.items():
        subparser = sub.add_parser(name, help=command.help)
        if only is None or only == name:
            command.add_arguments(subparser)
        subparser.set_defaults(run=command.run)
    return parser


def _command_word(words: Sequence[str]) -> str | None:
    """The first word that is not an option: the command ``build_parser`` needs the options of."""
    return next((word for word in words if not word.startswith("-")), None)


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``lightning-vtr`` with ``argv`` (default ``sys.argv[1:]``); returns the exit status."""
    words = list(sys.argv[1:] if argv is None else argv)
    text = shipped_help(words)
    if text is not None:  # `fit --help`: the live parser's text, without importing Lightning
        sys.stdout.write(text)
        raise SystemExit(0)  # as the live parser's --help does
    retain_freed_memory()  # this process trains: freed CPU memory is reused, not faulted in again every step
    if goes_to_lightning(words):
        from lightning_vtr.cli.lightning import run_lightning_cli

        command, run = words[0], lambda: run_lightning_cli(None if argv is None else words)
    else:
        try:
            word = _command_word(words)
            args = build_parser(word if word in COMMANDS else "").parse_args(words)
        except _ParseError as err:
            print(f"{err.prog}: error: {one_line(err)}", file=sys.stderr)
            return exit_status(err)
        args.command_line = shlex.join(["lightning-vtr", *words])  # shown in reports
        command, run = args.command, lambda: args.run(args)
    try:
        return int(run())
    except EXPECTED_ERRORS as err:
        # Errors a user can fix get one line, not a traceback: 2 for the command line, 1 for the data.
        print(f"lightning-vtr {command}: error: {printable(one_line(err))}", file=sys.stderr)
        return exit_status(err)


if __name__ == "__main__":
    sys.exit(main())
