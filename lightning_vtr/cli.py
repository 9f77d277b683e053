"""The ``lightning-vtr`` command line: one sub-command per job (``build-dataset``, ``dataset-info``, ...).

Each sub-command is a pair of functions registered in :data:`COMMANDS`: one adds its arguments to an
``argparse`` sub-parser, the other runs it and returns the exit status. Adding a command is adding a
pair and one entry. Errors a user can fix (a bad path, ``--shard 3/2``) print one line to stderr and
exit with status 2; argparse's own usage errors exit with 2 as well.
"""

from __future__ import annotations

import argparse
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


# ------------------------------------------------------------------------------------------ dispatcher

#: name -> (help, add_arguments(parser), run(args) -> exit status).
COMMANDS: dict[str, tuple[str, Callable[[argparse.ArgumentParser], None], Callable[[argparse.Namespace], int]]] = {
    "build-dataset": ("build a ShapeNet-VTR dataset (procedural, ShapeNetCore or a mesh folder)", _add_build_dataset, _run_build_dataset),
    "dataset-info": ("summarise a ShapeNet-VTR dataset", _add_dataset_info, _run_dataset_info),
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
        from lightning_vtr.lightning_cli import run_lightning_cli

        return run_lightning_cli(None if argv is None else words)
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args._run(args))
    except (ValueError, FileNotFoundError, RuntimeError) as err:
        # Errors a user can fix get one line, not a traceback.
        print(f"lightning-vtr {args.command}: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
