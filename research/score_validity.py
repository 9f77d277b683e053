"""The score-validity study: does a view score point at the views where the model actually fails?

For each object, every score :class:`lightning_vtr.selection.ErrorGuidedSelector` can select with (``paper``,
``released``, ``visible`` and the research score ``input``) rates every bin of the viewpoint grid
(:func:`selection_scores`); the robustness map (:func:`lightning_vtr.evaluation.robustness_map`) measures the
model's true loss ``1 - IoU`` there. Two measures of agreement, both per object and then summarised over objects:

* :func:`spearman_per_object`: Spearman's rank correlation between an object's scores and its losses (tied
  values get their average rank), summarised by :func:`mean_with_interval` (a Student-t 95 % interval).
* :func:`top_hit_rate`: the fraction of the score's top ``n`` bins (3: the views the selector keeps) that are
  among the object's truly worst ``fraction`` (10 %) of bins, next to the rate uniformly random distinct picks
  would get, computed exactly (:func:`chance_hit_rate`). Ties are resolved in expectation: a score tied at its
  ``n``-th place contributes each tied bin with the probability a random tie-break would pick it, so a constant
  score gets exactly the chance rate. With ``truth="category"`` the worst bins are those of the object's
  category mean loss map, the views the category as a whole is bad at.

Bins count equally (a random pick is a uniformly random bin, not an area-uniform viewpoint).
:func:`validity_table` puts both into a Markdown table; run as a script, it measures each checkpoint's map and
writes ``OUT/score_validity.md``::

    python -m research.score_validity --ckpt "None-VTR=runs/none/last.ckpt" --ckpt "VTR=runs/vtr/last.ckpt" \\
        --data embedded --split test --k 30 --objects 64 --out runs/score_validity
"""

from __future__ import annotations

import argparse
import math
import zlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from scipy import stats
from torch import Tensor

from lightning_vtr.evaluation import RobustnessMap
from lightning_vtr.geometry import check_bin_interval
from lightning_vtr.protocol import DEFAULT_THRESHOLD
from lightning_vtr.selection import ErrorGuidedSelector, SelectionContext
from lightning_vtr.utils.validation import check_choice, check_float, check_int, check_probabilities
from research.scores import InputScore

__all__ = [
    "OBJECT_SCORES",
    "Summary",
    "bce_per_object",
    "category_mean_loss",
    "chance_hit_rate",
    "format_validity_table",
    "main",
    "mean_with_interval",
    "selection_scores",
    "spearman_per_object",
    "top_hit_rate",
    "validity_rows",
    "validity_table",
    "worst_bins",
]

#: The scores computed for one object alone from its prediction (and, for ``"input"``, its rendered views).
OBJECT_SCORES: tuple[str, ...] = ("paper", "released", "visible", "input")


