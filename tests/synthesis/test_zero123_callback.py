"""End to end: the augmentation callback trains with views synthesized by the tiny Zero-1-to-3 model."""

from __future__ import annotations

import lightning as L
import numpy as np
import pytest
import torch
from helpers import TinyUserModel
from PIL import Image

from lightning_vtr.callback import ErrorGuidedViewAugmentation
from lightning_vtr.data.datamodule import VTRDataModule
from lightning_vtr.synthesis.cache import CachedSynthesizer
from lightning_vtr.synthesis.zero123 import Zero123Synthesizer


@pytest.mark.slow
def test_one_epoch_of_zero123_augmentation(tiny_dataset, tiny_zero123, tmp_path):
    previous = torch.get_num_threads()
    torch.set_num_threads(1)  # tiny ops: one thread is fastest on shared cores
    try:
        L.seed_everything(0, verbose=False)
        synth = Zero123Synthesizer.from_pretrained(tiny_zero123.layout_a, num_inference_steps=1, image_size=32)
        cached = CachedSynthesizer(synth, tmp_path / "cache")
        dm = VTRDataModule(str(tiny_dataset), image_size=32, batch_size=8, generated_dir=str(tmp_path / "gen"))
        callback = ErrorGuidedViewAugmentation(synthesizer=cached, fraction=0.1, progress_bar=False)
        trainer = L.Trainer(
            max_epochs=2,  # views are generated at the end of every epoch but the last
            accelerator="cpu",
            devices=1,
            callbacks=[callback],
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
        trainer.fit(TinyUserModel(), datamodule=dm)

        samples = dm.generated_samples
        # 21 training objects, round(0.1 * 21) = 2 objects before epoch 0 and 2 at the end of epoch 0
        assert [s["epoch"] for s in samples] == [-1, -1, 0, 0]
        assert len(dm.train_dataset()) == 21 + 4
        for s in samples:
            got = np.stack([np.asarray(Image.open(dm.generated_dir / s["dir"] / n)) for n in s["images"]])
            assert got.shape == (3, 32, 32, 4) and got.dtype == np.uint8
            # the stored views are the diffusion model's: regenerate them directly from the nearest source views
            request = callback._request(dm, dm.record(s["category"], s["object_id"]), torch.tensor(s["viewpoints"]))
            expected = synth.synthesize([request])[0]
            assert np.abs(got.astype(int) - expected.astype(int)).max() <= 2
            # and the cache holds every generated view under the synthesizer's key
            for vp, image in zip(s["viewpoints"], expected):
                cached_image = cached.cache.get(s["object_id"], vp, synth.config_key())
                assert cached_image is not None
                assert np.abs(cached_image.astype(int) - image.astype(int)).max() <= 2
    finally:
        torch.set_num_threads(previous)
