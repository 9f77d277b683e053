"""The path a user walks through the command line: ``lightning-vtr fit`` from every shipped model config and from
``--model`` (each package model, and a user's own class from its own folder), then every command that takes what
fit wrote: ``validate --ckpt_path``, ``test --ckpt_path``, ``predict --ckpt``, ``robustness --ckpt`` and, for the
model classes, ``report --model``.

Each fit runs one batch of one epoch on a tiny dataset and is shared by the tests of one case (a module-scoped
cache); the shipped configs are used as they are, with the trainer and data limits given on the command line as a
user would (and, for the Zero-1-to-3 config, its weights path pointing at a tiny random model).
"""

from __future__ import annotations

import csv
import functools
import importlib.util
import json
import sys
import textwrap
from pathlib import Path
from typing import Any

import pytest
import torch
from helpers import one_thread

from lightning_vtr.cli import main
from lightning_vtr.models.registry import load_model

pytestmark = pytest.mark.slow
_one_thread = pytest.fixture(autouse=True)(one_thread)

REPO = Path(__file__).resolve().parents[1]
CONFIGS = sorted(p.stem for p in (REPO / "configs").glob("*.yaml"))
#: ``--model`` cases: the class path fit is given, and its extra arguments.
MODELS = {
    "pix2vox": ["--model", "lightning_vtr.models.Pix2VoxPlusPlus", "--model.preset", "tiny"],
    "lrgt": ["--model", "lightning_vtr.models.LRGT", "--model.preset", "tiny"],
    "user": ["--model", "roundtrip_model.UserVoxelNet"],
}
#: The report's ``--model`` for each ``--model`` case.
REPORT_MODELS = {"pix2vox": "pix2vox", "lrgt": "lrgt", "user": "roundtrip_model.UserVoxelNet"}
CASES = [f"config:{name}" for name in CONFIGS] + [f"model:{name}" for name in MODELS]

#: A user's own model in its own folder: a plain LightningModule with the protocol's members and its own steps.
USER_MODEL = textwrap.dedent(
    """
    import lightning as L
    import torch
    import torch.nn.functional as F
    from torch import nn


    class UserVoxelNet(L.LightningModule):
        def __init__(self, image_size: int = 64, num_views: int = 3, voxel_resolution: int = 32):
            super().__init__()
            self.save_hyperparameters()
            self.image_size, self.num_views, self.voxel_resolution = image_size, num_views, voxel_resolution
            self.colour = nn.Linear(3, 4)
            self.grid = nn.Parameter(torch.randn(4, voxel_resolution, voxel_resolution, voxel_resolution))

        def predict_voxels(self, images):
            weights = torch.softmax(self.colour(images.mean(dim=(1, 3, 4))), dim=-1)
            return torch.sigmoid(torch.einsum("bk,kxyz->bxyz", weights, self.grid))

        def _loss(self, batch):
            return F.binary_cross_entropy(self.predict_voxels(batch["images"]), batch["voxels"])

        def training_step(self, batch, batch_idx):
            return self._loss(batch)

        def validation_step(self, batch, batch_idx, dataloader_idx=0):
            self.log("val/loss", self._loss(batch))

        def test_step(self, batch, batch_idx, dataloader_idx=0):
            self.log("test/loss", self._loss(batch))

        def configure_optimizers(self):
            return torch.optim.Adam(self.parameters(), lr=0.01)
    """
)

TRAINER_LIMITS = [
    "--trainer.max_epochs=1",
    "--trainer.limit_train_batches=1",
    "--trainer.limit_val_batches=1",
    "--trainer.limit_test_batches=1",
    "--trainer.num_sanity_val_steps=0",
    "--trainer.accelerator=cpu",
    "--trainer.devices=1",
    "--trainer.enable_progress_bar=false",
]


@pytest.fixture(scope="module")
def dataset_224(tmp_path_factory):
    """A tiny ShapeNet-VTR directory at 224 px, the image size of the paper configs."""
    from lightning_vtr.data.builder import build_dataset

    root = tmp_path_factory.mktemp("vtr_224")
    build_dataset(
        root,
        source="procedural",
        categories=["chair", "table"],
        objects_per_category=3,
        image_size=224,
        resolution=32,
        views_per_set=4,
        seed=0,
        workers=1,
        progress=False,
    )
    return root


