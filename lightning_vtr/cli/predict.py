"""``lightning-vtr predict``: run a trained model on your own images or on a dataset split and keep the result.

For each object it writes ``prediction.binvox``, a mesh (``prediction.obj`` by default) and ``sheet.png``
(input views | prediction | ground truth | error | error projection at the error-guided views) into
``OUT/<name>/``, then ``OUT/index.html`` showing every sheet and ``OUT/predictions.json``::

    lightning-vtr predict --ckpt last.ckpt --images photos/chair photos/lamp --out predictions
    lightning-vtr predict --ckpt last.ckpt --data ~/.cache/lightning_vtr/embedded --split test --out predictions

An image folder is one object: every picture in it (PNG, JPEG, WebP or BMP, any count and any size) is one
view. RGBA pictures are used as they are; an RGB picture gets its alpha from ``<stem>_mask.<ext>`` beside it
when there is one, else from ``--background-key R,G,B`` (pixels that colour, within ``--key-tolerance``, are
background), else it is used whole. Pictures are padded to squares and go through the image transform the
model was trained with (read from the checkpoint's datamodule hyperparameters). A ``*.binvox`` file in the
folder is taken as the ground truth (+Z up, as this package writes them).

Configs go to LightningCLI instead: ``lightning-vtr predict --config CONFIG.yaml --ckpt_path CKPT
--trainer.callbacks+=lightning_vtr.export.VoxelPredictionWriter --trainer.callbacks.output_dir=OUT``.
"""

from __future__ import annotations

import argparse
import importlib
import warnings
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from lightning_vtr.cli.arguments import check_output_folder, comma_separated, positive_int
from lightning_vtr.errors import DataError, UsageError

if TYPE_CHECKING:
    import lightning as L
    import numpy as np
    import torch

    from lightning_vtr.data.datamodule import VTRDataModule

__all__ = [
    "HELP",
    "IMAGE_SUFFIXES",
    "add_arguments",
    "check_checkpoint",
    "load_model",
    "make_datamodule",
    "predict_dataset",
    "predict_folders",
    "read_view_folder",
    "run",
]

HELP = "run a trained model on image folders or a dataset split; write binvox, meshes, sheets and index.html"
#: Picture files read from an image folder (case-insensitive).
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".webp", ".bmp")
_MASK_SUFFIX = "_mask"


