"""``lightning-vtr report``: its flags read the registries and build the ReportConfig they describe."""

from __future__ import annotations

import argparse

import pytest

from lightning_vtr.cli import main
from lightning_vtr.cli.report import add_arguments
from lightning_vtr.experiments.report import ABLATIONS, STRATEGIES, ReportConfig, default_experiment
from lightning_vtr.experiments.training import FINETUNE_LR_SCHEDULES, MODELS


@pytest.fixture
def captured(monkeypatch):
    """Runs `lightning-vtr report` up to the ReportConfig it would run; returns the list of configs."""
    configs = []

    def fake_run_report(config):
        configs.append(config)
        return {"markdown": "table", "paths": {}}

    monkeypatch.setattr("lightning_vtr.experiments.report.run_report", fake_run_report)
    return configs


def test_choices_are_the_registries():
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    choices = {a.dest: a.choices for a in parser._actions}
    assert list(choices["model"]) == list(MODELS)
    assert tuple(choices["finetune_lr"]) == FINETUNE_LR_SCHEDULES


def test_cli_builds_the_report_config(captured):
    argv = [
        "report",
        "--seeds",
        "0",
        "1",
        "--strategies",
        "none,viat",
        "--no-ablations",
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
    assert (config.seeds, config.strategies, config.ablations) == ([0, 1], ["none", "viat"], [])
    assert config.experiment == default_experiment(
        model="lrgt",
        data="/data/vtr",
        fraction=0.1,
        pretrain_epochs=3,
        out="somewhere",
        finetune_lr="constant",
        devices=2,
    )
    assert config.command == "lightning-vtr " + " ".join(argv)


def test_cli_defaults_are_the_report_defaults(captured):
    assert main(["report"]) == 0
    config = captured[-1]
    assert config.experiment == ReportConfig().experiment == default_experiment()
    assert config.strategies == list(STRATEGIES) and config.ablations == list(ABLATIONS)
    assert config.seeds == [0]


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--strategies", "none,ours"], "invalid choice(s) 'ours'"),
        (["--model", "unet"], "invalid choice: 'unet'"),
        (["--finetune-lr", "linear"], "invalid choice: 'linear'"),
        (["--pretrain-epochs", "0"], "positive integer"),
    ],
)
def test_cli_rejects_unknown_names_before_running(captured, capsys, argv, message):
    with pytest.raises(SystemExit) as exit_info:
        main(["report", *argv])
    assert exit_info.value.code == 2 and message in capsys.readouterr().err
    assert captured == []
