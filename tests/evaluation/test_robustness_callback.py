"""RobustnessMapLogger: the map of the model being trained, logged as a scalar and a picture every N epochs."""

from __future__ import annotations

import csv
from types import SimpleNamespace

import lightning as L
import numpy as np
import pytest
from helpers import TinyUserModel, make_datamodule, one_thread
from lightning.pytorch.loggers import CSVLogger
from PIL import Image

from lightning_vtr.evaluation.robustness import robustness_map
from lightning_vtr.evaluation.robustness_callback import (
    ObjectSubset,
    RobustnessMapLogger,
    spread_over_categories,
)
from lightning_vtr.synthesis.render import RenderSynthesizer

_one_thread = pytest.fixture(autouse=True)(one_thread)


def test_objects_are_spread_round_robin_over_sorted_categories():
    records = [SimpleNamespace(category=c, object_id=f"{c}{i}") for c in ("table", "chair") for i in range(3)]
    chosen = spread_over_categories(records, 3)
    assert [r.object_id for r in chosen] == ["chair0", "table0", "chair1"]
    assert spread_over_categories(records, 100) == sorted(
        records, key=lambda r: (int(r.object_id[-1]), r.category)
    )  # all of them, first of each category first
    assert spread_over_categories(records, None) == records


def test_the_logged_scalar_and_picture_are_the_map_of_the_trained_model(tiny_dataset, tmp_path):
    L.seed_everything(0)
    model = TinyUserModel()
    dm = make_datamodule(tiny_dataset, tmp_path)
    callback = RobustnessMapLogger(every_n_epochs=1, k=90, objects=2, split="val", synthesizer=RenderSynthesizer(32))
    logger = CSVLogger(str(tmp_path), name="logs", version=0)
    trainer = L.Trainer(
        max_epochs=2,
        accelerator="cpu",
        devices=1,
        callbacks=[callback],
        logger=logger,
        default_root_dir=str(tmp_path),
        enable_progress_bar=False,
        enable_model_summary=False,
        enable_checkpointing=False,
        limit_train_batches=2,
        limit_val_batches=1,
        num_sanity_val_steps=1,
    )
    trainer.fit(model, datamodule=dm)

    with open(tmp_path / "logs" / "version_0" / "metrics.csv", newline="") as f:
        logged = [float(row["robustness/mean_iou"]) for row in csv.DictReader(f) if row.get("robustness/mean_iou")]
    assert len(logged) == 2  # epochs 0 and 1, not the sanity check

    # the same objects (the first val object of each of 2 categories) and the same state: the last epoch's map
    subset = ObjectSubset.spread(dm, "val", 2)
    assert [r.category for r in subset.records] == ["airplane", "chair"]
    direct = robustness_map(model, subset, k=90, seed=0, synthesizer=RenderSynthesizer(32), progress=False)
    assert callback.last_map is not None
    np.testing.assert_array_equal(callback.last_map.iou, direct.iou)
    assert callback.last_map.object_ids == direct.object_ids
    assert logged[-1] == pytest.approx(direct.overall(), rel=1e-6)
    assert 0.0 < direct.overall() < 1.0  # an untrained model: neither empty nor perfect

    pictures = sorted((tmp_path / "logs" / "version_0" / "images" / "robustness" / "map").glob("step_*.png"))
    assert [p.name for p in pictures] == ["step_000002.png", "step_000004.png"]  # global steps after each epoch
    with Image.open(pictures[-1]) as image:
        assert image.size == (800, 450)


def test_the_map_is_measured_only_every_n_epochs(tiny_dataset, tmp_path):
    calls = []

    class Counting(RobustnessMapLogger):
        def on_validation_epoch_end(self, trainer, pl_module):
            calls.append((trainer.current_epoch, self._due(trainer)))

    callback = Counting(every_n_epochs=2)
    trainer = L.Trainer(
        max_epochs=3,
        accelerator="cpu",
        callbacks=[callback],
        logger=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        enable_checkpointing=False,
        limit_train_batches=1,
        limit_val_batches=1,
        num_sanity_val_steps=1,
    )
    trainer.fit(TinyUserModel(), datamodule=make_datamodule(tiny_dataset, tmp_path))
    assert calls == [(0, False), (0, False), (1, True), (2, False)]  # the sanity check first, then epochs 0-2


def test_bad_arguments_are_refused():
    with pytest.raises(ValueError, match="divides 180"):
        RobustnessMapLogger(k=7)
    with pytest.raises(ValueError, match="every_n_epochs"):
        RobustnessMapLogger(every_n_epochs=0)
    with pytest.raises(ValueError, match="split"):
        RobustnessMapLogger(split="valid")
