from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

from lightning_vtr.cli import main

CONFIG = Path(__file__).resolve().parents[2] / "configs" / "pix2vox_tiny_vtr.yaml"


def test_print_config_resolves_the_callback_and_model(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["fit", "--config", str(CONFIG), "--print_config"])
    assert exit_info.value.code == 0
    config = yaml.safe_load(capsys.readouterr().out)
    callback = config["trainer"]["callbacks"][0]
    assert callback["class_path"] == "lightning_vtr.ErrorGuidedViewAugmentation"
    assert callback["init_args"]["selector"]["init_args"]["k"] == 30
    assert config["model"]["class_path"] == "lightning_vtr.models.pix2vox.Pix2VoxPlusPlus"
    assert config["trainer"]["reload_dataloaders_every_n_epochs"] == 1


@pytest.mark.slow
def test_fit_from_the_config_generates_samples(tiny_dataset, tmp_path):
    main(
        [
            "fit", "--config", str(CONFIG),
            f"--data.root={tiny_dataset}",
            f"--trainer.default_root_dir={tmp_path}",
            "--trainer.max_epochs=2", "--trainer.limit_train_batches=1", "--trainer.limit_val_batches=1",
            "--trainer.logger=false", "--trainer.enable_progress_bar=false",
        ]
    )
    records = sorted((tmp_path / "vtr_selection").glob("epoch_*.json"))
    assert [r.name for r in records] == ["epoch_0000.json"]  # epoch 0 of 2: the last epoch generates nothing
    assert len(json.loads(records[0].read_text())["objects"]) == 1  # 5 % of 21 training objects, at least one
