r"""The report's files for a paper: Table 1 as Markdown, CSV and LaTeX, the paired differences as Markdown and
LaTeX, the per-category results, and ``report.json``, which holds every number with the command, the package
version and the settings that produced them.

Every function reads ``payloads``, ``{run: {seed: results.json payload}}``, and ``rows``, ``{row title: run}`` in
the report's row order. Numbers in CSV and JSON are fractions in [0, 1]; Markdown and LaTeX show percent (mIoU,
F-score) or percentage points (differences). A missing value (a metric a run did not log, a half-width over one
seed) is empty in CSV and ``null`` in JSON.
"""

from __future__ import annotations

import json
import math
import platform
import shlex
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, cast

from lightning_vtr.evaluation.tables import VIEW_SET_TITLES
from lightning_vtr.experiments.report_config import METRICS
from lightning_vtr.experiments.report_tables import (
    NO_INTERVAL,
    interval_text,
    metric_value,
    run_values,
    seed_estimate,
    separated_best,
)
from lightning_vtr.experiments.statistics import Estimate
from lightning_vtr.protocol import VIEW_SETS
from lightning_vtr.utils.io import atomic_write, csv_text

__all__ = [
    "METRIC_TITLES",
    "TABLE1_LATEX_METRICS",
    "category_estimates",
    "category_markdown",
    "category_rows",
    "difference_latex",
    "dump_json",
    "estimate_record",
    "report_record",
    "table1_csv",
    "table1_estimates",
    "table1_latex",
    "write_csv",
    "write_paper_files",
]

METRIC_TITLES: dict[str, str] = {"iou@0.4": "mIoU", "iou_best": "best mIoU", "fscore": "F-score"}
"""Column titles of the metrics of :data:`~lightning_vtr.experiments.report_config.METRICS`."""
TABLE1_LATEX_METRICS: tuple[str, ...] = ("iou@0.4", "fscore")
"""The metrics of ``table1.tex``: the paper's Table 1 columns (mIoU at 0.4 and F-score per view set)."""


def _finite(value: float | None) -> float | None:
    return None if value is None or not math.isfinite(value) else float(value)


def estimate_record(estimate: Estimate | None) -> dict[str, Any] | None:
    """An :class:`~lightning_vtr.experiments.statistics.Estimate` as JSON: ``mean``, ``half_width``, ``ci_low``,
    ``ci_high``, ``seeds`` and ``agree`` (the interval and the sign count ``null`` over one seed); ``None`` for no
    estimate."""
    if estimate is None:
        return None
    return {
        "mean": _finite(estimate.mean),
        "half_width": _finite(estimate.half_width),
        "ci_low": _finite(estimate.low),
        "ci_high": _finite(estimate.high),
        "seeds": estimate.n,
        "agree": estimate.agree if estimate.n > 1 else None,
    }


def table1_estimates(
    rows: dict[str, str], payloads: dict[str, dict[int, dict]], seeds: list[int], metrics: Sequence[str] = METRICS
) -> dict[str, dict[str, dict[str, Estimate | None]]]:
    """``{row title: {view_set: {metric: mean over seeds with its 95 % CI, or None}}}``: Table 1's numbers."""
    return {
        title: {
            view_set: {m: seed_estimate(list(run_values(payloads, run, view_set, m, seeds).values())) for m in metrics}
            for view_set in VIEW_SETS
        }
        for title, run in rows.items()
    }


def write_csv(path: Path, header: Sequence[str], rows: Sequence[Sequence[Any]]) -> None:
    """Write a CSV file atomically; floats as ``repr`` (every digit), ``None`` as an empty cell."""
    atomic_write(path, csv_text((["" if v is None else v for v in row] for row in rows), header))


def table1_csv(rows: dict[str, str], estimates: dict[str, dict[str, dict[str, Estimate | None]]]) -> list[list[Any]]:
    """``table1.csv``'s rows (header ``method, run, view_set, metric, mean, half_width, ci_low, ci_high, seeds``),
    one per row x view set x metric, fractions."""
    out: list[list[Any]] = []
    for title, per_set in estimates.items():
        for view_set, per_metric in per_set.items():
            for metric, estimate in per_metric.items():
                record = estimate_record(estimate) or {}
                out.append(
                    [title, rows[title], view_set, metric]
                    + [record.get(k) for k in ("mean", "half_width", "ci_low", "ci_high", "seeds")]
                )
    return out


_LATEX_SPECIAL = {
    "\\": r"\textbackslash{}",
    "&": r"\&",
    "%": r"\%",
    "$": r"\$",
    "#": r"\#",
    "_": r"\_",
    "{": r"\{",
    "}": r"\}",
    "~": r"\textasciitilde{}",
    "^": r"\textasciicircum{}",
}


