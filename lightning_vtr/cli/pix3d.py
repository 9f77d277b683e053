"""``lightning-vtr pix3d`` and ``lightning-vtr evaluate-folder``: trained models on real photographs or on a folder
test set, printed in the paper's Table 5 layout (``Method | mIoU | F-score``, one row per checkpoint)::

    lightning-vtr pix3d --root ~/data/Pix3D --category chair \\
        --checkpoint "Pix2Vox++=runs/none/last.ckpt" --checkpoint "Ours (Pix2Vox++)=runs/vtr/last.ckpt" --out pix3d_eval
    lightning-vtr evaluate-folder --images VTR_test/Spherical --voxels ShapeNetVox32 --views 3 \\
        --checkpoint runs/vtr/last.ckpt --out spherical_eval

Each writes ``OUT/table.md`` (the table, then what was measured), ``OUT/results.csv`` (one row per checkpoint and
category, ``category = all`` for the overall row; fractions) and ``OUT/results.json``. A checkpoint is
``[NAME=]PATH`` (the row's name; default the file's stem). Each model gets the image transform it was validated
with (the checkpoint's datamodule settings, as ``lightning-vtr predict`` reads them) and voxels at its
resolution. ``--frame-check N`` (pix3d) first projects the voxels of N photographs with their poses and prints the
silhouette IoU against the masks (:func:`lightning_vtr.evaluation.pix3d.frame_check`).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from lightning_vtr.cli.arguments import check_output_folder, positive_int
from lightning_vtr.errors import UsageError

__all__ = [
    "POOLINGS",
    "VIEW_CHOICES",
    "add_arguments",
    "add_folder_arguments",
    "checkpoint_argument",
    "run",
    "run_folder",
]

#: ``--pooling`` and ``--view-choice`` choices: :data:`lightning_vtr.data.pix3d.POOLINGS` and
#: :data:`lightning_vtr.data.folder_test_set.VIEW_CHOICES`, written out so that ``--help`` imports no torch (a test
#: keeps them equal).
POOLINGS = ("max", "mean")
VIEW_CHOICES = ("first", "spread", "random")


def checkpoint_argument(text: str) -> tuple[str, Path]:
    """Parse ``[NAME=]PATH`` into ``(name, path)``; the name defaults to the file's stem."""
    name, sep, path = text.partition("=")
    if not sep:
        name, path = "", text
    if not path:
        raise argparse.ArgumentTypeError(f"expected [NAME=]PATH to a checkpoint, got {text!r}")
    return (name.strip() or Path(path).stem), Path(path).expanduser()


