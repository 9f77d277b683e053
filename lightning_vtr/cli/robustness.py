"""``lightning-vtr robustness``: the viewpoint robustness map of one or more checkpoints, side by side.

Every checkpoint is measured with :func:`~lightning_vtr.evaluation.robustness.robustness_map` on the same objects
(``--objects N`` of the ``--split``, round-robin over the categories; every one by default), with the same seed and
so the same view sets (views per set: the first checkpoint's ``num_views``, for all of them)::

    lightning-vtr robustness --ckpt "None-VTR=runs/none/last.ckpt" --ckpt "VTR=runs/vtr/last.ckpt" \\
        --data embedded --split test --out robustness --k 30 --objects 64

It writes into ``OUT``:

* ``bins.csv``: one row per checkpoint, category and bin: the columns of
  :meth:`~lightning_vtr.evaluation.robustness.RobustnessMap.to_csv` (``category`` ``all`` for every object, then
  each category) after a first column ``checkpoint`` (its NAME);
* ``maps/<NAME>/``: each map's own ``bins.csv``, ``objects.csv`` (per-object IoU) and ``robustness.json``,
  which :meth:`~lightning_vtr.evaluation.robustness.RobustnessMap.from_csv` reads back;
* ``difference.csv`` (two checkpoints or more): per bin, the mean IoU of the first and the second checkpoint and
  ``difference`` = first - second;
* ``<NAME>.png``: the equal-area pictures, one colour scale for all; ``<FIRST>_minus_<SECOND>.png``: the
  difference map (blue where the first is better), and every further checkpoint minus the second;
* ``index.html``, written last: the pictures and a table of the maps. A folder without it is not a complete
  output.

A checkpoint is ``[NAME=]PATH`` (default NAME: the file's stem); names must differ. Every input is checked before a
model loads or anything is written.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from lightning_vtr.cli.arguments import EMBEDDED, check_output_folder, dataset_folder, positive_int
from lightning_vtr.cli.pix3d import checkpoint_argument
from lightning_vtr.errors import UsageError

__all__ = ["add_arguments", "run"]

#: The file whose presence marks an earlier output of this command (``--out`` may be reused).
MARKER = "bins.csv"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the options of ``lightning-vtr robustness`` to ``parser``."""
    parser.description = (
        "Measure each checkpoint's IoU on view sets drawn around every bin of the K-degree (yaw, pitch) grid, on "
        "the same objects and view sets for all. Writes OUT/bins.csv (a checkpoint column), OUT/maps/<NAME>/, "
        "OUT/difference.csv, equal-area PNG maps on one colour scale, the first-minus-second difference map and "
        "OUT/index.html (last)."
    )
    add = parser.add_argument
    add(
        "--ckpt",
        type=checkpoint_argument,
        action="append",
        required=True,
        metavar="[NAME=]CKPT",
        help="a checkpoint to measure (repeat the option); NAME labels its map (default: the file's stem)",
    )
    add(
        "--data",
        required=True,
        metavar="DATASET",
        help=f"a ShapeNet-VTR directory with meshes, or `{EMBEDDED}` for the embedded dataset",
    )
    add("--split", default="test", choices=("train", "val", "test"), help="the split measured (default test)")
    add("--out", type=Path, required=True, help="output directory")
    add("--k", type=int, default=30, help="bin interval in degrees, dividing 180 (default 30: 72 bins)")
    add("--seed", type=int, default=0, help="seed of the view sets (default 0)")
    add("--sets-per-bin", type=positive_int, default=1, help="view sets per bin and object (default 1)")
    add("--objects", type=positive_int, default=None, help="at most N objects, round-robin over categories")
    add(
        "--model",
        default=None,
        metavar="MODEL",
        help="pix2vox, lrgt or your class as module.Class, importable from the working folder (default: the "
        "package's class each checkpoint records, else the package's model that loads it)",
    )
    add("--batch-size", type=positive_int, default=64, help="view sets per forward pass (default 64)")
    add("--device", default="auto", help="torch device: auto (CUDA when available), cpu, cuda:0, ...")
    add("--no-progress", action="store_true", help="no progress bar")
    add(
        "--trust-checkpoint",
        action="store_true",
        help="load a --ckpt that only a full pickle load reads (it can run code in it): only files you made or "
        "whose maker you trust (see the Security page)",
    )


def _check_names(checkpoints: list[tuple[str, Path]]) -> None:
    """Names that differ, also as file names (``<NAME>.png``)."""
    from lightning_vtr.evaluation.robustness_plot import map_file_stem

    seen: dict[str, str] = {}
    for name, _ in checkpoints:
        stem = map_file_stem(name)
        if stem in seen:
            same = "is repeated" if seen[stem] == name else f"names the same files as {seen[stem]!r}"
            raise UsageError(
                f"`--ckpt` NAME {name!r} {same}: every checkpoint needs its own NAME (give one as NAME=CKPT)"
            )
        seen[stem] = name


