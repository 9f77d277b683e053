"""``lightning-vtr predict``: run a trained model on your own images or on a dataset split and keep the result.

For each object it writes ``prediction.binvox``, a mesh (``prediction.obj`` by default) and ``sheet.png``
(input views | prediction | ground truth | error | error projection at the error-guided views) into
``OUT/<name>/``, then ``OUT/index.html`` showing every sheet and ``OUT/predictions.json``::

    lightning-vtr predict --ckpt last.ckpt --images photos/chair photos/lamp --out predictions
    lightning-vtr predict --ckpt last.ckpt --data embedded --split test --out predictions

An image folder is one object (:mod:`lightning_vtr.evaluation.predict` reads it): every picture in it (PNG,
JPEG, WebP or BMP, any count and any size) is one view. RGBA pictures are used as they are; an RGB picture gets its alpha from ``<stem>_mask.<ext>`` beside it
when there is one, else from ``--background-key R,G,B`` (pixels that colour, within ``--key-tolerance``, are
background), else it is used whole. Pictures are padded to squares and go through the image transform the
model was trained with (read from the checkpoint's datamodule hyperparameters). A ``*.binvox`` file in the
folder is taken as the ground truth (+Z up, as this package writes them).

Configs go to LightningCLI instead: ``lightning-vtr predict --config CONFIG.yaml --ckpt_path CKPT
--trainer.callbacks+=lightning_vtr.export.VoxelPredictionWriter --trainer.callbacks.output_dir=OUT``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from lightning_vtr.cli.arguments import EMBEDDED, check_output_folder, comma_separated, dataset_folder, positive_int
from lightning_vtr.errors import UsageError
from lightning_vtr.protocol import VIEW_SETS

__all__ = ["MESH_FORMATS", "add_arguments", "run"]

#: ``--mesh-format`` choices: :data:`lightning_vtr.export.MESH_FORMATS`, written out so that ``--help`` imports no
#: torch (a test keeps the two equal).
MESH_FORMATS = ("obj", "ply", "stl", "off", "glb")


def _rgb(text: str) -> tuple[int, int, int]:
    try:
        values = tuple(int(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != 3 or not all(0 <= v <= 255 for v in values):
        raise argparse.ArgumentTypeError(f"expected R,G,B with integers in 0..255, e.g. 255,255,255, got {text!r}")
    return values


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the options of ``lightning-vtr predict`` to ``parser``."""
    parser.description = (
        "Run a trained model on image folders (one object each) or on a dataset split. For each object write "
        "prediction.binvox, a mesh and sheet.png (input views | prediction | ground truth | error | error "
        "projection at the error-guided views) into OUT/<name>/, then OUT/index.html and OUT/predictions.json."
    )
    parser.epilog = (
        "Image folders: every PNG/JPEG/WebP/BMP is a view (any count, any size). RGBA pictures are used as they "
        "are; an RGB picture takes its alpha from <stem>_mask.png beside it, else from --background-key, else it "
        "is used whole. A *.binvox in the folder is the ground truth. With --config/--ckpt_path/--trainer.* the "
        "command goes to LightningCLI instead."
    )
    add = parser.add_argument
    add("--ckpt", type=Path, required=True, help="a Lightning checkpoint of a lightning_vtr model")
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--images", type=Path, nargs="+", metavar="DIR", help="image folders, one object each")
    source.add_argument(
        "--data",
        metavar="DATASET",
        help=f"a ShapeNet-VTR directory (build-dataset), or `{EMBEDDED}` for the embedded dataset",
    )
    add("--out", type=Path, required=True, help="output directory")
    add("--split", default="test", choices=("train", "val", "test"), help="--data split (default test)")
    add(
        "--view-sets",
        type=comma_separated(VIEW_SETS),
        default=None,
        help="--data view sets, comma-separated (default: every one the dataset has)",
    )
    add(
        "--limit",
        type=positive_int,
        default=None,
        help="--data: at most N objects per view set, spread over categories",
    )
    add(
        "--model",
        default=None,
        metavar="MODEL",
        help="pix2vox, lrgt or your class as module.Class, importable from the working folder (default: the "
        "package's class the checkpoint records, else the package's model that loads it)",
    )
    add("--threshold", type=float, default=0.4, help="occupancy threshold of the exports (default 0.4)")
    add("--mesh-format", choices=MESH_FORMATS, default="obj", help="mesh file format (default obj)")
    add("--background-key", type=_rgb, default=None, metavar="R,G,B", help="background colour of RGB pictures")
    add("--key-tolerance", type=int, default=12, help="largest channel difference still background (default 12)")
    add("--batch-size", type=positive_int, default=8, help="objects per forward pass (default 8)")
    add("--device", default="auto", help="torch device: auto (CUDA when available), cpu, cuda:0, ...")
    add("--panel-size", type=positive_int, default=128, help="sheet panel side in pixels (default 128)")
    add("--no-sheets", action="store_true", help="write no sheets (no rendering)")
    add(
        "--trust-checkpoint",
        action="store_true",
        help="load a --ckpt that only a full pickle load reads (it can run code in it): only a file you made or "
        "whose maker you trust (see the Security page)",
    )
    add("--no-progress", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    """Run ``lightning-vtr predict`` on parsed arguments; returns the exit status 0.

    Every input is checked before the model loads or anything is written: the checkpoint file and the image
    folders' listings, then the checkpoint's content and every picture, then ``--out``.
    """
    from tqdm.auto import tqdm

    from lightning_vtr.evaluation.predict import (
        check_view_folder,
        export_predictions,
        make_datamodule,
        predict_dataset,
        predict_folders,
        view_folder_pictures,
    )
    from lightning_vtr.export import write_summary
    from lightning_vtr.models.registry import check_checkpoint, checkpoint_path, load_model, model_class
    from lightning_vtr.utils.paths import printable
    from lightning_vtr.utils.validation import check_float

    # 1. check inputs
    threshold = check_float("--threshold", args.threshold, minimum=0.0, maximum=1.0, min_open=True, max_open=True)
    if not 0 <= args.key_tolerance <= 255:
        raise UsageError(f"`--key-tolerance` must be in [0, 255], got {args.key_tolerance}")
    data = None if args.data is None else dataset_folder(args.data, progress=not args.no_progress)
    checkpoint_path(args.ckpt)
    for folder in args.images or ():  # every folder, then every picture, before the model loads or anything is written
        view_folder_pictures(Path(folder).expanduser(), folder)
    check_checkpoint(args.ckpt, trust_checkpoint=args.trust_checkpoint)
    for folder in args.images or ():
        check_view_folder(Path(folder).expanduser(), folder)
    if args.model is not None:
        model_class(args.model)  # a wrong --model is told before anything is written
    check_output_folder(args.out)
    # 2. load the model and its image transform
    model = load_model(args.ckpt, args.model, trust_checkpoint=args.trust_checkpoint)
    dm = make_datamodule(args.ckpt, model, data)
    # 3. predict
    if args.images is not None:
        results = predict_folders(
            model,
            args.images,
            dm.transform,
            device=args.device,
            background_key=args.background_key,
            key_tolerance=args.key_tolerance,
        )
    else:
        results = predict_dataset(
            model,
            dm,
            split=args.split,
            view_sets=args.view_sets,
            limit=args.limit,
            batch_size=args.batch_size,
            device=args.device,
        )
    # 4. export every object, then the page
    entries = []
    exported = export_predictions(
        args.out,
        results,
        threshold=threshold,
        mesh_format=args.mesh_format,
        sheets=not args.no_sheets,
        panel_size=args.panel_size,
    )
    for entry in tqdm(
        exported,
        total=getattr(results, "__len__", lambda: None)(),
        desc="predict: exporting",
        disable=True if args.no_progress else None,  # None: a bar on a terminal only
        leave=False,
    ):
        entries.append(entry)
        tqdm.write(
            printable(f"{entry['name']}: ")  # a name from data: no raw control character reaches the terminal
            + ", ".join(f"{k} {v:.4f}" if isinstance(v, float) else f"{k} {v}" for k, v in entry["facts"].items())
        )
    paths = write_summary(args.out, entries, title=f"lightning-vtr predict: {Path(args.ckpt).name}")
    print(f"Wrote {len(entries)} objects to {args.out}; open {paths['index']}")
    return 0
