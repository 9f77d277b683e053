"""Keep what a model predicts: binvox grids, OBJ / PLY meshes (marching cubes), PNG sheets and an HTML page.

:func:`export_prediction` writes one object's files; :func:`write_index_html` a page showing every object's
sheet; :class:`VoxelPredictionWriter` does both from ``Trainer.predict`` (and ``lightning-vtr predict``).
Grids are in the package's layout (``V[i, j, k]`` centred at ``((i + .5) / R - .5, ...)``, +Z up), so a
mesh lies in the object's cube ``[-0.5, 0.5]^3`` in the world frame of the dataset's meshes.
"""

from __future__ import annotations

import html
import io
import json
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Literal
from urllib.parse import quote

import numpy as np
import torch
import trimesh
from lightning.pytorch.callbacks import BasePredictionWriter
from PIL import Image

from lightning_vtr.data.binvox import write_binvox
from lightning_vtr.protocol import DEFAULT_THRESHOLD
from lightning_vtr.utils.io import atomic_write
from lightning_vtr.utils.paths import join_under
from lightning_vtr.utils.validation import check_choice, check_float, check_type
from lightning_vtr.visualize import as_voxel_grid

__all__ = [
    "MESH_FORMATS",
    "VoxelPredictionWriter",
    "describe_object",
    "export_binvox",
    "export_mesh",
    "export_prediction",
    "prediction_facts",
    "save_png",
    "voxels_to_mesh",
    "write_index_html",
    "write_summary",
]

MESH_FORMATS = ("obj", "ply", "stl", "off", "glb")
"""Mesh file formats :func:`export_mesh` writes (trimesh's exporters), by file suffix."""


def _binary(voxels: Any, threshold: float) -> np.ndarray:
    grid = as_voxel_grid(voxels)
    return grid if grid.dtype == np.bool_ else grid >= threshold


def voxels_to_mesh(voxels: Any, threshold: float = DEFAULT_THRESHOLD) -> trimesh.Trimesh:
    """The surface of a voxel grid by marching cubes, in world coordinates.

    A float grid of probabilities gives the iso-surface at ``threshold`` of the probabilities (smooth, and
    between cells above and below the threshold, so the cells inside are exactly ``voxels >= threshold``); a
    bool grid the iso-surface at 0.5 of its 0/1 values. The grid is padded by one empty cell so the surface is
    closed at the border. Vertex ``p`` (padded index) maps to ``(p - 0.5) / R - 0.5``: cell centres land on
    the package's voxel centres.

    Args:
        voxels: ``(R, R, R)`` occupancy probabilities in ``[0, 1]``, or a bool grid.
        threshold: the iso-level of a float grid (:data:`~lightning_vtr.protocol.DEFAULT_THRESHOLD`).

    Returns:
        a :class:`trimesh.Trimesh` (no faces when no cell reaches ``threshold``).

    Raises:
        TypeError: ``voxels`` is not a tensor or array, or ``threshold`` not a number.
        ValueError: ``voxels`` is not ``(R, R, R)`` with ``R >= 1``, or ``threshold`` is not in ``(0, 1)``.

    Example:
        >>> mesh = voxels_to_mesh(np.ones((2, 2, 2), dtype=bool))  # a full grid: its surface fills the cube
        >>> mesh.bounds.tolist(), mesh.is_watertight
        ([[-0.5, -0.5, -0.5], [0.5, 0.5, 0.5]], True)
        >>> len(voxels_to_mesh(np.zeros((2, 2, 2))).faces)
        0
    """
    from skimage.measure import marching_cubes

    threshold = check_float("threshold", threshold, minimum=0.0, maximum=1.0, min_open=True, max_open=True)
    grid = as_voxel_grid(voxels)
    if grid.dtype == np.bool_:
        values, level = grid.astype(np.float32), 0.5
    else:
        values, level = np.nan_to_num(grid.astype(np.float32)), threshold
    if not (values >= level).any():
        return trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), np.int64), process=False)
    verts, faces, _, _ = marching_cubes(np.pad(values, 1), level=level)
    vertices = (verts.astype(np.float64) - 0.5) / grid.shape[0] - 0.5
    # skimage winds the triangles clockwise seen from the low (empty) side; reversed, normals point outward
    # and a closed surface has a positive volume
    return trimesh.Trimesh(vertices, faces[:, ::-1], process=True)


