"""The report's Markdown (``report.md``): a header with the command and the budget, Table 1, the paired
differences to the baselines (test and validation splits), where the training views went, the ablations and
where the time went; and :func:`summarize`, the numbers those sections and the files share.
"""

from __future__ import annotations

import shlex
from dataclasses import dataclass
from typing import Any

from lightning_vtr.experiments.report_config import BASELINES, MAIN_K, METRICS, ReportConfig
from lightning_vtr.experiments.report_plan import ReportRun
from lightning_vtr.experiments.report_run import ReportResults
from lightning_vtr.experiments.report_tables import (
    difference_table,
    paired_differences,
    pooled_views,
    robustness_table,
    view_statistics,
    view_table,
)
from lightning_vtr.experiments.report_timing import time_tables

__all__ = ["ReportSummary", "equivalent_command", "render_markdown", "summarize"]

_TEST_NOTE = (
    "Per seed, each strategy minus {baseline}: the same pretrained model and the same test items. Each cell: "
    "the mean difference, its 95 % CI over seeds (with 2+ seeds) and how many seeds agree with the mean's sign."
)
_VALIDATION_NOTE = (
    "The same models on the validation objects, each on {repeats} fixed view set(s): "
    "choose among strategies here, and read the test-split tables above as the confirmation, so that no "
    "choice is tuned on the test split. Cells as above."
)


@dataclass
class ReportSummary:
    """The numbers of the report's main rows.

    Attributes:
        rows: row title -> run name, in the report's row order (the configured strategies).
        differences: ``{baseline: {row title: {view_set: Estimate or None}}}``: paired mIoU differences to each
            of :data:`~lightning_vtr.experiments.report_config.BASELINES` the report runs and to its
            ``reference``.
        validation_differences: the same on the validation split (empty when the report does not validate).
        views: row title -> statistics of its generated training views (rows that generated some).
    """

    rows: dict[str, str]
    differences: dict[str, dict[str, dict[str, Any]]]
    validation_differences: dict[str, dict[str, dict[str, Any]]]
    views: dict[str, dict[str, Any]]


def summarize(config: ReportConfig, results: ReportResults) -> ReportSummary:
    """Paired differences to every baseline the report runs and the view statistics of its main rows.

    Args:
        config: the report (its strategies, seeds and whether it validates).
        results: what its runs gave.

    Returns:
        The :class:`ReportSummary`.
    """
    seeds = list(config.seeds)
    titles = config.titles()
    rows = {titles[s]: s for s in config.variants if s in config.strategies}
    baselines = [b for b in BASELINES if b in rows.values()]
    if config.reference is not None and config.reference not in baselines:
        baselines.append(config.reference)
    differences = {b: paired_differences(rows, b, results.payloads, "iou@0.4", seeds) for b in baselines}
    validation_differences = {}
    if config.validation_repeats is not None:
        validation_differences = {
            b: paired_differences(rows, b, results.validation, "iou@0.4", seeds) for b in baselines
        }
    views = {}
    for title, run in rows.items():
        pooled = pooled_views(results.views.get(run, {}), seeds)
        if pooled is not None:
            views[title] = view_statistics(pooled)
    return ReportSummary(rows, differences, validation_differences, views)


def render_markdown(
    config: ReportConfig,
    runs: list[ReportRun],
    results: ReportResults,
    summary: ReportSummary,
    split: dict[str, Any],
    timing: dict[str, Any],
) -> str:
    """The whole ``report.md``.

    Args:
        config: the report.
        runs: its plan.
        results: what the runs gave.
        summary: :func:`summarize`'s numbers.
        split: the time split (:func:`~lightning_vtr.experiments.report_timing.time_split`).
        timing: ``timing.json``'s content (the wall time of every invocation, this one last).

    Returns:
        The Markdown text, ending with a newline.
    """
    seeds = list(config.seeds)
    sections = [
        *_header(config, timing),
        *_main_table(config, runs, results, summary),
        *_difference_sections(config, summary),
        *_view_section(summary),
        *_ablation_sections(config, results),
        "",
        "## Where the time goes",
        "",
        "Seconds summed over seeds, as measured when each run ran (a cached run keeps its first measurement).",
        "",
        time_tables(split, runs, seeds),
    ]
    return "\n".join(sections) + "\n"


def _header(config: ReportConfig, timing: dict[str, Any]) -> list[str]:
    exp, seeds = config.experiment, config.seeds
    total, wall = sum(timing["invocations"]), timing["invocations"][-1]
    return [
        "# View transformation robustness report",
        "",
        f"Command: `{config.command or equivalent_command(config)}`",
        "",
        f"Budget: {exp.model} ({exp.preset}) on {exp.data or 'the embedded procedural dataset'}; "
        f"seeds {', '.join(map(str, seeds))}; pretraining {exp.pretrain_epochs} epochs on Aligned, then "
        f"{exp.finetune_epochs} fine-tuning epochs per strategy ({exp.finetune_lr} learning rate); "
        f"{100 * exp.fraction:g} % of training objects given new views per selection; every test object "
        f"tested on {exp.test_repeats} fixed view set(s), the same for every strategy of a seed. "
        f"Total wall time: {total / 60:.1f} min over {len(timing['invocations'])} invocation(s) "
        f"(this one {wall / 60:.1f} min).",
    ]