def _check_inputs(args: argparse.Namespace) -> int:
    """Every check before a model loads; returns ``--k``."""
    from lightning_vtr.geometry import check_bin_interval
    from lightning_vtr.models.registry import check_checkpoint, checkpoint_path, model_class

    try:
        k = check_bin_interval(args.k, "--k")
    except ValueError as err:
        raise UsageError(str(err)) from None
    _check_names(args.ckpt)
    check_output_folder(args.out, marker=MARKER)
    for _, path in args.ckpt:
        checkpoint_path(path)
    for _, path in args.ckpt:
        check_checkpoint(path, trust_checkpoint=args.trust_checkpoint)
    if args.model is not None:
        model_class(args.model)
    args.data = dataset_folder(args.data, progress=not args.no_progress)
    return k


def _csv_text(header: list[str], rows: list[dict[str, Any]]) -> str:
    from lightning_vtr.utils.io import csv_text

    return csv_text(rows, header)


def _bins_rows(maps: dict[str, Any]) -> list[dict[str, Any]]:
    rows = []
    for name, rmap in maps.items():
        blocks = [rmap.bin_rows(None)] + [rmap.bin_rows(c) for c in rmap.category_names()]
        rows += [{"checkpoint": name, **row} for block in blocks for row in block]
    return rows


def _difference_rows(first: Any, second: Any) -> list[dict[str, Any]]:
    a, b = first.mean(), second.mean()
    return [
        {
            "bin": i,
            "yaw": float(first.centres[i, 0]),
            "pitch": float(first.centres[i, 1]),
            "area": float(first.areas[i]),
            "first": float(a[i]),
            "second": float(b[i]),
            "difference": float(a[i] - b[i]),
        }
        for i in range(first.num_bins)
    ]


def run(args: argparse.Namespace) -> int:
    """Run ``lightning-vtr robustness`` on parsed arguments; returns the exit status 0."""
    import numpy as np

    from lightning_vtr.evaluation.predict import make_datamodule, resolve_device
    from lightning_vtr.evaluation.robustness import robustness_map
    from lightning_vtr.evaluation.robustness_callback import ObjectSubset, spread_over_categories
    from lightning_vtr.evaluation.robustness_plot import map_file_stem, write_index_html
    from lightning_vtr.models.registry import load_model
    from lightning_vtr.utils.io import atomic_write
    from lightning_vtr.utils.paths import join_under

    # 1. check every input
    k = _check_inputs(args)
    device = resolve_device(args.device)
    # 2. measure each checkpoint on the first one's objects, with the first one's number of views
    maps: dict[str, Any] = {}
    records: list[Any] | None = None
    views_per_set: int | None = None
    for name, path in args.ckpt:
        model = load_model(path, args.model, trust_checkpoint=args.trust_checkpoint).to(device)
        dm = make_datamodule(path, model, Path(args.data).expanduser())
        if records is None:
            records = spread_over_categories(dm.split_records(args.split), args.objects)
            if not records:
                raise UsageError(f"`--split {args.split}` of {str(args.data)!r} holds no objects to measure")
            views_per_set = int(model.num_views)
        objects = ObjectSubset(dm, records)
        rmap = robustness_map(
            model,
            objects,
            k=k,
            views_per_set=views_per_set,
            sets_per_bin=args.sets_per_bin,
            seed=args.seed,
            split=args.split,
            batch_size=args.batch_size,
            progress=not args.no_progress,
        )
        rmap.extra.update(checkpoint=str(path), name=name)
        maps[name] = rmap
        print(f"{name}: IoU over the sphere {rmap.overall():.4f} ({rmap.num_objects} objects, {rmap.num_bins} bins)")
        del model
    # 3. write: bins.csv first (it marks the folder as this command's), index.html last
    out = Path(args.out).expanduser()
    header = ["checkpoint", *next(iter(maps.values())).bin_rows(None)[0]]
    atomic_write(out / MARKER, _csv_text(header, _bins_rows(maps)))
    for name, rmap in maps.items():
        rmap.to_csv(join_under(out, "maps", map_file_stem(name)), per_category=True)
    names = list(maps)
    if len(names) >= 2:
        rows = _difference_rows(maps[names[0]], maps[names[1]])
        atomic_write(out / "difference.csv", _csv_text(list(rows[0]), rows))
    index = write_index_html(
        out,
        maps,
        reference=names[1] if len(names) >= 2 else None,
        title=f"lightning-vtr robustness: {args.split} split, K = {k}",
    )
    overall = np.array([m.overall() for m in maps.values()])
    if len(names) >= 2:
        print(f"{names[0]} - {names[1]}: {overall[0] - overall[1]:+.4f} over the sphere")
    print(f"Wrote {out / MARKER}; open {index}")
    return 0