def _common(parser: argparse.ArgumentParser) -> None:
    add = parser.add_argument
    add(
        "--checkpoint",
        type=checkpoint_argument,
        action="append",
        required=True,
        metavar="[NAME=]CKPT",
        help="a checkpoint to evaluate, one table row each (repeat the option); NAME labels the row",
    )
    add(
        "--model",
        default=None,
        metavar="MODEL",
        help="pix2vox, lrgt or your class as module.Class, importable from the working folder (default: the class "
        "the checkpoint records, else the package's model that loads it)",
    )
    add("--category", action="append", default=None, help="keep only this category (repeat for more)")
    add("--split-file", type=Path, default=None, help="a Pix2Vox-style split JSON: keep only its --split entries")
    add("--split", default="test", choices=("train", "val", "test"), help="the split of --split-file (default test)")
    add("--per-category", action="store_true", help="add mIoU / F-score columns for each category")
    add("--batch-size", type=positive_int, default=8, help="items per forward pass (default 8)")
    add("--device", default="auto", help="torch device: auto (CUDA when available), cpu, cuda:0, ...")
    add("--fscore-points", type=positive_int, default=8192, help="points sampled per surface (default 8192)")
    add("--out", type=Path, required=True, help="output directory")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the options of ``lightning-vtr pix3d`` to ``parser``."""
    parser.description = (
        "Evaluate checkpoints on Pix3D (single-view real photographs): each photograph is cropped around its "
        "box, masked, and given to the model through the transform it was validated with; its voxel.mat is "
        "resampled to the model's resolution in the package frame. Writes OUT/table.md, results.csv, results.json."
    )
    add = parser.add_argument
    add("--root", type=Path, required=True, help="the Pix3D directory (pix3d.json, img/, mask/, model/)")
    _common(parser)
    add("--include-hidden", action="store_true", help="also use truncated / occluded / slightly occluded photographs")
    add("--limit", type=positive_int, default=None, help="at most N photographs (the first in pix3d.json order)")
    add("--margin", type=float, default=0.1, help="crop margin per side, fraction of the box's longer side (0.1)")
    add("--no-mask", action="store_true", help="keep the photograph's background (no mask compositing)")
    add("--pooling", choices=POOLINGS, default="max", help="voxel down-sampling rule (default max)")
    add("--yaw-offset", type=int, default=0, choices=(0, 90, 180, 270, -90), help="extra turn of the voxels about +Z")
    add("--frame-check", type=int, default=0, metavar="N", help="first check the voxel frame on N photographs")


def add_folder_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the options of ``lightning-vtr evaluate-folder`` to ``parser``."""
    parser.description = (
        "Evaluate checkpoints on a folder test set without camera metadata: IMAGES/<taxonomy>/<model>/NN.png with "
        "voxels VOXELS/<taxonomy>/<model>/model.binvox (ShapeNetVox32, +Y up). Writes OUT/table.md, results.csv "
        "and results.json."
    )
    add = parser.add_argument
    add("--images", type=Path, required=True, help="the set's folder, e.g. VTR_test/Spherical")
    add("--voxels", type=Path, required=True, help="the voxel folder, e.g. ShapeNetVox32")
    _common(parser)
    add("--views", type=positive_int, default=None, help="views per object (default: the model's num_views)")
    add("--view-choice", choices=VIEW_CHOICES, default="first", help="which views (default first)")
    add("--seed", type=int, default=0, help="seed of --view-choice random (default 0)")
    add("--voxel-up-axis", choices=("y", "z"), default="y", help="up axis of the voxel files (ShapeNetVox32: y)")


# ---------------------------------------------------------------------------------------------- shared
def _check_checkpoints_and_out(args: argparse.Namespace) -> None:
    """Every ``--checkpoint`` a readable Lightning checkpoint, ``--model`` a class, ``--out`` new, empty or an
    earlier table's."""
    from lightning_vtr.models.registry import check_checkpoint, model_class

    for _, path in args.checkpoint:
        check_checkpoint(path, "--checkpoint")
    if args.model is not None:
        model_class(args.model)
    check_output_folder(args.out, marker="table.md")


def _load(path: Path, model_class: str | None) -> tuple[Any, Any]:
    """The model and the evaluation transform it was validated with."""
    from lightning_vtr.evaluation.predict import make_datamodule
    from lightning_vtr.models.registry import load_model

    model = load_model(path, model_class, option="--checkpoint")
    return model, make_datamodule(path, model).transform


