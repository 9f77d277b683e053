"""Views rendered once into the dataset and read during training: no OpenGL on the training machine.

:func:`prerender_views` renders, for every training object of a finished ShapeNet-VTR dataset, the candidate
viewpoints the selectors choose from (the bin centres of :func:`~lightning_vtr.geometry.candidate_viewpoints`,
``K = 30`` degrees by default: 72 views) with :class:`~lightning_vtr.synthesis.render.RenderSynthesizer` at the
dataset's image size, into the object's folder::

    <root>/prerendered.json                              # {"version", "interval", "image_size", "renderer"}
    <root>/objects/<category>/<object_id>/prerendered/
        index.json                                       # written last: {"version", "interval", "image_size",
                                                         #                "viewpoints": [[yaw, pitch], ...]}
        <yaw>_<pitch>.png                                # thousandths of a degree, e.g. -165000_-75000.png

:class:`PrerenderedSynthesizer` answers a request with the image of the nearest rendered viewpoint (the
smallest great-circle angle) and records that angle, the snap, per requested view. It imports no renderer, so it
runs where ``pyrender`` or ``libEGL`` is missing (many GPU clusters).
"""

from __future__ import annotations

import io
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from PIL import Image
from torch import Tensor
from tqdm.auto import tqdm

from lightning_vtr.errors import DataError
from lightning_vtr.geometry import angular_distance, candidate_viewpoints, check_bin_interval, check_viewpoints
from lightning_vtr.synthesis.base import SynthesisRequest, Synthesizer
from lightning_vtr.synthesis.cache import viewpoint_key

__all__ = [
    "DEFAULT_INTERVAL",
    "PRERENDERED_DIR",
    "PrerenderReport",
    "PrerenderedSynthesizer",
    "prerender_views",
    "prerendered_image_name",
    "read_prerendered_index",
]

#: The folder of an object's prerendered views, beside its view sets.
PRERENDERED_DIR = "prerendered"
#: The index of an object's prerendered views, written after its images.
INDEX_FILE = "index.json"
#: The dataset-wide record of the prerendering options (a second pass with other options is refused).
CONFIG_FILE = "prerendered.json"
#: The format version of ``index.json`` and ``prerendered.json``.
INDEX_VERSION = 1
#: The bin interval ``K`` (degrees) rendered by default: the selectors' default grid.
DEFAULT_INTERVAL = 30


def prerendered_image_name(viewpoint: Any) -> str:
    """The file name of the prerendered image at ``viewpoint``.

    Args:
        viewpoint: one (yaw, pitch) pair in degrees.

    Returns:
        ``"<yaw>_<pitch>.png"`` in integer thousandths of a degree (yaw wrapped, as
        :func:`~lightning_vtr.synthesis.cache.viewpoint_key` keys it).

    Example:
        >>> prerendered_image_name((-165.0, -75.0))
        '-165000_-75000.png'
    """
    return f"{viewpoint_key(viewpoint)}.png"


def read_prerendered_index(directory: str | os.PathLike) -> tuple[np.ndarray, list[Path], int]:
    """Read an object's ``prerendered/index.json``.

    Args:
        directory: the object's ``prerendered`` folder.

    Returns:
        ``(viewpoints (N, 2) float64 degrees, image paths in the same order, image size in pixels)``.

    Raises:
        FileNotFoundError: the folder has no ``index.json``.
        DataError: the index is not valid JSON of the documented fields (names the file).

    Example::

        viewpoints, paths, size = read_prerendered_index("data/objects/chair/chair_0001/prerendered")
    """
    from lightning_vtr.utils.limits import read_json

    path = Path(directory) / INDEX_FILE
    try:
        index = read_json(path)
    except FileNotFoundError:
        raise
    except (OSError, ValueError) as err:
        raise DataError(f"{path}: cannot read the prerendered index: {err}") from None
    try:
        viewpoints = np.asarray(index["viewpoints"], dtype=np.float64)
        size = index["image_size"]
    except (TypeError, KeyError, ValueError):
        raise DataError(f"{path}: expected {{'viewpoints': [[yaw, pitch], ...], 'image_size': int}}") from None
    if viewpoints.ndim != 2 or viewpoints.shape[1] != 2 or not len(viewpoints) or not np.isfinite(viewpoints).all():
        raise DataError(f"{path}: `viewpoints` must be a non-empty list of finite [yaw, pitch] pairs")
    if isinstance(size, bool) or not isinstance(size, int) or size < 1:
        raise DataError(f"{path}: `image_size` must be a positive integer, got {size!r}")
    return viewpoints, [Path(directory) / prerendered_image_name(vp) for vp in viewpoints], size


