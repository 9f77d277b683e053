"""The report's data files: ``results.csv`` (one row per run x seed x view set), ``differences.csv`` (one row
per baseline x run x view set x metric) and the chart ``report.png``.
"""

from __future__ import annotations

import itertools
import math
from pathlib import Path
from typing import Any

from lightning_vtr.evaluation.tables import VIEW_SET_TITLES
from lightning_vtr.experiments.report_config import BASELINES, METRICS, PITCH_BANDS
from lightning_vtr.experiments.report_plan import ReportRun
from lightning_vtr.experiments.report_tables import metric_value, paired_differences, run_values, seed_estimate
from lightning_vtr.protocol import VIEW_SETS
from lightning_vtr.utils.io import save_figure, write_csv

__all__ = ["write_chart", "write_differences_csv", "write_results_csv"]


def write_results_csv(
    path: Path, runs: list[ReportRun], payloads: dict[str, dict[int, dict]], seeds: list[int]
) -> None:
    """One row per run x seed x view set: ``run, strategy, seed, view_set``, the metrics (fractions, unrounded) and
    the run's ``train_seconds``."""
    rows: list[list[Any]] = []
    for run in runs:
        for seed in seeds:
            payload = payloads[run.name][seed]
            for view_set in VIEW_SETS:
                values = payload["results"].get(view_set, {})
                rows.append(
                    [run.name, run.strategy, seed, view_set]
                    + [repr(float(_nan_if_none(metric_value(values, m)))) for m in METRICS]
                    + [f"{payload['train_seconds']:.3f}"]
                )
    write_csv(path, rows, ["run", "strategy", "seed", "view_set", *METRICS, "train_seconds"])


def _nan_if_none(value: float | None) -> float:
    return math.nan if value is None else value


def write_differences_csv(
    path: Path,
    rows: dict[str, str],
    payloads: dict[str, dict[int, dict]],
    seeds: list[int],
    baselines: list[str] | None = None,
) -> None:
    """One row per baseline x run x view set x metric: the paired difference as a fraction, its 95 % CI (with
    ``agree``, empty over one seed). ``baselines``: the runs compared with (default: those of :data:`BASELINES` among ``rows``)."""
    if baselines is None:
        baselines = [b for b in BASELINES if b in rows.values()]
    table: list[list[Any]] = []
    for baseline in baselines:
        for metric in METRICS:
            by_title = paired_differences(rows, baseline, payloads, metric, seeds)
            for title, per_set in by_title.items():
                for view_set, estimate in per_set.items():
                    if estimate is None:
                        continue
                    table.append(
                        [baseline, rows[title], view_set, metric]
                        + [repr(v) if math.isfinite(v) else "" for v in (estimate.mean, estimate.low, estimate.high)]
                        + [estimate.n, estimate.agree if estimate.n > 1 else ""]  # one seed: no interval, no count
                    )
    header = ["baseline", "run", "view_set", "metric", "mean", "ci_low", "ci_high", "seeds", "agree"]
    write_csv(path, table, header)