# ---------------------------------------------------------------------------------------------- pix3d
def run(args: argparse.Namespace) -> int:
    """Run ``lightning-vtr pix3d`` on parsed arguments; returns the exit status 0."""
    from lightning_vtr.data.pix3d import Pix3DDataset, read_pix3d
    from lightning_vtr.evaluation.dataset import evaluate_dataset, evaluation_notes, write_evaluation
    from lightning_vtr.evaluation.pix3d import frame_check_summary, frame_check_warning, write_frame_check
    from lightning_vtr.evaluation.predict import resolve_device

    # 1. check inputs and read the photographs
    if not 0.0 <= args.margin <= 2.0:
        raise UsageError(f"`--margin` must be in [0, 2], got {args.margin}")
    if args.frame_check < 0:
        raise UsageError(f"`--frame-check` must be >= 0, got {args.frame_check}")
    root = Path(args.root).expanduser()
    if not root.is_dir():
        found = "a file" if root.exists() else "no such folder"
        raise FileNotFoundError(
            f"`--root` must be the Pix3D folder (pix3d.json, img/, ...), got {str(args.root)!r} ({found})"
        )
    _check_checkpoints_and_out(args)
    records = read_pix3d(
        args.root,
        categories=args.category,
        include_hidden=args.include_hidden,
        split_file=args.split_file,
        split=args.split,
    )
    records = records[: args.limit] if args.limit else records
    if not records:
        raise ValueError(f"no Pix3D photographs of {str(args.root)!r} are left after the filters")
    # 2. the frame check
    args.out.mkdir(parents=True, exist_ok=True)
    if args.frame_check:
        ious = write_frame_check(args.out, records[: args.frame_check])
        print(frame_check_summary(ious))
        warning = frame_check_warning(ious)
        if warning is not None:
            print(warning, file=sys.stderr)
    # 3. each checkpoint
    results = {}
    for name, path in args.checkpoint:
        model, transform = _load(path, args.model)
        dataset = Pix3DDataset(
            records,
            transform=transform,
            resolution=int(model.voxel_resolution),
            margin=args.margin,
            use_mask=not args.no_mask,
            pooling=args.pooling,
            yaw_offset=args.yaw_offset,
        )
        results[name] = evaluate_dataset(
            model,
            dataset,
            batch_size=args.batch_size,
            device=resolve_device(args.device),
            fscore_points=args.fscore_points,
        )
    # 4. the table
    what = f"Pix3D ({args.root!s}), {len(records)} photographs, one view each"
    table = write_evaluation(
        args.out, results, title="Pix3D", notes=evaluation_notes(results, what), per_category=args.per_category
    )
    print(table)
    print(f"Wrote {args.out / 'table.md'}, results.csv and results.json")
    return 0


# ---------------------------------------------------------------------------------------------- folders
def run_folder(args: argparse.Namespace) -> int:
    """Run ``lightning-vtr evaluate-folder`` on parsed arguments; returns the exit status 0."""
    from lightning_vtr.data.folder_test_set import FolderTestSet
    from lightning_vtr.evaluation.dataset import evaluate_dataset, evaluation_notes, write_evaluation
    from lightning_vtr.evaluation.predict import resolve_device

    for option in ("--images", "--voxels"):
        folder = Path(getattr(args, option[2:])).expanduser()
        if not folder.is_dir():
            found = "a file" if folder.exists() else "no such folder"
            raise FileNotFoundError(f"`{option}` must be a folder, got {str(folder)!r} ({found})")
    _check_checkpoints_and_out(args)
    results, sizes = {}, set()
    for name, path in args.checkpoint:
        model, transform = _load(path, args.model)
        dataset = FolderTestSet(
            args.images,
            args.voxels,
            num_views=args.views or int(model.num_views),
            view_choice=args.view_choice,
            transform=transform,
            seed=args.seed,
            categories=args.category,
            split_file=args.split_file,
            split=args.split,
            voxel_up_axis=args.voxel_up_axis,
        )
        sizes.add((len(dataset), dataset.num_views, dataset.view_set))
        results[name] = evaluate_dataset(
            model,
            dataset,
            batch_size=args.batch_size,
            device=resolve_device(args.device),
            fscore_points=args.fscore_points,
        )
    what = "; ".join(
        f"{args.images!s} ({s}): {n} objects, {v} view(s) each ({args.view_choice})" for n, v, s in sorted(sizes)
    )
    table = write_evaluation(
        args.out, results, title=str(args.images), notes=evaluation_notes(results, what), per_category=args.per_category
    )
    print(table)
    print(f"Wrote {args.out / 'table.md'}, results.csv and results.json")
    return 0