def _rgb(text: str) -> tuple[int, int, int]:
    try:
        values = tuple(int(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != 3 or not all(0 <= v <= 255 for v in values):
        raise argparse.ArgumentTypeError(f"expected R,G,B with integers in 0..255, e.g. 255,255,255, got {text!r}")
    return values  # type: ignore[return-value]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from lightning_vtr.export import MESH_FORMATS
    from lightning_vtr.protocol import VIEW_SETS

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
    source.add_argument("--data", type=Path, metavar="DATASET", help="a ShapeNet-VTR directory (build-dataset)")
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
        "--model", default=None, help="model class: pix2vox, lrgt or a dotted class path (default: from the checkpoint)"
    )
    add("--threshold", type=float, default=0.4, help="occupancy threshold of the exports (default 0.4)")
    add("--mesh-format", choices=MESH_FORMATS, default="obj", help="mesh file format (default obj)")
    add("--background-key", type=_rgb, default=None, metavar="R,G,B", help="background colour of RGB pictures")
    add("--key-tolerance", type=int, default=12, help="largest channel difference still background (default 12)")
    add("--batch-size", type=positive_int, default=8, help="objects per forward pass (default 8)")
    add("--device", default="auto", help="torch device: auto (CUDA when available), cpu, cuda:0, ...")
    add("--panel-size", type=positive_int, default=128, help="sheet panel side in pixels (default 128)")
    add("--no-sheets", action="store_true", help="write no sheets (no rendering)")


# --------------------------------------------------------------------------------------------- the model
def _checkpoint_hparams(path: Path) -> tuple[dict[str, Any], dict[str, Any]]:
    """``(model hyperparameters, datamodule hyperparameters)`` stored in a checkpoint (empty when unreadable)."""
    import pickle

    import torch

    try:
        checkpoint = torch.load(path, map_location="cpu", weights_only=True)
    except (pickle.UnpicklingError, RuntimeError, AttributeError):
        return {}, {}
    return dict(checkpoint.get("hyper_parameters", {}) or {}), dict(
        checkpoint.get("datamodule_hyper_parameters", {}) or {}
    )


def _import_class(path: str) -> type:
    module, _, name = path.rpartition(".")
    if module:
        try:
            return getattr(importlib.import_module(module), name)
        except (ImportError, AttributeError):
            pass
    raise ValueError(f"`--model` must be pix2vox, lrgt or an importable class path (module.Class), got {path!r}")


def _checkpoint_file(ckpt: str | Path, option: str = "--ckpt") -> Path:
    path = Path(ckpt).expanduser()
    if not path.is_file():
        found = "a folder" if path.is_dir() else "no such file"
        raise FileNotFoundError(f"`{option}` must be a checkpoint file, got {str(ckpt)!r} ({found})")
    return path


#: The keys every Lightning checkpoint holds.
_LIGHTNING_KEYS = ("state_dict", "pytorch-lightning_version")


def check_checkpoint(ckpt: str | Path, option: str = "--ckpt") -> Path:
    """``ckpt`` as a path if it is a readable Lightning checkpoint file.

    Raises:
        FileNotFoundError: no file there (a usage error).
        DataError: an empty, truncated or non-torch file, or a ``torch.save`` file that is not a Lightning
            checkpoint (no ``state_dict`` / ``pytorch-lightning_version``); the message names the file.
    """
    import pickle

    import torch

    path = _checkpoint_file(ckpt, option)
    size = path.stat().st_size
    expected = f"`{option}` must be a Lightning checkpoint (a file `Trainer.fit` saved), got {str(ckpt)!r}"
    if size == 0:
        raise DataError(f"{expected}: an empty file (0 bytes)")
    try:
        checkpoint = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as err:
        if "Unsupported global" in str(err):
            return path  # a full pickle (objects in the hyperparameters): Lightning loads it, trust it
        raise DataError(f"{expected}: {size} bytes torch cannot read (a truncated copy, or not a torch file)") from None
    except (RuntimeError, OSError, EOFError, ValueError, AttributeError, KeyError, IndexError, TypeError):
        raise DataError(f"{expected}: {size} bytes torch cannot read (a truncated copy, or not a torch file)") from None
    if not isinstance(checkpoint, dict) or any(key not in checkpoint for key in _LIGHTNING_KEYS):
        what = (
            f"a plain torch.save file holding a dict of {len(checkpoint)} keys without "
            + " / ".join(repr(k) for k in _LIGHTNING_KEYS if k not in checkpoint)
            if isinstance(checkpoint, dict)
            else f"a plain torch.save file holding a {type(checkpoint).__name__}"
        )
        raise DataError(f"{expected}: {what}; save models with Trainer.fit / trainer.save_checkpoint")
    return path


def load_model(ckpt: str | Path, model: str | None = None, map_location: Any = "cpu") -> L.LightningModule:
    """Load a reconstruction model from a Lightning checkpoint, in eval mode.

    The class is ``model`` (``"pix2vox"``, ``"lrgt"`` or a dotted class path) when given, else the one a
    LightningCLI checkpoint names (``_class_path``), else the first of
    :data:`lightning_vtr.experiments.training.MODELS` whose ``load_from_checkpoint`` accepts the checkpoint.

    Raises:
        FileNotFoundError: no file at ``ckpt``.
        ValueError: no class loads it (the message lists each class's error).
    """
    from lightning_vtr.experiments.training import MODELS

    path = check_checkpoint(ckpt)
    hparams, _ = _checkpoint_hparams(path)
    if model is not None:
        candidates = [MODELS[model] if model in MODELS else _import_class(model)]
    elif isinstance(hparams.get("_class_path"), str):
        candidates = [_import_class(hparams["_class_path"])]
    else:
        candidates = list(MODELS.values())
    errors = []
    for cls in candidates:
        try:
            loaded = cls.load_from_checkpoint(path, map_location=map_location)
        except (RuntimeError, TypeError, KeyError, ValueError) as err:
            errors.append(f"{cls.__name__}: {(str(err).splitlines() or [type(err).__name__])[0][:600]}")
            continue
        return loaded.eval()
    raise DataError(f"no model class loads the checkpoint {str(path)!r}: " + "; ".join(errors))


def make_datamodule(ckpt: str | Path, model: Any, root: str | Path | None = None) -> VTRDataModule:
    """A :class:`~lightning_vtr.data.VTRDataModule` with the checkpoint's datamodule settings (image recipe,
    normalisation, background, seed), the model's image size and views, over ``root``; its ``transform`` is the
    evaluation transform the model was validated with."""
    import inspect

    from lightning_vtr.data.datamodule import VTRDataModule

    _, stored = _checkpoint_hparams(Path(ckpt).expanduser())
    if not stored:
        warnings.warn(
            f"the checkpoint {str(ckpt)!r} holds no datamodule hyperparameters; images are prepared with "
            "VTRDataModule's defaults (white background, ImageNet normalisation), which may not be the model's",
            stacklevel=2,
        )
    accepted = set(inspect.signature(VTRDataModule).parameters) - {"root", "shapenet_rendering", "n_views", "embedded"}
    kwargs = {k: v for k, v in stored.items() if k in accepted}
    kwargs.update(image_size=int(model.image_size), num_views=int(model.num_views), test_repeats=1)
    return VTRDataModule(None if root is None else str(root), **kwargs)


# --------------------------------------------------------------------------------------------- inputs
def _alpha_from_key(rgb: np.ndarray, key: Sequence[int], tolerance: int) -> np.ndarray:
    import numpy as np

    distance = np.abs(rgb.astype(np.int16) - np.asarray(key, np.int16)).max(axis=-1)
    return np.where(distance <= tolerance, 0, 255).astype(np.uint8)


def _square(rgba: np.ndarray) -> np.ndarray:
    """Pad an ``(H, W, 4)`` picture with transparent pixels to a centred square."""
    import numpy as np

    h, w = rgba.shape[:2]
    side = max(h, w)
    out = np.zeros((side, side, 4), np.uint8)
    top, left = (side - h) // 2, (side - w) // 2
    out[top : top + h, left : left + w] = rgba
    return out


def _folder_pictures(folder: Path, given: str | Path) -> tuple[dict[str, Path], list[Path]]:
    """``(mask files by view stem, view files)`` of an image folder, checked.

    Raises:
        FileNotFoundError: not a folder, or no picture in it (the message names the folder and the suffixes).
    """
    if not folder.is_dir():
        raise FileNotFoundError(f"`--images` must name folders of pictures, got {str(given)!r} (not a folder)")
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file())
    masks = {p.stem[: -len(_MASK_SUFFIX)]: p for p in files if p.stem.endswith(_MASK_SUFFIX)}
    views = [p for p in files if not p.stem.endswith(_MASK_SUFFIX)]
    if not views:
        found = f"it holds {len(files)} mask file(s) only" if files else "it holds none"
        raise FileNotFoundError(
            f"no pictures in the image folder {str(folder)!r}: expected files ending in {', '.join(IMAGE_SUFFIXES)} "
            f"(case-insensitive, masks <stem>{_MASK_SUFFIX}.<ext> aside); {found}"
        )
    return masks, views


