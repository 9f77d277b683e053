"""The plugin on its own: a Lightning Trainer, the error-guided callback, the datamodule and a model.

    python examples/quickstart.py [DATASET]     # ~2 min on 2 CPU cores, plus ~1-2 min to build the dataset once

DATASET is a ShapeNet-VTR directory; without it the embedded procedural dataset is built on first use and cached.
"""

import sys

import lightning as L

from lightning_vtr import ErrorGuidedViewAugmentation, VTRDataModule
from lightning_vtr.models import Pix2VoxPlusPlus
from lightning_vtr.utils.feedback import EpochSummary, silence_lightning_tips


def main(root: str | None = None) -> list[dict[str, float]]:
    L.seed_everything(0)
    silence_lightning_tips()  # Lightning's "💡 Tip" advertisements
    model = Pix2VoxPlusPlus(preset="tiny")  # 64 px input, about 0.2 M parameters
    datamodule = VTRDataModule(root, num_views=3, image_size=64, batch_size=16)
    trainer = L.Trainer(
        max_epochs=2,
        callbacks=[
            ErrorGuidedViewAugmentation(fraction=0.05),  # after each epoch: render the views it gets wrong
            EpochSummary(),  # one line per epoch: loss, val/iou@0.4, time
        ],
        reload_dataloaders_every_n_epochs=1,  # so the new views join the next epoch's training data
    )
    trainer.fit(model, datamodule=datamodule)
    print(f"generated samples: {len(datamodule.generated_samples)}")
    return trainer.test(model, datamodule=datamodule)  # Aligned / Hemispherical / Spherical test views


if __name__ == "__main__":
    main(*sys.argv[1:2])