def _latex_text(text: str) -> str:
    return "".join(_LATEX_SPECIAL.get(c, c) for c in text)


def table1_latex(
    estimates: dict[str, dict[str, dict[str, Estimate | None]]],
    metrics: Sequence[str] = TABLE1_LATEX_METRICS,
    *,
    caption: str = "",
    bold: Mapping[tuple[str, str], str | None] | None = None,
) -> str:
    r"""Table 1 as a booktabs ``tabular``: a row per strategy, the columns Aligned / Hemispherical / Spherical x
    ``metrics``, each cell ``mean $\pm$ half-width`` of the 95 % CI over seeds in percent (the mean alone over
    one seed); in bold, in each column, the row a confidence interval separates from the others (``bold``).

    Args:
        estimates: :func:`table1_estimates`' numbers.
        metrics: the metrics per view set, in column order.
        caption: a comment line above the table (``%`` lines; LaTeX ignores them).
        bold: ``{(view_set, metric): row title or None}``, the row to set in bold per column
            (:func:`~lightning_vtr.experiments.report_tables.separated_best`: the best mean, when its paired
            difference to every other row has a 95 % CI above zero); ``None``: no bold.

    Returns:
        The LaTeX text (needs ``\usepackage{booktabs}``), ending with a newline.

    Example::

        print(table1_latex(table1_estimates({"None-VTR": "none"}, payloads, [0, 1, 2])))
    """
    bold = bold or {}

    def cell(title: str, estimate: Estimate | None, view_set: str, metric: str) -> str:
        if estimate is None or not math.isfinite(estimate.mean):
            return "--"
        text = f"{100 * estimate.mean:.2f}"
        if bold.get((view_set, metric)) == title:
            text = rf"\textbf{{{text}}}"
        if math.isfinite(estimate.half_width):
            text += rf" $\pm$ {100 * estimate.half_width:.2f}"
        return text

    width = len(metrics)
    lines = [f"% {line}" for line in caption.splitlines()] + ["% needs \\usepackage{booktabs}"]
    lines += [
        r"\begin{tabular}{l" + "c" * (width * len(VIEW_SETS)) + "}",
        r"\toprule",
        " & ".join(["", *(rf"\multicolumn{{{width}}}{{c}}{{{VIEW_SET_TITLES[v]}}}" for v in VIEW_SETS)]) + r" \\",
        " ".join(rf"\cmidrule(lr){{{2 + i * width}-{1 + (i + 1) * width}}}" for i in range(len(VIEW_SETS))),
        " & ".join(["Method", *(METRIC_TITLES.get(m, _latex_text(m)) for _ in VIEW_SETS for m in metrics)]) + r" \\",
        r"\midrule",
    ]
    for title, per_set in estimates.items():
        cells = [cell(title, per_set[v][m], v, m) for v in VIEW_SETS for m in metrics]
        lines.append(" & ".join([_latex_text(title), *cells]) + r" \\")
    lines += [r"\bottomrule", r"\end{tabular}"]
    return "\n".join(lines) + "\n"


def difference_latex(differences: dict[str, dict[str, Estimate | None]], *, caption: str = "") -> str:
    r"""Paired differences to one baseline as a booktabs ``tabular``: a row per strategy, a column per view set,
    each cell ``mean [low, high]`` in percentage points (the mean alone over one seed).

    Args:
        differences: ``{row title: {view_set: Estimate or None}}``
            (:func:`~lightning_vtr.experiments.report_tables.paired_differences`).
        caption: a comment line above the table.

    Returns:
        The LaTeX text, ending with a newline.
    """

    def cell(estimate: Estimate | None) -> str:
        if estimate is None:
            return "--"
        text = f"${100 * estimate.mean:+.2f}$"
        if math.isfinite(estimate.half_width):
            text += f" [${100 * estimate.low:+.2f}$, ${100 * estimate.high:+.2f}$]"
        return text

    lines = [f"% {line}" for line in caption.splitlines()]
    lines += [
        r"\begin{tabular}{l" + "c" * len(VIEW_SETS) + "}",
        r"\toprule",
        " & ".join(["Method", *(VIEW_SET_TITLES[v] for v in VIEW_SETS)]) + r" \\",
        r"\midrule",
    ]
    for title, per_set in differences.items():
        lines.append(" & ".join([_latex_text(title), *(cell(per_set.get(v)) for v in VIEW_SETS)]) + r" \\")
    lines += [r"\bottomrule", r"\end{tabular}"]
    return "\n".join(lines) + "\n"