def _open_picture(path: Path) -> Any:
    """``PIL.Image.open(path)``, or :class:`~lightning_vtr.errors.DataError` naming the file when it is not a
    picture PIL can read (empty, truncated, another format under a picture's suffix)."""
    from PIL import Image, UnidentifiedImageError

    try:
        image = Image.open(path)
        image.load()
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as err:
        size = path.stat().st_size if path.is_file() else 0
        if size == 0:
            found = "an empty file"
        elif "truncated" in str(err):
            found = f"a truncated picture ({size} bytes)"
        else:
            found = f"{size} bytes PIL cannot read as a picture (another kind of file)"
        raise DataError(f"`--images`: {str(path)!r} must be a PNG, JPEG, WebP or BMP picture, got {found}") from None
    return image


def _check_pictures(folder: Path, given: str | Path) -> None:
    """Open every picture and mask of an image folder once (before the model loads or anything is written)."""
    masks, views = _folder_pictures(folder, given)
    for path in [*views, *masks.values()]:
        _open_picture(path).close()


def read_view_folder(
    directory: str | Path, *, background_key: Sequence[int] | None = None, key_tolerance: int = 12
) -> tuple[list[np.ndarray], list[str], np.ndarray | None]:
    """One object's views from a folder, as square RGBA pictures.

    Returns:
        ``(pictures, names, ground_truth)``: one ``(S_i, S_i, 4)`` uint8 picture per view (sizes may differ),
        the file names, and the folder's ``*.binvox`` grid ``(R, R, R)`` bool or ``None``.

    Raises:
        FileNotFoundError: not a folder, or no picture in it (the message names the folder and the suffixes).
        ValueError: a mask of another size than its picture, or more than one binvox file.
    """
    import numpy as np

    from lightning_vtr.data.binvox import read_binvox

    folder = Path(directory).expanduser()
    masks, views = _folder_pictures(folder, directory)
    pictures = []
    for path in views:
        with _open_picture(path) as image:
            has_alpha = image.mode in ("RGBA", "LA", "PA") or (image.mode == "P" and "transparency" in image.info)
            rgba = np.asarray(image.convert("RGBA")).copy()
        if path.stem in masks:
            with _open_picture(masks[path.stem]) as mask_image:
                mask = np.asarray(mask_image.convert("L"))
            if mask.shape != rgba.shape[:2]:
                raise DataError(
                    f"the mask {masks[path.stem].name!r} must have the size of {path.name!r} "
                    f"({rgba.shape[1]}x{rgba.shape[0]}), got {mask.shape[1]}x{mask.shape[0]}"
                )
            rgba[..., 3] = mask
        elif not has_alpha and background_key is not None:
            rgba[..., 3] = _alpha_from_key(rgba[..., :3], background_key, key_tolerance)
        pictures.append(_square(rgba))
    binvox = sorted(folder.glob("*.binvox"))
    if len(binvox) > 1:
        raise DataError(f"an image folder may hold one ground-truth .binvox file, got {len(binvox)} in {str(folder)!r}")
    truth = read_binvox(binvox[0]) if binvox else None
    return pictures, [p.name for p in views], truth


