"""Benchmark your own model and view selector with the package's report: paired differences over seeds, maps.

A small reconstruction model (``TinyVoxelNet``, a plain LightningModule) and a small view selector
(``ViewsFromBelow``, a ViewSelector that renders training views from under the objects, where the Aligned views
never look), both written below, go through ``lightning_vtr.experiments.report.run_report``: per seed the model is
pretrained on Aligned, then fine-tuned under one budget with no augmentation (None-VTR), area-uniform Random
views, the package's default rule and your selector, and each is tested on Aligned / Hemispherical / Spherical.
It prints Table 1 and the paired differences of your selector to the three others (mean, 95 % CI over seeds, seeds
agreeing in sign) and writes the report's files (Table 1 as Markdown / CSV / LaTeX, report.json, ...) and each
strategy's viewpoint robustness map under ``--out``.

    python examples/benchmark_your_method.py                       # 3 seeds: about 270 s of CPU time
    python examples/benchmark_your_method.py --seeds 0 --pretrain-epochs 1 --finetune-epochs 1   # a first look

Runs are cached under ``--out``: re-running skips the finished runs. Swap in your own classes: any LightningModule
with ``predict_voxels``, ``image_size``, ``num_views``, ``voxel_resolution``, ``training_step`` and
``configure_optimizers``; any ``lightning_vtr.selection.ViewSelector`` subclass.
"""

from __future__ import annotations

import argparse
import shlex
import sys
import warnings
from pathlib import Path

import lightning as L
import torch
import torch.nn.functional as F
from torch import nn

from lightning_vtr.evaluation.tables import VIEW_SET_TITLES
from lightning_vtr.experiments.report import ReportConfig, default_experiment, run_report
from lightning_vtr.experiments.report_tables import paired_differences
from lightning_vtr.protocol import VIEW_SETS
from lightning_vtr.selection import ViewSelector

# Lightning 2.6 on torch 2.13 warns about a deprecated pytree API at every epoch; it is not ours to fix.
warnings.filterwarnings("ignore", message=".*treespec.*")


class TinyVoxelNet(L.LightningModule):
    """Your model: a small CNN per view, views averaged, a 16^3 occupancy grid upsampled to 32^3.

    Args:
        image_size: input side in pixels.
        num_views: views per input set.
        voxel_resolution: side of the predicted grid (the dataset's).
        lr: Adam's learning rate.
    """

    def __init__(self, image_size: int = 64, num_views: int = 3, voxel_resolution: int = 32, lr: float = 3e-3):
        super().__init__()
        self.save_hyperparameters()
        self.image_size, self.num_views, self.voxel_resolution = image_size, num_views, voxel_resolution
        self.encoder = nn.Sequential(
            nn.Conv2d(3, 16, 4, stride=4),
            nn.ReLU(),
            nn.Conv2d(16, 32, 4, stride=4),
            nn.ReLU(),
            nn.AdaptiveAvgPool2d(2),
            nn.Flatten(),
            nn.Linear(128, 64),
            nn.ReLU(),
        )
        self.decoder = nn.Linear(64, 16**3)

    def predict_voxels(self, images: torch.Tensor) -> torch.Tensor:
        """``(B, V, 3, H, W)`` images -> ``(B, R, R, R)`` occupancy probabilities."""
        batch, views = images.shape[:2]
        features = self.encoder(images.flatten(0, 1)).view(batch, views, -1).mean(dim=1)
        logits = self.decoder(features).view(batch, 1, 16, 16, 16)
        size = (self.voxel_resolution,) * 3
        return torch.sigmoid(F.interpolate(logits, size=size, mode="trilinear", align_corners=False)[:, 0])

    def training_step(self, batch: dict, batch_idx: int) -> torch.Tensor:
        loss = F.binary_cross_entropy(self.predict_voxels(batch["images"]), batch["voxels"].float())
        self.log("train/loss", loss, prog_bar=True)
        return loss

    def configure_optimizers(self) -> torch.optim.Optimizer:
        return torch.optim.Adam(self.parameters(), lr=self.hparams.lr)


class ViewsFromBelow(ViewSelector):
    """Your selector: every view set from under the object, at a pitch drawn in ``[low, high]`` degrees and
    yaws spread evenly around it from a random start.

    Args:
        low: the lowest pitch, degrees.
        high: the highest pitch, degrees.
    """

    def __init__(self, low: float = -60.0, high: float = -20.0) -> None:
        self.low, self.high = low, high

    def select(self, predicted, target, categories, generator=None, context=None):
        batch, n = predicted.shape[0], self.num_views
        start = torch.rand(batch, 1, generator=generator) * 360.0
        yaw = (start + torch.arange(n) * (360.0 / n)) % 360.0 - 180.0
        pitch = self.low + (self.high - self.low) * torch.rand(batch, n, generator=generator)
        return torch.stack([yaw, pitch], dim=-1)

    def settings(self) -> dict:
        return {"low": self.low, "high": self.high}


