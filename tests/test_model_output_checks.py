"""ErrorGuidedViewAugmentation checks what ``predict_voxels`` returns: probabilities in [0, 1] (logits and NaN are
refused with the observed range) and the dataset's voxel grid (refused at fit start, before any training)."""

from __future__ import annotations

import re

import pytest
import torch
import torch.nn.functional as F
from helpers import TinyUserModel, make_callback, make_datamodule, make_trainer, one_thread
from lightning.pytorch.utilities.exceptions import MisconfigurationException

_one_thread = pytest.fixture(autouse=True)(one_thread)
_HINT = (
    "did predict_voxels return logits? apply torch.sigmoid to them (the callback thresholds occupancy "
    "probabilities); non-finite values mean the model diverged"
)


class FixedOutputModel(TinyUserModel):
    """Returns ``volume`` for every sample from its ``calls_before``-th call of ``predict_voxels`` on (the trained
    prediction before that) and counts its training steps."""

    def __init__(self, volume: torch.Tensor, calls_before: int = 0) -> None:
        super().__init__()
        self.volume = volume
        self.calls_before = calls_before
        self.calls = 0
        self.training_steps = 0

    def predict_voxels(self, images):
        self.calls += 1
        if self.calls <= self.calls_before:
            return super().predict_voxels(images)
        return self.volume.expand(len(images), *self.volume.shape).clone()

    def training_step(self, batch, batch_idx):
        self.training_steps += 1
        return F.binary_cross_entropy(super().predict_voxels(batch["images"]), batch["voxels"])


def _fit(tiny_dataset, tmp_path, model):
    # no sanity check: only the callback calls predict_voxels before training
    trainer = make_trainer(tmp_path, 2, [make_callback(fraction=0.1)], num_sanity_val_steps=0)
    trainer.fit(model, datamodule=make_datamodule(tiny_dataset, tmp_path))
    return trainer


def test_logits_are_refused_with_their_range_before_training(tiny_dataset, tmp_path):
    model = FixedOutputModel(torch.linspace(-2.5, 3.5, 32**3).view(32, 32, 32))
    message = (
        "`FixedOutputModel.predict_voxels` must return probabilities in [0, 1], got values in [-2.5, 3.5] "
        f"(0 non-finite of 32768); {_HINT}"
    )
    with pytest.raises(ValueError, match=f"^{re.escape(message)}$"):
        _fit(tiny_dataset, tmp_path, model)
    assert model.calls == 1 and model.training_steps == 0  # one prediction at fit start, no training


def test_non_finite_values_are_counted(tiny_dataset, tmp_path):
    volume = torch.full((32, 32, 32), 0.25)
    volume[0, 0, :5] = float("nan")
    volume[1, 1, 1] = float("inf")
    message = (
        "`FixedOutputModel.predict_voxels` must return probabilities in [0, 1], got values in [0.25, 0.25] "
        f"(6 non-finite of 32768); {_HINT}"
    )
    with pytest.raises(ValueError, match=f"^{re.escape(message)}$"):
        _fit(tiny_dataset, tmp_path, FixedOutputModel(volume))


def test_the_selection_checks_every_prediction(tiny_dataset, tmp_path):
    # a model that passes the fit-start check and returns logits afterwards: the first selection (on_train_start;
    # the default rule scores 35 % of the 21 training objects, 7, in one batch) refuses them
    model = FixedOutputModel(torch.full((32, 32, 32), -1.0), calls_before=1)
    message = (
        "`FixedOutputModel.predict_voxels` must return probabilities in [0, 1], got values in [-1, -1] "
        f"(0 non-finite of {7 * 32**3}); {_HINT}"
    )
    with pytest.raises(ValueError, match=f"^{re.escape(message)}$"):
        _fit(tiny_dataset, tmp_path, model)
    assert model.calls == 2 and model.training_steps == 0


def test_a_resolution_mismatch_is_refused_before_training(tiny_dataset, tmp_path):
    # declares the dataset's 32 (a declared 16 fails earlier, at the datamodule's setup) but returns 16^3
    model = FixedOutputModel(torch.full((16, 16, 16), 0.5))
    trainer = make_trainer(tmp_path, 2, [make_callback(fraction=0.1)])
    dm = make_datamodule(tiny_dataset, tmp_path)
    dm.setup("fit")
    first = dm.split_records("train")[0]
    message = (
        "ErrorGuidedViewAugmentation compares predictions with the dataset's voxels, but "
        "FixedOutputModel.predict_voxels returned shape (1, 16, 16, 16) for one training item "
        f"({first.category}/{first.object_id}, images (3, 3, 32, 32)) and the dataset's voxels have shape "
        "(32, 32, 32): use a model whose voxel_resolution is 32 or a dataset built at the model's resolution."
    )
    with pytest.raises(MisconfigurationException, match=f"^{re.escape(message)}$"):
        trainer.fit(model, datamodule=dm)
    assert model.calls == 1 and model.training_steps == 0 and trainer.global_step == 0


def test_an_output_of_another_rank_is_refused_with_both_shapes(tiny_dataset, tmp_path):
    model = FixedOutputModel(torch.full((1, 32, 32, 32), 0.5))  # (B, 1, R, R, R): a channel dimension too many
    message = (
        "`FixedOutputModel.predict_voxels` must return occupancy probabilities of shape (B, R, R, R) for images of "
        "shape (1, 3, 3, 32, 32), got (1, 1, 32, 32, 32)"
    )
    with pytest.raises(ValueError, match=f"^{re.escape(message)}$"):
        _fit(tiny_dataset, tmp_path, model)
    assert model.training_steps == 0
