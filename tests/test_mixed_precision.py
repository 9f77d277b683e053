"""Mixed precision: both models train with the augmentation callback under ``precision="bf16-mixed"`` (on CPU).

The loss is float32, the callback predicts under autocast and the selector receives float32 probabilities, and
the generated images are exactly the synthesizer's (uint8, not cast).
"""

from __future__ import annotations

import lightning as L
import numpy as np
import pytest
import torch
from helpers import one_thread
from PIL import Image

from lightning_vtr.callback import ErrorGuidedViewAugmentation
from lightning_vtr.data.datamodule import VTRDataModule
from lightning_vtr.models import LRGT, Pix2VoxPlusPlus
from lightning_vtr.selection import ErrorGuidedSelector
from lightning_vtr.synthesis.render import RenderSynthesizer

_one_thread = pytest.fixture(autouse=True)(one_thread)

#: 21 training objects in the tiny dataset; round(0.1 * 21) = 2 get new views per selection
FRACTION, PER_SELECTION = 0.1, 2


class RecordingSelector(ErrorGuidedSelector):
    """The error-guided selector (K = 90: 8 bins keep it quick) that records the dtype of every prediction it gets."""

    def __init__(self) -> None:
        super().__init__(k=90)
        self.dtypes: list[torch.dtype] = []

    def select(self, predicted, target, categories, generator=None, context=None):
        self.dtypes.append(predicted.dtype)
        return super().select(predicted, target, categories, generator=generator, context=context)


class RecordingSynthesizer(RenderSynthesizer):
    """32-px mesh rendering that keeps a copy of every image set it returns, in order."""

    def __init__(self) -> None:
        super().__init__(image_size=32)
        self.outputs: list[np.ndarray] = []

    def synthesize(self, requests):
        out = super().synthesize(requests)
        self.outputs += [np.array(images, copy=True) for images in out]
        return out


class LossRecorder(L.Callback):
    def __init__(self) -> None:
        self.losses: list[torch.Tensor] = []

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        self.losses.append(outputs["loss"].detach())


@pytest.mark.parametrize("model_cls", [Pix2VoxPlusPlus, LRGT], ids=["pix2vox", "lrgt"])
def test_bf16_mixed_fit_with_the_callback(tiny_dataset, tmp_path, monkeypatch, model_cls):
    L.seed_everything(0, verbose=False)
    model = model_cls(preset="tiny", validation_fscore=False)
    forwards: list[tuple[bool, bool]] = []  # (training, autocast on) per forward
    reconstruct = model.reconstruct

    def recording_reconstruct(images):
        forwards.append((model.training, torch.is_autocast_enabled("cpu")))
        return reconstruct(images)

    monkeypatch.setattr(model, "reconstruct", recording_reconstruct)
    selector, synthesizer, losses = RecordingSelector(), RecordingSynthesizer(), LossRecorder()
    callback = ErrorGuidedViewAugmentation(
        selector, synthesizer, fraction=FRACTION, progress_bar=False, log_images=False
    )
    dm = VTRDataModule(
        str(tiny_dataset), image_size=model.image_size, batch_size=2, generated_dir=str(tmp_path / "gen")
    )
    trainer = L.Trainer(
        max_epochs=2,
        accelerator="cpu",
        precision="bf16-mixed",
        callbacks=[callback, losses],
        default_root_dir=str(tmp_path),
        logger=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        enable_checkpointing=False,
        limit_train_batches=1,
        limit_val_batches=1,
        num_sanity_val_steps=0,
        reload_dataloaders_every_n_epochs=1,
    )
    trainer.fit(model, datamodule=dm)

    # autocast was on in training, validation and the callback's predictions (eval mode)
    assert all(autocast for _, autocast in forwards)
    # 2 training steps; 1 output check + 1 prediction per selection + 2 validation batches in eval mode
    assert sum(training for training, _ in forwards) == 2
    assert sum(not training for training, _ in forwards) == 1 + 2 + 2
    # the loss is float32 and finite, as returned by training_step and as logged
    assert len(losses.losses) == 2
    assert all(loss.dtype == torch.float32 and torch.isfinite(loss) for loss in losses.losses)
    for key in ("train/loss", "val/loss"):
        logged = trainer.callback_metrics[key]
        assert logged.dtype == torch.float32 and torch.isfinite(logged), key
    # selection on float32 probabilities: one call per searched object (not batched), 2 selections of
    # round(search_fraction * 21 training objects) searched objects each (7 at the default 0.35)
    searched = max(callback.min_objects, round(callback.search_fraction * len(dm.split_records("train"))))
    assert selector.dtypes == [torch.float32] * (2 * searched)
    # before epoch 0 and after epoch 0 (not after the last): 2 samples each
    samples = dm.generated_samples
    assert [s["epoch"] for s in samples] == [-1] * PER_SELECTION + [0] * PER_SELECTION
    assert len(synthesizer.outputs) == len(samples) == 2 * PER_SELECTION
    # the stored images are bit-equal to what the synthesizer returned
    for sample, expected in zip(samples, synthesizer.outputs):
        stored = np.stack([np.asarray(Image.open(dm.generated_dir / sample["dir"] / n)) for n in sample["images"]])
        assert expected.dtype == stored.dtype == np.uint8
        assert stored.shape == expected.shape == (selector.num_views, 32, 32, 4)
        assert np.array_equal(stored, expected)


@pytest.mark.parametrize("model_cls", [Pix2VoxPlusPlus, LRGT], ids=["pix2vox", "lrgt"])
def test_loss_and_predict_voxels_are_float32_for_half_precision_outputs(monkeypatch, model_cls):
    torch.manual_seed(0)
    model = model_cls(preset="tiny").eval()
    images = torch.rand(1, 2, 3, model.image_size, model.image_size)
    target = (torch.rand(1, 32, 32, 32) > 0.7).float()
    with torch.no_grad():
        outputs = {name: value.bfloat16() for name, value in model(images).items()}  # what autocast may give
        with torch.autocast("cpu", dtype=torch.bfloat16):
            loss = model.loss(outputs, target)
        expected = model.loss({name: value.float() for name, value in outputs.items()}, target)
        # a network whose output is bfloat16 still predicts float32 probabilities
        reconstruct = model.reconstruct
        monkeypatch.setattr(model, "reconstruct", lambda x: {k: v.bfloat16() for k, v in reconstruct(x).items()})
        predicted = model.predict_voxels(images)
    assert loss.dtype == torch.float32 and torch.isfinite(loss)
    assert torch.equal(loss, expected)  # the float32 loss of the bfloat16 probabilities
    assert predicted.dtype == torch.float32 and torch.equal(predicted, outputs["voxels"].float())