@dataclass
class PrerenderReport:
    """What a :func:`prerender_views` pass did.

    Attributes:
        root: the dataset directory.
        interval: the bin interval ``K`` rendered.
        views: views per object.
        rendered: ``"<category>/<object_id>"`` of the objects rendered in this pass.
        skipped: objects already complete (their ``index.json`` present), not redone.
        failed: key -> error message of the objects that failed in this pass.
        seconds: wall time of the pass.

    Example:
        >>> print(PrerenderReport(Path("data"), 30, 72, rendered=["chair/c0"]).summary())
        prerendered 1 objects (72 views each, K = 30), skipped 0 (already complete), failed 0 in 0.0 s
    """

    root: Path
    interval: int
    views: int
    rendered: list[str] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)
    failed: dict[str, str] = field(default_factory=dict)
    seconds: float = 0.0

    def summary(self) -> str:
        """One line per pass (and one per failed object)."""
        lines = [
            f"prerendered {len(self.rendered)} objects ({self.views} views each, K = {self.interval}), skipped "
            f"{len(self.skipped)} (already complete), failed {len(self.failed)} in {self.seconds:.1f} s"
        ]
        lines += [f"  FAILED {key}: {message}" for key, message in sorted(self.failed.items())]
        return "\n".join(lines)


def _check_config(root: Path, config: dict[str, Any]) -> None:
    from lightning_vtr.data.format import atomic_write_json
    from lightning_vtr.utils.limits import read_json

    path = root / CONFIG_FILE
    if path.is_file():
        old = read_json(path)
        old = old if isinstance(old, dict) else {}
        diff = ", ".join(f"{k}: {old.get(k)!r} on disk vs {v!r} now" for k, v in config.items() if old.get(k) != v)
        if diff:
            raise ValueError(
                f"{path} records prerendered views of other options ({diff}); pass the same options, or delete "
                "every objects/*/*/prerendered folder and that file to render them again"
            )
    else:
        atomic_write_json(path, config)


def prerender_views(
    root: str | os.PathLike,
    *,
    k: int = DEFAULT_INTERVAL,
    shard: tuple[int, int] = (0, 1),
    progress: bool = True,
) -> PrerenderReport:
    """Render the candidate viewpoints of every training object of a finished dataset into it.

    The views are :func:`~lightning_vtr.geometry.candidate_viewpoints` ``(k)`` (the bin centres the selectors
    choose from), rendered by :class:`~lightning_vtr.synthesis.render.RenderSynthesizer` at the dataset's image
    size, so each image equals what that synthesizer returns at its viewpoint. Like the build, it is resumable
    (``index.json`` is written after an object's images; objects that have it are skipped) and sharded
    (shard ``(i, n)`` renders training objects ``i, i + n, ...`` in ``metadata.json`` order); a failing object is
    reported and the pass goes on.

    Args:
        root: a finished ShapeNet-VTR dataset (with ``metadata.json``, hence its split) holding meshes.
        k: the bin interval ``K`` in degrees (divides 180): ``(180 / K) * (360 / K)`` views per object.
        shard: ``(i, n)``: this pass's share of the training objects.
        progress: show a progress bar.

    Returns:
        A :class:`PrerenderReport`.

    Raises:
        DatasetFormatError: ``root`` holds no finished dataset.
        ValueError: a bad ``k`` or ``shard``, or ``root`` was prerendered with another ``k`` or image size.

    Example::

        report = prerender_views("data/vtr-chairs", shard=(0, 4))  # one of four array jobs
        print(report.summary())
    """
    from lightning_vtr.data.format import load_metadata, scan_dataset
    from lightning_vtr.synthesis.render import RenderSynthesizer
    from lightning_vtr.utils.io import atomic_write, atomic_write_json
    from lightning_vtr.utils.validation import check_int

    k = check_bin_interval(k)
    index, count = shard
    check_int("shard[1]", count, minimum=1)
    check_int("shard[0]", index, minimum=0, maximum=count - 1)
    start = time.perf_counter()
    root = Path(root)
    size = int(load_metadata(root)["image_size"])
    renderer = RenderSynthesizer(image_size=size, max_cached_meshes=0)
    _check_config(
        root, {"version": INDEX_VERSION, "interval": k, "image_size": size, "renderer": renderer.config_key()}
    )
    grid = candidate_viewpoints(k).to(torch.float64)
    train = [r for r in scan_dataset(root) if r.split == "train"][index::count]
    report = PrerenderReport(root, k, len(grid))
    for record in tqdm(train, desc=f"prerendering {root.name}", unit="obj", disable=not progress, dynamic_ncols=True):
        directory = record.voxel_path.parent / PRERENDERED_DIR
        if (directory / INDEX_FILE).is_file():
            report.skipped.append(record.key)
            continue
        try:
            if record.mesh_path is None:
                raise ValueError(f"{record.voxel_path.parent} has no mesh.ply to render")
            request = SynthesisRequest(
                record.object_id, record.category, np.zeros((0, size, size, 4), np.uint8), torch.zeros(0, 2), grid,
                mesh_path=record.mesh_path,
            )  # fmt: skip
            images = renderer.synthesize([request])[0]
            directory.mkdir(parents=True, exist_ok=True)
            for viewpoint, image in zip(grid, images):
                buffer = io.BytesIO()
                Image.fromarray(np.asarray(image, np.uint8), mode="RGBA").save(buffer, format="PNG")
                atomic_write(directory / prerendered_image_name(viewpoint), buffer.getvalue())
            atomic_write_json(
                directory / INDEX_FILE,
                {"version": INDEX_VERSION, "interval": k, "image_size": size, "viewpoints": grid.tolist()},
            )
            report.rendered.append(record.key)
        except Exception as err:  # reported per object, as the build does
            report.failed[record.key] = f"{type(err).__name__}: {err}"
    report.seconds = time.perf_counter() - start
    return report


