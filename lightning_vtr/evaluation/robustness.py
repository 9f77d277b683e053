"""The viewpoint robustness map: a model's IoU on view sets drawn around every bin of the selection grid.

:func:`robustness_map` measures, for each object and each bin of the ``K``-degree (yaw, pitch) grid the
error-guided selector scores (:func:`~lightning_vtr.geometry.candidate_viewpoints`, pitch-major), the model's
IoU at :data:`~lightning_vtr.protocol.DEFAULT_THRESHOLD` when it is given ``views_per_set`` views drawn around
that bin's centre, exactly as the selector draws its views there
(:func:`~lightning_vtr.selection.projection.sample_around_bins`: ``N(centre, K / 6)`` in yaw and pitch, yaw
wrapped, pitch clamped). The result, a :class:`RobustnessMap`, answers where on the sphere a model fails: per
bin, per category, with confidence intervals over objects, and writes itself as CSV.

Angles are in degrees; bin areas are fractions of the whole sphere (they sum to 1).
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from scipy import stats
from torch import Tensor

from lightning_vtr.geometry import candidate_viewpoints, check_bin_interval
from lightning_vtr.metrics.functional import voxel_iou
from lightning_vtr.protocol import DEFAULT_THRESHOLD
from lightning_vtr.selection.diversity import bin_solid_angles
from lightning_vtr.selection.projection import sample_around_bins
from lightning_vtr.utils.validation import check_float, check_int, check_probabilities

__all__ = ["RobustnessMap", "bin_area_fractions", "read_bins_csv", "robustness_map", "view_sets_around_bins"]

#: The files :meth:`RobustnessMap.to_csv` writes into its directory.
BINS_FILE = "bins.csv"
OBJECTS_FILE = "objects.csv"
META_FILE = "robustness.json"

_BINS_HEADER = ("category", "bin", "yaw", "pitch", "area", "mean_iou", "ci_low", "ci_high", "objects")


def bin_area_fractions(k: int = 30) -> np.ndarray:
    """Fraction of the sphere each bin of interval ``K`` covers, ``(180/K * 360/K,)`` float64, pitch-major.

    Args:
        k: bin interval in degrees (divides 180).

    Returns:
        The bins' solid angles over ``4 pi``; they sum to 1, and bins near the poles are the smallest.

    Raises:
        ValueError: ``k`` does not divide 180.

    Example:
        >>> float(bin_area_fractions(90).sum())
        1.0
    """
    return (bin_solid_angles(k) / (4.0 * math.pi)).numpy()


def _object_generator(seed: int, category: str, object_id: str) -> torch.Generator:
    # keyed by the object, not its position: a map of a subset draws the same views for the objects it keeps
    key = zlib.crc32(f"{category}/{object_id}".encode())
    return torch.Generator().manual_seed(int(seed) * 4_294_967_311 + key)


def view_sets_around_bins(
    k: int, views_per_set: int, sets_per_bin: int, generator: torch.Generator | None = None
) -> Tensor:
    """View sets ``(bins, sets_per_bin, views_per_set, 2)`` (degrees) drawn around every bin centre.

    Each view is drawn as :class:`~lightning_vtr.selection.error_guided.ErrorGuidedSelector` draws one around a
    chosen bin (:func:`~lightning_vtr.selection.projection.sample_around_bins`, ``sigma = K / 6``); the bins are
    in :func:`~lightning_vtr.geometry.candidate_viewpoints` order.

    Args:
        k: bin interval in degrees (divides 180).
        views_per_set: views per set (the model's number of input views).
        sets_per_bin: sets drawn around each bin.
        generator: the random source (``None``: torch's global one).

    Returns:
        float32 ``(180/K * 360/K, sets_per_bin, views_per_set, 2)`` (yaw in ``[-180, 180)``, pitch in ``[-90, 90]``).

    Raises:
        ValueError: a bad ``k`` or a count below 1.

    Example:
        >>> view_sets_around_bins(60, 3, 2, torch.Generator().manual_seed(0)).shape
        torch.Size([18, 2, 3, 2])
    """
    k = check_bin_interval(k)
    views_per_set = check_int("views_per_set", views_per_set, minimum=1)
    sets_per_bin = check_int("sets_per_bin", sets_per_bin, minimum=1)
    n_bins = (180 // k) * (360 // k)
    bins = torch.arange(n_bins)[:, None, None].expand(n_bins, sets_per_bin, views_per_set)
    return sample_around_bins(bins, k, generator=generator).to(torch.float32)


def _t_interval(values: np.ndarray, confidence: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Column means of ``values (n, B)`` and their two-sided Student-t interval (``nan`` for ``n < 2``)."""
    n = values.shape[0]
    mean = values.mean(axis=0) if n else np.full(values.shape[1], np.nan)
    if n < 2:
        nan = np.full(values.shape[1], np.nan)
        return mean, nan, nan
    half = stats.t.ppf((1 + confidence) / 2, n - 1) * values.std(axis=0, ddof=1) / math.sqrt(n)
    return mean, mean - half, mean + half


@dataclass
class RobustnessMap:
    """A model's IoU per object and per viewpoint bin, with what is needed to read and plot it.

    Attributes:
        iou: ``(objects, bins)`` float64 IoU at ``threshold``, each the mean over ``sets_per_bin`` view sets.
        centres: ``(bins, 2)`` bin centres (yaw, pitch) in degrees, pitch-major as
            :func:`~lightning_vtr.geometry.candidate_viewpoints`.
        areas: ``(bins,)`` fraction of the sphere each bin covers (sums to 1).
        object_ids: ``objects`` object ids.
        categories: ``objects`` category names.
        k: bin interval in degrees.
        threshold: occupancy threshold of the IoU.
        views_per_set: views per set given to the model.
        sets_per_bin: view sets per bin and object.
        seed: the seed the view sets were drawn with.
        aligned_pitch: the elevation of the dataset's Aligned views (degrees; the median pitch of the objects'
            ``aligned`` view set), ``None`` when unknown.
        extra: free-form JSON-serialisable notes (the model's name, a checkpoint path), kept by the CSV files.

    Raises:
        ValueError: a bad ``k``, or ``iou``, ``centres``, ``areas``, ``object_ids`` or ``categories`` whose shapes
            do not fit ``k`` and each other.

    Example:
        >>> m = RobustnessMap.from_iou(np.full((2, 18), 0.5), k=60, object_ids=["a", "b"], categories=["c", "c"])
        >>> m.mean().shape, float(m.overall())
        ((18,), 0.5)
    """

    iou: np.ndarray
    centres: np.ndarray
    areas: np.ndarray
    object_ids: list[str]
    categories: list[str]
    k: int
    threshold: float = DEFAULT_THRESHOLD
    views_per_set: int = 3
    sets_per_bin: int = 1
    seed: int = 0
    aligned_pitch: float | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.iou = np.asarray(self.iou, dtype=np.float64)
        self.centres = np.asarray(self.centres, dtype=np.float64)
        self.areas = np.asarray(self.areas, dtype=np.float64)
        self.object_ids = [str(o) for o in self.object_ids]
        self.categories = [str(c) for c in self.categories]
        self.k = check_bin_interval(self.k)
        n_bins = (180 // self.k) * (360 // self.k)
        if self.iou.ndim != 2 or self.iou.shape[1] != n_bins:
            raise ValueError(f"`iou` must have shape (objects, {n_bins}) for K = {self.k}, got {self.iou.shape}")
        if self.centres.shape != (n_bins, 2) or self.areas.shape != (n_bins,):
            raise ValueError(
                f"`centres` and `areas` must have shapes ({n_bins}, 2) and ({n_bins},), got "
                f"{self.centres.shape} and {self.areas.shape}"
            )
        if len(self.object_ids) != self.iou.shape[0] or len(self.categories) != self.iou.shape[0]:
            raise ValueError(
                f"`object_ids` and `categories` must name the {self.iou.shape[0]} objects of `iou`, got "
                f"{len(self.object_ids)} and {len(self.categories)}"
            )

    @classmethod
    def from_iou(
        cls, iou: np.ndarray, *, k: int, object_ids: Sequence[str], categories: Sequence[str], **kwargs: Any
    ) -> RobustnessMap:
        """A map of ``iou (objects, bins)`` on the grid of interval ``k`` (centres and areas filled in).

        Args:
            iou: per-object per-bin IoU.
            k: bin interval in degrees.
            object_ids: one id per object.
            categories: one category per object.
            **kwargs: the other attributes (``threshold``, ``aligned_pitch``, ...).

        Raises:
            ValueError: shapes that do not match the grid of ``k`` or the number of objects.
        """
        k = check_bin_interval(k)
        return cls(
            iou=iou,
            centres=candidate_viewpoints(k).double().numpy(),
            areas=bin_area_fractions(k),
            object_ids=list(object_ids),
            categories=list(categories),
            k=k,
            **kwargs,
        )

    @property
    def num_objects(self) -> int:
        """Number of objects (rows of :attr:`iou`)."""
        return int(self.iou.shape[0])

    @property
    def num_bins(self) -> int:
        """Number of bins (columns of :attr:`iou`)."""
        return int(self.iou.shape[1])

    def category_names(self) -> list[str]:
        """The categories of the map's objects, sorted."""
        return sorted(set(self.categories))

    def _rows(self, category: str | None) -> np.ndarray:
        if category is None:
            return self.iou
        rows = [i for i, c in enumerate(self.categories) if c == category]
        if not rows:
            raise KeyError(f"The map has no object of category {category!r}; it has {self.category_names()}")
        return self.iou[rows]

    def subset(self, category: str) -> RobustnessMap:
        """The map of one category's objects only.

        Raises:
            KeyError: no object of ``category``.
        """
        rows = [i for i, c in enumerate(self.categories) if c == category]
        if not rows:
            raise KeyError(f"The map has no object of category {category!r}; it has {self.category_names()}")
        return RobustnessMap(
            iou=self.iou[rows],
            centres=self.centres,
            areas=self.areas,
            object_ids=[self.object_ids[i] for i in rows],
            categories=[self.categories[i] for i in rows],
            k=self.k,
            threshold=self.threshold,
            views_per_set=self.views_per_set,
            sets_per_bin=self.sets_per_bin,
            seed=self.seed,
            aligned_pitch=self.aligned_pitch,
            extra=dict(self.extra),
        )

    def mean(self, category: str | None = None) -> np.ndarray:
        """Per-bin mean IoU ``(bins,)`` over the objects (of ``category`` only, when given).

        Raises:
            KeyError: no object of ``category``.
        """
        return self._rows(category).mean(axis=0)

    def confidence_interval(
        self, category: str | None = None, confidence: float = 0.95
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per-bin ``(mean, low, high)``, each ``(bins,)``: the mean over objects and its Student-t interval.

        ``half width = t_{(1 + confidence) / 2, n - 1} s / sqrt(n)`` with ``s`` the sample standard deviation
        over the ``n`` objects; ``low`` and ``high`` are ``nan`` with a single object.

        Args:
            category: only the objects of this category (``None``: all).
            confidence: the interval's coverage, in ``(0, 1)``.

        Raises:
            KeyError: no object of ``category``.
            ValueError: ``confidence`` outside ``(0, 1)``.

        Example:
            >>> m = RobustnessMap.from_iou(np.array([[0.2] * 18, [0.4] * 18]), k=60, object_ids="ab", categories="cc")
            >>> mean, low, high = m.confidence_interval()
            >>> round(float(mean[0]), 3), round(float(high[0] - mean[0]), 3)  # t_{0.975, 1} = 12.706; s / sqrt(2) = 0.1
            (0.3, 1.271)
        """
        confidence = check_float("confidence", confidence, minimum=0.0, maximum=1.0, min_open=True, max_open=True)
        return _t_interval(self._rows(category), confidence)

    def overall(self, category: str | None = None) -> float:
        """Area-weighted mean IoU over the sphere (a view direction drawn uniformly on the sphere).

        Raises:
            KeyError: no object of ``category``.
        """
        return float((self.mean(category) * self.areas).sum() / self.areas.sum())

    def bin_rows(self, category: str | None = None, confidence: float = 0.95) -> list[dict[str, Any]]:
        """One dict per bin with the columns of ``bins.csv`` (``category`` ``"all"`` for every object)."""
        mean, low, high = self.confidence_interval(category, confidence)
        n = self._rows(category).shape[0]
        name = "all" if category is None else category
        return [
            {
                "category": name,
                "bin": b,
                "yaw": float(self.centres[b, 0]),
                "pitch": float(self.centres[b, 1]),
                "area": float(self.areas[b]),
                "mean_iou": float(mean[b]),
                "ci_low": float(low[b]),
                "ci_high": float(high[b]),
                "objects": n,
            }
            for b in range(self.num_bins)
        ]

    def to_csv(self, path: str | Path, *, per_category: bool = False, confidence: float = 0.95) -> Path:
        """Write the map into the directory ``path``; returns the path of ``bins.csv``.

        Files:

        * ``bins.csv``: one row per bin over all objects (``category`` ``all``), then, with ``per_category``,
          one row per bin and category; columns ``category, bin, yaw, pitch, area, mean_iou, ci_low, ci_high,
          objects`` (degrees, sphere fraction, IoU, Student-t ``confidence`` interval over the objects, their count).
        * ``objects.csv``: the per-object IoU, one row per object (``category, object_id``, then one column per bin).
        * ``robustness.json``: ``k``, ``threshold``, ``views_per_set``, ``sets_per_bin``, ``seed``, ``aligned_pitch``.

        :meth:`from_csv` reads the directory back into an equal map.

        Args:
            path: the output directory (created if missing).
            per_category: also write one block of rows per category into ``bins.csv``.
            confidence: coverage of the interval columns.

        Example::

            robustness_map(model, dm).to_csv("runs/robustness")  # runs/robustness/bins.csv, objects.csv, ...
        """
        from lightning_vtr.utils.io import atomic_write_json, write_csv

        out = Path(path)
        out.mkdir(parents=True, exist_ok=True)
        rows = self.bin_rows(None, confidence)
        if per_category:
            for category in self.category_names():
                rows += self.bin_rows(category, confidence)
        write_csv(out / BINS_FILE, rows, _BINS_HEADER)
        write_csv(
            out / OBJECTS_FILE,
            ([c, o, *map(float, values)] for c, o, values in zip(self.categories, self.object_ids, self.iou)),
            ["category", "object_id", *[f"bin_{b}" for b in range(self.num_bins)]],
        )
        meta = {
            "k": self.k,
            "threshold": self.threshold,
            "views_per_set": self.views_per_set,
            "sets_per_bin": self.sets_per_bin,
            "seed": self.seed,
            "aligned_pitch": self.aligned_pitch,
            "extra": self.extra,
        }
        atomic_write_json(out / META_FILE, meta)  # written last: it marks a complete map
        return out / BINS_FILE

    @classmethod
    def from_csv(cls, path: str | Path) -> RobustnessMap:
        """Read a map :meth:`to_csv` wrote into the directory ``path``.

        Raises:
            FileNotFoundError: ``objects.csv`` or ``robustness.json`` is missing.
            ValueError: the files disagree with each other (another number of bins than ``k`` gives).
        """
        import csv

        from lightning_vtr.utils.io import uncsv_cell
        from lightning_vtr.utils.limits import read_json

        directory = Path(path)
        meta = read_json(directory / META_FILE)
        with open(directory / OBJECTS_FILE, newline="") as f:
            reader = csv.reader(f)
            next(reader)
            rows = [[uncsv_cell(row[0]), uncsv_cell(row[1]), *row[2:]] for row in reader]
        iou = np.array([[float(v) for v in row[2:]] for row in rows], dtype=np.float64)
        n_bins = (180 // int(meta["k"])) * (360 // int(meta["k"]))
        iou = iou.reshape(len(rows), n_bins) if rows else np.zeros((0, n_bins))
        return cls.from_iou(
            iou,
            k=int(meta["k"]),
            object_ids=[row[1] for row in rows],
            categories=[row[0] for row in rows],
            threshold=float(meta["threshold"]),
            views_per_set=int(meta["views_per_set"]),
            sets_per_bin=int(meta["sets_per_bin"]),
            seed=int(meta["seed"]),
            aligned_pitch=meta.get("aligned_pitch"),
            extra=dict(meta.get("extra") or {}),
        )


def read_bins_csv(path: str | Path) -> list[dict[str, Any]]:
    """The rows of a ``bins.csv`` (:meth:`RobustnessMap.to_csv`) with numbers parsed (``bin``/``objects`` int).

    Args:
        path: the ``bins.csv`` file.

    Returns:
        One dict per row, in file order: ``category`` (str), ``bin`` and ``objects`` (int), ``yaw``, ``pitch``
        (degrees), ``area`` (sphere fraction), ``mean_iou``, ``ci_low`` and ``ci_high`` (float).

    Raises:
        FileNotFoundError: ``path`` does not exist.
        KeyError: a column of :meth:`RobustnessMap.to_csv` is missing.
        ValueError: a value is not a number.

    Example:
        >>> import tempfile
        >>> m = RobustnessMap.from_iou(np.full((2, 18), 0.5), k=60, object_ids=["a", "b"], categories=["c", "c"])
        >>> with tempfile.TemporaryDirectory() as directory:
        ...     rows = read_bins_csv(m.to_csv(directory))
        >>> first = rows[0]
        >>> len(rows), first["category"], first["bin"], first["mean_iou"], first["objects"]
        (18, 'all', 0, 0.5, 2)
    """
    import csv

    from lightning_vtr.utils.io import uncsv_cell

    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    parsed = []
    for row in rows:
        item: dict[str, Any] = {"category": uncsv_cell(row["category"])}
        for key in _BINS_HEADER[1:]:
            item[key] = int(row[key]) if key in ("bin", "objects") else float(row[key])
        parsed.append(item)
    return parsed


# ---------------------------------------------------------------------------------------------- measurement
def _model_device(model: Any) -> torch.device:
    try:
        return next(model.parameters()).device
    except (AttributeError, StopIteration, TypeError):
        return torch.device("cpu")


def _records_and_transform(objects: Any, split: str, model: Any) -> tuple[list[Any], Any, Any]:
    """``(records, transform, voxel loader)`` of a datamodule (its ``split``) or of a sequence of records."""
    from lightning_vtr.data.dataset import load_voxels

    if hasattr(objects, "split_records"):
        records = list(objects.split_records(split))
        loader = getattr(objects, "object_voxels", load_voxels)
        return records, objects.transform, loader
    records = list(objects)
    from lightning_vtr.data.transforms import ImageTransform

    return records, ImageTransform(int(model.image_size)), load_voxels


def _aligned_pitch(records: Sequence[Any]) -> float | None:
    pitches = [
        np.asarray(r.views["aligned"][1], dtype=np.float64)[:, 1]
        for r in records
        if "aligned" in (getattr(r, "views", None) or {}) and len(r.views["aligned"][1])
    ]
    return float(np.median(np.concatenate(pitches))) if pitches else None


def robustness_map(
    model: Any,
    objects: Any,
    *,
    k: int = 30,
    views_per_set: int | None = None,
    sets_per_bin: int = 1,
    seed: int = 0,
    synthesizer: Any = None,
    transform: Any = None,
    split: str = "test",
    source_view_set: str = "aligned",
    batch_size: int = 64,
    objects_per_call: int = 4,
    threshold: float = DEFAULT_THRESHOLD,
    overlap: bool = True,
    progress: bool = True,
) -> RobustnessMap:
    """Measure a model's IoU on view sets drawn around every bin of the ``K``-degree grid, per object.

    For each object, :func:`view_sets_around_bins` draws ``sets_per_bin`` sets of ``views_per_set`` viewpoints
    around each bin centre from a generator keyed by ``(seed, category, object_id)`` (so an object gets the same
    views whatever else is measured with it). ``objects_per_call`` objects at a time are rendered in one
    ``synthesizer.synthesize`` call (every view of every set), transformed, and predicted from in batches of
    ``batch_size`` sets under :func:`torch.inference_mode` with the model in eval mode (its mode is restored
    afterwards), in a worker thread while the next objects render (``overlap``); each prediction's IoU at
    ``threshold`` against the object's voxels is averaged over its bin's sets.

    Args:
        model: a :class:`~lightning_vtr.protocol.ReconstructionModel` (``predict_voxels``, ``image_size``,
            ``num_views``, ``voxel_resolution``).
        objects: a datamodule with ``split_records`` and ``transform`` (its ``split`` objects, its evaluation
            transform), or a sequence of :class:`~lightning_vtr.data.format.ObjectRecord` (transformed with
            ``ImageTransform(model.image_size)``).
        k: bin interval in degrees (divides 180); 30 gives 72 bins.
        views_per_set: views per set; ``None``: ``model.num_views``.
        sets_per_bin: view sets per bin and object (more sets, less noise, proportionally more time).
        seed: seeds the view sets.
        synthesizer: a :class:`~lightning_vtr.synthesis.base.Synthesizer`; ``None``:
            ``RenderSynthesizer(image_size=model.image_size)`` (objects need meshes).
        transform: turns ``(T, H, W, 4)`` uint8 RGBA images into model input ``(T, 3, h, w)``; ``None``: the
            datamodule's ``transform`` (or ``ImageTransform(model.image_size)`` for records).
        split: the datamodule split measured.
        source_view_set: the view set whose images a synthesizer that needs source images is given.
        batch_size: view sets per ``predict_voxels`` call.
        objects_per_call: objects per synthesizer call.
        threshold: occupancy threshold of the IoU.
        overlap: predict a chunk in a worker thread while the next one renders (same result; ``False``: one
            thread does both in turn).
        progress: show a tqdm bar over the objects.

    Returns:
        A :class:`RobustnessMap` with ``iou (objects, 180/K * 360/K)``.

    Raises:
        ValueError: no objects, a bad argument, or a model output that is not ``(N, R, R, R)`` probabilities
            matching the objects' voxel grids.

    Example::

        dm = VTRDataModule("data/vtr", image_size=64)
        rmap = robustness_map(model, dm, k=30, seed=0)
        rmap.to_csv("runs/robustness")
    """
    from tqdm.auto import tqdm

    from lightning_vtr.synthesis.base import SynthesisRequest

    k = check_bin_interval(k)
    views_per_set = check_int(
        "views_per_set", int(model.num_views) if views_per_set is None else views_per_set, minimum=1
    )
    sets_per_bin = check_int("sets_per_bin", sets_per_bin, minimum=1)
    batch_size = check_int("batch_size", batch_size, minimum=1)
    objects_per_call = check_int("objects_per_call", objects_per_call, minimum=1)
    threshold = check_float("threshold", threshold, minimum=0.0, maximum=1.0)
    records, default_transform, load_target = _records_and_transform(objects, split, model)
    transform = default_transform if transform is None else transform
    if not records:
        raise ValueError("`objects` must hold at least one object to measure, got none")
    if synthesizer is None:
        from lightning_vtr.synthesis.render import RenderSynthesizer

        synthesizer = RenderSynthesizer(image_size=int(model.image_size))
    n_bins = (180 // k) * (360 // k)
    per_object = n_bins * sets_per_bin
    device = _model_device(model)
    iou = np.zeros((len(records), n_bins), dtype=np.float64)
    was_training = bool(getattr(model, "training", False))
    if hasattr(model, "eval"):
        model.eval()
    bar = tqdm(total=len(records), desc=f"Robustness map (K = {k})", disable=not progress, leave=False)

    def predict_chunk(images: list[np.ndarray], targets: Tensor, start: int) -> tuple[int, np.ndarray]:
        """IoU ``(objects of the chunk, bins)`` of one rendered chunk (runs in the prediction thread)."""
        inputs = torch.cat([torch.as_tensor(transform(np.asarray(img))) for img in images])
        inputs = inputs.reshape(len(images) * per_object, views_per_set, *inputs.shape[1:])
        scores = []
        with torch.inference_mode():  # thread-local: entered in the thread that predicts
            for lo in range(0, inputs.shape[0], batch_size):
                batch = inputs[lo : lo + batch_size].to(device)
                pred = model.predict_voxels(batch)
                target = targets[torch.arange(lo, lo + batch.shape[0]) // per_object]
                if not isinstance(pred, Tensor) or tuple(pred.shape) != tuple(target.shape):
                    found = tuple(pred.shape) if isinstance(pred, Tensor) else type(pred).__name__
                    raise ValueError(
                        f"`{type(model).__name__}.predict_voxels` must return occupancy probabilities of shape "
                        f"{tuple(target.shape)} (the objects' voxel grids) for images {tuple(batch.shape)}, "
                        f"got {found}"
                    )
                pred = check_probabilities("predict_voxels", pred.detach().float().cpu())
                scores.append(voxel_iou(pred, target, thresholds=(threshold,))[:, 0])
        per_set = torch.cat(scores).double().reshape(len(images), n_bins, sets_per_bin)
        return start, per_set.mean(-1).numpy()

    def _store(result: tuple[int, np.ndarray]) -> None:
        first, values = result
        iou[first : first + len(values)] = values
        bar.update(len(values))

    # Rendering stays in this thread (a GL context is bound to the thread that made it current); the model
    # predicts the previous chunk in a worker thread meanwhile. One worker: the model sees its calls in order.
    executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="robustness-predict") if overlap else None
    pending: Future | None = None
    try:
        for start in range(0, len(records), objects_per_call):
            chunk = records[start : start + objects_per_call]
            requests = []
            for rec in chunk:
                sets = view_sets_around_bins(
                    k, views_per_set, sets_per_bin, _object_generator(seed, rec.category, rec.object_id)
                )
                if getattr(synthesizer, "needs_source_images", False):
                    paths, src_vp = rec.views[source_view_set]
                    from lightning_vtr.data.dataset import load_rgba

                    source = np.stack([load_rgba(p, root=getattr(rec, "root", None)) for p in paths])
                else:
                    _, src_vp = (getattr(rec, "views", None) or {}).get(source_view_set, ([], np.zeros((0, 2))))
                    source = np.zeros((0, 0, 0, 4), np.uint8)
                requests.append(
                    SynthesisRequest(
                        object_id=rec.object_id,
                        category=rec.category,
                        source_images=source,
                        source_viewpoints=torch.as_tensor(np.asarray(src_vp, dtype=np.float32).reshape(-1, 2)),
                        target_viewpoints=sets.reshape(-1, 2),
                        mesh_path=getattr(rec, "mesh_path", None),
                    )
                )
            images = synthesizer.synthesize(requests)
            if len(images) != len(chunk) or any(len(img) != per_object * views_per_set for img in images):
                raise ValueError(
                    f"The synthesizer returned {[len(img) for img in images]} images for {len(chunk)} objects of "
                    f"{per_object * views_per_set} views each"
                )
            targets = torch.stack([torch.as_tensor(load_target(rec)).float() for rec in chunk])
            if pending is not None:  # at most one chunk waits for the model: memory stays bounded
                _store(pending.result())
            args = (images, targets, start)
            pending = executor.submit(predict_chunk, *args) if executor is not None else None
            if executor is None:
                _store(predict_chunk(*args))
        if pending is not None:
            _store(pending.result())
    finally:
        if executor is not None:
            executor.shutdown(wait=True, cancel_futures=True)
        bar.close()
        if hasattr(model, "train"):
            model.train(was_training)
    return RobustnessMap.from_iou(
        iou,
        k=k,
        object_ids=[r.object_id for r in records],
        categories=[r.category for r in records],
        threshold=threshold,
        views_per_set=views_per_set,
        sets_per_bin=sets_per_bin,
        seed=int(seed),
        aligned_pitch=_aligned_pitch(records),
    )
