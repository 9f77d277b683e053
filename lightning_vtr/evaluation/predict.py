"""Predicting with a trained model: image folders or a dataset split in, voxels, meshes and sheets out.

An image folder is one object: every picture in it (a file ending in one of
:data:`~lightning_vtr.data.format.IMAGE_SUFFIXES`, any case; any count and any size) is one view. RGBA pictures
are used as they are; an RGB picture gets its alpha from ``<stem>_mask.<ext>`` beside it when there is one, else
from a background key colour (pixels that colour, within a tolerance, are background), else it is used whole.
Pictures are padded to squares. A ``*.binvox`` file in the folder is the ground truth (+Z up, as this package
writes them).

:func:`make_datamodule` gives the image transform the model was trained with (from the checkpoint's
datamodule hyperparameters); :func:`predict_folders` and :func:`predict_dataset` yield one result per object;
:func:`export_predictions` writes each one's ``prediction.binvox``, mesh and sheet (:func:`prediction_sheet`)::

    from lightning_vtr.export import write_summary
    from lightning_vtr.models import load_model

    model = load_model("last.ckpt")
    transform = make_datamodule("last.ckpt", model).transform
    results = predict_folders(model, ["photos/chair"], transform)
    entries = list(export_predictions("predictions", results, threshold=0.4))
    write_summary("predictions", entries, title="chairs")
"""

from __future__ import annotations

import warnings
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from PIL import Image, UnidentifiedImageError

from lightning_vtr import export
from lightning_vtr.data.binvox import read_binvox
from lightning_vtr.data.datamodule import VTRDataModule
from lightning_vtr.data.dataset import VTRDataset, load_rgba
from lightning_vtr.data.format import IMAGE_SUFFIXES
from lightning_vtr.errors import DataError
from lightning_vtr.models.registry import checkpoint_hyperparameters
from lightning_vtr.renderer import composite
from lightning_vtr.selection.error_guided import ErrorGuidedSelector
from lightning_vtr.utils.paths import join_under
from lightning_vtr.visualize import object_sheet

__all__ = [
    "CHECKPOINT_DATA_SETTINGS",
    "check_view_folder",
    "checkpoint_data_settings",
    "export_predictions",
    "make_datamodule",
    "predict_dataset",
    "predict_folders",
    "prediction_sheet",
    "read_view_folder",
    "resolve_device",
    "view_folder_pictures",
]

_MASK_SUFFIX = "_mask"


# ----------------------------------------------------------------------------------------- the model's inputs
def make_datamodule(ckpt: str | Path, model: Any, root: str | Path | None = None) -> VTRDataModule:
    """A :class:`~lightning_vtr.data.VTRDataModule` over ``root`` that prepares images as the model was trained.

    It takes the checkpoint's datamodule settings (image recipe, normalisation, background colour, seed, view
    sets; see :func:`checkpoint_data_settings`) and the model's image size and number of views. A checkpoint
    never widens what is read from disk: folders it names (a ``"folder:PATH"`` background, ``generated_dir``, a
    dataset) are not used.

    Args:
        ckpt: the checkpoint the model came from; a checkpoint without datamodule hyperparameters warns and
            gets ``VTRDataModule``'s defaults.
        model: the loaded model (its ``image_size`` and ``num_views`` are used).
        root: a ShapeNet-VTR directory, or ``None`` when only the transform is wanted.

    Returns:
        The datamodule; its ``transform`` is the evaluation transform the model was validated with.

    Raises:
        FileNotFoundError: ``ckpt`` does not exist.

    Example::

        transform = make_datamodule("last.ckpt", model).transform  # RGBA uint8 (S, S, 4) -> (3, H, W)
    """
    _, stored = checkpoint_hyperparameters(Path(ckpt).expanduser())
    if not stored:
        warnings.warn(
            f"the checkpoint {str(ckpt)!r} holds no datamodule hyperparameters; images are prepared with "
            "VTRDataModule's defaults (white background, ImageNet normalisation), which may not be the model's",
            stacklevel=2,
        )
    kwargs = checkpoint_data_settings(stored)
    kwargs.update(image_size=int(model.image_size), num_views=int(model.num_views), test_repeats=1)
    return VTRDataModule(None if root is None else str(root), **kwargs)


