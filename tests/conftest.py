"""Shared fixtures: a tiny embedded dataset built once per test session."""

from __future__ import annotations

import os

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")

import pytest  # noqa: E402
import torch  # noqa: E402

torch.set_num_threads(2)

TINY_DATASET = dict(
    categories=["chair", "table", "airplane"],
    objects_per_category=10,
    image_size=64,
    resolution=32,
    views_per_set=8,
    seed=0,
    workers=1,
    progress=False,
)


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory):
    """A ShapeNet-VTR directory of 3 procedural categories x 10 objects at 64 px (7/1/2 split each)."""
    from lightning_vtr.data.builder import build_dataset

    root = tmp_path_factory.mktemp("tiny_vtr")
    build_dataset(root, source="procedural", **TINY_DATASET)
    return root
