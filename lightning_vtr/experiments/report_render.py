"""The report's Markdown (``report.md``): a header with the command and the budget, Table 1, the paired
differences to the baselines (test and validation splits), where the training views went, the ablations and
where the time went; and :func:`summarize`, the numbers those sections and the files share.
"""

from __future__ import annotations

import shlex
from dataclasses import dataclass
from typing import Any, cast

from lightning_vtr.experiments.report_config import BASELINES, MAIN_K, METRICS, ReportConfig
from lightning_vtr.experiments.report_plan import ReportRun
from lightning_vtr.experiments.report_run import ReportResults
from lightning_vtr.experiments.report_tables import (
    difference_note,
    difference_table,
    interval_text,
    paired_differences,
    plural,
    pooled_views,
    robustness_table,
    view_statistics,
    view_table,
)
from lightning_vtr.experiments.report_timing import time_tables
from lightning_vtr.models.registry import MODELS

__all__ = ["ReportSummary", "equivalent_command", "render_markdown", "summarize"]

_VALIDATION_NOTE = (
    "The same models on the validation objects, each on {repeats}: "
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
    model = exp.model if exp.model not in MODELS else f"{exp.model} ({exp.preset})"
    arguments = ", ".join(f"{k}={v!r}" for k, v in exp.model_kwargs.items())
    if arguments:
        model += f" with {arguments}"
    if exp.image_size is not None:
        model += f" at {exp.image_size} px"
    return [
        "# View transformation robustness report",
        "",
        f"Command: `{config.command or equivalent_command(config)}`",
        "",
        f"Budget: {model} on {exp.data or 'the embedded procedural dataset'}; "
        f"{'seed' if len(seeds) == 1 else 'seeds'} {', '.join(map(str, seeds))}; pretraining "
        f"{plural(exp.pretrain_epochs, 'epoch')} on Aligned, then {plural(exp.finetune_epochs, 'fine-tuning epoch')} "
        f"per strategy ({exp.finetune_lr} learning rate); {100 * exp.fraction:g} % of training objects given new "
        f"views per selection; every test object tested on {plural(exp.test_repeats, 'fixed view set')}, the same "
        f"for every strategy of a seed. Total wall time: {total / 60:.1f} min over "
        f"{plural(len(timing['invocations']), 'invocation')} (this one {wall / 60:.1f} min).",
    ]


def _main_table(
    config: ReportConfig, runs: list[ReportRun], results: ReportResults, summary: ReportSummary
) -> list[str]:
    seeds = list(config.seeds)
    interval = interval_text(len(seeds), "over seeds (Student t)")
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
    seeds = len(config.seeds)
    repeats = plural(config.validation_repeats or 0, "fixed view set")
    headed = (
        ("Paired difference to {baseline} (mIoU points)", None, summary.differences),
        (
            "Validation split: paired difference to {baseline} (mIoU points)",
            _VALIDATION_NOTE.replace("{repeats}", repeats),
            summary.validation_differences,
        ),
    )
    for heading, note, tables in headed:
        for baseline, by_title in tables.items():
            if by_title:
                title = config.titles()[baseline]
                text = difference_note(title, seeds) if note is None else note
                sections += ["", "## " + heading.format(baseline=title), "", text, ""]
                sections.append(difference_table(by_title, seeds))
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


#: The flags :func:`equivalent_command` always writes, even at their defaults, so that the command reads whole.
_ALWAYS = ("model", "out", "seeds", "pretrain_epochs", "finetune_epochs", "strategies", "fraction", "test_repeats")


def _flag_words(name: str, value: Any, spec: dict[str, Any]) -> list[str]:
    from lightning_vtr.experiments.flags import option

    if isinstance(value, bool):
        return [option(name)] if value else []
    if isinstance(value, (list, tuple)):
        if not value:
            return []
        return (
            [option(name), ",".join(map(str, value))] if spec["comma_separated"] else [option(name), *map(str, value)]
        )
    return [option(name), str(value)]


def equivalent_command(config: ReportConfig) -> str:
    """The ``lightning-vtr report`` command line that runs ``config`` again: the same experiment and report
    settings, so that it reuses the runs ``config`` wrote and writes the same ``report.json`` settings.

    Every flag whose value differs from the command's default is written, and the flags of :data:`_ALWAYS`
    regardless; ``--preset`` for a registered model (a class of yours takes no preset, so it is written only when
    not the default), ``--model-arg KEY=VALUE`` per model argument, ``--jobs`` always (the command's default
    depends on the machine), ``--no-progress`` when the fits show no progress bar. Settings without a flag
    (``k_values``, ``selector_kwargs``, ``callback_kwargs``, ``synthesizer`` and the experiment's ``embedded`` and
    other ``trainer_kwargs``) cannot be written; ``report.json`` records them.

    Example:
        >>> from lightning_vtr.experiments.report_config import default_experiment
        >>> config = ReportConfig(default_experiment(model="mine.Net", image_size=64, model_kwargs={"width": 8}), seeds=[0])
        >>> print(equivalent_command(config))  # doctest: +NORMALIZE_WHITESPACE
        lightning-vtr report --model mine.Net --pretrain-epochs 30 --finetune-epochs 10 --image-size 64
            --fraction 0.05 --test-repeats 4 --out runs/report --model-arg width=8 --seeds 0
            --strategies none,random,random_area,paper,error_guided --jobs 1
    """
    from lightning_vtr.experiments.flags import flag_fields, yaml_word
    from lightning_vtr.experiments.report_config import default_experiment

    exp, defaults = config.experiment, default_experiment()
    words = ["lightning-vtr", "report"]
    for f in flag_fields(type(exp), exclude=("seed",)):
        value, default = getattr(exp, f.name), getattr(defaults, f.name)
        if f.name == "preset":
            keep = exp.model in MODELS or value != default
        else:
            keep = f.name in _ALWAYS or str(value) != str(default)
        if keep and value is not None:
            words += _flag_words(f.name, value, f.metadata["flag"])
    for key, value in exp.model_kwargs.items():
        words += ["--model-arg", f"{key}={yaml_word(value)}"]
    if exp.trainer_kwargs.get("enable_progress_bar") is False:
        words.append("--no-progress")
    for f in flag_fields(type(config)):
        value, default = getattr(config, f.name), cast(Any, f.default)
        if isinstance(value, (list, tuple)):
            value, default = list(value), list(default)
        if value is not None and (f.name == "jobs" or f.name in _ALWAYS or value != default):
            words += _flag_words(f.name, value, f.metadata["flag"])
    return shlex.join(words)
