"""The ``lightning-vtr`` dispatcher: one sub-parser per registered command, LightningCLI words passed on."""

from __future__ import annotations

import importlib
import json
import sys

import pytest

import lightning_vtr.cli.lightning as lightning_cli
from lightning_vtr.cli import main
from lightning_vtr.cli.dispatch import (
    COMMANDS,
    HELP_DIR,
    HELP_ENVIRONMENT_FILE,
    LIGHTNING_COMMANDS,
    build_parser,
    help_environment,
    shipped_help,
)

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
    with pytest.raises(SystemExit) as exit_info:
        main(["fit", "--help"])
    printed = capsys.readouterr().out
    assert exit_info.value.code == 0
    assert "--data.max_generated" not in printed and "--data.root" in printed


def _written_here() -> bool:
    """Whether this environment is the one the shipped help texts were written in (else the live parser serves)."""
    recorded = json.loads((HELP_DIR / HELP_ENVIRONMENT_FILE).read_text(encoding="utf-8"))
    return recorded == help_environment()


def _assert_the_live_parser_serves_help_here():
    # another Python or library version: the shipped texts are not used, so they cannot mislead
    for command in LIGHTNING_COMMANDS:
        assert shipped_help([command, "--help"]) is None


@pytest.mark.slow
def test_the_shipped_lightning_help_equals_the_live_parsers():
    import os
    import subprocess

    if not _written_here():
        _assert_the_live_parser_serves_help_here()
        return

    # a fresh process: the texts list the "known subclasses" of the imported modules, and this one imported more;
    # a wide terminal there must not change the texts (they are wrapped at 80 columns)
    code = "import json\nfrom lightning_vtr.cli.gen_help import generate\nprint(json.dumps(generate()))"
    env = {**os.environ, "COLUMNS": "200"}
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, env=env)
    assert done.returncode == 0, done.stderr[-3000:]
    live = json.loads(done.stdout)
    assert set(live) == {"fit.txt", "validate.txt", "test.txt", HELP_ENVIRONMENT_FILE}
    for name, text in live.items():
        shipped = (HELP_DIR / name).read_text(encoding="utf-8")
        assert shipped == text, (
            f"{HELP_DIR / name} differs from the live LightningCLI parser's text: regenerate the shipped help with "
            "`python -m lightning_vtr.cli.gen_help`"
        )
    for command in LIGHTNING_COMMANDS:
        assert live[f"{command}.txt"].startswith(f"usage: lightning-vtr [options] {command} [-c CONFIG]\n")
        assert "--data.root" in live[f"{command}.txt"] and "max_generated" not in live[f"{command}.txt"]


def test_lightning_help_prints_the_shipped_text_without_importing_lightning():
    import subprocess

    if not _written_here():
        _assert_the_live_parser_serves_help_here()
        return

    code = (
        "import sys\nfrom lightning_vtr.cli import main\n"
        "for command in ('fit', 'validate', 'test'):\n"
        "    for flag in ('--help', '-h'):\n"
        "        try:\n            main([command, flag])\n        except SystemExit as exit_:\n"
        "            print(f'EXIT {exit_.code}')\n"
        "print(sorted({'torch', 'lightning', 'jsonargparse'} & set(sys.modules)), file=sys.stderr)"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=60)
    assert done.stderr.strip().splitlines()[-1] == "[]"
    expected = "".join(
        (HELP_DIR / f"{command}.txt").read_text(encoding="utf-8") + "EXIT 0\n"
        for command in ("fit", "validate", "test")
        for _ in range(2)
    )
    assert done.stdout == expected


@pytest.mark.parametrize(
    "words",
    [
        ["fit", "--config", "c.yaml", "--help"],
        ["fit", "--model", "mymodel.MyVoxelNet", "--help"],
        ["fit", "--help", "--trainer.max_epochs", "3"],
        ["fit", "--print_config"],
        ["predict", "--config", "c.yaml", "--help"],
    ],
)
def test_help_of_other_lightning_command_lines_comes_from_the_live_parser(monkeypatch, words):
    seen = []
    monkeypatch.setattr(lightning_cli, "run_lightning_cli", lambda argv: seen.append(argv) or 0)
    assert MAIN_MODULE.shipped_help(words) is None
    assert main(words) == 0 and seen == [words]


def test_help_from_another_environment_or_with_jsonargparse_settings_comes_from_the_live_parser(monkeypatch):
    seen = []
    monkeypatch.setattr(lightning_cli, "run_lightning_cli", lambda argv: seen.append(argv) or 0)
    written_in = help_environment()
    assert MAIN_MODULE.shipped_help(["test", "-h"]) == (HELP_DIR / "test.txt").read_text(encoding="utf-8")
    monkeypatch.setattr(
        MAIN_MODULE,
        "help_environment",
        lambda: {**written_in, "distributions": {**written_in["distributions"], "lightning": "9.9.9"}},
    )
    assert MAIN_MODULE.shipped_help(["test", "-h"]) is None
    assert main(["test", "-h"]) == 0 and seen == [["test", "-h"]]
    monkeypatch.setattr(MAIN_MODULE, "help_environment", lambda: written_in)
    monkeypatch.setenv("JSONARGPARSE_DEFAULT_ENV", "true")  # adds the ENV: names to the help
    assert main(["fit", "--help"]) == 0 and seen[-1] == ["fit", "--help"]


def test_help_environment_names_python_and_the_installed_versions():
    from importlib.metadata import version

    environment = help_environment()
    assert environment["python"] == f"{sys.version_info.major}.{sys.version_info.minor}"
    assert environment["distributions"]["lightning"] == version("lightning")
    assert environment["distributions"]["jsonargparse"] == version("jsonargparse")
    assert set(environment["distributions"]) == {"lightning", "jsonargparse", "docstring-parser", "typeshed-client"}


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


def test_lightning_help_refuses_a_command_that_is_not_lightning_clis():
    with pytest.raises(ValueError, match="`command` must be one of fit, validate, test, predict, got 'report'"):
        lightning_cli.lightning_help("report")