def _categories(payloads: dict[str, dict[int, dict]], runs: Sequence[str], seeds: list[int]) -> list[str]:
    """Every category with a result in any of ``runs``, sorted."""
    found = set()
    for run in runs:
        for seed in seeds:
            for key in payloads[run][seed]["results"]:
                view_set, _, category = key.partition("/")
                if category and view_set in VIEW_SETS:
                    found.add(category)
    return sorted(found)


def category_rows(rows: dict[str, str], payloads: dict[str, dict[int, dict]], seeds: list[int]) -> list[list[Any]]:
    """``categories.csv``'s rows (header ``method, run, seed, view_set, category`` and the metrics), one per row x
    seed x view set x category with a result, fractions as the runs logged them."""
    out: list[list[Any]] = []
    for category in _categories(payloads, list(rows.values()), seeds):
        for title, run in rows.items():
            for seed in seeds:
                for view_set in VIEW_SETS:
                    values = payloads[run][seed]["results"].get(f"{view_set}/{category}")
                    if values is None:
                        continue
                    metrics = [_finite(metric_value(values, m)) for m in METRICS]
                    out.append([title, run, seed, view_set, category, *metrics])
    return out


def category_estimates(
    rows: dict[str, str], payloads: dict[str, dict[int, dict]], seeds: list[int], metric: str = "iou@0.4"
) -> dict[str, dict[str, dict[str, Estimate | None]]]:
    """``{category: {row title: {view_set: mean of the category's ``metric`` over seeds, or None}}}``."""
    out: dict[str, dict[str, dict[str, Estimate | None]]] = {}
    for category in _categories(payloads, list(rows.values()), seeds):
        out[category] = {}
        for title, run in rows.items():
            out[category][title] = {}
            for view_set in VIEW_SETS:
                key = f"{view_set}/{category}"
                values = [
                    v
                    for s in seeds
                    if (v := metric_value(payloads[run][s]["results"].get(key, {}), metric)) is not None
                    and math.isfinite(v)
                ]
                out[category][title][view_set] = seed_estimate(values)
    return out


def category_markdown(estimates: dict[str, dict[str, dict[str, Estimate | None]]], seeds: int) -> str:
    """``categories.md``: per view set, a table of mean IoU\\@0.4 (%) with a row per category and a column per
    strategy (``mean ± 95 % CI half-width`` over several seeds)."""
    titles = list(next(iter(estimates.values()))) if estimates else []
    interval = interval_text(seeds, "over {n} seeds")
    lines = [f"# Per-category results: mIoU@0.4 (%, test set; {interval})"]
    if not estimates:
        return "\n".join([*lines, "", "The runs logged no per-category results."]) + "\n"
    for view_set in VIEW_SETS:
        lines += ["", f"## {VIEW_SET_TITLES[view_set]}", ""]
        lines += ["| " + " | ".join(["Category", *titles]) + " |", "|" + "---|" * (1 + len(titles))]
        for category, per_title in estimates.items():
            cells = []
            for title in titles:
                estimate = per_title[title][view_set]
                if estimate is None:
                    cells.append("-")
                elif math.isfinite(estimate.half_width):
                    cells.append(f"{100 * estimate.mean:.2f} ± {100 * estimate.half_width:.2f}")
                else:
                    cells.append(f"{100 * estimate.mean:.2f}")
            lines.append("| " + " | ".join([category, *cells]) + " |")
    return "\n".join(lines) + "\n"


def _json_safe(value: Any) -> Any:
    """``value`` with non-finite floats as ``None``, tuples as lists and other objects as their ``repr``."""
    if isinstance(value, float):
        return _finite(value)
    if isinstance(value, (str, int, bool)) or value is None:
        return value
    if isinstance(value, dict):
        return {str(k): _json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_safe(v) for v in value]
    if isinstance(value, Path):
        return str(value)
    return repr(value)


def _environment() -> dict[str, str]:
    import lightning
    import torch

    import lightning_vtr

    return {
        "lightning_vtr": lightning_vtr.__version__,
        "python": platform.python_version(),
        "torch": torch.__version__,
        "lightning": lightning.__version__,
        "platform": platform.platform(),
    }


