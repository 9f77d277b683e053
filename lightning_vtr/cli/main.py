"""The ``lightning-vtr`` command line: one sub-command per job (``build-dataset``, ``dataset-info``, ...).

Each sub-command is a pair of functions registered in :data:`COMMANDS`: one adds its arguments to an
``argparse`` sub-parser, the other runs it and returns the exit status. Adding a command is adding a
pair and one entry. Errors a user can fix (a bad path, ``--shard 3/2``) print one line to stderr and
exit with status 2; argparse's own usage errors exit with 2 as well.
"""

from __future__ import annotations

import argparse
import shlex
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

__all__ = ["COMMANDS", "build_parser", "main"]


# ------------------------------------------------------------------------------------------ helpers


def _shard(text: str) -> tuple[int, int]:
    """Parse ``"i/n"`` (0-based shard ``i`` of ``n``)."""
    try:
        index, count = (int(part) for part in text.split("/"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected i/n with integers, e.g. 0/4, got {text!r}") from None
    if count < 1 or not 0 <= index < count:
        raise argparse.ArgumentTypeError(f"shard index must satisfy 0 <= i < n, got {index}/{count}")
    return index, count


def _csv(text: str) -> list[str]:
    items = [item.strip() for item in text.split(",") if item.strip()]
    if not items:
        raise argparse.ArgumentTypeError(f"expected a comma-separated list, got {text!r}")
    return items


def _ratios(text: str) -> tuple[float, float, float]:
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != 3:
        raise argparse.ArgumentTypeError(f"expected three comma-separated ratios train,val,test, got {text!r}")
    return values  # type: ignore[return-value]


def _positive(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return value


# ------------------------------------------------------------------------------------------ build-dataset


def _add_build_dataset(parser: argparse.ArgumentParser) -> None:
    parser.description = (
        "Render the Aligned / Hemispherical / Spherical view sets and voxelize every object into a ShapeNet-VTR "
        "directory (docs/dataset_format.md). Re-running finishes a killed build without redoing finished "
        "objects. With --shard i/n each array job builds every n-th object; the last shard to finish (or a "
        "later run with --finalize) writes metadata.json."
    )
    parser.add_argument("output", nargs="?", type=Path, help="dataset directory (omit with --embedded: the cache directory)")
    parser.add_argument("--source", default="procedural", help="'procedural' or a folder: ShapeNetCore v1/v2 or <category>/<object>.<ext>")
    parser.add_argument("--embedded", action="store_true", help="use the embedded dataset's options for every option not given")
    parser.add_argument("--objects-per-category", type=_positive, default=None, help="first N objects per category (default: 30 procedural, all from a folder)")
    parser.add_argument("--categories", type=_csv, default=None, help="comma-separated categories (or synset ids)")
    parser.add_argument("--image-size", type=_positive, default=None, help="image side in pixels (default 128)")
    parser.add_argument("--resolution", type=_positive, default=None, help="voxel grid side R (default 32)")
    parser.add_argument("--views-per-set", type=_positive, default=None, help="views per view set (default 24)")
    parser.add_argument("--aligned-pitch", type=float, default=None, help="Aligned elevation in degrees (default 30)")
    parser.add_argument("--split", type=_ratios, default=(0.7, 0.1, 0.2), help="train,val,test ratios (default 0.7,0.1,0.2)")
    parser.add_argument("--seed", type=int, default=None, help="seed of shapes, view sets and split (default 0)")
    parser.add_argument("--workers", type=_positive, default=1, help="parallel build processes (default 1)")
    parser.add_argument("--shard", type=_shard, default=(0, 1), help="build shard i of n (0-based), e.g. 3/16")
    parser.add_argument("--finalize", action="store_true", help="only write metadata.json once every shard has finished")
    parser.add_argument("--layout", default="auto", choices=["auto", "shapenet_v1", "shapenet_v2", "generic"], help="source folder layout")
    parser.add_argument("--up-axis", choices=["y", "z"], default=None, help="meshes' up axis (default: y for ShapeNet, z for generic)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def _run_build_dataset(args: argparse.Namespace) -> int:
    from lightning_vtr.data.builder import EMBEDDED_DEFAULTS, build_dataset, embedded_dataset_dir, finalize_dataset
    from lightning_vtr.data.format import dataset_summary

    if args.output is None and not args.embedded:
        raise ValueError("OUTPUT is required unless --embedded is given")
    if args.finalize:
        if args.output is None:
            raise ValueError("--finalize needs OUTPUT, the directory the shards built")
        report = finalize_dataset(args.output)
        print(report.summary())
        print(dataset_summary(args.output))
        return 0
    given = {
        "objects_per_category": args.objects_per_category,
        "categories": args.categories,
        "image_size": args.image_size,
        "resolution": args.resolution,
        "views_per_set": args.views_per_set,
        "aligned_pitch": args.aligned_pitch,
        "seed": args.seed,
    }
    given = {k: v for k, v in given.items() if v is not None}
    if args.embedded:
        if args.source != "procedural":
            raise ValueError(f"--embedded builds the procedural source, got --source {args.source!r}")
        options = {**EMBEDDED_DEFAULTS, **given}
        output = args.output or embedded_dataset_dir(**given)
    else:
        options, output = given, args.output
    report = build_dataset(
        output,
        source=args.source,
        split=args.split,
        workers=args.workers,
        shard=args.shard,
        progress=not args.no_progress,
        source_layout=args.layout,
        up_axis=args.up_axis,
        **options,
    )
    print(report.summary())
    if report.finalized:
        print(dataset_summary(output))
    elif args.shard[1] > 1:
        print(f"Shard {args.shard[0]}/{args.shard[1]} done; metadata.json is written when every shard has finished "
              f"(or run `lightning-vtr build-dataset {output} --finalize`).")
    return 0


# ------------------------------------------------------------------------------------------ dataset-info


def _add_dataset_info(parser: argparse.ArgumentParser) -> None:
    parser.description = "Print a per-category, per-split summary of a ShapeNet-VTR directory."
    parser.add_argument("root", type=Path, help="dataset directory")


def _run_dataset_info(args: argparse.Namespace) -> int:
    from lightning_vtr.data.format import dataset_summary

    print(dataset_summary(args.root))
    return 0


# ------------------------------------------------------------------------------------------ report


def _add_report(parser: argparse.ArgumentParser) -> None:
    from lightning_vtr.experiments.report import ReportConfig, STRATEGIES

    defaults = ReportConfig()
    parser.description = (
        "Pretrain a model on Aligned, fine-tune it with each view strategy under one budget, test on Aligned / "
        "Hemispherical / Spherical and write report.md (the paper's Table 1 and ablations), results.csv and "
        "report.png into --out. A killed report re-run skips every finished run."
    )
    parser.add_argument("--model", choices=["pix2vox", "lrgt"], default=defaults.model, help="reconstruction model (default pix2vox)")
    parser.add_argument("--preset", default=defaults.preset, help="model preset (default tiny)")
    parser.add_argument("--data", default=None, help="ShapeNet-VTR directory (default: the embedded procedural dataset)")
    parser.add_argument("--out", default=defaults.out, help=f"output directory (default {defaults.out})")
    parser.add_argument("--seeds", type=int, nargs="+", default=list(defaults.seeds), help="seeds; several give mean ± std (default 0)")
    parser.add_argument("--pretrain-epochs", type=_positive, default=defaults.pretrain_epochs, help=f"epochs on Aligned (default {defaults.pretrain_epochs})")
    parser.add_argument("--finetune-epochs", type=_positive, default=defaults.finetune_epochs, help=f"fine-tuning epochs per strategy (default {defaults.finetune_epochs})")
    parser.add_argument("--strategies", type=_csv, default=list(STRATEGIES), help=f"comma-separated subset of {','.join(STRATEGIES)} (default all)")
    parser.add_argument("--no-ablations", action="store_true", help="skip the K, pool and single-view ablations")
    parser.add_argument("--fraction", type=float, default=defaults.fraction, help=f"share of training objects searched per epoch (default {defaults.fraction})")
    parser.add_argument("--finetune-lr", choices=["cosine", "constant"], default=defaults.finetune_lr, help=f"fine-tuning learning-rate schedule: annealed to 0 or the model's own (default {defaults.finetune_lr})")
    parser.add_argument("--batch-size", type=_positive, default=defaults.batch_size, help=f"batch size (default {defaults.batch_size})")
    parser.add_argument("--accelerator", default=defaults.accelerator, help="Trainer accelerator (default auto)")
    parser.add_argument("--devices", default=defaults.devices, help="Trainer devices (default 1)")


def _run_report(args: argparse.Namespace) -> int:
    from lightning_vtr.experiments.report import ABLATIONS, ReportConfig, run_report

    devices = int(args.devices) if str(args.devices).isdigit() else args.devices
    config = ReportConfig(
        model=args.model,
        preset=args.preset,
        data=args.data,
        out=args.out,
        seeds=args.seeds,
        pretrain_epochs=args.pretrain_epochs,
        finetune_epochs=args.finetune_epochs,
        strategies=args.strategies,
        ablations=() if args.no_ablations else ABLATIONS,
        fraction=args.fraction,
        finetune_lr=args.finetune_lr,
        batch_size=args.batch_size,
        accelerator=args.accelerator,
        devices=devices,
        command=args._command_line,
    )
    result = run_report(config)
    print(result["markdown"])
    print("Wrote " + ", ".join(str(p) for p in result["paths"].values()))
    return 0


# ------------------------------------------------------------------------------------------ dispatcher

#: name -> (help, add_arguments(parser), run(args) -> exit status).
COMMANDS: dict[str, tuple[str, Callable[[argparse.ArgumentParser], None], Callable[[argparse.Namespace], int]]] = {
    "build-dataset": ("build a ShapeNet-VTR dataset (procedural, ShapeNetCore or a mesh folder)", _add_build_dataset, _run_build_dataset),
    "dataset-info": ("summarise a ShapeNet-VTR dataset", _add_dataset_info, _run_dataset_info),
    "report": ("run the paper's comparison and ablations; write Table 1, a CSV and a chart", _add_report, _run_report),
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="lightning-vtr", description="View transformation robustness for multi-view 3D reconstruction.")
    parser.epilog = "Training and testing: `lightning-vtr fit|validate|test --config CONFIG.yaml` (LightningCLI; --help there)."
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, (help_text, add_arguments, run) in COMMANDS.items():
        command = sub.add_parser(name, help=help_text)
        add_arguments(command)
        command.set_defaults(_run=run)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``lightning-vtr`` with ``argv`` (default ``sys.argv[1:]``); returns the exit status."""
    words = list(sys.argv[1:] if argv is None else argv)
    if words and words[0] in ("fit", "validate", "test"):
        from lightning_vtr.cli.lightning import run_lightning_cli

        return run_lightning_cli(None if argv is None else words)
    parser = build_parser()
    args = parser.parse_args(argv)
    args._command_line = shlex.join(["lightning-vtr", *words])  # shown in reports
    try:
        return int(args._run(args))
    except (ValueError, FileNotFoundError, RuntimeError) as err:
        # Errors a user can fix get one line, not a traceback.
        print(f"lightning-vtr {args.command}: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