def _build_hint(root: Path | None) -> str:
    target = str(root) if root is not None else "ROOT"
    return f"build them with `lightning-vtr build-dataset {target} --prerender-views` (on a machine with OpenGL)"


class PrerenderedSynthesizer(Synthesizer):
    """Serves each requested view with the object's prerendered image at the nearest rendered viewpoint.

    The views come from :func:`prerender_views` (``lightning-vtr build-dataset ROOT --prerender-views``); this
    class reads PNG files only and imports no renderer, so training runs without OpenGL. A requested viewpoint
    is snapped to the rendered one at the smallest great-circle angle (:func:`~lightning_vtr.geometry.angular_distance`;
    the first in grid order on a tie); the snap angles in degrees are kept per request in
    :attr:`last_snap_angles` (the latest :meth:`synthesize` call) and accumulated until :meth:`pop_snap_angles`
    (the callback logs their mean as ``vtr/snap_angle_mean`` after every round). With the default ``K = 30``
    grid the selectors' views, drawn around bin centres with ``sigma = K / 6``, snap by about 6 degrees on
    average; a random viewpoint by at most about 21.

    Args:
        root: the dataset directory; ``None``: each object's folder is the one holding its mesh
            (``SynthesisRequest.mesh_path``, as the datamodule's records give it), so a config needs no path.

    Raises:
        DataError: at setup (:meth:`check_serves`) or at synthesis, an object without prerendered views (one
            line naming the object, the dataset and the command that builds them), or an unreadable index.

    Attributes:
        last_snap_angles: one ``(T_i,)`` float64 array of snap angles (degrees) per request of the latest call.

    Example::

        synthesizer = PrerenderedSynthesizer()  # or PrerenderedSynthesizer("data/vtr-chairs")
        callback = ErrorGuidedViewAugmentation(synthesizer=synthesizer)
        images = synthesizer.synthesize([request])  # [(T, S, S, 4) uint8] at the dataset's image size S
        synthesizer.last_snap_angles[0]  # (T,) degrees between each requested and served viewpoint
    """

    needs_source_images = False

    def __init__(self, root: str | Path | None = None) -> None:
        self.root = None if root is None else Path(root)
        self.image_size = 0  # the dataset's, once an index is read
        self.last_snap_angles: list[np.ndarray] = []
        self._pending: list[np.ndarray] = []
        self._indexes: dict[Path, tuple[Tensor, list[Path], int]] = {}

    def __repr__(self) -> str:
        return f"PrerenderedSynthesizer(root={None if self.root is None else str(self.root)!r})"

    def config_key(self) -> str:
        return "PrerenderedSynthesizer"

    def _locate(self, category: str, object_id: str, mesh_path: Any) -> tuple[Path, Path | None]:
        """``(the object's prerendered folder, the dataset root)``."""
        from lightning_vtr.utils.paths import join_under

        if self.root is not None:
            return join_under(self.root, "objects", category, object_id, PRERENDERED_DIR), self.root
        if mesh_path is None:
            raise DataError(
                f"PrerenderedSynthesizer cannot find the folder of {category}/{object_id}: the request has no "
                "mesh_path; pass the dataset directory, PrerenderedSynthesizer(root=...)"
            )
        folder = Path(mesh_path).parent
        return folder / PRERENDERED_DIR, folder.parents[2] if len(folder.parents) > 2 else None

    def _index(self, category: str, object_id: str, mesh_path: Any) -> tuple[Tensor, list[Path], int]:
        directory, root = self._locate(category, object_id, mesh_path)
        if directory not in self._indexes:
            try:
                viewpoints, paths, size = read_prerendered_index(directory)
            except FileNotFoundError:
                raise DataError(
                    f"object {category}/{object_id} of dataset {root} has no prerendered views "
                    f"({directory / INDEX_FILE} does not exist); {_build_hint(root)}"
                ) from None
            self._indexes[directory] = (torch.as_tensor(viewpoints), paths, size)
        return self._indexes[directory]

    def check_serves(self, records: Sequence[Any], *, view_set: str | None = None) -> None:
        """Refuse, before training, training objects without prerendered views (``index.json``); the one-line
        message names how many, the first object, the dataset and the command that builds them."""
        lacking = []
        for record in records:
            directory, root = self._locate(record.category, record.object_id, getattr(record, "mesh_path", None))
            if not (directory / INDEX_FILE).is_file():
                lacking.append((record, root))
        if lacking:
            (first, root) = lacking[0]
            raise DataError(
                f"PrerenderedSynthesizer: {len(lacking)} of {len(records)} training objects have no prerendered "
                f"views (first: object {first.category}/{first.object_id} of dataset {root}); {_build_hint(root)}"
            )

    def snap(self, request: SynthesisRequest) -> tuple[list[Path], np.ndarray]:
        """The prerendered images serving ``request`` and the snap angles, without reading the images.

        Args:
            request: the request (its ``category``, ``object_id``, ``mesh_path`` and ``target_viewpoints``).

        Returns:
            ``(one image path per target viewpoint, (T,) float64 great-circle angles in degrees between each
            target and the rendered viewpoint it snapped to)``.

        Raises:
            DataError: the object has no prerendered views.

        Example::

            paths, angles = synthesizer.snap(request)
        """
        grid, paths, _ = self._index(request.category, request.object_id, request.mesh_path)
        targets = check_viewpoints(torch.as_tensor(request.target_viewpoints), "target_viewpoints").reshape(-1, 2)
        if not len(targets):
            return [], np.zeros(0)
        angles = angular_distance(targets.to(torch.float64)[:, None, :], grid[None, :, :])  # (T, N)
        best = angles.argmin(dim=1)
        return [paths[int(i)] for i in best], angles.gather(1, best[:, None])[:, 0].numpy()

    def synthesize(self, requests: list[SynthesisRequest]) -> list[np.ndarray]:
        """One ``(T_i, S, S, 4)`` uint8 array per request (``S``: the dataset's image size); see the class."""
        from lightning_vtr.data.dataset import load_rgba

        out, snaps = [], []
        for request in requests:
            paths, angles = self.snap(request)
            _, _, size = self._index(request.category, request.object_id, request.mesh_path)
            self.image_size = size
            images = [load_rgba(path, size) for path in paths]
            for path, image in zip(paths, images):
                if image.shape != (size, size, 4):
                    raise DataError(
                        f"{path}: prerendered image of the wrong size (expected {size}x{size}, got "
                        f"{image.shape[1]}x{image.shape[0]})"
                    )
            out.append(np.stack(images) if images else np.zeros((0, size, size, 4), np.uint8))
            snaps.append(angles)
        self.last_snap_angles = snaps
        self._pending.extend(snaps)
        return out

    def pop_snap_angles(self) -> np.ndarray:
        """Every snap angle (degrees) since the last call, in request order, and forget them.

        Returns:
            A ``(n,)`` float64 array (empty when nothing was synthesized).

        Example::

            angles = synthesizer.pop_snap_angles()
            print(f"mean snap {angles.mean():.1f} degrees")
        """
        angles = np.concatenate(self._pending) if self._pending else np.zeros(0)
        self._pending = []
        return angles
