"""Shared fixtures: a tiny embedded dataset built once per test session."""

from __future__ import annotations

import os

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")

import pytest
import torch

# Two intra-op threads for the 2-core test machine; under pytest-xdist (``-n N``) each worker gets its share, so
# the workers do not fight over the cores.
torch.set_num_threads(max(1, 2 // int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))))

# The suite trains many small models: reuse freed memory as the package's own training processes do.
from lightning_vtr.utils.memory import retain_freed_memory  # noqa: E402

retain_freed_memory()

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


@pytest.fixture(scope="session")
def pix2vox_run_4_epochs(tiny_dataset, tmp_path_factory):
    """An uninterrupted ``fit_pix2vox(tiny_dataset, ..., epochs=4)`` on one torch thread, fitted once and read by the
    resume tests (tests/test_resume_weights.py, tests/test_kill_during_generation.py). Returns ``(trainer, run dir)``."""
    from helpers import fit_pix2vox

    run = tmp_path_factory.mktemp("pix2vox_full") / "full"
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        trainer = fit_pix2vox(tiny_dataset, run, epochs=4)
    finally:
        torch.set_num_threads(previous)
    return trainer, run
