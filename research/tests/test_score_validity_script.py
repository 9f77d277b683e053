"""``python -m research.score_validity``: each checkpoint's score-validity table, as the library computes it."""

from __future__ import annotations

import pytest
import torch
from helpers import save_tiny_checkpoint

from lightning_vtr.evaluation import make_datamodule, robustness_map
from lightning_vtr.evaluation.robustness_callback import ObjectSubset, spread_over_categories
from lightning_vtr.models.pix2vox import Pix2VoxPlusPlus
from lightning_vtr.models.registry import load_model
from research.score_validity import main, selection_scores, validity_table

K = 90  # 2 x 4 = 8 bins


@pytest.fixture(scope="module")
def checkpoints(tmp_path_factory):
    """Two tiny Pix2Vox++ checkpoints with different weights."""
    folder = tmp_path_factory.mktemp("validity_ckpt")
    paths = []
    for seed in (0, 1):
        paths.append(save_tiny_checkpoint(folder / f"{seed}.ckpt", seed=seed))
    return paths


@pytest.fixture(autouse=True)
def view_dependent(monkeypatch):
    """Predictions that depend on the views and the weights (an untrained tiny model's barely do)."""
    field = torch.randn(32, 32, 32, generator=torch.Generator().manual_seed(0))

    def predict_voxels(self, images):
        level = images.float().mean(dim=(2, 3, 4))
        contrast = level[:, 0] - level.mean(dim=1)
        offset = next(self.parameters()).detach().flatten()[:64].sum().cpu()
        return torch.sigmoid(30 * contrast[:, None, None, None] + field + 4 * offset)

    monkeypatch.setattr(Pix2VoxPlusPlus, "predict_voxels", predict_voxels)


def test_the_script_writes_each_checkpoints_table_of_the_library_map(tiny_dataset, checkpoints, tmp_path):
    a, b = checkpoints
    out = tmp_path / "validity"
    argv = ["--ckpt", f"A={a}", "--ckpt", f"B={b}", "--data", str(tiny_dataset), "--k", str(K), "--objects", "2"]
    assert main([*argv, "--out", str(out), "--device", "cpu"]) == 0
    model = load_model(a)
    dm = make_datamodule(a, model, tiny_dataset)
    records = spread_over_categories(dm.split_records("test"), 2)
    assert sorted(r.category for r in records) == ["airplane", "chair"]
    subset = ObjectSubset(dm, records)
    rmap = robustness_map(model, subset, k=K, seed=0, progress=False)
    expected = validity_table(rmap, selection_scores(model, subset, k=K, seed=0))
    markdown = (out / "score_validity.md").read_text()
    assert markdown.startswith("# Score validity\n\n## A\n\n")
    assert f"## A\n\n{expected.rstrip()}\n\n## B\n\n" in markdown
    rows = [line.split("|")[1].strip() for line in expected.splitlines()[2:]]
    assert rows == ["paper", "released", "visible", "input"]