def export_binvox(path: str | os.PathLike, voxels: Any, threshold: float = DEFAULT_THRESHOLD) -> Path:
    """Write ``voxels >= threshold`` (a bool grid as is) as a binvox file; returns the path.

    The file is written atomically by :func:`lightning_vtr.data.binvox.write_binvox` (``translate -0.5``,
    ``scale 1``, +Z up), so its voxel centres are those of :func:`lightning_vtr.geometry.voxel_centers`.

    Args:
        path: the file to write; its folder is created.
        voxels: ``(R, R, R)`` occupancy probabilities in ``[0, 1]`` (tensor or array), or a bool grid.
        threshold: a voxel with probability ``>= threshold`` is occupied (ignored for a bool grid).

    Returns:
        ``path`` as a :class:`~pathlib.Path`.

    Raises:
        TypeError: ``voxels`` is not a tensor or array, or ``threshold`` not a number.
        ValueError: ``voxels`` is not ``(R, R, R)`` with ``R >= 1``, or ``threshold`` is not in ``[0, 1]``.

    Example::

        export_binvox("predictions/chair.binvox", model.predict_voxels(images)[0])
    """
    threshold = check_float("threshold", threshold, minimum=0.0, maximum=1.0)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    write_binvox(path, _binary(voxels, threshold))
    return path


def export_mesh(path: str | os.PathLike, voxels: Any, threshold: float = DEFAULT_THRESHOLD) -> Path:
    """Write the marching-cubes surface of :func:`voxels_to_mesh` to ``path``; returns the path.

    The suffix picks the format (one of :data:`MESH_FORMATS`). An empty prediction writes a file with no faces.
    The file is written atomically.

    Args:
        path: the file to write, ending in ``.obj``, ``.ply``, ``.stl``, ``.off`` or ``.glb``; its folder is
            created.
        voxels: ``(R, R, R)`` occupancy probabilities in ``[0, 1]`` (tensor or array), or a bool grid.
        threshold: the iso-level of a float grid, in ``(0, 1)`` (ignored for a bool grid).

    Returns:
        ``path`` as a :class:`~pathlib.Path`; the mesh is in world units, inside ``[-0.5, 0.5]^3``.

    Raises:
        TypeError: ``voxels`` is not a tensor or array, or ``threshold`` not a number.
        ValueError: ``path`` has another suffix, ``voxels`` is not ``(R, R, R)`` with ``R >= 1``, or ``threshold``
            is not in ``(0, 1)``.

    Example::

        export_mesh("predictions/chair.ply", model.predict_voxels(images)[0], threshold=0.4)
    """
    path = Path(path)
    if path.suffix.lstrip(".").lower() not in MESH_FORMATS:
        raise ValueError(f"`path` must end in one of {', '.join('.' + f for f in MESH_FORMATS)}, got {path.name!r}")
    mesh = voxels_to_mesh(voxels, threshold)
    path.parent.mkdir(parents=True, exist_ok=True)
    data = mesh.export(file_type=path.suffix.lstrip(".").lower())
    atomic_write(path, data if isinstance(data, (bytes, str)) else bytes(data))
    return path


def save_png(path: str | os.PathLike, image: np.ndarray) -> Path:
    """Write an ``(H, W, 3)`` uint8 picture as PNG, atomically; returns the path.

    Args:
        path: the file to write; its folder is created.
        image: ``(H, W, 3)`` uint8 RGB picture.

    Returns:
        ``path`` as a :class:`~pathlib.Path`.

    Raises:
        ValueError: ``image`` is not an ``(H, W, 3)`` uint8 array.

    Example::

        from lightning_vtr.visualize import object_sheet

        save_png("predictions/chair/sheet.png", object_sheet(voxels, target))
    """
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[-1] != 3 or image.dtype != np.uint8:
        raise ValueError(f"`image` must be an (H, W, 3) uint8 array, got {image.shape} {image.dtype}")
    buffer = io.BytesIO()
    Image.fromarray(image).save(buffer, format="PNG")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(path, buffer.getvalue())
    return path


