"""A model and a selector of a user's own, not the package's classes, through every command: ``fit``, ``predict``,
``robustness`` (both with ``--model``: a checkpoint never chooses the code that runs) and a 1-seed 1-epoch
``report`` with a strategies file, run from the folder holding them."""

from __future__ import annotations

import csv
import json
import sys
import textwrap

import pytest
import torch
from helpers import USER_SELECTOR_SOURCE as SELECTOR_SOURCE
from helpers import one_thread

from lightning_vtr.cli import main
from lightning_vtr.models.registry import CLASS_PATH_KEY, checkpoint_class_path, load_model

_one_thread = pytest.fixture(autouse=True)(one_thread)

#: ``mymodel.py``: a plain LightningModule (no package base class) with the protocol's members.
MODEL_SOURCE = textwrap.dedent(
    """
    import lightning as L
    import torch
    import torch.nn.functional as F
    from torch import nn


    class TinyVoxelNet(L.LightningModule):
        def __init__(self, image_size: int = 64, num_views: int = 3, voxel_resolution: int = 32, lr: float = 0.01):
            super().__init__()
            self.save_hyperparameters()
            self.image_size, self.num_views, self.voxel_resolution = image_size, num_views, voxel_resolution
            self.colour = nn.Linear(3, 8)
            self.grid = nn.Parameter(torch.zeros(8, voxel_resolution, voxel_resolution, voxel_resolution))

        def predict_voxels(self, images):
            weights = torch.softmax(self.colour(images.mean(dim=(1, 3, 4))), dim=-1)
            return torch.sigmoid(torch.einsum("bk,kxyz->bxyz", weights, self.grid))

        def training_step(self, batch, batch_idx):
            return F.binary_cross_entropy(self.predict_voxels(batch["images"]), batch["voxels"])

        def configure_optimizers(self):
            return torch.optim.Adam(self.parameters(), lr=self.hparams.lr)


    class NoSteps(L.LightningModule):
        image_size, num_views, voxel_resolution = 64, 3, 32

        def predict_voxels(self, images):
            return images.new_zeros(len(images), 32, 32, 32)


    class NotAModel(L.LightningModule):
        pass
    """
)
STRATEGIES = textwrap.dedent(
    """
    side:
      title: Side views
      description: three fixed side views
      selector:
        class_path: myselector.SideViews
        init_args: {pitch: 20.0}
      callback_kwargs: {fraction: 0.5}
    """
)


@pytest.fixture(scope="module")
def user_folder(tmp_path_factory):
    """A folder holding ``mymodel.py``, ``myselector.py`` and ``my_strategies.yaml``; the modules are forgotten after."""
    folder = tmp_path_factory.mktemp("user")
    (folder / "mymodel.py").write_text(MODEL_SOURCE)
    (folder / "myselector.py").write_text(SELECTOR_SOURCE)
    (folder / "my_strategies.yaml").write_text(STRATEGIES)
    yield folder
    for name in ("mymodel", "myselector"):
        sys.modules.pop(name, None)
    while str(folder) in sys.path:
        sys.path.remove(str(folder))


@pytest.fixture(scope="module")
def fitted(user_folder, tiny_dataset):
    """``lightning-vtr fit --model mymodel.TinyVoxelNet`` for one short epoch, from the user's folder."""
    with pytest.MonkeyPatch.context() as patch:
        patch.chdir(user_folder)
        torch.set_num_threads(1)
        status = main(
            [
                "fit",
                "--model",
                "mymodel.TinyVoxelNet",
                "--data.root",
                str(tiny_dataset),
                "--data.batch_size",
                "4",
                "--data.image_size",
                "64",
                "--trainer.max_epochs",
                "1",
                "--trainer.limit_train_batches",
                "2",
                "--trainer.limit_val_batches",
                "1",
                "--trainer.accelerator",
                "cpu",
                "--trainer.enable_progress_bar",
                "false",
                "--trainer.logger",
                "false",
                "--trainer.default_root_dir",
                str(user_folder / "run"),
            ]
        )
    assert status == 0
    (ckpt,) = (user_folder / "run").rglob("last.ckpt")
    return ckpt


