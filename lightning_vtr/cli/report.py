"""``lightning-vtr report``: the paper's comparison on your data (Table 1 with confidence intervals, paired
differences, where the training views went and where the time went; CSVs and a chart).

The flags set the fields of :class:`~lightning_vtr.experiments.report.ReportConfig` and of its
:class:`~lightning_vtr.experiments.training.ExperimentConfig`; their defaults are
:class:`~lightning_vtr.experiments.report.ReportConfig`'s and
:func:`~lightning_vtr.experiments.report.default_experiment`'s.
"""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

from lightning_vtr.cli.arguments import comma_separated, positive_int

if TYPE_CHECKING:
    from lightning_vtr.experiments.report import ReportConfig

__all__ = ["HELP", "add_arguments", "report_config", "run"]

HELP = "run the paper's comparison over seeds; write Table 1 with CIs, paired differences, CSVs and a chart"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from lightning_vtr.data import IMAGE_RECIPES
    from lightning_vtr.experiments.report import ABLATIONS, ReportConfig, default_experiment
    from lightning_vtr.experiments.training import FINETUNE_LR_SCHEDULES, MODELS, VARIANTS

    defaults = default_experiment()
    report_defaults = ReportConfig(defaults)
    parser.description = (
        "Per seed, pretrain a model on Aligned, fine-tune it with each view strategy under one budget, test on "
        "Aligned / Hemispherical / Spherical and write report.md (Table 1 with 95 % confidence intervals, paired "
        "differences to None-VTR and Random, the training views' distribution, the time split), results.csv, "
        "differences.csv, report.png and timing.json into --out. A killed report re-run skips every finished run."
    )
    add = parser.add_argument
    add(
        "--model", choices=list(MODELS), default=defaults.model, help=f"reconstruction model (default {defaults.model})"
    )
    add("--preset", default=defaults.preset, help=f"model preset (default {defaults.preset})")
    add("--data", default=defaults.data, help="ShapeNet-VTR directory (default: the embedded procedural dataset)")
    add("--out", default=defaults.out, help=f"output directory (default {defaults.out})")
    add(
        "--seeds",
        type=int,
        nargs="+",
        default=list(report_defaults.seeds),
        help="seeds; each pretrains its own model, several give confidence intervals "
        f"(default {' '.join(map(str, report_defaults.seeds))})",
    )
    add(
        "--pretrain-epochs",
        type=positive_int,
        default=defaults.pretrain_epochs,
        help=f"epochs on Aligned (default {defaults.pretrain_epochs})",
    )
    add(
        "--finetune-epochs",
        type=positive_int,
        default=defaults.finetune_epochs,
        help=f"fine-tuning epochs per strategy (default {defaults.finetune_epochs})",
    )
    add(
        "--strategies",
        type=comma_separated(VARIANTS),
        default=list(report_defaults.strategies),
        help=f"comma-separated rows among {','.join(VARIANTS)} (default {','.join(report_defaults.strategies)})",
    )
    ablations = parser.add_mutually_exclusive_group()
    ablations.add_argument(
        "--ablations",
        type=comma_separated(ABLATIONS),
        default=list(report_defaults.ablations),
        help=f"comma-separated ablations of the error-guided method to run, among {','.join(ABLATIONS)} (default none)",
    )
    ablations.add_argument(
        "--no-ablations", action="store_true", help="run no ablation (the default; kept for old command lines)"
    )
    add(
        "--test-triplets",
        "--test-repeats",
        dest="test_repeats",
        metavar="T",
        type=positive_int,
        default=defaults.test_repeats,
        help="fixed view sets each test object is tested on, the same for every strategy of a seed "
        f"(default {defaults.test_repeats})",
    )
    add(
        "--validation-triplets",
        metavar="T",
        type=positive_int,
        default=None,
        help="also test every fine-tuned model on the validation objects, each on T fixed view sets, and print "
        "the paired differences there: choose strategies on those, not on the test split (default: off)",
    )
    add(
        "--jobs",
        metavar="N",
        type=positive_int,
        default=1,
        help="fits run at once, each in its own process with (torch threads // N) threads; output per fit in "
        "OUT/seed_<s>/logs (default 1; on 2 CPU cores 2 ran the default report in 39 min instead of 50)",
    )
    add(
        "--fraction",
        type=float,
        default=defaults.fraction,
        help=f"share of training objects given new views per selection (default {defaults.fraction})",
    )
    add(
        "--finetune-lr",
        choices=FINETUNE_LR_SCHEDULES,
        default=defaults.finetune_lr,
        help=f"fine-tuning learning-rate schedule: annealed to 0 or the model's own (default {defaults.finetune_lr})",
    )
    add(
        "--recipe",
        choices=("reference", *IMAGE_RECIPES),
        default=defaults.recipe,
        help=f"training-image recipe: reference (the model's published one) or a named recipe (default {defaults.recipe})",
    )
    add(
        "--batch-size",
        type=positive_int,
        default=defaults.batch_size,
        help=f"batch size (default {defaults.batch_size})",
    )
    add("--accelerator", default=defaults.accelerator, help=f"Trainer accelerator (default {defaults.accelerator})")
    add("--devices", default=str(defaults.devices), help=f"Trainer devices (default {defaults.devices})")


def report_config(args: argparse.Namespace, command: str | None = None) -> ReportConfig:
    """The :class:`~lightning_vtr.experiments.report.ReportConfig` that parsed ``args`` describe."""
    from lightning_vtr.experiments.report import ReportConfig, default_experiment

    experiment = default_experiment(
        model=args.model,
        preset=args.preset,
        data=args.data,
        out=args.out,
        pretrain_epochs=args.pretrain_epochs,
        finetune_epochs=args.finetune_epochs,
        fraction=args.fraction,
        finetune_lr=args.finetune_lr,
        recipe=args.recipe,
        test_repeats=args.test_repeats,
        batch_size=args.batch_size,
        accelerator=args.accelerator,
        devices=args.devices,
    )
    return ReportConfig(
        experiment,
        seeds=args.seeds,
        strategies=args.strategies,
        ablations=[] if args.no_ablations else args.ablations,
        command=command,
        validation_triplets=args.validation_triplets,
        jobs=args.jobs,
    )


def check_inputs(args: argparse.Namespace) -> None:
    """Check ``--data``, ``--out`` and ``--fraction`` before anything starts (Lightning, the embedded build).

    Raises:
        DatasetNotFoundError / FileNotFoundError: ``--data`` is no dataset folder (exit status 2).
        DatasetFormatError: its ``metadata.json`` is invalid (exit status 1).
        UsageError: ``--fraction`` out of (0, 1], ``--out`` a file or a folder of other files.
    """
    from pathlib import Path

    from lightning_vtr.cli.arguments import check_output_folder
    from lightning_vtr.data.format import load_metadata
    from lightning_vtr.errors import UsageError

    if not 0.0 < args.fraction <= 1.0:
        raise UsageError(f"`--fraction` must be in (0, 1], got {args.fraction!r}")
    if args.data is not None:
        data = Path(args.data).expanduser()
        if data.exists() and not data.is_dir():
            raise FileNotFoundError(f"`--data` must be a ShapeNet-VTR directory, got {str(args.data)!r} (a file)")
        load_metadata(data)
    check_output_folder(Path(args.out), marker="seed_*")


def run(args: argparse.Namespace) -> int:
    from lightning_vtr.experiments.report import run_report

    check_inputs(args)
    result = run_report(report_config(args, command=args.command_line))
    print(result["markdown"])
    print("Wrote " + ", ".join(str(p) for p in result["paths"].values()))
    return 0
