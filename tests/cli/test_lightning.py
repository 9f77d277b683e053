"""``lightning-vtr fit|validate|test`` and VTRLightningCLI: the package's defaults live in the class."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

from lightning_vtr.cli import main
from lightning_vtr.cli.lightning import VTRLightningCLI
from lightning_vtr.data.datamodule import VTRDataModule
from lightning_vtr.models.pix2vox import Pix2VoxPlusPlus

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
            "fit",
            "--config",
            str(CONFIG),
            f"--data.root={tiny_dataset}",
            f"--trainer.default_root_dir={tmp_path}",
            "--trainer.max_epochs=2",
            "--trainer.limit_train_batches=1",
            "--trainer.limit_val_batches=1",
            "--trainer.logger=false",
            "--trainer.enable_progress_bar=false",
        ]
    )
    records = sorted((tmp_path / "vtr_selection").glob("epoch_*.json"))
    assert [r.name for r in records] == ["epoch_0000.json"]  # epoch 0 of 2: the last epoch generates nothing
    assert len(json.loads(records[0].read_text())["objects"]) == 1  # 5 % of 21 training objects, at least one


def test_the_class_alone_has_the_package_defaults(tmp_path):
    cli = VTRLightningCLI(
        run=False,
        args=[
            "--model=lightning_vtr.models.pix2vox.Pix2VoxPlusPlus",
            "--model.preset=tiny",
            f"--data.root={tmp_path}",
            "--trainer.logger=false",
            "--trainer.enable_checkpointing=false",
        ],
    )
    assert isinstance(cli.model, Pix2VoxPlusPlus)  # any VoxelReconstructionModule subclass
    assert isinstance(cli.datamodule, VTRDataModule)
    assert cli.trainer.reload_dataloaders_every_n_epochs == 1
    # The model's own optimizer and scheduler are kept, not replaced by LightningCLI's.
    assert cli.model.configure_optimizers.__func__ is Pix2VoxPlusPlus.configure_optimizers


def test_given_trainer_defaults_merge_over_the_package_defaults(tmp_path):
    cli = VTRLightningCLI(
        run=False,
        trainer_defaults={"max_epochs": 3},
        args=["--model=lightning_vtr.models.pix2vox.Pix2VoxPlusPlus", "--trainer.logger=false"],
    )
    assert cli.trainer.max_epochs == 3 and cli.trainer.reload_dataloaders_every_n_epochs == 1


def test_a_checkpoint_of_another_preset_gets_one_line_naming_the_model_and_the_keys():
    """torch's multi-line ``load_state_dict`` error on ``--ckpt_path`` becomes one line with the counts."""
    import torch

    from lightning_vtr.cli.lightning import _weights_mismatch

    class Small(torch.nn.Module):
        def __init__(self, width: int) -> None:
            super().__init__()
            self.a, self.b = torch.nn.Linear(2, width), torch.nn.Linear(width, 1)

    saved = {k: v for k, v in Small(4).state_dict().items() if k != "b.bias"}
    saved["c.weight"] = torch.zeros(1)
    with pytest.raises(RuntimeError) as err:
        Small(3).load_state_dict(saved)
    line = _weights_mismatch(str(err.value), "x.ckpt")
    assert "\n" not in line
    assert line.startswith("`--ckpt_path` must be a checkpoint of the configured model (Small), got 'x.ckpt': ")
    assert "1 missing keys, 1 unexpected keys, 3 shape mismatches" in line