def export_prediction(
    directory: str | os.PathLike,
    voxels: Any,
    *,
    threshold: float = DEFAULT_THRESHOLD,
    mesh_format: str | None = "obj",
    sheet: np.ndarray | None = None,
    name: str = "prediction",
) -> dict[str, Path]:
    """Write one prediction: ``<name>.binvox``, ``<name>.<mesh_format>`` and, when given, ``sheet.png``.

    Args:
        directory: the object's folder (created).
        voxels: ``(R, R, R)`` occupancy probabilities, or a bool grid.
        threshold: binarisation threshold (and iso-level of the mesh).
        mesh_format: one of :data:`MESH_FORMATS`, or ``None`` for no mesh.
        sheet: an ``(H, W, 3)`` uint8 picture (e.g. :func:`lightning_vtr.visualize.object_sheet`).
        name: the stem of the voxel and mesh files.

    Returns:
        ``{"binvox": path, "mesh": path, "sheet": path}`` for the files written.

    Raises:
        TypeError: ``voxels`` is not a tensor or array, or ``threshold`` not a number.
        ValueError: ``voxels`` is not ``(R, R, R)``, ``threshold`` is not in ``[0, 1]`` (``(0, 1)`` with a mesh),
            an unknown ``mesh_format``, or a ``sheet`` that is not ``(H, W, 3)`` uint8.

    Example::

        paths = export_prediction("predictions/chair/1a2b", model.predict_voxels(images)[0], mesh_format="ply")
        paths["mesh"]  # Path('predictions/chair/1a2b/prediction.ply')
    """
    directory = Path(directory)
    # the files are replaced whole (utils.io), never written through a link an earlier output left there
    paths = {"binvox": export_binvox(join_under(directory, f"{name}.binvox", replace_link=True), voxels, threshold)}
    if mesh_format is not None:
        check_choice("mesh_format", mesh_format, MESH_FORMATS)
        paths["mesh"] = export_mesh(
            join_under(directory, f"{name}.{mesh_format}", replace_link=True), voxels, threshold
        )
    if sheet is not None:
        paths["sheet"] = save_png(directory / "sheet.png", sheet)
    return paths


_PAGE = """<!DOCTYPE html>
<html lang="en">
<head>
<meta charset="utf-8">
<title>{title}</title>
<style>
body {{ font-family: system-ui, sans-serif; margin: 1.5em; color: #222; }}
h1 {{ font-size: 1.3em; margin: 0 0 .3em; }}
p.summary {{ color: #555; margin: 0 0 1.2em; }}
section {{ display: inline-block; vertical-align: top; margin: 0 1.2em 1.6em 0; }}
h2 {{ font-size: 1em; margin: 0 0 .2em; }}
p.facts {{ font-size: .85em; color: #555; margin: 0 0 .4em; }}
img {{ border: 1px solid #ddd; max-width: 100%; }}
</style>
</head>
<body>
<h1>{title}</h1>
<p class="summary">{summary}</p>
{sections}
</body>
</html>
"""


def _link(path: str | Path, root: Path) -> str:
    relative = Path(os.path.relpath(Path(path), root)).as_posix()
    return quote(relative)


def write_index_html(
    directory: str | os.PathLike,
    entries: Sequence[Mapping[str, Any]],
    *,
    title: str = "lightning_vtr predictions",
    summary: str = "",
) -> Path:
    """Write ``<directory>/index.html``: every object's sheet with its facts and links to its files.

    Args:
        directory: where the page goes; the entries' files are linked relative to it.
        entries: one mapping per object: ``"name"`` (the heading), ``"files"`` (``{"sheet", "binvox", "mesh"}``
            paths, any missing) and ``"facts"`` (``{label: value}`` shown under the heading, e.g. IoU).
        title: the page title.
        summary: a line under the title.

    Returns:
        the page's path.

    Example::

        files = export_prediction("predictions/chair/1a2b", voxels, sheet=sheet)
        write_index_html("predictions", [{"name": "chair/1a2b", "files": files, "facts": {"IoU@0.4": 0.61}}])
    """
    root = Path(directory)
    sections = []
    for entry in entries:
        name = html.escape(str(entry["name"]))
        files = dict(entry.get("files", {}))
        facts = [f"{html.escape(str(k))}: {html.escape(_fact(v))}" for k, v in dict(entry.get("facts", {})).items()]
        links = [f'<a href="{_link(files[k], root)}">{k}</a>' for k in ("binvox", "mesh") if files.get(k)]
        lines = [f'<section id="{quote(str(entry["name"]), safe="")}">', f"<h2>{name}</h2>"]
        lines.append(f'<p class="facts">{" · ".join(facts + links)}</p>')
        if files.get("sheet"):
            lines.append(f'<img src="{_link(files["sheet"], root)}" alt="sheet of {name}" loading="lazy">')
        lines.append("</section>")
        sections.append("\n".join(lines))
    page = _PAGE.format(title=html.escape(title), summary=html.escape(summary), sections="\n".join(sections))
    path = root / "index.html"
    root.mkdir(parents=True, exist_ok=True)
    atomic_write(path, page)
    return path


def _fact(value: Any) -> str:
    return f"{value:.4f}" if isinstance(value, float) else str(value)


