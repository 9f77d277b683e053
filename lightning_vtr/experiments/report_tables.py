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
    "difference_table",
    "metric_value",
    "paired_differences",
    "pooled_views",
    "robustness_table",
    "run_values",
    "seed_estimate",
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


def _format_difference(estimate: Estimate | None) -> str:
    """``"+2.80 [0.80, 4.80], 3/3"`` in percentage points: mean, 95 % CI (with 2+ seeds), seeds agreeing in sign."""
    if estimate is None:
        return "-"
    text = f"{100 * estimate.mean:+.2f}"
    if math.isfinite(estimate.half_width):
        text += f" [{100 * estimate.low:+.2f}, {100 * estimate.high:+.2f}]"
    return f"{text}, {estimate.agree}/{estimate.n}"


def difference_table(differences: dict[str, dict[str, Estimate | None]]) -> str:
    header = ["Method", *(VIEW_SET_TITLES[v] for v in VIEW_SETS)]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for title, per_set in differences.items():
        lines.append("| " + " | ".join([title, *(_format_difference(per_set[v]) for v in VIEW_SETS)]) + " |")
    return "\n".join(lines)


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
