"""The report's Markdown tables and the numbers in them: Table 1 layout with confidence intervals over seeds,
paired differences to a baseline, where the generated training views went.

Every function reads ``payloads``, ``{run: {seed: results.json payload}}``, and names runs by their report name.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from typing import Any

from lightning_vtr.evaluation.tables import BEST_IOU, VIEW_SET_TITLES, best_threshold_iou, format_robustness_table
from lightning_vtr.experiments.report_config import PITCH_BANDS
from lightning_vtr.experiments.statistics import (
    Estimate,
    antipodal_share,
    mean_estimate,
    paired_difference,
    pitch_histogram,
    triplet_spread,
)
from lightning_vtr.protocol import VIEW_SETS

__all__ = [
    "NO_INTERVAL",
    "difference_note",
    "difference_table",
    "interval_text",
    "metric_value",
    "paired_differences",
    "plural",
    "pooled_views",
    "robustness_table",
    "run_values",
    "seed_estimate",
    "separated_best",
    "verdict",
    "view_statistics",
    "view_table",
]


def run_values(payloads: dict[str, dict[int, dict]], run: str, view_set: str, metric: str, seeds: list[int]) -> dict:
    """``{seed: value}`` of one run, view set and metric, for the seeds that have a finite value."""
    out = {}
    for seed in seeds:
        value = metric_value(payloads[run][seed]["results"].get(view_set, {}), metric)
        if value is not None and not math.isnan(value):
            out[seed] = float(value)
    return out


def metric_value(values: dict[str, float], metric: str) -> float | None:
    """One metric of a view set's results; the best-threshold mIoU is derived from the ``iou@<t>`` values."""
    return best_threshold_iou(values) if metric == BEST_IOU else values.get(metric)


def seed_estimate(values: Sequence[float]) -> Estimate | None:
    return mean_estimate(values) if values else None


def robustness_table(
    rows: dict[str, str], payloads: dict[str, dict[int, dict]], metrics: Sequence[str], seeds: list[int]
) -> str:
    """A Table-1-layout Markdown table of ``rows`` (title -> run name); ``mean ± 95 % CI half-width`` over
    several seeds (Student t), the value alone with one."""
    means: dict[str, dict[str, dict[str, float]]] = {}
    spreads: dict[str, dict[str, dict[str, float]]] = {}
    for title, run in rows.items():
        means[title], spreads[title] = {}, {}
        for view_set in VIEW_SETS:
            for metric in metrics:
                estimate = seed_estimate(list(run_values(payloads, run, view_set, metric, seeds).values()))
                means[title].setdefault(view_set, {})[metric] = estimate.mean if estimate else math.nan
                spreads[title].setdefault(view_set, {})[metric] = estimate.half_width if estimate else math.nan
    return format_robustness_table(means, std=spreads, metric_names=tuple(metrics))


def paired_differences(
    rows: dict[str, str], baseline: str, payloads: dict[str, dict[int, dict]], metric: str, seeds: list[int]
) -> dict[str, dict[str, Estimate | None]]:
    """``{title: {view_set: paired difference to baseline}}`` for every row but the baseline's own."""
    out: dict[str, dict[str, Estimate | None]] = {}
    for title, run in rows.items():
        if run == baseline:
            continue
        out[title] = {}
        for view_set in VIEW_SETS:
            treatment = run_values(payloads, run, view_set, metric, seeds)
            reference = run_values(payloads, baseline, view_set, metric, seeds)
            shared = set(treatment) & set(reference)
            out[title][view_set] = paired_difference(treatment, reference) if shared else None
    return out


NO_INTERVAL = "1 seed: no interval"
"""What the report says instead of a confidence interval when it has one seed."""


def plural(count: int, word: str, words: str | None = None) -> str:
    """``"1 epoch"``, ``"2 epochs"``: ``count`` and ``word``, or its plural (``words``; default ``word + "s"``).

    Example:
        >>> plural(1, "epoch"), plural(3, "epoch"), plural(2, "view set")
        ('1 epoch', '3 epochs', '2 view sets')
    """
    return f"{count} {word if count == 1 else words or word + 's'}"


def interval_text(seeds: int, over: str = "over {n} seeds (Student t)") -> str:
    """How a table states its spread: ``"mean ± 95 % CI over 3 seeds (Student t)"``, or :data:`NO_INTERVAL`.

    Example:
        >>> interval_text(3), interval_text(1)
        ('mean ± 95 % CI over 3 seeds (Student t)', '1 seed: no interval')
    """
    return f"mean ± 95 % CI {over.format(n=seeds)}" if seeds > 1 else NO_INTERVAL


def verdict(estimate: Estimate) -> str | None:
    """Where a paired difference's 95 % CI lies: ``"above"`` zero, ``"below"`` it, or ``"level"`` (it holds zero:
    no difference shown); ``None`` without an interval (one seed).

    Example:
        >>> verdict(Estimate(0.02, 0.01, 3, 3)), verdict(Estimate(0.02, 0.03, 3, 2)), verdict(Estimate(0.02, math.nan, 1, 1))
        ('above', 'level', None)
    """
    if not math.isfinite(estimate.half_width):
        return None
    return "above" if estimate.low > 0 else "below" if estimate.high < 0 else "level"


