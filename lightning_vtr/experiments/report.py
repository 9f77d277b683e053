r"""The paper's comparison on your data: ``lightning-vtr report`` and :func:`run_report`.

For each seed the report pretrains one model on Aligned (:func:`~lightning_vtr.experiments.training.pretrain`),
fine-tunes a copy with every strategy under the same budget
(:func:`~lightning_vtr.experiments.training.run_strategy`) and tests each on Aligned / Hemispherical /
Spherical, every test object on ``test_repeats`` fixed view sets that are the same for every strategy of
the seed. Every strategy is also compared seed by seed with ``none`` and ``random``: the same pretrained model,
the same test items (a paired difference, :mod:`~lightning_vtr.experiments.statistics`).

The rows are names of :data:`~lightning_vtr.experiments.strategies.VARIANTS` (the rows of
``strategies.yaml``; ``lightning-vtr report --list-strategies`` prints them). By default
:data:`MAIN_STRATEGIES`: ``none`` (no augmentation), ``random`` (Random as the paper draws it, angle-uniform),
``random_area`` (area-uniform Random), ``paper`` (the paper's rule) and ``error_guided`` (the package's default
rule, ``ErrorGuidedViewAugmentation()``). The ablations of the default rule (:data:`ABLATIONS`) are opt-in:

* ``k``: bin interval :math:`K \in \{15, 30, 60, 90\}` degrees (the K = 30 run is the ``error_guided`` row);
* ``pool``: with vs without the per-category viewpoint pool (``use_pool=False``);
* ``single_view``: the "none" and "error_guided" fine-tuned models tested with 1 input view.

Strategies that resolve to the same selector and callback arguments are fitted once and shown in both rows.

The work is split in steps, each a module: :mod:`~lightning_vtr.experiments.report_config` (what to run),
:mod:`~lightning_vtr.experiments.report_plan` (the runs of a seed), :mod:`~lightning_vtr.experiments.report_run`
(running them, cached), :mod:`~lightning_vtr.experiments.report_tables` and
:mod:`~lightning_vtr.experiments.report_render` (the Markdown), :mod:`~lightning_vtr.experiments.report_timing`
(the time split) and :mod:`~lightning_vtr.experiments.report_files` (CSV files and chart). It writes into
``out`` (the experiment's, :attr:`ReportConfig.experiment`):

* ``report.md``: a header (command, budget, wall time); Table 1 (a row per strategy, columns view set x
  mIoU\@0.4, best-threshold mIoU and F-score, in %; over several seeds ``mean ± half-width of the 95 % Student-t
  confidence interval``); the paired difference of every row to None-VTR and to Random (mIoU points: mean, 95 %
  CI, how many seeds agree in sign); where each strategy's generated training views went (share per 30-degree
  pitch band, share of view sets with an antipodal pair, mean angle within a set; from the callback's
  ``vtr_selection`` records, pooled over seeds); the ablation tables; where the time went (pretraining;
  fine-tuning split into training steps, data loading, validation, selection + synthesis and the rest;
  testing split into the model and data loading; then per run);
* ``results.csv``: one row per run x seed x view set (``run, strategy, seed, view_set, iou@0.4, iou_best,
  fscore, train_seconds``), metrics as fractions in [0, 1]; ``iou_best`` is VTR's best-threshold mIoU (the
  largest of the mean IoUs at 0.2, 0.3, 0.4 and 0.5), the F-score is the community convention (What3D's);
* ``differences.csv``: one row per baseline x run x view set x metric (``baseline, run, view_set,
  metric, mean, ci_low, ci_high, seeds, agree``), fractions;
* ``report.png``: mIoU per view set and strategy as grouped bars (error bars: 95 % CI over seeds) and the
  pitch histogram of each strategy's generated views;
* ``table1.md``, ``table1.csv``, ``table1.tex``: Table 1 alone, as Markdown, as one row per strategy x view set x
  metric (``method, run, view_set, metric, mean, half_width, ci_low, ci_high, seeds``, fractions) and as a
  booktabs LaTeX ``tabular`` (mIoU and F-score per view set, ``mean $\pm$ half-width`` in %, best in bold);
* ``differences.md``, ``differences.tex``: the paired-difference tables (to None-VTR, Random and
  :attr:`ReportConfig.reference`);
* ``categories.csv`` (one row per strategy x seed x view set x category, the metrics as fractions) and
  ``categories.md`` (per view set, mean IoU per category and strategy);
* ``maps/`` (:attr:`ReportConfig.maps`): each strategy's viewpoint robustness map, pooled over seeds
  (:mod:`~lightning_vtr.experiments.report_maps`);
* ``report.json``, written last: every number above, every run's results, the command, ``sys.argv``, the package
  version, the resolved :class:`ReportConfig` and each strategy's resolved selector and callback
  (:func:`~lightning_vtr.experiments.report_paper.report_record`);
* ``timing.json``: the wall time of every invocation and the time split (seconds per stage);
* ``seed_<s>/<run>/results.json`` (metrics and stage timings), the ``vtr_selection`` records and
  checkpoints of every run, ``seed_<s>/pretrain/timing.json``.

Resumable: a finished run (its ``results.json``, refused when written under another experiment
configuration), a finished pretraining (``pretrained.ckpt``) and a finished single-view evaluation are
reused, and an interrupted fit resumes from its ``last.ckpt``; so a killed report re-run only does what
is missing. Every JSON file read back from ``out`` is checked against what the report writes
(:mod:`~lightning_vtr.experiments.output_files`): a truncated or tampered one is refused with one line naming
the file, the field, the type expected and found, and which file or folder to delete to redo it.
"""