#: The datamodule settings a checkpoint may set for prediction: how images are prepared and which views and
#: objects are served. Paths (``root``, ``generated_dir``, a background folder), build options and the loader's
#: worker processes come from the caller only.
CHECKPOINT_DATA_SETTINGS = (
    "background",
    "normalize",
    "background_range",
    "recipe",
    "seed",
    "test_view_sets",
    "categories",
    "train_view_set",
    "test_split",
)


def checkpoint_data_settings(stored: dict[str, Any]) -> dict[str, Any]:
    """The datamodule settings of :data:`CHECKPOINT_DATA_SETTINGS` in a checkpoint's datamodule hyperparameters,
    with every folder dropped: a ``"folder:PATH"`` background becomes the plain colour, a recipe's
    ``background_folder`` is removed (both touch training views only, so the evaluation transform is the same).

    Args:
        stored: the checkpoint's datamodule hyperparameters (untrusted).

    Returns:
        Keyword arguments of :class:`~lightning_vtr.data.VTRDataModule`.

    Example:
        >>> checkpoint_data_settings({"background": "folder:/", "generated_dir": "/", "normalize": "pm1"})
        {'normalize': 'pm1'}
    """
    kwargs = {k: v for k, v in stored.items() if k in CHECKPOINT_DATA_SETTINGS}
    if isinstance(kwargs.get("background"), str):  # "folder:PATH": its crops are training backgrounds only
        del kwargs["background"]
        kwargs.pop("background_range", None)
    recipe = kwargs.get("recipe")
    if isinstance(recipe, dict) and recipe.get("background_folder") is not None:
        kwargs["recipe"] = {**recipe, "background_folder": None}
    return kwargs


# --------------------------------------------------------------------------------------------- image folders
def _alpha_from_key(rgb: np.ndarray, key: Sequence[int], tolerance: int) -> np.ndarray:
    distance = np.abs(rgb.astype(np.int16) - np.asarray(key, np.int16)).max(axis=-1)
    return np.where(distance <= tolerance, 0, 255).astype(np.uint8)


def _square(rgba: np.ndarray) -> np.ndarray:
    """Pad an ``(H, W, 4)`` picture with transparent pixels to a centred square."""

    h, w = rgba.shape[:2]
    side = max(h, w)
    out = np.zeros((side, side, 4), np.uint8)
    top, left = (side - h) // 2, (side - w) // 2
    out[top : top + h, left : left + w] = rgba
    return out


