"""Fixtures and toy models shared by the robustness-map tests (tests/evaluation) and the score-validity study's
tests (research/tests): a 4-object procedural dataset and models whose predictions are known."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from lightning_vtr.data.format import scan_dataset

K = 60
N_BINS = (180 // K) * (360 // K)


@pytest.fixture(scope="module")
def dataset_root(tmp_path_factory):
    """A dataset of 2 procedural chairs and 2 tables, all in the train split, with meshes and 32-px images."""
    from lightning_vtr.data.builder import build_dataset

    root = tmp_path_factory.mktemp("robustness_vtr")
    build_dataset(
        root,
        source="procedural",
        categories=["chair", "table"],
        objects_per_category=2,
        image_size=32,
        resolution=32,
        views_per_set=3,
        split=(1.0, 0.0, 0.0),
        seed=0,
        workers=1,
        progress=False,
    )
    return root


@pytest.fixture(scope="module")
def objects(dataset_root):
    """Three of its objects (two chairs, one table)."""
    return scan_dataset(dataset_root)[:3]


class ImageMeanModel(nn.Module):
    """Occupancy ``sigmoid(30 (mean of view 0 - mean of all views) + b)`` with a fixed random ``b`` per voxel:
    what it predicts depends on the views, so view sets drawn with another seed give another IoU."""

    image_size = 32
    num_views = 3
    voxel_resolution = 32

    def __init__(self) -> None:
        super().__init__()
        self.bias = nn.Parameter(torch.randn(32, 32, 32, generator=torch.Generator().manual_seed(0)))

    def predict_voxels(self, images):
        level = images.float().mean(dim=(2, 3, 4))
        contrast = level[:, 0] - level.mean(dim=1)
        return torch.sigmoid(30 * contrast[:, None, None, None] + self.bias)


class OracleModel:
    """Returns each object's ground truth, in the order the map asks: ``per_object`` sets per object."""

    image_size = 32
    num_views = 3
    voxel_resolution = 32

    def __init__(self, targets: torch.Tensor, per_object: int) -> None:
        self.targets, self.per_object, self.seen = targets, per_object, 0

    def predict_voxels(self, images):
        rows = (torch.arange(images.shape[0]) + self.seen) // self.per_object
        self.seen += images.shape[0]
        return self.targets[rows]