def _pair(scores: np.ndarray, loss: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    scores = np.asarray(scores, dtype=np.float64)
    loss = np.asarray(loss, dtype=np.float64)
    if scores.ndim != 2 or scores.shape != loss.shape:
        raise ValueError(
            f"`scores` and `loss` must both have shape (objects, bins), got {scores.shape} and {loss.shape}"
        )
    if not (np.isfinite(scores).all() and np.isfinite(loss).all()):
        raise ValueError("`scores` and `loss` must hold finite numbers only")
    return scores, loss


@dataclass(frozen=True)
class Summary:
    """A mean over objects with its two-sided Student-t interval.

    Attributes:
        mean: the mean (``nan`` over no objects).
        low: lower end of the interval (``nan`` with fewer than 2 values).
        high: upper end of the interval.
        n: the number of values averaged.
    """

    mean: float
    low: float
    high: float
    n: int

    def format(self, digits: int = 3) -> str:
        """``"0.412 [0.371, 0.453]"`` (the interval left out when it is undefined)."""
        if not math.isfinite(self.low):
            return f"{self.mean:.{digits}f}"
        return f"{self.mean:.{digits}f} [{self.low:.{digits}f}, {self.high:.{digits}f}]"


def mean_with_interval(values: Sequence[float] | np.ndarray, confidence: float = 0.95) -> Summary:
    """Mean of the finite ``values`` with a Student-t interval: ``t_{(1+c)/2, n-1} s / sqrt(n)`` half width.

    Args:
        values: per-object values; ``nan`` entries (an undefined correlation) are left out.
        confidence: coverage of the interval, in ``(0, 1)``.

    Returns:
        A :class:`Summary`; its ``n`` counts the finite values.

    Raises:
        TypeError: ``confidence`` is not a number.
        ValueError: ``confidence`` is outside ``(0, 1)``.

    Example:
        >>> s = mean_with_interval([0.2, 0.4])
        >>> round(s.mean, 3), round(s.high - s.mean, 3)
        (0.3, 1.271)
    """
    confidence = check_float("confidence", confidence, minimum=0.0, maximum=1.0, min_open=True, max_open=True)
    arr = np.asarray(values, dtype=np.float64).reshape(-1)
    arr = arr[np.isfinite(arr)]
    n = int(arr.size)
    if n == 0:
        return Summary(math.nan, math.nan, math.nan, 0)
    mean = float(arr.mean())
    if n < 2:
        return Summary(mean, math.nan, math.nan, n)
    half = float(stats.t.ppf((1 + confidence) / 2, n - 1)) * float(arr.std(ddof=1)) / math.sqrt(n)
    return Summary(mean, mean - half, mean + half, n)


def spearman_per_object(scores: np.ndarray, loss: np.ndarray) -> np.ndarray:
    """Spearman's rank correlation of each object's scores with its losses, ``(objects,)``.

    Tied values get their average rank (the Pearson correlation of the average ranks); an object whose scores or
    losses are all equal has no ranking and gets ``nan``.

    Args:
        scores: ``(objects, bins)`` selection scores (higher: the score expects more error).
        loss: ``(objects, bins)`` measured loss, e.g. ``1 - IoU`` of a robustness map.

    Returns:
        ``(objects,)`` float64 correlations in ``[-1, 1]`` (``nan`` for an object without a ranking).

    Raises:
        ValueError: shapes that differ or are not 2-D, or non-finite values.

    Example:
        >>> spearman_per_object(np.array([[1.0, 1.0, 2.0, 3.0]]), np.array([[1.0, 2.0, 3.0, 4.0]])).round(4)
        array([0.9487])
    """
    scores, loss = _pair(scores, loss)
    rs = stats.rankdata(scores, axis=1)
    rl = stats.rankdata(loss, axis=1)
    rs -= rs.mean(axis=1, keepdims=True)
    rl -= rl.mean(axis=1, keepdims=True)
    denom = np.sqrt((rs**2).sum(axis=1) * (rl**2).sum(axis=1))
    with np.errstate(invalid="ignore", divide="ignore"):
        rho = (rs * rl).sum(axis=1) / denom
    return np.where(denom > 0, rho, np.nan)


def worst_bins(loss: np.ndarray, fraction: float = 0.1) -> np.ndarray:
    """Boolean ``(objects, bins)``: each row's truly worst ``fraction`` of bins.

    The worst ``m = ceil(fraction * bins)`` bins (8 of the 72 bins at K = 30), and every bin tied with the
    ``m``-th worst loss (so a tie never decides membership arbitrarily).

    Args:
        loss: ``(objects, bins)`` loss (or a 1-D ``(bins,)`` row).
        fraction: the share of bins, in ``(0, 1]``.

    Raises:
        ValueError: ``fraction`` outside ``(0, 1]``.

    Example:
        >>> worst_bins(np.array([[0.1, 0.9, 0.5, 0.9]]), 0.25)
        array([[False,  True, False,  True]])
    """
    fraction = check_float("fraction", fraction, minimum=0.0, maximum=1.0, min_open=True)
    loss = np.atleast_2d(np.asarray(loss, dtype=np.float64))
    m = max(1, math.ceil(fraction * loss.shape[1] - 1e-9))
    cutoff = -np.sort(-loss, axis=1)[:, m - 1 : m]
    return loss >= cutoff


def chance_hit_rate(truth: np.ndarray, n: int = 3) -> np.ndarray:
    """Expected top-``n`` hit rate ``(objects,)`` of ``n`` distinct bins drawn uniformly at random.

    Each drawn bin lies in an object's worst set with probability ``|worst| / bins``, so the expected fraction of
    hits is exactly ``|worst| / bins`` whatever ``n`` (linearity of expectation).

    Args:
        truth: boolean ``(objects, bins)`` worst-bin sets (:func:`worst_bins`).
        n: picks per object (does not change the expectation; checked against ``bins``).

    Example:
        >>> chance_hit_rate(np.array([[True, False, False, False]]))
        array([0.25])
    """
    truth = np.atleast_2d(np.asarray(truth, dtype=bool))
    check_int("n", n, minimum=1, maximum=truth.shape[1])
    return truth.mean(axis=1)


def _expected_top_hits(scores: np.ndarray, truth: np.ndarray, n: int) -> np.ndarray:
    """Expected number of the top-``n`` scored bins in ``truth`` per row, ties at the cut broken at random."""
    cutoff = -np.sort(-scores, axis=1)[:, n - 1 : n]
    above = scores > cutoff
    tied = scores == cutoff
    slots = n - above.sum(axis=1)
    hits_above = (above & truth).sum(axis=1)
    hits_tied = (tied & truth).sum(axis=1)
    return hits_above + slots * hits_tied / tied.sum(axis=1)


def category_mean_loss(loss: np.ndarray, categories: Sequence[str]) -> np.ndarray:
    """``(objects, bins)``: each object's row replaced by the mean loss map of its category.

    Raises:
        ValueError: not one category per row.
    """
    loss = np.asarray(loss, dtype=np.float64)
    if len(categories) != loss.shape[0]:
        raise ValueError(f"`categories` must name one category per object, got {len(categories)} for {loss.shape[0]}")
    out = np.empty_like(loss)
    names = np.asarray(list(categories), dtype=object)
    for name in set(categories):
        rows = names == name
        out[rows] = loss[rows].mean(axis=0)
    return out


def top_hit_rate(
    scores: np.ndarray,
    loss: np.ndarray,
    *,
    n: int = 3,
    fraction: float = 0.1,
    categories: Sequence[str] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Per-object top-``n`` hit rate of a score and the rate uniformly random picks would get.

    The hit rate of an object is the (expected, over random tie-breaks at the ``n``-th place) fraction of its
    ``n`` best-scored bins that are among its worst ``fraction`` of bins by ``loss`` (:func:`worst_bins`). With
    ``categories``, the worst bins are those of the object's category mean loss (:func:`category_mean_loss`).

    Args:
        scores: ``(objects, bins)`` selection scores (higher: more expected error).
        loss: ``(objects, bins)`` measured loss (``1 - IoU``).
        n: bins the selector keeps (3).
        fraction: share of bins that counts as the worst (0.1).
        categories: one category per object for category-level truth; ``None``: each object's own losses.

    Returns:
        ``(hit_rate (objects,), chance (objects,))`` in ``[0, 1]``; the largest reachable rate of an object is
        ``min(n, |worst|) / n``.

    Raises:
        ValueError: shapes that differ, non-finite values, ``n`` outside ``[1, bins]`` or a bad ``fraction``.

    Example:
        >>> loss = np.array([[0.0, 0.1, 0.2, 0.9, 0.8, 0.7, 0.3, 0.4, 0.5, 0.6]])
        >>> top_hit_rate(loss, loss, n=3, fraction=0.3)
        (array([1.]), array([0.3]))
    """
    scores, loss = _pair(scores, loss)
    n = check_int("n", n, minimum=1, maximum=scores.shape[1])
    reference = loss if categories is None else category_mean_loss(loss, categories)
    truth = worst_bins(reference, fraction)
    return _expected_top_hits(scores, truth, n) / n, chance_hit_rate(truth, n)


def validity_rows(
    scores: Mapping[str, np.ndarray],
    loss: np.ndarray,
    categories: Sequence[str],
    *,
    n: int = 3,
    fraction: float = 0.1,
    confidence: float = 0.95,
) -> list[dict[str, Any]]:
    """One row per score: mean Spearman correlation and top-``n`` hit rates (object and category truth), with chance.

    Args:
        scores: score name -> ``(objects, bins)`` scores, rows aligned with ``loss``.
        loss: ``(objects, bins)`` measured loss (``1 - IoU`` of a robustness map).
        categories: one category per object.
        n: bins the selector keeps.
        fraction: share of bins that counts as the worst.
        confidence: coverage of the intervals.

    Returns:
        Dicts with ``score``, ``spearman``, ``hit_rate``, ``hit_rate_category`` (:class:`Summary` s over objects),
        ``chance``, ``chance_category`` (floats: the mean chance rate) and ``objects``.

    Raises:
        ValueError: shapes that differ, non-finite values, not one category per object, ``n`` outside
            ``[1, bins]``, or a ``fraction`` or ``confidence`` out of range.

    Example:
        >>> loss = np.array([[0.0, 0.1, 0.9, 0.2], [0.8, 0.1, 0.0, 0.3]])
        >>> scores = {"oracle": loss, "constant": np.zeros((2, 4))}
        >>> for row in validity_rows(scores, loss, ["chair", "chair"], n=1, fraction=0.25):
        ...     print(row["score"], row["hit_rate"].mean, row["chance"])
        oracle 1.0 0.25
        constant 0.25 0.25
    """
    rows = []
    for name, values in scores.items():
        rho = spearman_per_object(values, loss)
        hits, chance = top_hit_rate(values, loss, n=n, fraction=fraction)
        cat_hits, cat_chance = top_hit_rate(values, loss, n=n, fraction=fraction, categories=categories)
        rows.append(
            {
                "score": name,
                "spearman": mean_with_interval(rho, confidence),
                "hit_rate": mean_with_interval(hits, confidence),
                "chance": float(chance.mean()),
                "hit_rate_category": mean_with_interval(cat_hits, confidence),
                "chance_category": float(cat_chance.mean()),
                "objects": int(np.asarray(loss).shape[0]),
            }
        )
    return rows


def format_validity_table(rows: Sequence[Mapping[str, Any]], *, n: int = 3, fraction: float = 0.1) -> str:
    """The rows of :func:`validity_rows` as a Markdown table (means with their intervals in brackets).

    Args:
        rows: from :func:`validity_rows`.
        n: the ``n`` the rows were computed with (names the hit-rate columns).
        fraction: the ``fraction`` the rows were computed with (names the hit-rate columns).

    Returns:
        The table, one line per row after the header, ending in a newline.

    Raises:
        KeyError: a row lacks one of the keys :func:`validity_rows` gives.

    Example:
        >>> loss = np.array([[0.0, 0.1, 0.9, 0.2], [0.8, 0.1, 0.0, 0.3]])
        >>> rows = validity_rows({"oracle": loss}, loss, ["chair", "chair"], n=1, fraction=0.25)
        >>> print(format_validity_table(rows, n=1, fraction=0.25))
        | score | Spearman ρ | top-1 in worst 25 % | Random | ...
        |---|---|---|---|---|---|---|
        | oracle | 1.000 [1.000, 1.000] | 1.000 [1.000, 1.000] | 0.250 | ...
    """
    share = f"{fraction * 100:g} %"
    header = (
        f"| score | Spearman ρ | top-{n} in worst {share} | Random | top-{n} in category's worst {share} "
        "| Random (category) | objects |\n|---|---|---|---|---|---|---|"
    )
    lines = [header]
    for row in rows:
        lines.append(
            f"| {row['score']} | {row['spearman'].format()} | {row['hit_rate'].format()} | {row['chance']:.3f} "
            f"| {row['hit_rate_category'].format()} | {row['chance_category']:.3f} | {row['objects']} |"
        )
    return "\n".join(lines) + "\n"


def _model_device(model: Any) -> torch.device:
    try:
        return next(model.parameters()).device
    except (AttributeError, StopIteration, TypeError):
        return torch.device("cpu")


def _records_and_transform(objects: Any, split: str, model: Any) -> tuple[list[Any], Any, Any]:
    """``(records, transform, voxel loader)`` of a datamodule (its ``split``) or of a sequence of records."""
    from lightning_vtr.data.dataset import load_voxels
    from lightning_vtr.data.transforms import ImageTransform

    if hasattr(objects, "split_records"):
        records = list(objects.split_records(split))
        return records, objects.transform, getattr(objects, "object_voxels", load_voxels)
    return list(objects), ImageTransform(int(model.image_size)), load_voxels


def bce_per_object(pred: Tensor, target: Tensor) -> Tensor:
    """Mean binary cross-entropy per object ``(B,)`` of ``pred, target (B, R, R, R)``; the loss the augmentation
    callback gives the ``input`` score (predictions clamped to ``[1e-6, 1 - 1e-6]``)."""
    return F.binary_cross_entropy(pred.clamp(1e-6, 1 - 1e-6), target, reduction="none").flatten(1).mean(1)


def _training_images(objects: Any, record: Any, view_set: str, seed: int, num_views: int, transform: Any) -> Tensor:
    """``(V, 3, h, w)``: the views the callback predicts an object from (``eval_item``), or a seeded choice."""
    if hasattr(objects, "eval_item"):
        return torch.as_tensor(objects.eval_item(record, view_set, seed=seed)["images"])
    from lightning_vtr.data.dataset import load_rgba

    paths, _ = record.views[view_set]
    rng = np.random.default_rng([seed, zlib.crc32(f"{record.category}/{record.object_id}".encode())])
    chosen = rng.choice(len(paths), size=num_views, replace=False)
    return torch.as_tensor(transform(np.stack([load_rgba(paths[i]) for i in chosen])))


def selection_scores(
    model: Any,
    objects: Any,
    *,
    k: int = 30,
    scores: Sequence[str] = OBJECT_SCORES,
    source_view_set: str = "aligned",
    seed: int = 0,
    synthesizer: Any = None,
    transform: Any = None,
    split: str = "test",
    batch_size: int = 16,
    threshold: float = DEFAULT_THRESHOLD,
) -> dict[str, np.ndarray]:
    """Each selection score of every object, ``{score: (objects, 180/K * 360/K)}``, bins pitch-major.

    Each object is predicted from ``model.num_views`` of its ``source_view_set`` images (a datamodule's
    ``eval_item(record, source_view_set, seed)``, the views the augmentation callback predicts from; for records, a
    choice seeded by ``(seed, category/object_id)``), then scored by ``ErrorGuidedSelector(k, score=name,
    threshold=threshold).score_views``. The ``input`` score renders every bin centre with ``synthesizer`` and
    predicts from each alone (:func:`bce_per_object` as the loss, as in the callback).

    Args:
        model: a :class:`~lightning_vtr.protocol.ReconstructionModel`.
        objects: a datamodule (its ``split`` objects) or a sequence of records, as for
            :func:`~lightning_vtr.evaluation.robustness.robustness_map`; pass the same to both to align rows.
        k: bin interval in degrees (divides 180).
        scores: the score names, among ``paper``, ``released``, ``visible`` and ``input``.
        source_view_set: the view set the training views come from.
        seed: seeds the choice of training views.
        synthesizer: renders the ``input`` score's views; ``None``: ``RenderSynthesizer(model.image_size)``.
        transform: RGBA uint8 -> model input; ``None``: the datamodule's (``ImageTransform(model.image_size)``).
        split: the datamodule split.
        batch_size: objects per ``predict_voxels`` call (and single-view sets per call for ``input``).
        threshold: the selector's occupancy threshold.

    Returns:
        Score name -> float64 ``(objects, bins)`` array, objects in the order of ``objects``.

    Raises:
        ValueError: an unknown score name, no objects, or a model output that is not probabilities.

    Example::

        scores = selection_scores(model, dm, k=30)
        scores["paper"].shape  # (objects, 72)
    """
    k = check_bin_interval(k)
    for name in scores:
        check_choice("scores", name, OBJECT_SCORES)
    batch_size = check_int("batch_size", batch_size, minimum=1)
    records, default_transform, load_target = _records_and_transform(objects, split, model)
    transform = default_transform if transform is None else transform
    if not records:
        raise ValueError("`objects` must hold at least one object to score, got none")
    device = _model_device(model)
    num_views = int(model.num_views)
    was_training = bool(getattr(model, "training", False))
    if hasattr(model, "eval"):
        model.eval()
    try:
        images = [_training_images(objects, r, source_view_set, seed, num_views, transform) for r in records]
        preds = []
        with torch.inference_mode():
            for lo in range(0, len(images), batch_size):
                batch = model.predict_voxels(torch.stack(images[lo : lo + batch_size]).to(device))
                preds.append(check_probabilities("predict_voxels", batch.detach().float().cpu()))
        predicted = torch.cat(preds)
        target = torch.stack([torch.as_tensor(load_target(r)).float() for r in records])
        context = None
        if "input" in scores:
            from lightning_vtr.synthesis.base import SynthesisRequest

            if synthesizer is None:
                from lightning_vtr.synthesis.render import RenderSynthesizer

                synthesizer = RenderSynthesizer(image_size=int(model.image_size))
            requests = [
                SynthesisRequest(
                    object_id=r.object_id,
                    category=r.category,
                    source_images=np.zeros((0, 0, 0, 4), np.uint8),
                    source_viewpoints=torch.as_tensor(
                        np.asarray(r.views[source_view_set][1], dtype=np.float32).reshape(-1, 2)
                    ),
                    target_viewpoints=torch.zeros(0, 2),
                    mesh_path=getattr(r, "mesh_path", None),
                )
                for r in records
            ]
            context = SelectionContext(
                model=model,
                synthesizer=synthesizer,
                requests=requests,
                transform=transform,
                loss_fn=bce_per_object,
                device=device,
            )
        out: dict[str, np.ndarray] = {}
        for name in scores:
            score: Any = name  # one of OBJECT_SCORES, checked above
            if name == "input":
                score = InputScore(model_batch_size=batch_size)
            selector = ErrorGuidedSelector(score=score, k=k, threshold=threshold)
            out[name] = selector.score_views(predicted, target, context if name == "input" else None).double().numpy()
    finally:
        if hasattr(model, "train"):
            model.train(was_training)
    return out


def validity_table(
    rmap: RobustnessMap,
    scores: dict[str, np.ndarray],
    *,
    object_ids: Sequence[str] | None = None,
    n: int = 3,
    fraction: float = 0.1,
) -> str:
    """The score validity table (Markdown) of ``scores`` against the measured loss ``1 - rmap.iou``.

    Args:
        rmap: the robustness map (the truth).
        scores: score name -> ``(objects, bins)`` from :func:`selection_scores` on the same objects.
        object_ids: the ids the score rows belong to, checked against the map's (``None``: not checked).
        n: bins a selector keeps.
        fraction: share of bins that counts as the worst.

    Returns:
        The table of :func:`format_validity_table`.

    Raises:
        ValueError: scores of another shape than the map, or rows of other objects.

    Example::

        print(validity_table(rmap, selection_scores(model, dm, k=rmap.k)))
    """
    if object_ids is not None and list(object_ids) != rmap.object_ids:
        raise ValueError("The scores' objects must be the map's objects, in the map's order")
    for name, values in scores.items():
        if np.shape(values) != rmap.iou.shape:
            raise ValueError(f"Score {name!r} must have the map's shape {rmap.iou.shape}, got {np.shape(values)}")
    rows = validity_rows(scores, 1.0 - rmap.iou, rmap.categories, n=n, fraction=fraction)
    return format_validity_table(rows, n=n, fraction=fraction)


def main(argv: Sequence[str] | None = None) -> int:
    """Measure each checkpoint's robustness map and write its score-validity table to ``OUT/score_validity.md``.

    The options are those of ``lightning-vtr robustness`` that choose the objects and view sets (``--ckpt``,
    ``--data``, ``--split``, ``--k``, ``--seed``, ``--objects``, ``--batch-size``, ``--device``); every checkpoint
    is measured on the same objects. Returns the exit status 0.
    """
    from lightning_vtr.cli.arguments import dataset_folder
    from lightning_vtr.cli.pix3d import checkpoint_argument
    from lightning_vtr.evaluation import make_datamodule, robustness_map
    from lightning_vtr.evaluation.predict import resolve_device
    from lightning_vtr.evaluation.robustness_callback import ObjectSubset, spread_over_categories
    from lightning_vtr.models.registry import load_model

    parser = argparse.ArgumentParser(prog="python -m research.score_validity", description=main.__doc__)
    add = parser.add_argument
    add("--ckpt", type=checkpoint_argument, action="append", required=True, metavar="[NAME=]CKPT")
    add("--data", required=True, metavar="DATASET", help="a ShapeNet-VTR directory with meshes, or `embedded`")
    add("--split", default="test", choices=("train", "val", "test"))
    add("--out", type=Path, required=True, help="output directory (score_validity.md)")
    add("--k", type=int, default=30, help="bin interval in degrees, dividing 180 (default 30)")
    add("--seed", type=int, default=0, help="seed of the view sets and the training views (default 0)")
    add("--objects", type=int, default=None, help="at most N objects, round-robin over the categories")
    add("--batch-size", type=int, default=64, help="view sets per forward pass (default 64)")
    add("--device", default="auto", help="torch device: auto, cpu, cuda:0, ...")
    args = parser.parse_args(argv)
    k = check_bin_interval(args.k, "--k")
    device = resolve_device(args.device)
    records: list[Any] | None = None
    tables: dict[str, str] = {}
    for name, path in args.ckpt:
        model = load_model(path).to(device)
        dm = make_datamodule(path, model, dataset_folder(args.data))
        if records is None:
            records = spread_over_categories(dm.split_records(args.split), args.objects)
        objects = ObjectSubset(dm, records)
        rmap = robustness_map(model, objects, k=k, seed=args.seed, split=args.split, batch_size=args.batch_size)
        scores = selection_scores(model, objects, k=k, seed=args.seed, split=args.split)
        tables[name] = validity_table(rmap, scores, object_ids=[r.object_id for r in records])
        print(f"{name}:\n{tables[name]}")
    out = Path(args.out).expanduser()
    out.mkdir(parents=True, exist_ok=True)
    text = "".join(f"## {name}\n\n{table.rstrip()}\n\n" for name, table in tables.items())
    (out / "score_validity.md").write_text(f"# Score validity\n\n{text}", encoding="utf-8")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