def _format_difference(estimate: Estimate | None, note_one_seed: bool = True) -> str:
    """``"+2.80 [+0.80, +4.80] above, 3/3"`` in percentage points: the mean, the 95 % CI, where the interval lies
    (:func:`verdict`) and how many seeds agree with the mean's sign; over one seed the mean alone (with
    :data:`NO_INTERVAL` unless ``note_one_seed`` is off: the table's note says it)."""
    if estimate is None:
        return "-"
    text = f"{100 * estimate.mean:+.2f}"
    word = verdict(estimate)
    if word is None:
        return f"{text} ({NO_INTERVAL})" if note_one_seed else text
    return f"{text} [{100 * estimate.low:+.2f}, {100 * estimate.high:+.2f}] {word}, {estimate.agree}/{estimate.n}"


def difference_note(baseline: str, seeds: int) -> str:
    """The note above a table of paired differences to ``baseline`` (a row title) over ``seeds`` seeds.

    Example:
        >>> difference_note("None-VTR", 1).endswith("1 seed: no interval, so no cell says whether its difference is more than noise.")
        True
    """
    head = f"Per seed, each strategy minus {baseline}: the same pretrained model and the same test items."
    if seeds < 2:
        return (
            f"{head} Each cell: the one seed's difference; {NO_INTERVAL}, so no cell says whether its difference "
            "is more than noise."
        )
    return (
        f"{head} Each cell: the mean difference, its 95 % CI over seeds, where that interval lies (above zero: "
        '"above"; below zero: "below"; holding zero: "level", no difference shown) and how many seeds agree with '
        "the mean's sign."
    )


def difference_table(differences: dict[str, dict[str, Estimate | None]], seeds: int = 2) -> str:
    """A Markdown table of paired differences, a row per strategy and a column per view set
    (:func:`_format_difference` cells; over one seed the means alone, the note saying :data:`NO_INTERVAL`)."""
    header = ["Method", *(VIEW_SET_TITLES[v] for v in VIEW_SETS)]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for title, per_set in differences.items():
        cells = [_format_difference(per_set[v], note_one_seed=seeds > 1) for v in VIEW_SETS]
        lines.append("| " + " | ".join([title, *cells]) + " |")
    return "\n".join(lines)


def separated_best(
    rows: dict[str, str], payloads: dict[str, dict[int, dict]], seeds: list[int], metrics: Sequence[str]
) -> dict[tuple[str, str], str | None]:
    """Per ``(view_set, metric)``, the row a confidence interval separates from every other, or ``None``.

    The row with the best mean over seeds counts as best only when its paired difference to each other row (the
    same seeds' pretrained models and test items) has a 95 % CI above zero; rows that are level with it leave the
    column without a best. One seed has no interval: no row is separated.

    Args:
        rows: row title -> run name.
        payloads: ``{run: {seed: results.json payload}}``.
        seeds: the seeds.
        metrics: the metrics of the columns.

    Returns:
        ``{(view_set, metric): row title or None}``.

    Example::

        bold = separated_best({"None-VTR": "none", "Ours": "mine"}, payloads, [0, 1, 2], ["iou@0.4"])
    """
    out: dict[tuple[str, str], str | None] = {}
    for view_set in VIEW_SETS:
        for metric in metrics:
            values = {title: run_values(payloads, run, view_set, metric, seeds) for title, run in rows.items()}
            means = {title: math.fsum(v.values()) / len(v) for title, v in values.items() if v}
            best = max(means, key=lambda title: means[title]) if len(means) > 1 else None
            for title in means:
                if best is None or title == best:
                    continue
                shared = set(values[best]) & set(values[title])
                difference = paired_difference(values[best], values[title]) if shared else None
                if difference is None or verdict(difference) != "above":
                    best = None
            out[view_set, metric] = best
    return out


def view_statistics(view_sets: Any) -> dict[str, Any]:
    """Pitch-band shares, share of sets with an antipodal pair and mean pairwise angle of ``(B, n, 2)`` sets."""
    return {
        "view_sets": int(view_sets.shape[0]),
        "pitch_histogram": pitch_histogram(view_sets, PITCH_BANDS).tolist(),
        "antipodal_share": antipodal_share(view_sets),
        "triplet_spread": triplet_spread(view_sets),
    }


def pooled_views(views: dict[int, Any], seeds: list[int]) -> Any:
    import torch

    parts = [views[s] for s in seeds if views.get(s) is not None]
    sizes = {p.shape[1] for p in parts}
    return torch.cat(parts) if parts and len(sizes) == 1 else None


def view_table(statistics: dict[str, dict[str, Any]]) -> str:
    bands = [
        f"[{lo}, {hi}{']' if i == len(PITCH_BANDS) - 2 else ')'}"
        for i, (lo, hi) in enumerate(itertools.pairwise(PITCH_BANDS))
    ]
    header = ["Method", "View sets", *(f"Pitch {b}" for b in bands), "Antipodal pairs", "Mean spread (°)"]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for title, stats in statistics.items():
        cells = [title, str(stats["view_sets"])]
        cells += [f"{100 * share:.1f}" for share in stats["pitch_histogram"]]
        cells += [f"{100 * stats['antipodal_share']:.1f}", f"{stats['triplet_spread']:.1f}"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)