@pytest.fixture(scope="module")
def tiny_prerendered(tiny_dataset, tmp_path_factory):
    """A copy of the tiny dataset with prerendered views (K = 90: 8 per training object), for the config whose
    synthesizer reads them."""
    import shutil

    from lightning_vtr.synthesis import prerender_views

    root = tmp_path_factory.mktemp("tiny_prerendered") / "data"
    shutil.copytree(tiny_dataset, root)
    assert not prerender_views(root, k=90, progress=False).failed
    return root


@pytest.fixture(scope="module")
def workspace(tmp_path_factory):
    """The user's folder: their model module and a copy of the Zero-1-to-3 config naming a tiny local model."""
    folder = tmp_path_factory.mktemp("user")
    (folder / "roundtrip_model.py").write_text(USER_MODEL)
    spec = importlib.util.spec_from_file_location("_synthesis_fixtures", REPO / "tests" / "synthesis" / "conftest.py")
    assert spec is not None and spec.loader is not None
    fixtures = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = fixtures  # its dataclasses look their module up
    spec.loader.exec_module(fixtures)
    weights = fixtures.save_layout(fixtures.build_tiny_components(), folder / "zero123", "cc_projection")
    shipped = (REPO / "configs" / "pix2vox_tiny_zero123.yaml").read_text()
    assert "/weights/zero123-xl-diffusers" in shipped
    (folder / "pix2vox_tiny_zero123.yaml").write_text(shipped.replace("/weights/zero123-xl-diffusers", str(weights)))
    yield folder
    for name in ("roundtrip_model", "_synthesis_fixtures"):
        sys.modules.pop(name, None)
    while str(folder) in sys.path:
        sys.path.remove(str(folder))


class Fitted:
    """What one fit wrote, and the options that rebuild the same model and data for the other commands."""

    def __init__(self, case: str, ckpt: Path, model_args: list[str], data: Path, run_dir: Path) -> None:
        self.case, self.ckpt, self.model_args, self.data, self.run_dir = case, ckpt, model_args, data, run_dir

    @property
    def is_user_model(self) -> bool:
        return self.case == "model:user"

    def model_option(self) -> list[str]:
        """``--model`` for predict / robustness: the user's own class is named, as for any class outside the
        package; the package's classes are found from the checkpoint."""
        return ["--model", "roundtrip_model.UserVoxelNet"] if self.is_user_model else []


_FITTED: dict[str, Fitted] = {}


def _data_args(case: str, tiny_dataset: Path, dataset_224: Path) -> tuple[Path, list[str]]:
    data = dataset_224 if "_paper_" in case else tiny_dataset
    return data, [f"--data.root={data}", "--data.batch_size=2", "--data.num_workers=0"]


def _source_args(case: str, workspace: Path) -> list[str]:
    kind, name = case.split(":")
    if kind == "model":
        return [*MODELS[name], "--data.image_size=64"]
    config = workspace / f"{name}.yaml" if (workspace / f"{name}.yaml").is_file() else REPO / "configs" / f"{name}.yaml"
    return ["--config", str(config)]


@pytest.fixture
def fitted(request, tiny_dataset, dataset_224, workspace, monkeypatch) -> Fitted:
    """``lightning-vtr fit`` for the test's case (run once per case, in the user's folder)."""
    case = request.param
    monkeypatch.chdir(workspace)
    if case not in _FITTED:
        if "prerendered" in case:  # its synthesizer reads views rendered into the dataset
            tiny_dataset = request.getfixturevalue("tiny_prerendered")
        data, data_args = _data_args(case, tiny_dataset, dataset_224)
        run_dir = workspace / "runs" / case.replace(":", "_")
        source = _source_args(case, workspace)
        main(["fit", *source, *data_args, *TRAINER_LIMITS, f"--trainer.default_root_dir={run_dir}"])
        found = sorted(run_dir.rglob("last.ckpt"))
        assert len(found) == 1, f"fit wrote no single last.ckpt under {run_dir}: {sorted(run_dir.rglob('*.ckpt'))}"
        _FITTED[case] = Fitted(case, found[0], [*source, *data_args], data, run_dir)
    return _FITTED[case]