def _main_table(
    config: ReportConfig, runs: list[ReportRun], results: ReportResults, summary: ReportSummary
) -> list[str]:
    seeds = list(config.seeds)
    interval = "mean ± 95 % CI over seeds (Student t)" if len(seeds) > 1 else "one seed"
    sections = [
        "",
        f"## Table 1: robustness to view transformations (%, test set; {interval})",
        "",
        robustness_table(summary.rows, results.payloads, METRICS, seeds),
    ]
    merged = [
        (run.strategy, run.same_as) for run in runs if run.same_as is not None and run.name in summary.rows.values()
    ]
    strategy_of = {run.name: run.strategy for run in runs}
    titles = config.titles()
    if merged:
        sections += [
            "",
            "Rows fitted once because their selector and callback arguments are identical: "
            + "; ".join(f"{titles[strategy]} = {titles[strategy_of[same_as]]}" for strategy, same_as in merged)
            + ".",
        ]
    return sections


def _difference_sections(config: ReportConfig, summary: ReportSummary) -> list[str]:
    sections: list[str] = []
    headed = (
        ("Paired difference to {baseline} (mIoU points)", _TEST_NOTE, summary.differences),
        (
            "Validation split: paired difference to {baseline} (mIoU points)",
            _VALIDATION_NOTE.replace("{repeats}", str(config.validation_repeats)),
            summary.validation_differences,
        ),
    )
    for heading, note, tables in headed:
        for baseline, by_title in tables.items():
            if by_title:
                title = config.titles()[baseline]
                sections += ["", "## " + heading.format(baseline=title), "", note.format(baseline=title), ""]
                sections.append(difference_table(by_title))
    return sections


def _view_section(summary: ReportSummary) -> list[str]:
    if not summary.views:
        return []
    return [
        "",
        "## Where the training views went",
        "",
        "The viewpoints of every generated training sample, pooled over seeds: share (%) per pitch band "
        "(degrees), share (%) of view sets holding an antipodal pair (views at least 165° apart) and the "
        "mean angle between two views of a set.",
        "",
        view_table(summary.views),
    ]


def _ablation_sections(config: ReportConfig, results: ReportResults) -> list[str]:
    seeds, payloads = list(config.seeds), results.payloads
    sections: list[str] = []
    if "k" in config.ablations:
        k_rows = {f"K = {k}": ("error_guided" if k == MAIN_K else f"error_guided_k{k}") for k in config.k_values}
        table = robustness_table(k_rows, payloads, ("iou@0.4",), seeds)
        sections += ["", "## Ablation: bin interval K (mIoU, %)", "", table]
    if "pool" in config.ablations:
        pool_rows = {"Default rule (with pool)": "error_guided", "Default rule (without pool)": "error_guided_no_pool"}
        sections += ["", "## Ablation: viewpoint pool (%)", "", robustness_table(pool_rows, payloads, METRICS, seeds)]
    if "single_view" in config.ablations:
        single_rows = {"None-VTR (1 view)": "single_view_none", "Default rule (1 view)": "single_view_error_guided"}
        table = robustness_table(single_rows, payloads, METRICS, seeds)
        sections += ["", "## Ablation: single-view input (%)", "", table]
    return sections


def equivalent_command(config: ReportConfig) -> str:
    """The ``lightning-vtr report`` command line that runs ``config``."""
    exp = config.experiment
    words = ["lightning-vtr", "report", "--model", exp.model, "--preset", exp.preset]
    if exp.data:
        words += ["--data", exp.data]
    words += ["--out", exp.out, "--seeds", *map(str, config.seeds)]
    words += ["--pretrain-epochs", str(exp.pretrain_epochs), "--finetune-epochs", str(exp.finetune_epochs)]
    words += ["--strategies", ",".join(config.strategies), "--fraction", str(exp.fraction)]
    if config.strategies_file is not None:
        words += ["--strategies-file", str(config.strategies_file)]
        if config.only_strategies_file:
            words.append("--only-strategies-file")
    words += ["--test-repeats", str(exp.test_repeats)]
    if exp.finetune_lr != "cosine":
        words += ["--finetune-lr", exp.finetune_lr]
    if config.ablations:
        words += ["--ablations", ",".join(config.ablations)]
    if config.validation_repeats is not None:
        words += ["--validation-repeats", str(config.validation_repeats)]
    if config.reference is not None:
        words += ["--reference", config.reference]
    if config.maps:
        words += ["--maps", "--map-k", str(config.map_k), "--map-objects", str(config.map_objects)]
    if config.jobs > 1:
        words += ["--jobs", str(config.jobs)]
    return shlex.join(words)
