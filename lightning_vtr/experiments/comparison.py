"""One model with and without error-guided view augmentation: the job of ``examples/*_vtr.py``.

Pretrains the model on Aligned views, fine-tunes it for the same number of epochs twice, once without
augmentation and once with :class:`~lightning_vtr.callback.ErrorGuidedViewAugmentation`, tests both on
Aligned / Hemispherical / Spherical and prints the paper's Table-1 layout (mIoU@0.4 and F-score). Runs
are cached under ``out`` (:func:`~lightning_vtr.experiments.training.run_strategy`): re-running skips
finished runs, and an interrupted run resumes from its last checkpoint.
"""

from __future__ import annotations

import argparse
import time
from typing import Any

from lightning_vtr.evaluation.tables import format_robustness_table
from lightning_vtr.experiments.training import FINETUNE_LR_SCHEDULES, MODELS, ExperimentConfig, pretrain, run_strategy
from lightning_vtr.utils.validation import check_choice

__all__ = ["MODEL_TITLES", "add_comparison_arguments", "compare", "run_comparison"]

#: Printed name of each model of :data:`~lightning_vtr.experiments.training.MODELS`.
MODEL_TITLES: dict[str, str] = {"pix2vox": "Pix2Vox++", "lrgt": "LRGT"}


def add_comparison_arguments(parser: argparse.ArgumentParser, model: str) -> argparse.ArgumentParser:
    """Add the flags of :func:`run_comparison` to ``parser`` (``--out`` defaults to ``runs/<model>_vtr``)."""
    check_choice("model", model, MODELS)
    add = parser.add_argument
    add("--preset", default="tiny", choices=["tiny", "paper"])
    add("--data", default=None, help="ShapeNet-VTR directory (default: the embedded procedural dataset)")
    add("--pretrain-epochs", type=int, default=16)
    add("--finetune-epochs", type=int, default=12)
    # Small batches: the embedded dataset has 210 training objects, and the tiny model needs optimizer steps.
    add("--batch-size", type=int, default=8)
    add("--num-workers", type=int, default=0)
    add("--fraction", type=float, default=0.05, help="share of training objects searched per epoch")
    add(
        "--finetune-lr",
        default=FINETUNE_LR_SCHEDULES[0],
        choices=FINETUNE_LR_SCHEDULES,
        help="fine-tuning learning rate: annealed to 0, or the model's own schedule",
    )
    add(
        "--recipe",
        default="plain",
        help="training-image recipe: plain (white background, ImageNet normalisation), reference (the model's "
        "published recipe), or pix2vox / lrgt",
    )
    add("--seed", type=int, default=0)
    add("--accelerator", default="auto")
    add("--devices", default="1")
    add("--precision", default="32-true")
    add("--zero123", default=None, help="local Zero-1-to-3 diffusers directory (default: render the meshes)")
    add("--out", default=f"runs/{model}_vtr")
    return parser


def compare(config: ExperimentConfig, *, synthesizer: Any = None) -> dict[str, dict]:
    """Pretrain, fine-tune without and with the callback, print both rows of Table 1.

    Args:
        config: the experiment (model, data, budget, ``out``).
        synthesizer: the callback's synthesizer (``None``: mesh rendering).

    Returns:
        ``{"<Model> (no VTR)": payload, "Ours (<Model>)": payload}``, each the run's ``results.json``.
    """
    title = MODEL_TITLES[check_choice("model", config.model, MODEL_TITLES)]
    start = time.perf_counter()
    ckpt = pretrain(config)
    print(f"pretrained on Aligned: {ckpt} ({time.perf_counter() - start:.0f} s)")
    runs = {
        f"{title} (no VTR)": run_strategy("none", config, ckpt),
        f"Ours ({title})": run_strategy("error_guided", config, ckpt, synthesizer=synthesizer),
    }
    print()
    print(format_robustness_table({k: v["results"] for k, v in runs.items()}))
    print(f"\ntotal time {time.perf_counter() - start:.0f} s; runs in {config.out}")
    return runs


def run_comparison(args: argparse.Namespace, model: str, **model_kwargs: Any) -> dict[str, dict]:
    """:func:`compare` as the flags of :func:`add_comparison_arguments` in ``args`` describe it.

    ``model_kwargs`` are further arguments of the model class (``ExperimentConfig.model_kwargs``).
    """
    config = ExperimentConfig(
        model=model,
        preset=args.preset,
        data=args.data,
        pretrain_epochs=args.pretrain_epochs,
        finetune_epochs=args.finetune_epochs,
        batch_size=args.batch_size,
        num_workers=args.num_workers,
        fraction=args.fraction,
        finetune_lr=args.finetune_lr,
        recipe=args.recipe,
        seed=args.seed,
        accelerator=args.accelerator,
        devices=args.devices,
        precision=args.precision,
        out=args.out,
        model_kwargs=model_kwargs,
    )
    synthesizer = None
    if args.zero123:
        from lightning_vtr.synthesis.zero123 import Zero123Synthesizer

        synthesizer = Zero123Synthesizer.from_pretrained(args.zero123)
    return compare(config, synthesizer=synthesizer)
