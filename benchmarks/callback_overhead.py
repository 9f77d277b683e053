"""The callback's share of an epoch's wall time (target: at most 15 % at the default 5 %).

Trains tiny Pix2Vox++ on the embedded dataset for a few epochs twice in the same process: once without the
callback (the reference) and once with ``ErrorGuidedViewAugmentation`` (default settings: error-guided
selection, viewpoint pool, mesh rendering, 5 % of the training objects). Prints the mean epoch time of
both, the time spent inside the callback and its share.

    python benchmarks/callback_overhead.py [--epochs 4] [--fraction 0.05] [--threads 2]
"""

from __future__ import annotations

import argparse
import tempfile
import time

import lightning as L
import torch

from lightning_vtr.callback import ErrorGuidedViewAugmentation
from lightning_vtr.data.datamodule import VTRDataModule
from lightning_vtr.models.pix2vox import Pix2VoxPlusPlus


class EpochTimer(L.Callback):
    def __init__(self) -> None:
        self.starts: list[float] = []
        self.ends: list[float] = []

    def on_train_epoch_start(self, trainer, pl_module):
        self.starts.append(time.perf_counter())

    def on_train_epoch_end(self, trainer, pl_module):
        self.ends.append(time.perf_counter())  # registered last: runs after the augmentation callback


class TimedAugmentation(ErrorGuidedViewAugmentation):
    """Times its own epoch-end hook, where the search and the rendering run (at every epoch end but the last)."""

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        self.seconds: list[float] = []

    def on_train_epoch_end(self, trainer, pl_module):
        start = time.perf_counter()
        super().on_train_epoch_end(trainer, pl_module)
        self.seconds.append(time.perf_counter() - start)


def run(epochs: int, callback: L.Callback | None, out: str) -> EpochTimer:
    L.seed_everything(0, verbose=False)
    model = Pix2VoxPlusPlus(preset="tiny")
    dm = VTRDataModule(image_size=model.image_size, batch_size=16)
    timer = EpochTimer()
    callbacks = ([callback] if callback else []) + [timer]
    trainer = L.Trainer(
        max_epochs=epochs,
        accelerator="cpu",
        callbacks=callbacks,
        default_root_dir=out,
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        reload_dataloaders_every_n_epochs=1,
        limit_val_batches=0,
        num_sanity_val_steps=0,
    )
    trainer.fit(model, datamodule=dm)
    return timer


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--epochs", type=int, default=4)
    p.add_argument("--fraction", type=float, default=0.05)
    p.add_argument("--threads", type=int, default=2)
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    VTRDataModule().prepare_data()  # build the embedded dataset outside the timings
    with tempfile.TemporaryDirectory() as tmp:
        base = run(args.epochs, None, tmp + "/base")
        aug = TimedAugmentation(fraction=args.fraction, progress_bar=False)
        with_cb = run(args.epochs, aug, tmp + "/vtr")
    # Skip epoch 0 (warm-up); the callback runs at every epoch end but the last.
    base_epochs = [e - s for s, e in zip(base.starts, base.ends)][1:]
    cb_epochs = [e - s for s, e in zip(with_cb.starts, with_cb.ends)][1:-1]
    searches = aug.seconds[1:-1]
    callback_s = sum(searches) / max(1, len(searches))
    epoch_s = sum(cb_epochs) / len(cb_epochs)
    print(f"epochs={args.epochs} fraction={args.fraction} threads={args.threads}")
    print(f"reference epoch (no callback):  {sum(base_epochs) / len(base_epochs):7.2f} s")
    print(f"epoch with the callback:        {epoch_s:7.2f} s")
    print(f"time inside the callback:       {callback_s:7.2f} s per epoch")
    print(f"callback share of epoch time:   {100 * callback_s / epoch_s:6.1f} %  (target <= 15 %)")


if __name__ == "__main__":
    main()