#: The rows: three of the package's (by their names in ``lightning-vtr report --list-strategies``) and yours.
ROWS = ("none", "random_area", "error_guided", "mine")


def strategies_yaml(selector: type, fraction: float) -> str:
    """The strategies file of your row: its selector by class path, as in a LightningCLI config."""
    return (
        "mine:\n"
        "  title: Views from below (mine)\n"
        "  description: views under the object, evenly spread in yaw\n"
        "  selector:\n"
        f"    class_path: {selector.__module__}.{selector.__qualname__}\n"
        "    init_args: {low: -60.0, high: -20.0}\n"
        f"  callback_kwargs: {{fraction: {fraction}}}\n"
    )


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n")[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter
    )
    add = parser.add_argument
    add("--data", default=None, help="a ShapeNet-VTR directory (default: the embedded procedural dataset)")
    add("--out", default="runs/benchmark_your_method", help="output folder (runs are cached there)")
    add("--seeds", type=int, nargs="+", default=[0, 1, 2], help="seeds; each pretrains its own model")
    add("--pretrain-epochs", type=int, default=4, help="pretraining epochs on Aligned")
    add("--finetune-epochs", type=int, default=2, help="fine-tuning epochs per strategy")
    add("--batch-size", type=int, default=16, help="batch size")
    add("--train-batches", type=int, default=10, help="training batches per epoch (Trainer limit_train_batches)")
    add("--fraction", type=float, default=0.1, help="share of training objects given new views per selection")
    add("--test-repeats", type=int, default=1, help="fixed view sets per test object")
    add("--map-k", type=int, default=90, help="bin interval of the robustness maps, degrees (90: 8 bins)")
    add("--map-objects", type=int, default=4, help="test objects per seed of the robustness maps")
    add("--accelerator", default="cpu", help="Lightning accelerator")
    return parser.parse_args(argv)


def difference_cell(estimate) -> str:
    """``+2.80 [+0.80, +4.80] 3/3``: mean difference in mIoU points, its 95 % CI (2+ seeds), seeds agreeing."""
    if estimate is None:
        return "-"
    text = f"{100 * estimate.mean:+.2f}"
    if estimate.n > 1:
        text += f" [{100 * estimate.low:+.2f}, {100 * estimate.high:+.2f}]"
    return f"{text} {estimate.agree}/{estimate.n}"


def main(argv: list[str] | None = None) -> dict:
    """Run the benchmark; returns :func:`run_report`'s result with ``"mine"``: ``{other row title: {view_set:
    Estimate}}``, the paired mIoU@0.4 differences of your row to each other row."""
    argv = sys.argv[1:] if argv is None else list(argv)
    args = parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    strategies = out / "strategies.yaml"
    strategies.write_text(strategies_yaml(ViewsFromBelow, args.fraction))
    experiment = default_experiment(
        model=f"{TinyVoxelNet.__module__}.{TinyVoxelNet.__qualname__}",  # any class, by its import path
        data=args.data,
        out=str(out),
        pretrain_epochs=args.pretrain_epochs,
        finetune_epochs=args.finetune_epochs,
        batch_size=args.batch_size,
        fraction=args.fraction,
        test_repeats=args.test_repeats,
        accelerator=args.accelerator,
        trainer_kwargs={"limit_train_batches": args.train_batches, "enable_progress_bar": False},
    )
    config = ReportConfig(
        experiment,
        seeds=args.seeds,
        strategies=list(ROWS),
        strategies_file=str(strategies),
        reference="error_guided",  # the package's default rule: every row is also compared with it
        maps=True,
        map_k=args.map_k,
        map_objects=args.map_objects,
        callback_kwargs={"progress_bar": False},
        command=shlex.join(["python", "examples/benchmark_your_method.py", *argv]),
    )
    result = run_report(config)
    titles = config.titles()
    rows = {titles[name]: name for name in ROWS}
    print((out / "table1.md").read_text())
    mine = titles["mine"]
    differences = {
        titles[other]: paired_differences(rows, other, result["runs"], "iou@0.4", list(args.seeds))[mine]
        for other in ROWS[:-1]
    }
    seeds = len(args.seeds)
    print(f"## {mine} minus each other row (mIoU@0.4 points; mean, 95 % CI over {seeds} seeds, seeds agreeing)\n")
    print("| " + " | ".join(["Minus", *(VIEW_SET_TITLES[v] for v in VIEW_SETS)]) + " |")
    print("|" + "---|" * (1 + len(VIEW_SETS)))
    for title, per_set in differences.items():
        print("| " + " | ".join([title, *(difference_cell(per_set[v]) for v in VIEW_SETS)]) + " |")
    print()
    for title, summary in result["maps"].items():
        print(f"{title}: IoU over the sphere {summary['overall']:.4f} ({out / summary['picture']})")
    print(f"Wrote {out / 'report.md'}, {out / 'table1.tex'}, {out / 'report.json'}, {out / 'maps' / 'index.html'}")
    return {**result, "mine": differences}


if __name__ == "__main__":
    main()
