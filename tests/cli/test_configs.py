"""Every YAML file in ``configs/`` parses with ``lightning-vtr fit --print_config``; the tiny ones also train one
``fast_dev_run`` step on a tiny dataset."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml
from helpers import one_thread

from lightning_vtr.callback import ErrorGuidedViewAugmentation
from lightning_vtr.cli import main

_one_thread = pytest.fixture(autouse=True)(one_thread)
CONFIGS = sorted((Path(__file__).resolve().parents[2] / "configs").glob("*.yaml"))
STRATEGIES = ("nature", "random", "viat", "mvtn", "error_guided")


def test_the_configs_cover_the_models_strategies_and_synthesizers():
    names = {path.stem for path in CONFIGS}
    assert {"lrgt_tiny_vtr", "lrgt_paper_vtr", "pix2vox_paper_vtr", "pix2vox_tiny_zero123"} <= names
    assert {f"strategy_{s}" for s in STRATEGIES} <= names


@pytest.mark.parametrize("path", CONFIGS, ids=lambda p: p.stem)
def test_every_config_parses(path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["fit", "--config", str(path), "--print_config"])
    assert exit_info.value.code == 0
    config = yaml.safe_load(capsys.readouterr().out)
    callbacks = {c["class_path"]: c["init_args"] for c in config["trainer"]["callbacks"]}
    checkpoint = callbacks["lightning.pytorch.callbacks.ModelCheckpoint"]
    assert checkpoint["save_last"] is True
    assert (checkpoint["monitor"], checkpoint["mode"]) == ("val/iou@0.4", "max")
    if path.stem.startswith("strategy_"):
        selector = callbacks["lightning_vtr.ErrorGuidedViewAugmentation"]["selector"]
        assert selector == path.stem.removeprefix("strategy_")
    if "_paper_" in path.stem:  # the configs "as published" name the paper's exact rule, not the default
        init_args = callbacks["lightning_vtr.ErrorGuidedViewAugmentation"]
        assert init_args["selector"] == "paper"
        pool = init_args["pool"].get("init_args", init_args["pool"])  # the printed form of a ViewpointPool
        callback = ErrorGuidedViewAugmentation(
            selector=init_args["selector"],
            fraction=init_args["fraction"],
            search_fraction=init_args["search_fraction"],
            pool={k: pool[k] for k in ("capacity", "prefer_others", "refresh")},
        )
        assert (callback.selector.score, callback.selector.min_separation, callback.selector.temperature) == (
            "paper",
            None,
            None,
        )
        assert (callback.search_fraction, callback.pool.refresh) == (init_args["fraction"], False)
    if "zero123" in path.stem:
        synth = callbacks["lightning_vtr.ErrorGuidedViewAugmentation"]["synthesizer"]["init_args"]["synthesizer"]
        assert synth["class_path"] == "lightning_vtr.synthesis.Zero123Synthesizer.from_pretrained"
    assert config["trainer"]["reload_dataloaders_every_n_epochs"] == 1


@pytest.mark.slow
@pytest.mark.parametrize("name", ["lrgt_tiny_vtr", "strategy_error_guided"])
def test_a_tiny_config_trains_a_step(name, tiny_dataset, tmp_path):
    main(
        [
            "fit",
            "--config",
            str(CONFIGS[[p.stem for p in CONFIGS].index(name)]),
            f"--data.root={tiny_dataset}",
            "--data.batch_size=4",
            f"--trainer.default_root_dir={tmp_path}",
            "--trainer.fast_dev_run=true",
            "--trainer.logger=false",
            "--trainer.enable_progress_bar=false",
            "--trainer.accelerator=cpu",
        ]
    )
    assert (tmp_path / "vtr_selection" / "start.json").is_file()  # the callback selected and synthesized
