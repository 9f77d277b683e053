"""The ``lightning-vtr`` dispatcher: one sub-parser per registered command, LightningCLI words passed on."""

from __future__ import annotations

import importlib
import sys

import pytest

import lightning_vtr.cli.lightning as lightning_cli
from lightning_vtr.cli import main
from lightning_vtr.cli.dispatch import COMMANDS, build_parser

# The dispatcher module (`lightning_vtr.cli.main` is the function the package exports).
MAIN_MODULE = importlib.import_module("lightning_vtr.cli.dispatch")


def _subcommands(parser):
    action = next(a for a in parser._actions if a.dest == "command")
    return action.choices


def test_the_package_exports_the_dispatcher():
    import lightning_vtr.cli as cli

    assert cli.main is MAIN_MODULE.main and cli.build_parser is build_parser and cli.COMMANDS is COMMANDS


def test_every_registered_command_has_a_sub_parser_and_a_help_line(capsys):
    assert list(COMMANDS) == [
        "build-dataset",
        "dataset-info",
        "report",
        "predict",
        "pix3d",
        "evaluate-folder",
        "robustness",
    ]
    assert list(_subcommands(build_parser())) == list(COMMANDS)
    with pytest.raises(SystemExit) as exit_info:
        main(["--help"])
    assert exit_info.value.code == 0
    printed = capsys.readouterr().out
    for name, (help_text, _, _) in COMMANDS.items():
        assert name in printed and help_text.split()[0] in printed
    assert "fit|validate|test" in printed


@pytest.mark.parametrize("word", lightning_cli.LIGHTNING_SUBCOMMANDS)
def test_lightning_subcommands_go_to_lightning_cli_with_every_word(monkeypatch, word):
    seen = []
    monkeypatch.setattr(MAIN_MODULE, "run_lightning_cli", lambda argv: seen.append(argv) or 0)
    assert main([word, "--config", "c.yaml"]) == 0
    assert seen == [[word, "--config", "c.yaml"]]
    # From the entry point (argv None), LightningCLI reads sys.argv itself.
    monkeypatch.setattr(sys, "argv", ["lightning-vtr", word, "--print_config"])
    assert main() == 0 and seen[-1] is None


def test_an_unknown_command_is_a_usage_error(capsys):
    assert main(["export"]) == 2
    err = capsys.readouterr().err
    assert "invalid choice: 'export'" in err and "usage:" not in err and len(err.splitlines()) == 1


def test_an_error_the_user_can_fix_prints_one_line_and_returns_2(monkeypatch, capsys):
    def failing_run(args):
        raise FileNotFoundError(f"no dataset at {args.root}")

    monkeypatch.setitem(COMMANDS, "dataset-info", (*COMMANDS["dataset-info"][:2], failing_run))
    assert main(["dataset-info", "/nowhere"]) == 2
    err = capsys.readouterr().err
    assert err == "lightning-vtr dataset-info: error: no dataset at /nowhere\n"