def report_record(
    *,
    command: str,
    equivalent: str,
    settings: dict[str, Any],
    strategies: dict[str, Any],
    rows: dict[str, str],
    seeds: list[int],
    payloads: dict[str, dict[int, dict]],
    table1: dict[str, dict[str, dict[str, Estimate | None]]],
    differences: dict[str, dict[str, dict[str, dict[str, Estimate | None]]]],
    categories: dict[str, dict[str, dict[str, dict[str, Estimate | None]]]],
    maps: dict[str, Any],
    files: dict[str, str],
) -> dict[str, Any]:
    """``report.json``'s content: every number of the report with what produced it.

    Args:
        command: the command line the report shows (the user's, or the equivalent one).
        equivalent: the ``lightning-vtr report`` command that reruns it.
        settings: the resolved :class:`~lightning_vtr.experiments.report_config.ReportConfig`, JSON-ready.
        strategies: per strategy name of the rows, its title, description and resolved selector and callback.
        rows: row title -> run name.
        seeds: the seeds.
        payloads: every run's ``results.json`` payload per seed.
        table1: :func:`table1_estimates`.
        differences: ``{baseline: {metric: {row title: {view_set: Estimate or None}}}}``.
        categories: ``{metric: {category: {row title: {view_set: Estimate or None}}}}``.
        maps: row title -> the robustness map's summary (empty without maps).
        files: name -> file name of everything the report wrote.

    Returns:
        A JSON-ready dict: ``command``, ``argv`` (this process's ``sys.argv`` joined with :func:`shlex.join`),
        ``equivalent_command``, ``version`` and ``environment``, ``settings``, ``strategies``, ``rows``, ``seeds``,
        ``runs`` (``{run: {seed: {"results", "train_seconds", "eval_seconds", "generated_samples"}}}``, every
        metric per view set and category as the runs logged it), ``table1``, ``differences``, ``categories``,
        ``maps`` and ``files``. Estimates are :func:`estimate_record` dicts; non-finite numbers are ``null``.
    """
    import lightning_vtr

    runs = {
        run: {
            str(seed): {
                key: payload.get(key)
                for key in ("results", "train_seconds", "eval_seconds", "generated_samples", "num_views", "timing")
                if key in payload
            }
            for seed, payload in per_seed.items()
            if payload is not None
        }
        for run, per_seed in payloads.items()
    }

    def records(tree: Any) -> Any:
        if isinstance(tree, Estimate) or tree is None:
            return estimate_record(tree)
        return {k: records(v) for k, v in tree.items()}

    return _json_safe(
        {
            "command": command,
            "argv": shlex.join(sys.argv),
            "equivalent_command": equivalent,
            "version": lightning_vtr.__version__,
            "environment": _environment(),
            "settings": settings,
            "strategies": strategies,
            "rows": rows,
            "seeds": seeds,
            "runs": runs,
            "table1": records(table1),
            "differences": records(differences),
            "categories": records(categories),
            "maps": maps,
            "files": files,
        }
    )


def dump_json(path: Path, record: dict[str, Any]) -> None:
    """Write ``record`` as strict JSON (no NaN), atomically."""
    atomic_write(path, json.dumps(record, indent=1, allow_nan=False) + "\n")


def _settings(config: Any) -> dict[str, Any]:
    """The resolved :class:`~lightning_vtr.experiments.report_config.ReportConfig`, field by field."""
    import dataclasses

    settings = {f.name: getattr(config, f.name) for f in dataclasses.fields(config)}
    settings["experiment"] = dataclasses.asdict(config.experiment)
    settings["synthesizer"] = None if config.synthesizer is None else repr(config.synthesizer)
    return settings


def _strategy_settings(config: Any, runs: Sequence[Any]) -> dict[str, Any]:
    """Per run of the plan that fine-tunes: its row, arguments and the selector and callback they build."""
    from lightning_vtr.experiments import training

    variants = config.variants
    seed_exp = config.seed_config(config.seeds[0])
    out: dict[str, Any] = {}
    for run in runs:
        if run.single_view_of is not None:
            continue
        variant = variants[run.strategy]
        callback_kwargs = {**config.callback_kwargs, **run.callback_kwargs}
        entry: dict[str, Any] = {
            "strategy": run.strategy,
            "title": variant.title,
            "description": variant.description,
            "same_as": run.same_as,
            "selector_kwargs": run.selector_kwargs,
            "callback_kwargs": callback_kwargs,
            "resolved": training.resolved_strategy(
                run.strategy, run.selector_kwargs, callback_kwargs, variants=variants
            ),
        }
        callback = training.make_strategy(
            run.strategy, seed_exp, config.synthesizer, run.selector_kwargs, callback_kwargs, variants=variants
        )
        if callback is not None:
            callback = cast(Any, callback)  # an ErrorGuidedViewAugmentation (make_strategy's annotation: Callback)
            selector = callback.selector
            entry["selector"] = f"{type(selector).__module__}.{type(selector).__qualname__}"
            entry["selector_repr"] = repr(selector)
            entry["selector_settings"] = selector.settings()
            entry["callback_repr"] = repr(callback)
            entry["callback_settings"] = callback.settings()
        out[run.name] = entry
    return out