def test_fit_trains_a_plain_lightning_module_and_records_its_class(fitted):
    checkpoint = torch.load(fitted, map_location="cpu", weights_only=True)
    assert checkpoint[CLASS_PATH_KEY] == "mymodel.TinyVoxelNet"
    assert checkpoint_class_path(fitted) == "mymodel.TinyVoxelNet"
    assert checkpoint["global_step"] == 2  # two batches: the model's own training_step ran
    assert not torch.equal(checkpoint["state_dict"]["grid"], torch.zeros_like(checkpoint["state_dict"]["grid"]))


def test_predict_loads_the_custom_checkpoint_with_model(fitted, user_folder, tiny_dataset, monkeypatch, capsys):
    monkeypatch.chdir(user_folder)
    out = user_folder / "predictions"
    argv = ["predict", "--ckpt", str(fitted), "--data", str(tiny_dataset), "--limit", "1", "--out", str(out)]
    argv += ["--no-sheets", "--device", "cpu", "--view-sets", "aligned"]
    # the checkpoint records mymodel.TinyVoxelNet, but a checkpoint never chooses the code that runs
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "names the model class 'mymodel.TinyVoxelNet', outside lightning_vtr" in err
    assert "pass `--model mymodel.TinyVoxelNet` if you trust it" in err and len(err.strip().splitlines()) == 1
    assert not out.exists()
    assert main([*argv, "--model", "mymodel.TinyVoxelNet"]) == 0
    model = load_model(fitted, "mymodel.TinyVoxelNet")
    assert type(model).__qualname__ == "TinyVoxelNet"
    weights = torch.load(fitted, map_location="cpu", weights_only=True)["state_dict"]["grid"]
    assert torch.equal(model.grid.detach(), weights)
    written = json.loads((out / "predictions.json").read_text())
    assert len(written["objects"] if isinstance(written, dict) else written) == 1


def test_robustness_maps_the_custom_checkpoint(fitted, user_folder, tiny_dataset, monkeypatch):
    monkeypatch.chdir(user_folder)
    out = user_folder / "robustness"
    argv = ["robustness", "--ckpt", f"mine={fitted}", "--data", str(tiny_dataset), "--out", str(out), "--k", "90"]
    argv += ["--model", "mymodel.TinyVoxelNet"]
    assert main([*argv, "--objects", "2", "--no-progress", "--device", "cpu"]) == 0
    with open(out / "bins.csv") as f:
        rows = [row for row in csv.DictReader(f) if row["category"] == "all"]
    assert {row["checkpoint"] for row in rows} == {"mine"} and len(rows) == 8  # K = 90: 2 x 4 bins


def test_report_compares_a_custom_model_and_selector(user_folder, tiny_dataset, monkeypatch, capsys):
    monkeypatch.chdir(user_folder)
    out = user_folder / "report"
    argv = ["report", "--model", "mymodel.TinyVoxelNet", "--data", str(tiny_dataset), "--seeds", "0", "--jobs", "1"]
    argv += ["--pretrain-epochs", "1", "--finetune-epochs", "1", "--batch-size", "4", "--accelerator", "cpu"]
    argv += ["--strategies-file", "my_strategies.yaml", "--strategies", "none,side", "--out", str(out)]
    assert main(argv) == 0
    with open(out / "results.csv") as f:
        rows = list(csv.DictReader(f))
    runs = {row["run"] for row in rows}
    assert runs == {"none", "side"}
    generated = json.loads((out / "seed_0" / "side" / "results.json").read_text())["generated_samples"]
    assert generated > 0  # the side-view selector's callback ran and rendered views
    assert json.loads((out / "seed_0" / "none" / "results.json").read_text())["generated_samples"] == 0


@pytest.mark.parametrize(
    ("argv", "expected"),
    [
        (["fit", "--model", "mymodel.NoSteps"], "missing training_step, configure_optimizers"),
        (["fit", "--model", "mymodel.NotAModel"], "missing predict_voxels"),
        (["fit", "--model", "nosuchmodule.Net"], "module 'nosuchmodule' not found"),
        (["fit", "--model", "mymodel.Missing"], "mymodel has no 'Missing'"),
    ],
)
def test_a_model_without_the_protocol_gets_one_line(user_folder, monkeypatch, capsys, argv, expected):
    monkeypatch.chdir(user_folder)
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert expected in err and len(err.strip().splitlines()) == 1
