"""Does a view score point at the views where the model actually fails? Pure statistics on ``(objects, bins)``.

A selection score (e.g. :class:`~lightning_vtr.selection.error_guided.ErrorGuidedSelector`'s ``paper`` score)
ranks every bin of the viewpoint grid per object; the robustness map
(:func:`~lightning_vtr.evaluation.robustness.robustness_map`) measures the model's true loss ``1 - IoU`` there.
Two measures of agreement, both per object and then summarised over objects:

* :func:`spearman_per_object`: Spearman's rank correlation between an object's scores and its losses (tied
  values get their average rank), summarised by :func:`mean_with_interval` (a Student-t 95 % interval).
* :func:`top_hit_rate`: the fraction of the score's top ``n`` bins (3: the views the selector keeps) that are
  among the object's truly worst ``fraction`` (10 %) of bins, next to the rate uniformly random distinct picks
  would get, computed exactly (:func:`chance_hit_rate`). Ties are resolved in expectation: a score tied at its
  ``n``-th place contributes each tied bin with the probability a random tie-break would pick it, so a constant
  score gets exactly the chance rate. With ``truth="category"`` the worst bins are those of the object's
  category mean loss map, the views the category as a whole is bad at.

Bins count equally (a random pick is a uniformly random bin, not an area-uniform viewpoint).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import stats

from lightning_vtr.utils.validation import check_float, check_int

__all__ = [
    "Summary",
    "category_mean_loss",
    "chance_hit_rate",
    "format_validity_table",
    "mean_with_interval",
    "spearman_per_object",
    "top_hit_rate",
    "validity_rows",
    "worst_bins",
]


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