class VoxelPredictionWriter(BasePredictionWriter):
    """Write every prediction of ``Trainer.predict`` to disk: binvox, mesh, sheet, plus ``index.html`` and
    ``predictions.json`` listing them.

    The model's ``predict_step`` returns occupancy probabilities ``(B, R, R, R)`` (the package's models do;
    a dict with ``"voxels"`` works too). From the batch it reads ``images`` (for the sheet's input row),
    and, when present, ``voxels`` (ground truth: the sheet gets its error rows and the facts the IoU),
    ``viewpoints``, ``category``, ``object_id`` and ``view_set`` (the folder is
    ``<output_dir>/<view_set>/<category>/<object_id>``; without names ``object_<dataloader_idx>_<index>``).

    Args:
        output_dir: where to write.
        threshold: binarisation threshold (:data:`~lightning_vtr.protocol.DEFAULT_THRESHOLD`).
        mesh_format: one of :data:`MESH_FORMATS`, or ``None`` for no mesh.
        sheets: draw a sheet per object (:func:`lightning_vtr.visualize.object_sheet`; a few renders each).
        panel_size: side of a sheet's panels in pixels.

    Example::

        trainer = L.Trainer(callbacks=[VoxelPredictionWriter("predictions")])
        trainer.predict(model, dataloaders=loader, return_predictions=False)  # then open predictions/index.html
    """

    def __init__(
        self,
        output_dir: str | os.PathLike,
        threshold: float = DEFAULT_THRESHOLD,
        mesh_format: Literal["obj", "ply", "stl", "off", "glb"] | None = "obj",
        sheets: bool = True,
        panel_size: int = 128,
    ) -> None:
        super().__init__(write_interval="batch")
        self.output_dir = Path(output_dir)
        self.threshold = check_float("threshold", threshold, minimum=0.0, maximum=1.0, min_open=True, max_open=True)
        if mesh_format is not None:
            check_choice("mesh_format", mesh_format, MESH_FORMATS)
        self.mesh_format = mesh_format
        self.sheets = check_type("sheets", sheets, bool)
        self.panel_size = panel_size
        self.entries: list[dict[str, Any]] = []

    def on_predict_start(self, trainer: Any, pl_module: Any) -> None:
        self.entries = []

    def write_on_batch_end(
        self,
        trainer: Any,
        pl_module: Any,
        prediction: Any,
        batch_indices: Sequence[int] | None,
        batch: Any,
        batch_idx: int,
        dataloader_idx: int = 0,
    ) -> None:
        from lightning_vtr.visualize import object_sheet

        voxels = prediction["voxels"] if isinstance(prediction, Mapping) else prediction
        batch = batch if isinstance(batch, Mapping) else {"images": batch}
        normalize = getattr(getattr(getattr(trainer, "datamodule", None), "transform", None), "normalize", "auto")
        for i in range(len(voxels)):
            index = batch_indices[i] if batch_indices is not None and i < len(batch_indices) else len(self.entries)
            entry = describe_object(batch, i, index, dataloader_idx)
            target = batch["voxels"][i] if "voxels" in batch else None
            sheet = None
            if self.sheets:
                sheet = object_sheet(
                    voxels[i],
                    target,
                    batch["images"][i] if "images" in batch else None,
                    input_viewpoints=batch["viewpoints"][i].cpu() if "viewpoints" in batch else None,
                    threshold=self.threshold,
                    panel_size=self.panel_size,
                    normalize=normalize,
                    title=entry["name"],
                )
            entry["files"] = export_prediction(
                join_under(self.output_dir, entry["name"]),
                voxels[i],
                threshold=self.threshold,
                mesh_format=self.mesh_format,
                sheet=sheet,
            )
            entry["facts"] = prediction_facts(voxels[i], target, self.threshold)
            self.entries.append(entry)

    def on_predict_end(self, trainer: Any, pl_module: Any) -> None:
        entries = self.entries
        if torch.distributed.is_available() and torch.distributed.is_initialized() and trainer.world_size > 1:
            parts: list[Any] = [None] * trainer.world_size
            torch.distributed.all_gather_object(parts, entries)  # every rank wrote its own objects' files
            entries = sorted((e for part in parts for e in part), key=lambda e: e["name"])
        if trainer.is_global_zero:
            write_summary(self.output_dir, entries)