def view_folder_pictures(folder: Path, given: str | Path) -> tuple[dict[str, Path], list[Path]]:
    """The pictures of an image folder, listed (none is opened).

    Args:
        folder: the image folder.
        given: the folder as the user named it, quoted in the message.

    Returns:
        ``(mask files by view stem, view files)``, sorted by name.

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

    from lightning_vtr.utils.limits import open_image

    try:
        image = open_image(path)  # its header's size checked before decoding (a small file may expand)
        image.load()
    except DataError as err:
        raise DataError(f"`--images`: {err}") from None
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


#: Pictures larger than this per side are scaled down (aspect kept) as they are read: the model sees a few hundred
#: pixels, and a full-size picture of thousands of pixels a side would take gigabytes on its way there.
WORKING_SIDE = 1024


def _working_copy(image: Any) -> Any:
    """``image`` scaled down to at most :data:`WORKING_SIDE` per side (box filter), else itself."""
    from PIL import Image

    if max(image.size) <= WORKING_SIDE:
        return image
    scale = WORKING_SIDE / max(image.size)
    size = (max(1, round(image.size[0] * scale)), max(1, round(image.size[1] * scale)))
    return image.resize(size, Image.Resampling.BOX)


def check_view_folder(folder: Path, given: str | Path) -> None:
    """Open every picture and mask of an image folder once (before the model loads or anything is written).

    Args:
        folder: the image folder.
        given: the folder as the user named it, quoted in the messages.

    Raises:
        FileNotFoundError: not a folder, or no picture in it.
        DataError: a file PIL cannot read as a picture (names the file).
    """
    masks, views = view_folder_pictures(folder, given)
    for path in [*views, *masks.values()]:
        _open_picture(path).close()


def read_view_folder(
    directory: str | Path, *, background_key: Sequence[int] | None = None, key_tolerance: int = 12
) -> tuple[list[np.ndarray], list[str], np.ndarray | None]:
    """One object's views from a folder, as square RGBA pictures (see the module docstring).

    Args:
        directory: the image folder.
        background_key: ``(R, G, B)`` of the background of RGB pictures without a mask, or ``None``.
        key_tolerance: the largest channel difference from ``background_key`` still background.

    Returns:
        ``(pictures, names, ground_truth)``: one ``(S_i, S_i, 4)`` uint8 picture per view (sizes may differ),
        the file names, and the folder's ``*.binvox`` grid ``(R, R, R)`` bool or ``None``.

    Raises:
        FileNotFoundError: not a folder, or no picture in it (the message names the folder and the suffixes).
        DataError: a file that is not a picture, a mask of another size than its picture, or more than one
            binvox file (a ``ValueError``).

    Example::

        pictures, names, truth = read_view_folder("photos/chair", background_key=(255, 255, 255))
    """

    folder = Path(directory).expanduser()
    masks, views = view_folder_pictures(folder, directory)
    pictures = []
    for path in views:
        with _open_picture(path) as image:
            has_alpha = image.mode in ("RGBA", "LA", "PA") or (image.mode == "P" and "transparency" in image.info)
            size = image.size
            rgba = np.asarray(_working_copy(image.convert("RGBA"))).copy()
        if path.stem in masks:
            with _open_picture(masks[path.stem]) as mask_image:
                if mask_image.size != size:
                    raise DataError(
                        f"the mask {masks[path.stem].name!r} must have the size of {path.name!r} "
                        f"({size[0]}x{size[1]}), got {mask_image.size[0]}x{mask_image.size[1]}"
                    )
                mask = np.asarray(_working_copy(mask_image.convert("L")))
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
def resolve_device(name: str | torch.device) -> torch.device:
    """The torch device ``name`` stands for: ``"auto"`` is CUDA when available, else the CPU.

    Args:
        name: ``"auto"``, or any name ``torch.device`` takes (``"cpu"``, ``"cuda:0"``, ...).

    Returns:
        The device.

    Example:
        >>> resolve_device("cpu")
        device(type='cpu')
    """
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


def _predict(model: Any, images: torch.Tensor, device: torch.device) -> torch.Tensor:
    with torch.no_grad():
        return model.predict_voxels(images.to(device)).float().cpu()


def predict_folders(
    model: Any, folders: Sequence[str | Path], transform: Any, *, device: str = "auto", **read: Any
) -> Iterator[dict[str, Any]]:
    """Predict each image folder (one object each; one forward pass per folder, as view counts differ).

    Args:
        model: a reconstruction model (moved to ``device``).
        folders: image folders (:func:`read_view_folder`).
        transform: RGBA uint8 ``(S, S, 4)`` picture -> ``(3, H, W)`` model input (:func:`make_datamodule`).
        device: ``"auto"`` or a torch device name (:func:`resolve_device`).
        **read: ``background_key`` / ``key_tolerance`` of :func:`read_view_folder`.

    Yields:
        ``{"name", "display" (V, S, S, 4) uint8 list, "images" (V, 3, H, W), "predicted" (R, R, R),
        "target" (R, R, R) or None, "viewpoints" None, "view_names"}`` per folder; names are the folder names,
        made unique; ``view_names`` are the pictures' file names.

    Raises:
        FileNotFoundError: a folder is not a folder, or holds no picture.
        DataError: a file that is not a picture, a mask of another size than its picture, more than one binvox
            file, or a ground truth whose shape is not the prediction's.

    Example::

        transform = make_datamodule("last.ckpt", model).transform
        for result in predict_folders(model, ["photos/chair", "photos/lamp"], transform, device="cpu"):
            print(result["name"], tuple(result["predicted"].shape))  # chair (32, 32, 32), then lamp ...
    """
    dev = resolve_device(device)
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
    """Predict a split of a ShapeNet-VTR dataset, each object from ``dm.num_views`` fixed views per view set.

    The views are those ``trainer.test`` sees (:class:`~lightning_vtr.data.dataset.VTRDataset` over the whole
    split with the datamodule's seed), whichever objects ``limit`` keeps.

    Args:
        model: a reconstruction model (moved to ``device``).
        dm: the datamodule over the dataset (:func:`make_datamodule` with a ``root``).
        split: ``"train"``, ``"val"`` or ``"test"``.
        view_sets: the view sets to predict (default: every one the dataset has).
        limit: at most this many objects per view set, taken round-robin over categories.
        batch_size: objects per forward pass.
        device: ``"auto"`` or a torch device name (:func:`resolve_device`).

    Yields:
        Per view set and object, the dicts of :func:`predict_folders` with ``name``
        ``<view_set>/<category>/<object_id>``, ``target`` the ``(R, R, R)`` ground truth, ``viewpoints`` the
        views' ``(V, 2)`` (yaw, pitch) in degrees and ``category`` (no ``view_names``).

    Raises:
        ValueError: the split holds no objects, or a view set the dataset does not have.

    Example::

        dm = make_datamodule("last.ckpt", model, root="data/shapenet-vtr")
        results = predict_dataset(model, dm, view_sets=["spherical"], limit=10)
        entries = list(export_predictions("predictions", results, threshold=0.4))
    """

    dev = resolve_device(device)
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
                    "display": [
                        load_rgba(paths[j], records[i].image_size, root=records[i].root)
                        for j in dataset.view_indices(i)
                    ],
                    "images": item["images"],
                    "predicted": pred,
                    "target": item["voxels"],
                    "viewpoints": item["viewpoints"],
                    "category": item["category"],
                }


def prediction_sheet(result: dict[str, Any], threshold: float, panel_size: int) -> np.ndarray:
    """One object's sheet: input views | prediction | ground truth | error | error projection at the views
    error-guided selection picks (the last three only with a ground truth).

    Args:
        result: a dict :func:`predict_folders` or :func:`predict_dataset` yields.
        threshold: the occupancy threshold, in ``(0, 1)``.
        panel_size: the panel side in pixels.

    Returns:
        The sheet, ``(H, W, 3)`` uint8 (:func:`lightning_vtr.visualize.object_sheet`).
    """
    selected = None
    if result["target"] is not None:
        generator = torch.Generator().manual_seed(0)
        selected = ErrorGuidedSelector.paper().select(
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
    return np.asarray(Image.fromarray(composite(rgba)).resize((size, size), Image.BILINEAR))  # type: ignore[attr-defined]  # PIL sets the alias at runtime


# --------------------------------------------------------------------------------------------- exporting
def export_predictions(
    out: str | Path,
    results: Iterable[dict[str, Any]],
    *,
    threshold: float = 0.4,
    mesh_format: str = "obj",
    sheets: bool = True,
    panel_size: int = 128,
) -> Iterator[dict[str, Any]]:
    """Export each result into ``out/<name>/``: ``prediction.binvox``, a mesh and (``sheets``) ``sheet.png``.

    Args:
        out: the output folder.
        results: the dicts :func:`predict_folders` or :func:`predict_dataset` yield.
        threshold: the occupancy threshold of the exports, in ``(0, 1)``.
        mesh_format: one of :data:`lightning_vtr.export.MESH_FORMATS`.
        sheets: also render each object's sheet (:func:`prediction_sheet`).
        panel_size: the sheet's panel side in pixels.

    Yields:
        ``{"name", "files", "facts"}`` per object, once its files are written: the entries
        :func:`lightning_vtr.export.write_summary` takes; ``facts`` are
        :func:`lightning_vtr.export.prediction_facts`.

    Raises:
        TypeError: ``threshold`` is not a number.
        ValueError: ``threshold`` is out of range or ``mesh_format`` unknown (see
            :func:`lightning_vtr.export.export_prediction`).

    Example::

        entries = list(export_predictions("predictions", predict_folders(model, folders, transform)))
    """
    out = Path(out)
    for result in results:
        sheet = prediction_sheet(result, threshold, panel_size) if sheets else None
        files = export.export_prediction(
            join_under(out, result["name"]),
            result["predicted"],
            threshold=threshold,
            mesh_format=mesh_format,
            sheet=sheet,
        )
        facts = export.prediction_facts(result["predicted"], result["target"], threshold)
        yield {"name": result["name"], "files": files, "facts": facts}
