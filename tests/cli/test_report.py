"""``lightning-vtr report``: its flags read the registries and build the ReportConfig they describe."""

from __future__ import annotations

import argparse

import pytest
import torch

from lightning_vtr.cli import main
from lightning_vtr.cli.report import add_arguments
from lightning_vtr.experiments.report import MAIN_STRATEGIES, ReportConfig, default_experiment
from lightning_vtr.experiments.report_config import AUTO_JOBS, auto_jobs
from lightning_vtr.experiments.training import FINETUNE_LR_SCHEDULES, MODELS, VARIANTS


@pytest.fixture
def captured(monkeypatch):
    """Runs `lightning-vtr report` up to the ReportConfig it would run; returns the list of configs."""
    configs = []

    def fake_run_report(config):
        configs.append(config)
        return {"markdown": "table", "paths": {}}

    monkeypatch.setattr("lightning_vtr.experiments.report.run_report", fake_run_report)
    # --data and --out name no real folders here (tests/cli/test_bad_input_table.py checks them)
    monkeypatch.setattr("lightning_vtr.cli.report.check_inputs", lambda args: None)
    return configs


def test_choices_are_the_registries():
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    choices = {a.dest: a.choices for a in parser._actions}
    assert choices["model"] is None  # a registered name or a class path of yours, checked when the command runs
    assert set(MODELS) == {"pix2vox", "lrgt"}
    assert tuple(choices["finetune_lr"]) == FINETUNE_LR_SCHEDULES
    strategies = next(a for a in parser._actions if a.dest == "strategies")
    assert strategies.type(",".join(VARIANTS)) == list(VARIANTS)  # every variant is a valid row


def test_cli_builds_the_report_config(captured):
    argv = [
        "report",
        "--seeds",
        "0",
        "1",
        "--strategies",
        "none,viat,error_guided",
        "--ablations",
        "k,single_view",
        "--test-repeats",
        "2",
        "--fraction",
        "0.1",
        "--pretrain-epochs",
        "3",
        "--out",
        "somewhere",
        "--finetune-lr",
        "constant",
        "--devices",
        "2",
        "--model",
        "lrgt",
        "--data",
        "/data/vtr",
    ]
    assert main(argv) == 0
    config = captured[-1]
    assert isinstance(config, ReportConfig)
    assert (config.seeds, config.strategies, config.ablations) == (
        [0, 1],
        ["none", "viat", "error_guided"],
        ["k", "single_view"],
    )
    assert config.experiment == default_experiment(
        test_repeats=2,
        model="lrgt",
        data="/data/vtr",
        fraction=0.1,
        pretrain_epochs=3,
        out="somewhere",
        finetune_lr="constant",
        devices=2,
    )
    assert config.command == "lightning-vtr " + " ".join(argv)


def test_cli_defaults_are_the_report_defaults(captured, monkeypatch):
    # a CPU-only machine with 3 torch threads, whatever this one has
    monkeypatch.setattr(torch, "get_num_threads", lambda: 3)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    monkeypatch.setattr(torch.backends.mps, "is_available", lambda: False)
    assert main(["report"]) == 0
    config = captured[-1]
    assert config.experiment == ReportConfig().experiment == default_experiment()
    assert config.strategies == list(MAIN_STRATEGIES) == ["none", "random", "random_area", "paper", "error_guided"]
    assert config.ablations == [] and config.seeds == [0, 1, 2]
    assert config.experiment.test_repeats == 4
    # Old command lines: --no-ablations is the default now, still accepted.
    assert main(["report", "--no-ablations", "--test-repeats", "3"]) == 0
    assert captured[-1].ablations == [] and captured[-1].experiment.test_repeats == 3
    assert config.experiment.recipe == "plain"
    assert main(["report", "--recipe", "reference"]) == 0 and captured[-1].experiment.recipe == "reference"
    assert config.validation_repeats is None
    assert main(["report", "--validation-repeats", "12"]) == 0 and captured[-1].validation_repeats == 12
    # one fit per torch thread on a CPU, at most AUTO_JOBS; one on a GPU or with two devices; --jobs overrides
    assert config.jobs == auto_jobs(config.experiment) == 3
    monkeypatch.setattr(torch, "get_num_threads", lambda: 16)
    assert main(["report"]) == 0 and captured[-1].jobs == AUTO_JOBS == 4
    assert main(["report", "--accelerator", "gpu"]) == 0 and captured[-1].jobs == 1
    assert main(["report", "--devices", "2"]) == 0 and captured[-1].jobs == 1
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert main(["report"]) == 0 and captured[-1].jobs == 1  # accelerator "auto" finds the GPU
    assert main(["report", "--jobs", "2"]) == 0 and captured[-1].jobs == 2


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--strategies", "none,ours"], "`--strategies` names unknown row(s) 'ours'"),
        (["--ablations", "k,dropout"], "invalid choice(s) 'dropout'"),
        (["--ablations", "k", "--no-ablations"], "not allowed with argument"),
        (["--test-repeats", "0"], "positive integer"),
        (["--validation-repeats", "0"], "positive integer"),
        (["--jobs", "0"], "positive integer"),
        (["--model", "unet"], "`--model` must be pix2vox, lrgt or a class path module.Class, got 'unet'"),
        (["--finetune-lr", "linear"], "invalid choice: 'linear'"),
        (["--recipe", "imagenet"], "invalid choice: 'imagenet'"),
        (["--pretrain-epochs", "0"], "positive integer"),
    ],
)
def test_cli_rejects_unknown_names_before_running(captured, capsys, argv, message):
    assert main(["report", *argv]) == 2
    assert message in capsys.readouterr().err
    assert captured == []


def test_list_strategies_prints_one_line_per_row_and_runs_nothing(captured, capsys):
    assert main(["report", "--list-strategies"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == len(VARIANTS)
    for line, (name, variant) in zip(lines, VARIANTS.items()):
        assert line == f"{name}: {variant.title} - {variant.description}"
    assert lines[0].startswith("none: None-VTR - ") and captured == []


def test_every_flag_is_a_config_field_with_one_name_and_the_configs_default():
    from dataclasses import fields

    from lightning_vtr.experiments.training import ExperimentConfig

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    actions = {a.dest: a for a in parser._actions if a.dest != "help"}
    experiment, report = default_experiment(), ReportConfig()
    # every flag but these sets the field of its name, under that one name (--model-arg KEY=VALUE fills the
    # experiment's model_kwargs, --no-progress its trainer_kwargs)
    switches = {"no_ablations", "list_strategies", "no_progress", "model_args"}
    config_fields = {f.name for f in fields(ExperimentConfig)} | {f.name for f in fields(ReportConfig)}
    assert set(actions) - switches <= config_fields
    for dest, action in actions.items():
        if dest not in switches:
            assert action.option_strings == ["--" + dest.replace("_", "-")], dest
    for name in ("model", "pretrain_epochs", "finetune_epochs", "batch_size", "test_repeats", "fraction", "out"):
        assert actions[name].default == getattr(experiment, name)
    assert actions["seeds"].default == list(report.seeds)
    assert actions["jobs"].default is None and report.jobs == 1  # the command's default is auto_jobs
    assert "seed" not in actions  # --seeds sets it