# --------------------------------------------------------------------------------------------- predicting
def _device(name: str) -> torch.device:
    import torch

    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


def _predict(model: Any, images: torch.Tensor, device: torch.device) -> torch.Tensor:
    import torch

    with torch.no_grad():
        return model.predict_voxels(images.to(device)).float().cpu()


def predict_folders(
    model: Any, folders: Sequence[str | Path], transform: Any, *, device: str = "auto", **read: Any
) -> Iterator[dict[str, Any]]:
    """Predict each image folder (one object each; one forward pass per folder, as view counts differ).

    Yields:
        ``{"name", "display" (V, S, S, 4) uint8 list, "images" (V, 3, H, W), "predicted" (R, R, R),
        "target" (R, R, R) or None, "viewpoints" None, "captions"}`` per folder; names are the folder names,
        made unique.
    """
    import torch

    dev = _device(device)
    model.to(dev)
    seen: dict[str, int] = {}
    for folder in folders:
        pictures, names, truth = read_view_folder(folder, **read)
        images = torch.stack([transform(p) for p in pictures])
        predicted = _predict(model, images[None], dev)[0]
        if truth is not None and truth.shape != tuple(predicted.shape):
            raise DataError(
                f"the ground truth in {str(folder)!r} must be a {tuple(predicted.shape)} grid like the prediction, "
                f"got {truth.shape}"
            )
        name = Path(folder).expanduser().resolve().name or "object"
        seen[name] = seen.get(name, 0) + 1
        if seen[name] > 1:
            name = f"{name}_{seen[name]}"
        yield {
            "name": name,
            "display": pictures,
            "images": images,
            "predicted": predicted,
            "target": None if truth is None else torch.from_numpy(truth.astype("float32")),
            "viewpoints": None,
            "view_names": names,
        }


def _spread(records: Sequence[Any], limit: int | None) -> list[Any]:
    """At most ``limit`` records, taken round-robin over categories (fixed order)."""
    if limit is None:
        return list(records)
    rank: dict[str, int] = {}
    keyed = []
    for record in records:
        keyed.append((rank.setdefault(record.category, 0), record.category, record.object_id, record))
        rank[record.category] += 1
    return [k[-1] for k in sorted(keyed, key=lambda k: k[:3])[:limit]]


