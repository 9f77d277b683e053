"""lightning_vtr.experiments.comparison: the examples' flags, the config they give, the two runs and the table."""

from __future__ import annotations

import argparse

import pytest

import lightning_vtr.experiments.comparison as comparison
from lightning_vtr.experiments.strategies import DEFAULT_STRATEGY
from lightning_vtr.experiments.training import FINETUNE_LR_SCHEDULES, MODELS, ExperimentConfig


def _parse(model: str, argv: list[str]) -> argparse.Namespace:
    return comparison.add_comparison_arguments(argparse.ArgumentParser(), model).parse_args(argv)


def test_every_model_has_a_title():
    assert list(comparison.MODEL_TITLES) == list(MODELS)


def test_flags_default_per_model_and_read_the_schedules():
    assert _parse("pix2vox", []).out == "runs/pix2vox_vtr" and _parse("lrgt", []).out == "runs/lrgt_vtr"
    parser = comparison.add_comparison_arguments(argparse.ArgumentParser(), "pix2vox")
    choices = {a.dest: a.choices for a in parser._actions}
    assert tuple(choices["finetune_lr"]) == FINETUNE_LR_SCHEDULES
    with pytest.raises(ValueError, match="`model` must be one of"):
        comparison.add_comparison_arguments(argparse.ArgumentParser(), "unet")


def test_run_comparison_fine_tunes_without_and_with_the_callback_and_prints_both_rows(monkeypatch, capsys, tmp_path):
    seen = []

    def fake_run_strategy(name, config, ckpt, synthesizer=None):
        seen.append((name, config, ckpt, synthesizer))
        return {"results": {"aligned": {"iou@0.4": 0.5 if name == "none" else 0.625, "fscore": 0.25}}}

    monkeypatch.setattr(comparison, "pretrain", lambda config: tmp_path / "pre.ckpt")
    monkeypatch.setattr(comparison, "run_strategy", fake_run_strategy)
    args = _parse("lrgt", ["--devices", "2", "--pretrain-epochs", "3", "--out", str(tmp_path), "--fraction", "0.1"])
    runs = comparison.run_comparison(args, "lrgt", lr=0.01)

    assert list(runs) == ["LRGT (no VTR)", "LRGT + VTR (default rule)"]
    assert [s[0] for s in seen] == ["none", DEFAULT_STRATEGY]  # the callback's default rule
    config = seen[0][1]
    assert config == ExperimentConfig(
        model="lrgt",
        pretrain_epochs=3,
        finetune_epochs=12,
        batch_size=8,
        fraction=0.1,
        devices=2,
        out=str(tmp_path),
        model_kwargs={"lr": 0.01},
    )
    assert seen[1][1] is config and seen[0][2] == seen[1][2] == tmp_path / "pre.ckpt"
    printed = capsys.readouterr().out
    assert "| LRGT (no VTR) | 50.00 | 25.00 | - | - | - | - |" in printed
    assert "| LRGT + VTR (default rule) | 62.50 | 25.00 | - | - | - | - |" in printed
