"""The ``lightning-vtr`` dispatcher: one sub-parser per registered command, LightningCLI words passed on."""

from __future__ import annotations

import importlib
import sys

import pytest

import lightning_vtr.cli.lightning as lightning_cli
from lightning_vtr.cli import main
from lightning_vtr.cli.dispatch import COMMANDS, LIGHTNING_COMMANDS, build_parser

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
    assert list(_subcommands(build_parser())) == [*LIGHTNING_COMMANDS, *COMMANDS]
    with pytest.raises(SystemExit) as exit_info:
        main(["--help"])
    assert exit_info.value.code == 0
    printed = capsys.readouterr().out
    helps = {**LIGHTNING_COMMANDS, **{name: command.help for name, command in COMMANDS.items()}}
    for name, help_text in helps.items():
        assert f"    {name} " in printed or f"    {name}\n" in printed
        assert help_text.split()[0] in printed
    assert "fit|validate|test" in printed
    assert list(LIGHTNING_COMMANDS) == [w for w in lightning_cli.LIGHTNING_SUBCOMMANDS if w not in COMMANDS]


def test_help_imports_no_torch_and_lists_every_command():
    import subprocess

    code = (
        "import sys\nfrom lightning_vtr.cli import main\n"
        "for argv in ([], ['report'], ['predict'], ['robustness'], ['pix3d'], ['build-dataset'], ['dataset-info']):\n"
        "    try:\n        main([*argv, '--help'])\n    except SystemExit:\n        pass\n"
        "print('TORCH' if 'torch' in sys.modules else 'LIGHT', file=sys.stderr)"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert done.stderr.strip().splitlines()[-1] == "LIGHT"
    for name in ("fit", "validate", "test", "report", "robustness"):
        assert f"    {name} " in done.stdout


def test_written_out_choices_equal_the_library_constants():
    from lightning_vtr.cli import build_dataset, pix3d, predict
    from lightning_vtr.data import IMAGE_RECIPES, builder, folder_test_set
    from lightning_vtr.data import pix3d as pix3d_data
    from lightning_vtr.evaluation.tables import BEST_IOU
    from lightning_vtr.experiments import config, report_config
    from lightning_vtr.export import MESH_FORMATS

    assert predict.MESH_FORMATS == MESH_FORMATS
    assert (build_dataset.PROTOCOLS, build_dataset.SOURCE_LAYOUTS) == (builder.PROTOCOLS, builder.SOURCE_LAYOUTS)
    assert (pix3d.POOLINGS, pix3d.VIEW_CHOICES) == (pix3d_data.POOLINGS, folder_test_set.VIEW_CHOICES)
    assert ("reference", *IMAGE_RECIPES) == config.RECIPES
    assert report_config.METRICS[1] == BEST_IOU


def test_fit_help_hides_the_removed_option(capsys):
    with pytest.raises(SystemExit):
        main(["fit", "--help"])
    printed = capsys.readouterr().out
    assert "--data.max_generated" not in printed and "--data.root" in printed


@pytest.mark.parametrize("word", lightning_cli.LIGHTNING_SUBCOMMANDS)
def test_lightning_subcommands_go_to_lightning_cli_with_every_word(monkeypatch, word):
    seen = []
    monkeypatch.setattr(lightning_cli, "run_lightning_cli", lambda argv: seen.append(argv) or 0)
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

    monkeypatch.setattr(COMMANDS["dataset-info"], "run", failing_run)
    assert main(["dataset-info", "/nowhere"]) == 2
    err = capsys.readouterr().err
    assert err == "lightning-vtr dataset-info: error: no dataset at /nowhere\n"
