"""The plugin on its own: a Lightning Trainer, the error-guided callback, the datamodule and a model.

    python examples/quickstart.py [DATASET]     # ~2 min on 2 CPU cores, plus ~1-2 min to build the dataset once

DATASET is a ShapeNet-VTR directory; without it the embedded procedural dataset is built on first use and cached.
It ends with one table, mIoU@0.4 and F-score per test view set; the per-category figures at every threshold go
to the Trainer's logger and to ``test_metrics.csv`` in its log directory (the last line says where).
"""

import csv
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path

import lightning as L

from lightning_vtr import ErrorGuidedViewAugmentation, VTRDataModule
from lightning_vtr.evaluation.tables import VIEW_SET_TITLES, format_cell, results_from_test_output
from lightning_vtr.models import Pix2VoxPlusPlus
from lightning_vtr.protocol import VIEW_SETS
from lightning_vtr.utils.feedback import EpochSummary, silence_lightning_tips


def compact_table(outputs: Sequence[Mapping[str, float]]) -> str:
    """One line per test view set: mIoU@0.4 and F-score in %, from ``trainer.test``'s output."""
    results = results_from_test_output(outputs)
    rows = [("test views", "mIoU@0.4 %", "F-score %")]
    rows += [
        (VIEW_SET_TITLES[s], format_cell(results[s].get("iou@0.4")), format_cell(results[s].get("fscore")))
        for s in VIEW_SETS
        if s in results
    ]
    widths = [max(len(row[i]) for row in rows) for i in range(3)]
    return "\n".join(
        "  ".join(cell.ljust(w) if i == 0 else cell.rjust(w) for i, (cell, w) in enumerate(zip(row, widths)))
        for row in rows
    )


def write_test_metrics(outputs: Sequence[Mapping[str, float]], path: Path) -> Path:
    """Every ``test/...`` value of ``trainer.test``'s output as CSV rows ``view_set, category, metric, value``
    (``category`` empty for a view set's mean over all objects)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="") as file:
        writer = csv.writer(file)
        writer.writerow(["view_set", "category", "metric", "value"])
        for group, metrics in results_from_test_output(outputs).items():
            view_set, _, category = group.partition("/")
            writer.writerows([view_set, category, metric, value] for metric, value in sorted(metrics.items()))
    return path


def main(root: str | None = None) -> list[dict[str, float]]:
    L.seed_everything(0)
    silence_lightning_tips()  # Lightning's "💡 Tip" advertisements
    model = Pix2VoxPlusPlus(preset="tiny")  # 64 px input, about 0.76 M parameters
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
    # Aligned / Hemispherical / Spherical test views; verbose=False: no table of every category and threshold
    outputs = trainer.test(model, datamodule=datamodule, verbose=False)
    print()
    print(compact_table(outputs))
    csv_path = write_test_metrics(outputs, Path(trainer.log_dir or ".") / "test_metrics.csv")
    print(f"per-category figures, every threshold: {csv_path} (and the logger's files in {trainer.log_dir})")
    return outputs


if __name__ == "__main__":
    main(*sys.argv[1:2])