def write_paper_files(
    config: Any, runs: Sequence[Any], results: Any, summary: Any, maps: dict[str, Any], files: dict[str, Path]
) -> dict[str, Path]:
    """Write ``table1.{md,csv,tex}``, ``differences.{md,tex}``, ``categories.{csv,md}`` and, last,
    ``report.json`` into the report's folder.

    Args:
        config: the :class:`~lightning_vtr.experiments.report_config.ReportConfig`.
        runs: its plan.
        results: the runs' :class:`~lightning_vtr.experiments.report_run.ReportResults`.
        summary: :func:`~lightning_vtr.experiments.report_render.summarize`'s numbers.
        maps: row title -> map summary (:func:`~lightning_vtr.experiments.report_maps.write_maps`; empty without
            maps).
        files: the report's other files, name -> path, listed in ``report.json``.

    Returns:
        name -> path of every file written here.
    """
    from lightning_vtr.experiments.report_render import equivalent_command
    from lightning_vtr.experiments.report_tables import (
        difference_note,
        difference_table,
        paired_differences,
        robustness_table,
    )

    out = Path(config.experiment.out)
    seeds, rows, payloads = list(config.seeds), summary.rows, results.payloads
    titles = config.titles()
    interval = interval_text(len(seeds))
    command = config.command or equivalent_command(config)
    paths = {
        "table1_markdown": out / "table1.md",
        "table1_csv": out / "table1.csv",
        "table1_latex": out / "table1.tex",
        "differences_markdown": out / "differences.md",
        "differences_latex": out / "differences.tex",
        "categories_csv": out / "categories.csv",
        "categories_markdown": out / "categories.md",
    }
    table1 = table1_estimates(rows, payloads, seeds)
    heading = f"Table 1: robustness to view transformations (%, test set; {interval})"
    atomic_write(paths["table1_markdown"], f"# {heading}\n\n{robustness_table(rows, payloads, METRICS, seeds)}\n")
    write_csv(
        paths["table1_csv"],
        ["method", "run", "view_set", "metric", "mean", "half_width", "ci_low", "ci_high", "seeds"],
        table1_csv(rows, table1),
    )
    bold = separated_best(rows, payloads, seeds, TABLE1_LATEX_METRICS)
    caption = f"{heading}\nbold: the row whose paired difference to every other row has a 95 % CI above zero"
    if len(seeds) < 2:
        caption += f" (none: {NO_INTERVAL})"
    atomic_write(paths["table1_latex"], table1_latex(table1, caption=f"{caption}\n{command}", bold=bold))

    baselines = list(summary.differences)
    differences = {b: {m: paired_differences(rows, b, payloads, m, seeds) for m in METRICS} for b in baselines}
    markdown = ["# Paired differences (mIoU@0.4 points, test set)"]
    latex = [f"% {command}"]
    for baseline in baselines:
        note = difference_note(titles[baseline], len(seeds))
        markdown += ["", f"## Paired difference to {titles[baseline]}", "", note, ""]
        markdown.append(difference_table(differences[baseline]["iou@0.4"], len(seeds)))
        caption = f"Paired difference to {titles[baseline]} (mIoU@0.4 points, {interval})"
        latex.append(difference_latex(differences[baseline]["iou@0.4"], caption=caption))
    atomic_write(paths["differences_markdown"], "\n".join(markdown) + "\n")
    atomic_write(paths["differences_latex"], "\n".join(latex))

    write_csv(
        paths["categories_csv"],
        ["method", "run", "seed", "view_set", "category", *METRICS],
        category_rows(rows, payloads, seeds),
    )
    categories = {m: category_estimates(rows, payloads, seeds, m) for m in METRICS}
    atomic_write(paths["categories_markdown"], category_markdown(categories["iou@0.4"], len(seeds)))

    paths["json"] = out / "report.json"
    listed = {name: Path(path).name for name, path in {**files, **paths}.items()}
    if maps:
        listed["maps"] = "maps/index.html"
    record = report_record(
        command=command,
        equivalent=equivalent_command(config),
        settings=_settings(config),
        strategies=_strategy_settings(config, runs),
        rows=rows,
        seeds=seeds,
        payloads=payloads,
        table1=table1,
        differences=differences,
        categories=categories,
        maps=maps,
        files=listed,
    )
    dump_json(paths["json"], record)
    return paths
