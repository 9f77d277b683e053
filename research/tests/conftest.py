"""The research tests' set-up: headless rendering, offline model hubs, two torch threads (the 2-core test machine)."""

from __future__ import annotations

import os

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
os.environ.setdefault("HF_HUB_OFFLINE", "1")

import pytest
import torch

torch.set_num_threads(max(1, 2 // int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))))


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory):
    """A ShapeNet-VTR directory of 3 procedural categories x 10 objects at 64 px (7/1/2 split each), as the
    package's tests build it."""
    from lightning_vtr.data.builder import build_dataset

    root = tmp_path_factory.mktemp("tiny_vtr")
    build_dataset(
        root,
        source="procedural",
        categories=["chair", "table", "airplane"],
        objects_per_category=10,
        image_size=64,
        resolution=32,
        views_per_set=8,
        seed=0,
        workers=1,
        progress=False,
    )
    return root


# the robustness-map tests' dataset fixtures, shared with tests/evaluation
from robustness_fixtures import dataset_root, objects  # noqa: E402, F401