def write_chart(
    path: Path,
    rows: dict[str, str],
    payloads: dict[str, dict[int, dict]],
    seeds: list[int],
    view_statistics: dict[str, dict[str, Any]],
) -> Any:
    """The report's picture: what the decisions rest on beside the absolute numbers; returns the saved
    matplotlib ``Figure``.

    Top row: mIoU per view set and row as grouped bars (error bars: 95 % CI over seeds, which mostly shows the
    seed-to-seed spread of the pretrained models) and, with ``view_statistics``, the pitch histogram of each
    row's generated views. Bottom row, for each baseline the report runs (None-VTR, Random): every other row's
    paired mIoU difference to it per view set, in points, with its 95 % CI over seeds (the pairs share the
    pretrained model and the test items within a seed, so the seed spread cancels).
    """
    import matplotlib
    import numpy as np
    from matplotlib.figure import Figure  # no pyplot: no global figure manager, no backend switch

    baselines = [(title, run) for title, run in rows.items() if run in BASELINES]
    columns = 2 if view_statistics or len(baselines) > 1 else 1
    bottom = 1 if baselines else 0
    # the legends go under the panels, two entries a line: the figure grows with the rows
    legend_lines = math.ceil(len(rows) / 2)
    height = (4.2 + 0.2 * legend_lines) + bottom * 3.6
    fig = Figure(figsize=(8 * columns, height), dpi=120, layout="constrained")
    grid = fig.subplots(1 + bottom, columns, squeeze=False, height_ratios=[4.2 + 0.2 * legend_lines, 3.6][: 1 + bottom])
    # one colour per strategy in every panel (the view panel has no row for None-VTR), distinct up to 20 rows
    palette = [f"C{i}" for i in range(10)] if len(rows) <= 10 else [matplotlib.colormaps["tab20"](i) for i in range(20)]
    colours = {title: palette[i % len(palette)] for i, title in enumerate(rows)}
    x = np.arange(len(VIEW_SETS))
    several = len(seeds) > 1

    ax = grid[0][0]
    width = 0.8 / max(1, len(rows))
    for i, (title, run) in enumerate(rows.items()):
        stats = [seed_estimate(list(run_values(payloads, run, v, "iou@0.4", seeds).values())) for v in VIEW_SETS]
        means = [100 * e.mean if e else math.nan for e in stats]
        errors = [100 * e.half_width if e and math.isfinite(e.half_width) else 0.0 for e in stats]
        ax.bar(
            x - 0.4 + (i + 0.5) * width,
            means,
            width,
            yerr=errors if several else None,
            capsize=3 if several else 0,
            label=title,
            color=colours[title],
        )
    ax.set_xticks(x, [VIEW_SET_TITLES[v] for v in VIEW_SETS])
    ax.set_ylabel("mIoU@0.4 (%)")
    spread = f" (mean, 95 % CI over {len(seeds)} seeds)" if several else ""
    ax.set_title(f"Reconstruction IoU per test view set{spread}")
    ax.legend(ncol=2, fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.08))
    ax.grid(axis="y", alpha=0.3)
    if view_statistics:
        _view_panel(grid[0][1], view_statistics, colours)
    elif columns == 2:
        grid[0][1].set_axis_off()

    for column, (baseline_title, baseline) in enumerate(baselines[:2]):
        ax = grid[1][column]
        by_title = paired_differences(rows, baseline, payloads, "iou@0.4", seeds)
        width = 0.8 / max(1, len(by_title))
        for i, (title, per_set) in enumerate(by_title.items()):
            estimates = [per_set.get(v) for v in VIEW_SETS]
            means = [100 * e.mean if e else math.nan for e in estimates]
            bounded = [e is not None and math.isfinite(e.half_width) for e in estimates]
            below = [100 * (e.mean - e.low) if ok and e else 0.0 for e, ok in zip(estimates, bounded)]
            above = [100 * (e.high - e.mean) if ok and e else 0.0 for e, ok in zip(estimates, bounded)]
            ax.bar(
                x - 0.4 + (i + 0.5) * width,
                means,
                width,
                yerr=[below, above] if several else None,
                capsize=3 if several else 0,
                color=colours[title],
            )
        ax.axhline(0.0, color="black", linewidth=0.8)
        ax.set_xticks(x, [VIEW_SET_TITLES[v] for v in VIEW_SETS])
        ax.set_ylabel("paired difference (mIoU points)")
        ax.set_title(f"Paired difference to {baseline_title}" + (" (95 % CI over seeds)" if several else ""))
        ax.grid(axis="y", alpha=0.3)
    if bottom and len(baselines) == 1 and columns == 2:
        grid[1][1].set_axis_off()
    save_figure(fig, path)
    return fig


def _view_panel(ax: Any, view_statistics: dict[str, dict[str, Any]], colours: dict[str, Any]) -> None:
    """The pitch histogram of each row's generated training views."""
    centres = [(lo + hi) / 2 for lo, hi in itertools.pairwise(PITCH_BANDS)]
    band = PITCH_BANDS[1] - PITCH_BANDS[0]
    width = 0.8 * band / len(view_statistics)
    for i, (title, stats) in enumerate(view_statistics.items()):
        offsets = [c - 0.4 * band + (i + 0.5) * width for c in centres]
        label = f"{title} (antipodal {100 * stats['antipodal_share']:.0f} %, spread {stats['triplet_spread']:.0f}°)"
        shares = [100 * share for share in stats["pitch_histogram"]]
        ax.bar(offsets, shares, width, label=label, color=colours.get(title))
    ax.set_xticks(list(PITCH_BANDS))
    ax.set_xlabel("pitch of the generated training views (degrees)")
    ax.set_ylabel("share of views (%)")
    ax.set_title("Where each strategy's training views went")
    ax.legend(ncol=2, fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.14))
    ax.grid(axis="y", alpha=0.3)