def predict_dataset(
    model: Any,
    dm: VTRDataModule,
    *,
    split: str = "test",
    view_sets: Sequence[str] | None = None,
    limit: int | None = None,
    batch_size: int = 8,
    device: str = "auto",
) -> Iterator[dict[str, Any]]:
    """Predict a split of a ShapeNet-VTR dataset, each object from ``dm.num_views`` fixed views of each view
    set: the views ``trainer.test`` sees (:class:`~lightning_vtr.data.dataset.VTRDataset` over the whole split
    with the datamodule's seed), whichever objects ``limit`` keeps. Yields the dicts of
    :func:`predict_folders` with ``name`` ``<view_set>/<category>/<object_id>``, the ground truth, the views'
    viewpoints and ``category``."""
    import torch

    from lightning_vtr.data.dataset import VTRDataset, load_rgba

    dev = _device(device)
    model.to(dev)
    records = dm.split_records(split)
    if not records:
        raise ValueError(f"`--split` {split!r} of the dataset at {dm.root} holds no objects")
    chosen = {id(r) for r in _spread(records, limit)}
    positions = [i for i, r in enumerate(records) if id(r) in chosen]  # the test loader's item indices
    available = [v for v in ("aligned", "hemispherical", "spherical") if v in records[0].views]
    for view_set in view_sets or available:
        if view_set not in records[0].views:
            raise ValueError(f"`--view-sets` must be among the dataset's {available}, got {view_set!r}")
        dataset = VTRDataset(records, view_set, num_views=dm.num_views, transform=dm.transform, seed=dm.seed)
        for start in range(0, len(positions), batch_size):
            indices = positions[start : start + batch_size]
            items = [dataset[i] for i in indices]
            predicted = _predict(model, torch.stack([item["images"] for item in items]), dev)
            for i, item, pred in zip(indices, items, predicted):
                paths = records[i].views[view_set][0]
                yield {
                    "name": f"{view_set}/{item['category']}/{item['object_id']}",
                    "display": [load_rgba(paths[j]) for j in dataset.view_indices(i)],
                    "images": item["images"],
                    "predicted": pred,
                    "target": item["voxels"],
                    "viewpoints": item["viewpoints"],
                    "category": item["category"],
                }


def _sheet(result: dict[str, Any], threshold: float, panel_size: int) -> np.ndarray:
    import numpy as np
    import torch

    from lightning_vtr.visualize import object_sheet

    selected = None
    if result["target"] is not None:
        from lightning_vtr.selection.error_guided import ErrorGuidedSelector

        generator = torch.Generator().manual_seed(0)
        selected = ErrorGuidedSelector().select(
            result["predicted"][None],
            result["target"][None].float(),
            [result.get("category", "object")],
            generator=generator,
        )[0]
    return object_sheet(
        result["predicted"],
        result["target"],
        np.stack([_composite_square(p, panel_size) for p in result["display"]]),
        input_viewpoints=result["viewpoints"],
        input_captions=result.get("view_names"),
        selected_viewpoints=selected,
        threshold=threshold,
        panel_size=panel_size,
        title=result["name"],
    )


def _composite_square(rgba: np.ndarray, size: int) -> np.ndarray:
    import numpy as np
    from PIL import Image

    from lightning_vtr.renderer import composite

    return np.asarray(Image.fromarray(composite(rgba)).resize((size, size), Image.BILINEAR))


def run(args: argparse.Namespace) -> int:
    from lightning_vtr.export import export_prediction, prediction_facts, write_summary
    from lightning_vtr.utils.validation import check_float

    # 1. check inputs
    threshold = check_float("--threshold", args.threshold, minimum=0.0, maximum=1.0, min_open=True, max_open=True)
    if not 0 <= args.key_tolerance <= 255:
        raise UsageError(f"`--key-tolerance` must be in [0, 255], got {args.key_tolerance}")
    if args.data is not None:
        from lightning_vtr.data.format import load_metadata

        if not Path(args.data).expanduser().is_dir():
            found = "a file" if Path(args.data).expanduser().exists() else "no such folder"
            raise FileNotFoundError(f"`--data` must be a ShapeNet-VTR directory, got {str(args.data)!r} ({found})")
        load_metadata(Path(args.data).expanduser())  # a folder of something else: DatasetFormatError
    _checkpoint_file(args.ckpt)
    for folder in args.images or ():  # every folder, then every picture, before the model loads or anything is written
        _folder_pictures(Path(folder).expanduser(), folder)
    check_checkpoint(args.ckpt)
    for folder in args.images or ():
        _check_pictures(Path(folder).expanduser(), folder)
    check_output_folder(args.out)
    # 2. load the model and its image transform
    model = load_model(args.ckpt, args.model)
    dm = make_datamodule(args.ckpt, model, args.data)
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
    for result in results:
        sheet = None if args.no_sheets else _sheet(result, threshold, args.panel_size)
        files = export_prediction(
            args.out / result["name"],
            result["predicted"],
            threshold=threshold,
            mesh_format=args.mesh_format,
            sheet=sheet,
        )
        facts = prediction_facts(result["predicted"], result["target"], threshold)
        entries.append({"name": result["name"], "files": files, "facts": facts})
        print(
            f"{result['name']}: "
            + ", ".join(f"{k} {v:.4f}" if isinstance(v, float) else f"{k} {v}" for k, v in facts.items())
        )
    paths = write_summary(args.out, entries, title=f"lightning-vtr predict: {Path(args.ckpt).name}")
    print(f"Wrote {len(entries)} objects to {args.out}; open {paths['index']}")
    return 0