def _checkpoint_weights(ckpt: Path) -> dict[str, torch.Tensor]:
    return torch.load(ckpt, map_location="cpu", weights_only=True)["state_dict"]


@pytest.mark.parametrize("fitted", CASES, indirect=True)
@pytest.mark.parametrize("stage", ["validate", "test"])
def test_validate_and_test_take_what_fit_wrote(fitted, stage, monkeypatch):
    import lightning as L

    seen: dict[str, Any] = {}
    monkeypatch.setattr(L.Trainer, stage, _recording(getattr(L.Trainer, stage), seen))
    main([stage, *fitted.model_args, *TRAINER_LIMITS, f"--trainer.default_root_dir={fitted.run_dir}",
          f"--ckpt_path={fitted.ckpt}"])  # fmt: skip
    trainer = seen["trainer"]
    weights = _checkpoint_weights(fitted.ckpt)
    name, expected = next(iter(weights.items()))
    assert torch.equal(trainer.lightning_module.state_dict()[name].cpu(), expected)  # the checkpoint's weights ran
    assert seen["results"], f"{stage} logged no metrics"
    assert all(torch.isfinite(torch.tensor(float(v))) for r in seen["results"] for v in r.values())


def _recording(method: Any, seen: dict[str, Any]) -> Any:
    @functools.wraps(method)  # LightningCLI reads the method's signature for the sub-command's options
    def wrapper(self: Any, *args: Any, **kwargs: Any) -> Any:
        seen["trainer"] = self
        seen["results"] = method(self, *args, **kwargs)
        return seen["results"]

    return wrapper


@pytest.mark.parametrize("fitted", CASES, indirect=True)
def test_predict_takes_what_fit_wrote(fitted, tmp_path):
    out = tmp_path / "pred"
    argv = ["predict", "--ckpt", str(fitted.ckpt), "--data", str(fitted.data), "--limit", "1", "--out", str(out)]
    argv += ["--view-sets", "aligned", "--no-sheets", "--device", "cpu", "--no-progress", *fitted.model_option()]
    assert main(argv) == 0
    model = load_model(fitted.ckpt, "roundtrip_model.UserVoxelNet" if fitted.is_user_model else None)
    weights = _checkpoint_weights(fitted.ckpt)
    assert all(torch.equal(model.state_dict()[k], v) for k, v in weights.items())
    written = json.loads((out / "predictions.json").read_text())
    objects = written["objects"] if isinstance(written, dict) else written
    assert len(objects) == 1
    assert 0.0 <= objects[0]["facts"]["IoU@0.4"] <= 1.0


@pytest.mark.parametrize("fitted", CASES, indirect=True)
def test_robustness_takes_what_fit_wrote(fitted, tmp_path):
    out = tmp_path / "rob"
    argv = ["robustness", "--ckpt", f"run={fitted.ckpt}", "--data", str(fitted.data), "--out", str(out), "--k", "90"]
    assert main([*argv, "--objects", "1", "--no-progress", "--device", "cpu", *fitted.model_option()]) == 0
    with open(out / "bins.csv") as f:
        rows = [row for row in csv.DictReader(f) if row["category"] == "all"]
    assert len(rows) == 8  # K = 90: 2 pitch x 4 yaw bins
    assert all(0.0 <= float(row["mean_iou"]) <= 1.0 for row in rows)


@pytest.mark.parametrize("fitted", [f"model:{name}" for name in MODELS], indirect=True)
def test_report_takes_the_model_fit_was_given(fitted, tmp_path):
    name = fitted.case.split(":")[1]
    out = tmp_path / "report"
    argv = ["report", "--model", REPORT_MODELS[name], "--data", str(fitted.data), "--seeds", "0", "--jobs", "1"]
    argv += ["--pretrain-epochs", "1", "--finetune-epochs", "1", "--batch-size", "4", "--accelerator", "cpu"]
    argv += ["--strategies", "none", "--no-ablations", "--test-repeats", "1", "--out", str(out)]
    argv += ["--image-size", "64"] if name != "user" else []
    assert main(argv) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["settings"]["experiment"]["model"] == REPORT_MODELS[name]
    with open(out / "results.csv") as f:
        rows = list(csv.DictReader(f))
    assert {row["strategy"] for row in rows} == {"none"}
