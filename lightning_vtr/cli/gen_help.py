"""``python -m lightning_vtr.cli.gen_help``: write the help texts ``lightning-vtr fit|validate|test --help``
prints without importing Lightning (:func:`lightning_vtr.cli.dispatch.shipped_help`).

Each text is the live ``LightningCLI`` parser's (:func:`lightning_vtr.cli.lightning.lightning_help`: 80 columns,
program ``lightning-vtr``), written to ``lightning_vtr/cli/help/COMMAND.txt`` with ``environment.json``, the
Python and library versions they were made with. Run it in a fresh process after changing the options of the
LightningCLI commands (the models' or the datamodule's arguments or docstrings, :class:`VTRLightningCLI`) or the
versions of :data:`~lightning_vtr.cli.dispatch.HELP_DISTRIBUTIONS`; ``tests/cli/test_main.py`` fails until then.

Usage: ``python -m lightning_vtr.cli.gen_help [--check]`` (``--check``: write nothing; exit status 1 and the
names of the files that differ when a text is out of date).
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence

from lightning_vtr.cli.dispatch import HELP_DIR, HELP_ENVIRONMENT_FILE, LIGHTNING_COMMANDS, help_environment
from lightning_vtr.utils.io import atomic_write

__all__ = ["generate", "main"]


def generate() -> dict[str, str]:
    """The shipped help files as they should be: file name in :data:`~lightning_vtr.cli.dispatch.HELP_DIR` ->
    text, one ``COMMAND.txt`` per LightningCLI command and the environment file.

    The texts list the ``known subclasses`` of the modules imported so far: call it in a fresh process (as
    ``lightning-vtr fit --help`` runs), not in one that imported other model or callback classes.
    """
    from lightning_vtr.cli.lightning import lightning_help

    files = {f"{command}.txt": lightning_help(command) for command in LIGHTNING_COMMANDS}
    files[HELP_ENVIRONMENT_FILE] = json.dumps(help_environment(), indent=2, sort_keys=True) + "\n"
    return files


def main(argv: Sequence[str] | None = None) -> int:
    """Write (or with ``--check`` compare) the shipped help files; returns the exit status."""
    parser = argparse.ArgumentParser(prog="python -m lightning_vtr.cli.gen_help", description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="write nothing; exit 1 when a file is out of date")
    args = parser.parse_args(argv)
    files = generate()
    stale = []
    for name, text in files.items():
        path = HELP_DIR / name
        if not path.is_file() or path.read_text(encoding="utf-8") != text:
            stale.append(path)
    if args.check:
        for path in stale:
            print(f"{path}: out of date (regenerate with `python -m lightning_vtr.cli.gen_help`)", file=sys.stderr)
        return 1 if stale else 0
    HELP_DIR.mkdir(exist_ok=True)
    for path in stale:
        atomic_write(path, files[path.name])
        print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
