"""``lightning-vtr build-dataset``: render and voxelize a ShapeNet-VTR dataset (procedural, ShapeNetCore, meshes)."""

from __future__ import annotations

import argparse
from pathlib import Path

from lightning_vtr.cli.arguments import comma_separated, positive_int, ratios, shard

__all__ = ["PROTOCOLS", "SOURCE_LAYOUTS", "add_arguments", "run"]


def _pitch_range(text: str) -> tuple[float, float]:
    """Parse ``"low,high"`` degrees, e.g. ``0,40``."""
    try:
        low, high = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected two comma-separated angles low,high in degrees, got {text!r}"
        ) from None
    if not -90 <= low <= high <= 90:
        raise argparse.ArgumentTypeError(f"expected -90 <= low <= high <= 90, got {text!r}")
    return low, high


#: ``--protocol`` / ``--layout`` choices: :data:`lightning_vtr.data.builder.PROTOCOLS` and ``SOURCE_LAYOUTS``,
#: written out so that ``--help`` imports no torch or trimesh (a test keeps them equal).
PROTOCOLS: tuple[str, ...] = ("vtr", "pix3d")
SOURCE_LAYOUTS: tuple[str, ...] = ("auto", "shapenet_v1", "shapenet_v2", "generic")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from lightning_vtr.data.format import UP_AXES

    parser.description = (
        "Render the Aligned / Hemispherical / Spherical view sets and voxelize every object into a ShapeNet-VTR "
        "directory (docs/dataset_format.md). Re-running finishes a killed build without redoing finished "
        "objects. With --shard i/n each array job builds every n-th object; the last shard to finish (or a "
        "later run with --finalize) writes metadata.json. --protocol pix3d instead renders one 'pix3d' view set "
        "of --views-per-object random views per object (the paper's Pix3D training set: --categories chair, 60 views)."
    )
    add = parser.add_argument
    add("output", nargs="?", type=Path, help="dataset directory (omit with --embedded: the cache directory)")
    add(
        "--source",
        default="procedural",
        help="'procedural' or a folder: ShapeNetCore v1/v2 or <category>/<object>.<ext>",
    )
    add("--embedded", action="store_true", help="use the embedded dataset's options for every option not given")
    add(
        "--objects-per-category",
        type=positive_int,
        default=None,
        help="first N objects per category (default: 30 procedural, all from a folder)",
    )
    add("--categories", type=comma_separated(), default=None, help="comma-separated categories (or synset ids)")
    add("--image-size", type=positive_int, default=None, help="image side in pixels (default 128)")
    add("--resolution", type=positive_int, default=None, help="voxel grid side R (default 32)")
    add("--views-per-set", type=positive_int, default=None, help="views per view set (default 24)")
    add("--aligned-pitch", type=float, default=None, help="Aligned elevation in degrees (default 30)")
    add(
        "--protocol",
        choices=PROTOCOLS,
        default=None,
        help="'vtr' (default): the aligned/hemispherical/spherical view sets; 'pix3d': one 'pix3d' set of random views",
    )
    add(
        "--views-per-object",
        type=positive_int,
        default=None,
        help="--protocol pix3d: views per object (default 60, at most 100)",
    )
    add(
        "--pitch-range",
        type=_pitch_range,
        default=None,
        help="--protocol pix3d: low,high pitch in degrees (default 0,40; write --pitch-range=-10,30 for a negative low); "
        "yaw is uniform",
    )
    add(
        "--split",
        type=ratios,
        default=(0.7, 0.1, 0.2),
        help="train,val,test ratios (default 0.7,0.1,0.2); a category of >= 3 objects gets >= 1 val and >= 1 test "
        "object, a smaller one warns",
    )
    add("--seed", type=int, default=None, help="seed of shapes, view sets and split (default 0)")
    add("--workers", type=positive_int, default=1, help="parallel build processes (default 1)")
    add("--shard", type=shard, default=(0, 1), help="build shard i of n (0-based), e.g. 3/16")
    add("--finalize", action="store_true", help="only write metadata.json once every shard has finished")
    add("--layout", default="auto", choices=SOURCE_LAYOUTS, help="source folder layout")
    add("--up-axis", choices=UP_AXES, default=None, help="meshes' up axis (default: y for ShapeNet, z for generic)")
    add(
        "--prerender-views",
        action="store_true",
        help="also render every training object's candidate viewpoints into objects/<cat>/<id>/prerendered/ for "
        "PrerenderedSynthesizer (training without OpenGL), once the dataset is finalized; this shard's share with "
        "--shard. On a finished build with no build option given, only this step runs",
    )
    add(
        "--prerender-interval",
        type=positive_int,
        default=30,
        help="--prerender-views: bin interval K in degrees of the rendered grid, dividing 180 (default 30: 72 views)",
    )
    add("--no-progress", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
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
        return _prerender(args, args.output) if args.prerender_views else 0
    given = {
        "objects_per_category": args.objects_per_category,
        "categories": args.categories,
        "image_size": args.image_size,
        "resolution": args.resolution,
        "views_per_set": args.views_per_set,
        "aligned_pitch": args.aligned_pitch,
        "seed": args.seed,
        "protocol": args.protocol,
        "views_per_object": args.views_per_object,
        "pitch_range": args.pitch_range,
    }
    given = {k: v for k, v in given.items() if v is not None}
    finished = args.output is not None and (args.output / "metadata.json").is_file()
    if args.prerender_views and finished and not given and not args.embedded and args.source == "procedural":
        return _prerender(args, args.output)  # a finished build, no build option given: only the new step
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
        if args.prerender_views:
            return _prerender(args, output)
    elif args.shard[1] > 1:
        print(
            f"Shard {args.shard[0]}/{args.shard[1]} done; metadata.json is written when every shard has finished "
            f"(or run `lightning-vtr build-dataset {output} --finalize`)."
        )
        if args.prerender_views:
            print(
                "Prerendered views need the split, known once the dataset is finalized: then run "
                f"`lightning-vtr build-dataset {output} --prerender-views --shard {args.shard[0]}/{args.shard[1]}` "
                "(every shard), or once without --shard."
            )
    return 0


def _prerender(args: argparse.Namespace, output: Path) -> int:
    """The ``--prerender-views`` pass of this shard over a finished dataset; status 1 when an object failed."""
    from lightning_vtr.synthesis.prerendered import prerender_views

    report = prerender_views(output, k=args.prerender_interval, shard=args.shard, progress=not args.no_progress)
    print(report.summary())
    return 1 if report.failed else 0