def describe_object(batch: Mapping[str, Any], i: int, index: int, dataloader_idx: int = 0) -> dict[str, Any]:
    """Name (``<view_set>/<category>/<object_id>``, or ``object_<dataloader_idx>_<index>``) of sample ``i`` of a batch.

    The name is also the sample's folder under the writer's output directory.

    Args:
        batch: the batch: a mapping whose ``"view_set"``, ``"category"`` and ``"object_id"`` entries, when
            present, are sequences of ``B`` names.
        i: position of the sample in the batch.
        index: the sample's index in its dataloader, used when the batch has no ``"object_id"``.
        dataloader_idx: index of the dataloader, used with ``index``.

    Returns:
        ``{"name": name}``: the names present joined with ``/``, or ``object_<dataloader_idx>_<index>`` (index
        padded to five digits) without an ``"object_id"``.

    Example:
        >>> describe_object({"category": ["chair"], "object_id": ["1a2b"]}, 0, 7)
        {'name': 'chair/1a2b'}
        >>> describe_object({"images": None}, 0, 7)
        {'name': 'object_0_00007'}
    """
    parts = [str(batch[key][i]) for key in ("view_set", "category", "object_id") if key in batch]
    name = "/".join(parts) if "object_id" in batch else f"object_{dataloader_idx}_{index:05d}"
    return {"name": name}


def prediction_facts(voxels: Any, target: Any | None, threshold: float) -> dict[str, Any]:
    """What the page and ``predictions.json`` say about a prediction: occupied voxels, and IoU with a target.

    Args:
        voxels: ``(R, R, R)`` predicted occupancy probabilities (tensor or array), or a bool grid.
        target: ``(R, R, R)`` ground truth in {0, 1} (binarised at 0.5; a bool grid as is), or ``None``.
        threshold: a predicted voxel with probability ``>= threshold`` is occupied.

    Returns:
        ``{"occupied voxels": int}`` and, with a ``target``, ``"true voxels"`` (int) and ``"IoU@<threshold>"``
        (float in ``[0, 1]``; 1.0 when both grids are empty).

    Raises:
        TypeError: ``voxels`` or ``target`` is not a tensor or array.
        ValueError: ``voxels`` or ``target`` is not ``(R, R, R)`` with ``R >= 1``.

    Example:
        >>> predicted = np.zeros((2, 2, 2))
        >>> predicted[0] = 0.9
        >>> truth = np.zeros((2, 2, 2), dtype=bool)
        >>> truth[:, 0] = True
        >>> prediction_facts(predicted, truth, 0.4)
        {'occupied voxels': 4, 'true voxels': 4, 'IoU@0.4': 0.3333333333333333}
    """
    occupied = _binary(voxels, threshold)
    facts: dict[str, Any] = {"occupied voxels": int(occupied.sum())}
    if target is not None:
        truth = _binary(target, 0.5)
        union = int((occupied | truth).sum())
        facts["true voxels"] = int(truth.sum())
        facts[f"IoU@{threshold:g}"] = float((occupied & truth).sum() / union) if union else 1.0
    return facts


def write_summary(directory: str | os.PathLike, entries: Sequence[Mapping[str, Any]], **page: Any) -> dict[str, Path]:
    """Write ``index.html`` (:func:`write_index_html`) and ``predictions.json`` for the exported objects.

    ``predictions.json`` lists every entry's name, facts and files (paths relative to ``directory``). The page's
    summary line defaults to the number of objects and, when their facts hold one, the mean IoU over those with
    ground truth.

    Args:
        directory: the output folder the entries' files lie under (created).
        entries: one mapping per object, as :func:`write_index_html` takes them: ``"name"``, ``"files"`` and
            ``"facts"``.
        **page: keyword arguments of :func:`write_index_html` (``title``, ``summary``).

    Returns:
        ``{"index": path of index.html, "summary": path of predictions.json}``.

    Example::

        entries = [{"name": "chair/1a2b", "files": export_prediction("predictions/chair/1a2b", voxels)}]
        write_summary("predictions", entries, title="Chairs")  # predictions/index.html, predictions/predictions.json
    """
    root = Path(directory)
    ious = {k: v for e in entries for k, v in e.get("facts", {}).items() if k.startswith("IoU@")}
    summary = f"{len(entries)} objects"
    if ious:
        key = next(iter(ious))
        values = [e["facts"][key] for e in entries if key in e.get("facts", {})]
        summary += f"; mean {key} {np.mean(values):.4f} over the {len(values)} with ground truth"
    page.setdefault("summary", summary)
    index = write_index_html(root, entries, **page)
    listing = [
        {
            "name": e["name"],
            "facts": dict(e.get("facts", {})),
            "files": {k: Path(os.path.relpath(v, root)).as_posix() for k, v in dict(e.get("files", {})).items()},
        }
        for e in entries
    ]
    summary_path = root / "predictions.json"
    atomic_write(summary_path, json.dumps(listing, indent=1))
    return {"index": index, "summary": summary_path}