from __future__ import annotations

import time
from pathlib import Path

from lightning_vtr.experiments.report_config import (
    ABLATIONS,
    BASELINES,
    MAIN_STRATEGIES,
    PITCH_BANDS,
    STRATEGIES,
    STRATEGY_TITLES,
    ReportConfig,
    default_experiment,
)
from lightning_vtr.experiments.report_files import write_chart, write_differences_csv, write_results_csv
from lightning_vtr.experiments.report_paper import write_paper_files
from lightning_vtr.experiments.report_plan import plan_runs
from lightning_vtr.experiments.report_render import render_markdown, summarize
from lightning_vtr.experiments.report_run import execute_runs
from lightning_vtr.experiments.report_timing import record_invocation, time_split
from lightning_vtr.utils.io import atomic_write

__all__ = [
    "ABLATIONS",
    "BASELINES",
    "MAIN_STRATEGIES",
    "PITCH_BANDS",
    "STRATEGIES",
    "STRATEGY_TITLES",
    "ReportConfig",
    "default_experiment",
    "run_report",
]


def run_report(config: ReportConfig) -> dict:
    """Run (or resume) the whole comparison and write ``report.md``, ``results.csv``, ``differences.csv``,
    ``report.png`` and ``timing.json``.

    Args:
        config: the report's models, data, budget, strategies and ablations.

    Returns:
        ``{"runs": {run: {seed: results.json payload}}, "markdown": str, "paths": {name: Path},
        "wall_seconds": this call's wall time, "total_wall_seconds": over every call on ``out``,
        "differences": {baseline: {row title: {view_set: Estimate}}} (mIoU, fractions),
        "validation": {run: {seed: {"results": ...}}} and "validation_differences" (empty unless the report
        validates), "views": {row title: view statistics}, "time_split": seconds per stage}``.

    Raises:
        ValueError: for an invalid configuration (from :class:`ReportConfig`).
        RuntimeError: a fit of a parallel report (``jobs`` > 1) failed.

    Example::

        result = run_report(ReportConfig(default_experiment(out="runs/report"), seeds=[0, 1, 2]))
        print(result["markdown"])
    """
    start = time.perf_counter()
    out = Path(config.experiment.out)
    out.mkdir(parents=True, exist_ok=True)
    runs = plan_runs(config)
    results = execute_runs(config, runs)
    wall = time.perf_counter() - start

    seeds = list(config.seeds)
    split = time_split(runs, results.payloads, results.pretraining, seeds)
    paths = {
        "markdown": out / "report.md",
        "csv": out / "results.csv",
        "differences": out / "differences.csv",
        "chart": out / "report.png",
        "timing": out / "timing.json",
    }
    timing = record_invocation(paths["timing"], wall, split)
    summary = summarize(config, results)
    markdown = render_markdown(config, runs, results, summary, split, timing)
    atomic_write(paths["markdown"], markdown)
    write_results_csv(paths["csv"], runs, results.payloads, seeds)
    write_differences_csv(paths["differences"], summary.rows, results.payloads, seeds, list(summary.differences))
    write_chart(paths["chart"], summary.rows, results.payloads, seeds, summary.views)
    maps: dict = {}
    if config.maps:
        from lightning_vtr.experiments.report_maps import strategy_maps, write_maps

        reference = next((title for title, run in summary.rows.items() if run == "none"), None)
        maps = write_maps(out, strategy_maps(config, summary.rows, runs), reference)
        paths["maps"] = out / "maps" / "index.html"
    paths.update(write_paper_files(config, runs, results, summary, maps, dict(paths)))
    return {
        "runs": results.payloads,
        "markdown": markdown,
        "paths": paths,
        "wall_seconds": wall,
        "total_wall_seconds": sum(timing["invocations"]),
        "differences": summary.differences,
        "validation": results.validation if config.validation_repeats is not None else {},
        "validation_differences": summary.validation_differences,
        "views": summary.views,
        "time_split": split,
        "maps": maps,
    }
