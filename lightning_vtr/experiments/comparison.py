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
from lightning_vtr.experiments.config import ExperimentConfig
from lightning_vtr.experiments.flags import add_config_arguments, config_from_arguments
from lightning_vtr.experiments.strategies import DEFAULT_STRATEGY
from lightning_vtr.experiments.training import MODELS, pretrain, run_strategy
from lightning_vtr.utils.validation import check_choice

__all__ = ["MODEL_TITLES", "add_comparison_arguments", "compare", "comparison_defaults", "run_comparison"]

MODEL_TITLES: dict[str, str] = {"pix2vox": "Pix2Vox++", "lrgt": "LRGT"}
"""Printed name of each model of :data:`~lightning_vtr.experiments.training.MODELS`."""
_EXCLUDED = ("model",)
"""ExperimentConfig fields without a flag here: the example fixes the model."""


def comparison_defaults(model: str) -> ExperimentConfig:
    """The comparison's experiment before any flag: ExperimentConfig's defaults, ``model`` and ``out``
    ``runs/<model>_vtr``.

    Args:
        model: a name in :data:`~lightning_vtr.experiments.training.MODELS`.

    Returns:
        An :class:`~lightning_vtr.experiments.config.ExperimentConfig` of ``model`` writing to
        ``runs/<model>_vtr``.

    Raises:
        ValueError: ``model`` is not in :data:`~lightning_vtr.experiments.training.MODELS`.

    Example:
        >>> config = comparison_defaults("lrgt")
        >>> config.model, config.out
        ('lrgt', 'runs/lrgt_vtr')
    """
    check_choice("model", model, MODELS)
    return ExperimentConfig(model=model, out=f"runs/{model}_vtr")


def add_comparison_arguments(parser: argparse.ArgumentParser, model: str) -> argparse.ArgumentParser:
    """Add the flags of :func:`run_comparison` to ``parser``: one per field of
    :class:`~lightning_vtr.experiments.config.ExperimentConfig` but ``model``, defaulting to
    :func:`comparison_defaults`, and ``--zero123``.

    Args:
        parser: the parser to add the flags to.
        model: a name in :data:`~lightning_vtr.experiments.training.MODELS`; it sets the defaults (``--out``
            is ``runs/<model>_vtr``) and has no flag.

    Returns:
        ``parser``.

    Raises:
        ValueError: ``model`` is not in :data:`~lightning_vtr.experiments.training.MODELS`.

    Example:
        >>> parser = add_comparison_arguments(argparse.ArgumentParser(), "pix2vox")
        >>> args = parser.parse_args(["--finetune-epochs", "3"])
        >>> args.finetune_epochs, args.out, args.zero123
        (3, 'runs/pix2vox_vtr', None)
    """
    add_config_arguments(parser, comparison_defaults(model), exclude=_EXCLUDED)
    parser.add_argument(
        "--zero123", default=None, help="local Zero-1-to-3 diffusers directory (default: render the meshes)"
    )
    return parser


def compare(config: ExperimentConfig, *, synthesizer: Any = None) -> dict[str, dict]:
    """Pretrain, fine-tune without and with the callback, print both rows of Table 1.

    Args:
        config: the experiment (model, data, budget, ``out``).
        synthesizer: the callback's synthesizer (``None``: mesh rendering).

    Returns:
        ``{"<Model> (no VTR)": payload, "<Model> + VTR (default rule)": payload}``, each the run's ``results.json``.

    Raises:
        ValueError: ``config.model`` has no title in :data:`MODEL_TITLES`, or a cached run under ``config.out``
            was written with another configuration (:func:`~lightning_vtr.experiments.training.run_strategy`).

    Example::

        runs = compare(ExperimentConfig(model="lrgt", pretrain_epochs=2, finetune_epochs=2, out="runs/lrgt_vtr"))
    """
    title = MODEL_TITLES[check_choice("model", config.model, MODEL_TITLES)]
    start = time.perf_counter()
    ckpt = pretrain(config)
    print(f"pretrained on Aligned: {ckpt} ({time.perf_counter() - start:.0f} s)")
    runs = {
        f"{title} (no VTR)": run_strategy("none", config, ckpt),
        f"{title} + VTR (default rule)": run_strategy(DEFAULT_STRATEGY, config, ckpt, synthesizer=synthesizer),
    }
    print()
    print(format_robustness_table({k: v["results"] for k, v in runs.items()}))
    print(f"\ntotal time {time.perf_counter() - start:.0f} s; runs in {config.out}")
    return runs


def run_comparison(args: argparse.Namespace, model: str, **model_kwargs: Any) -> dict[str, dict]:
    """:func:`compare` as the flags of :func:`add_comparison_arguments` in ``args`` describe it.

    Args:
        args: what a parser of :func:`add_comparison_arguments` parsed; ``args.zero123``, when set, is a local
            Zero-1-to-3 diffusers directory whose synthesizer replaces mesh rendering.
        model: a name in :data:`~lightning_vtr.experiments.training.MODELS` (the one the parser was built for).
        model_kwargs: further arguments of the model class (``ExperimentConfig.model_kwargs``).

    Returns:
        :func:`compare`'s result: the ``results.json`` payload of both runs.

    Raises:
        ValueError: ``model`` is not in :data:`~lightning_vtr.experiments.training.MODELS`, or as for
            :func:`compare`.

    Example::

        parser = add_comparison_arguments(argparse.ArgumentParser(), "pix2vox")
        runs = run_comparison(parser.parse_args(["--finetune-epochs", "4"]), "pix2vox")
    """
    config = config_from_arguments(args, comparison_defaults(model), exclude=_EXCLUDED, model_kwargs=model_kwargs)
    synthesizer = None
    if args.zero123:
        from lightning_vtr.synthesis.zero123 import Zero123Synthesizer

        synthesizer = Zero123Synthesizer.from_pretrained(args.zero123)
    return compare(config, synthesizer=synthesizer)
