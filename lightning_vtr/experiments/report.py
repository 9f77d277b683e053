r"""The paper's comparison on your data: ``lightning-vtr report`` and :func:`run_report`.

For each seed the report pretrains one model on Aligned (:func:`~lightning_vtr.experiments.training.pretrain`),
fine-tunes a copy with every strategy under the same budget
(:func:`~lightning_vtr.experiments.training.run_strategy`) and tests each on Aligned / Hemispherical /
Spherical, every test object on ``test_repeats`` fixed view sets that are the same for every strategy of
the seed. A comparison is a claim about a difference, so every strategy is also compared seed by seed
with ``none`` and ``random``: the same pretrained model, the same test items (a paired difference,
:mod:`~lightning_vtr.experiments.statistics`).

The rows are names of :data:`~lightning_vtr.experiments.training.VARIANTS`. By default
:data:`MAIN_STRATEGIES`: ``none`` (no augmentation), ``random`` (angle-uniform views, the released code's
sampler), ``error_guided`` (the callback's default, whatever it is) and ``paper`` (the paper's exact rule).
Opt-in: the paper's other baselines (``nature``, ``viat``, ``mvtn``), ``random_area`` (area-uniform views),
the error-guided variants (``released``, ``visible``, ``visible_nms``, ``visible_tau``, ``visible_tau3``,
``visible_nms_search``, ``visible_tau_search``), and the paper's ablations of the error-guided method:

* ``k``: bin interval :math:`K \in \{15, 30, 60, 90\}` degrees (the K = 30 run is the main "Ours" run);
* ``pool``: with vs without the per-category viewpoint pool (``use_pool=False``);
* ``single_view``: the "none" and "error_guided" fine-tuned models tested with 1 input view.

Time: at the default budget (:func:`default_experiment`) the main comparison took 50 min on 2 idle CPU cores
(per seed: ~7 min of pretraining, ~3 min of fine-tuning and testing per strategy; training steps 80 %).
Strategies that resolve to the same selector and callback arguments (``error_guided`` and ``paper`` while the
default is the paper's rule) are fitted once and shown in both rows. ``jobs`` (``--jobs``) runs several fits at
once in child processes, which uses small CPUs better (:attr:`ReportConfig.jobs`): with ``--jobs 2`` the main
comparison took 39 min on the same 2 cores.

It writes into ``out`` (the experiment's, :attr:`ReportConfig.experiment`):

* ``report.md``: a header (command, budget, wall time); Table 1 (a row per strategy, columns view set x
  mIoU\@0.4, best-threshold mIoU and F-score, in %; over several seeds ``mean ± half-width of the 95 % Student-t confidence
  interval``); the paired difference of every row to None-VTR and to Random (mIoU points: mean, 95 % CI,
  how many seeds agree in sign); where each strategy's generated training views went (share per 30-degree
  pitch band, share of view sets with an antipodal pair, mean angle within a set; from the callback's
  ``vtr_selection`` records, pooled over seeds); the ablation tables; where the time went (pretraining;
  fine-tuning split into training steps, data loading, validation, selection + synthesis and the rest;
  testing split into the model and data loading; then per run);
* ``results.csv``: one row per run x seed x view set (``run, strategy, seed, view_set, iou@0.4, iou_best,
  fscore, train_seconds``), metrics as fractions in [0, 1]; ``iou_best`` is VTR's best-threshold mIoU (the
  largest of the mean IoUs at 0.2, 0.3, 0.4 and 0.5), the F-score is the community convention (What3D's, as
  LegoFormer and LRGT report it, so it sits beside published tables);
* ``differences.csv``: one row per baseline x run x view set x metric (``baseline, run, view_set,
  metric, mean, ci_low, ci_high, seeds, agree``), fractions;
* ``report.png``: mIoU per view set and strategy as grouped bars (error bars: 95 % CI over seeds) and the
  pitch histogram of each strategy's generated views;
* ``timing.json``: the wall time of every invocation and the time split (seconds per stage);
* ``seed_<s>/<run>/results.json`` (metrics and stage timings), the ``vtr_selection`` records and
  checkpoints of every run, ``seed_<s>/pretrain/timing.json``.

Resumable: a finished run (its ``results.json``, refused when written under another experiment
configuration), a finished pretraining (``pretrained.ckpt``) and a finished single-view evaluation are
reused, and an interrupted fit resumes from its ``last.ckpt``; so a killed report re-run only does what
is missing.

Default budget (:class:`ReportConfig`, :func:`default_experiment`): tiny Pix2Vox++ on the embedded dataset
(170 training, 20 validation and 50 test objects), 3 seeds, 30 pretraining epochs, 10 fine-tuning epochs
per strategy, 5 % of the training objects given new views per selection, 4 test view sets per object,
the four main strategies and no ablation: per seed one pretraining, three fine-tunings and three test passes
of 600 items (50 objects x 4 view sets x 3 sets). Where the time goes, measured on a small run (the
30-object test dataset of the tests, 3 + 3 epochs, one seed, one torch thread, 100 s in all): fine-tuning
45 % (training steps 33 %, validation 7 %, selection + synthesis 2.6 %, data loading 0.8 %), testing 47 %
(almost all in the test step, where the F-score's surface sampling and nearest-neighbour queries cost
about 0.04 s per item, as much as the forward pass), pretraining 8 %. At the default budget the training
steps dominate (about 5,000 pretraining and 7,000 fine-tuning samples per seed against 2,400 test items);
``report.md`` prints the measured split of every run.
"""

from __future__ import annotations

import contextlib
import csv
import json
import math
import pickle
import shlex
import time
import traceback
from collections.abc import Sequence
from concurrent import futures
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from lightning_vtr.experiments import training
from lightning_vtr.experiments.statistics import (
    Estimate,
    antipodal_share,
    mean_estimate,
    paired_difference,
    pitch_histogram,
    triplet_spread,
)
from lightning_vtr.evaluation.tables import BEST_IOU, VIEW_SET_TITLES, best_threshold_iou, format_robustness_table
from lightning_vtr.experiments.training import STRATEGIES, VARIANTS, ExperimentConfig
from lightning_vtr.protocol import VIEW_SETS
from lightning_vtr.utils.io import atomic_write
from lightning_vtr.utils.validation import check_choice, check_int, check_type

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

#: Row titles of the tables, per strategy name of :data:`~lightning_vtr.experiments.training.VARIANTS`.
STRATEGY_TITLES: dict[str, str] = {name: variant.title for name, variant in VARIANTS.items()}
#: The report's default rows: no augmentation, angle-uniform random views, the callback's default and the
#: paper's exact rule. Any other name of :data:`~lightning_vtr.experiments.training.VARIANTS` is opt-in.
MAIN_STRATEGIES: tuple[str, ...] = ("none", "random", "error_guided", "paper")
#: The strategies every other one is compared with, seed by seed (when the report runs them).
BASELINES: tuple[str, ...] = ("none", "random")
#: The ablations of the error-guided method the report can run (none by default).
ABLATIONS: tuple[str, ...] = ("k", "pool", "single_view")
#: Pitch bands (degrees) of the view-distribution table and chart.
PITCH_BANDS: tuple[int, ...] = (-90, -60, -30, 0, 30, 60, 90)
_METRICS = ("iou@0.4", BEST_IOU, "fscore")
_MAIN_K = 30  # the paper's K; the "error_guided" run uses it


def default_experiment(**changes: Any) -> ExperimentConfig:
    """The report's default experiment with ``changes``: tiny Pix2Vox++ on the embedded dataset, 30 pretraining
    and 10 fine-tuning epochs, batch size 8, every test object on 4 view sets, written to ``runs/report``
    (see the module docstring for the time).

    Example::

        run_report(ReportConfig(default_experiment(data="/data/shapenet_vtr", out="runs/shapenet"), seeds=[0, 1, 2]))
    """
    defaults = {"out": "runs/report", "pretrain_epochs": 30, "finetune_epochs": 10, "batch_size": 8, "test_repeats": 4}
    return ExperimentConfig(**{**defaults, **changes})


@dataclass
class ReportConfig:
    """What the report trains and where it writes: one experiment, repeated per seed and per strategy.

    Attributes:
        experiment: model, data, budget and Trainer settings of every run
            (:class:`~lightning_vtr.experiments.training.ExperimentConfig`; default
            :func:`default_experiment`). Its ``out`` is the report's directory (runs go to
            ``out/seed_<s>/``, tables, CSV and chart to ``out``) and its ``seed`` is replaced by each of
            ``seeds`` (:meth:`seed_config`). The report needs ``pretrain_epochs`` and ``finetune_epochs``
            of at least 1.
        seeds: one full comparison per seed (pretraining included); several give means with 95 %
            confidence intervals and paired differences.
        strategies: the rows, names of :data:`~lightning_vtr.experiments.training.VARIANTS` (default
            :data:`MAIN_STRATEGIES`).
        ablations: which of :data:`ABLATIONS` to run (default none; they add the "error_guided" run, and
            ``single_view`` the "none" run, when ``strategies`` lacks them).
        k_values: bin intervals of the K ablation, degrees (each must divide 180).
        selector_kwargs: per strategy name, arguments of its selector over the variant's (e.g.
            ``{"viat": {"population": 4}}``).
        callback_kwargs: arguments of every strategy's
            :class:`~lightning_vtr.callback.ErrorGuidedViewAugmentation` (e.g. ``{"progress_bar": False}``),
            over the variants'.
        synthesizer: the callbacks' synthesizer (``None``: mesh rendering).
        command: the command line shown in the header (``None``: the equivalent ``lightning-vtr report``).
        validation_triplets: also test every fine-tuned model on the *validation* objects, each on this many
            fixed view sets (:func:`~lightning_vtr.experiments.training.validate_run`), and add the paired
            differences there to ``report.md``: the place to choose among strategies, so the test split only
            confirms. ``None`` (the default): off.
        jobs: fits run at once, each in its own (spawned) process with ``torch.get_num_threads() // jobs``
            torch threads (at least 1): every seed's pretraining first, then its runs as soon as it is done.
            Their output goes to ``seed_<s>/logs/<run>.log``; the report prints a line per finished fit, then
            builds the tables from the runs' caches as usual. Results equal a one-process report's at the same
            thread count per fit (a fit's numbers depend on its thread count). On 2 CPU cores ``jobs=2`` ran the
            default report in 39 min against 50 min in one two-thread process. Needs ``devices`` 1 and a
            picklable ``synthesizer``. Default 1: everything in this process.
    """

    experiment: ExperimentConfig = field(default_factory=default_experiment)
    seeds: Sequence[int] = (0, 1, 2)
    strategies: Sequence[str] = MAIN_STRATEGIES
    ablations: Sequence[str] = ()
    k_values: Sequence[int] = (15, 30, 60, 90)
    selector_kwargs: dict[str, dict[str, Any]] = field(default_factory=dict)
    callback_kwargs: dict[str, Any] = field(default_factory=dict)
    synthesizer: Any = None
    command: str | None = None
    validation_triplets: int | None = None
    jobs: int = 1

    def __post_init__(self) -> None:
        check_type("experiment", self.experiment, ExperimentConfig)
        for name in ("pretrain_epochs", "finetune_epochs"):
            check_int(f"experiment.{name}", getattr(self.experiment, name), minimum=1)
        self.seeds = [check_int("seeds", s) for s in self.seeds]
        self.strategies = list(self.strategies)
        self.ablations = list(self.ablations)
        self.k_values = [check_int("k_values", k, minimum=1) for k in self.k_values]
        if not self.seeds or len(set(self.seeds)) != len(self.seeds):
            raise ValueError(f"`seeds` must be a non-empty list of distinct seeds, got {self.seeds}")
        if not self.strategies:
            raise ValueError(f"`strategies` must name at least one of {list(VARIANTS)}, got []")
        for strategy in self.strategies:
            check_choice("strategies", strategy, VARIANTS)
        for ablation in self.ablations:
            check_choice("ablations", ablation, ABLATIONS)
        bad = [k for k in self.k_values if 180 % k]
        if bad:
            raise ValueError(f"`k_values` must divide 180 (degrees), got {bad}")
        for strategy in self.selector_kwargs:
            check_choice("selector_kwargs", strategy, VARIANTS)
        if self.validation_triplets is not None:
            check_int("validation_triplets", self.validation_triplets, minimum=1)
        if check_int("jobs", self.jobs, minimum=1) > 1:
            if self.experiment.devices != 1:
                raise ValueError(
                    f"`jobs` > 1 runs one-device fits side by side; got jobs={self.jobs} with "
                    f"experiment.devices={self.experiment.devices!r} (use jobs=1 for multi-device fits)"
                )
            try:
                pickle.dumps(self.synthesizer)
            except Exception as error:  # noqa: BLE001 - any pickling failure means the same thing here
                raise ValueError(
                    f"`jobs` > 1 sends the synthesizer to child processes, but {type(self.synthesizer).__name__} "
                    f"cannot be pickled ({error}); use jobs=1"
                ) from error

    def seed_config(self, seed: int) -> ExperimentConfig:
        """The :class:`~lightning_vtr.experiments.training.ExperimentConfig` of every run of ``seed``."""
        return replace(self.experiment, seed=seed, out=str(Path(self.experiment.out) / f"seed_{seed}"))


@dataclass(frozen=True)
class _Run:
    """One fine-tuning run (or a single-view evaluation of one) of the report."""

    name: str  # directory and CSV ``run`` name
    strategy: str  # a name of VARIANTS
    selector_kwargs: dict[str, Any] = field(default_factory=dict)
    callback_kwargs: dict[str, Any] = field(default_factory=dict)
    single_view_of: str | None = None  # the fine-tuned run a single-view evaluation tests
    same_as: str | None = None  # an earlier run whose selector and callback resolve to the same arguments


def _plan(config: ReportConfig) -> list[_Run]:
    """Every run of one seed, in execution order (the order of ``VARIANTS``, then the ablations), once each."""
    strategies = list(config.strategies)
    if config.ablations and "error_guided" not in strategies:
        strategies.append("error_guided")
    if "single_view" in config.ablations and "none" not in strategies:
        strategies.insert(0, "none")
    base = {s: dict(config.selector_kwargs.get(s, {})) for s in VARIANTS}
    runs = [_Run(s, s, base[s]) for s in VARIANTS if s in strategies]
    if "k" in config.ablations:
        runs += [
            _Run(f"error_guided_k{k}", "error_guided", {**base["error_guided"], "k": k})
            for k in config.k_values
            if k != _MAIN_K
        ]
    if "pool" in config.ablations:
        runs.append(_Run("error_guided_no_pool", "error_guided", base["error_guided"], {"use_pool": False}))
    if "single_view" in config.ablations:
        runs += [_Run(f"single_view_{s}", s, single_view_of=s) for s in ("none", "error_guided")]
    return _merge_identical(runs, config)


def _merge_identical(runs: list[_Run], config: ReportConfig) -> list[_Run]:
    """Mark each fine-tuning run that would train exactly what an earlier one trains (the callback's default
    and ``"paper"`` while the default is the paper's rule) as the same run: the report fits it once."""
    seen: dict[str, str] = {}
    out = []
    for run in runs:
        if run.single_view_of is None:
            callback_kwargs = {**config.callback_kwargs, **run.callback_kwargs}
            resolved = training.resolved_strategy(run.strategy, run.selector_kwargs, callback_kwargs)
            key = json.dumps(resolved, sort_keys=True, default=repr)
            if key in seen:
                run = replace(run, same_as=seen[key])
            else:
                seen[key] = run.name
        out.append(run)
    return out


def _fit_and_validate(
    config: ReportConfig, seed_exp: ExperimentConfig, pretrained: Path, run: _Run
) -> tuple[dict, dict | None]:
    """One run's fit and test (``results.json`` payload) and, when the report validates, its validation results;
    both cached in the run's directory."""
    payload = training.run_strategy(
        run.strategy,
        seed_exp,
        pretrained,
        run_name=run.name,
        synthesizer=config.synthesizer,
        selector_kwargs=run.selector_kwargs,
        callback_kwargs={**config.callback_kwargs, **run.callback_kwargs},
    )
    if config.validation_triplets is None:
        return payload, None
    return payload, training.validate_run(seed_exp, Path(seed_exp.out) / run.name, config.validation_triplets)


@contextlib.contextmanager
def _log_handlers_to(stream: Any) -> Any:
    """Point every logging handler that writes to the console (Lightning's "GPU available" lines) at ``stream``
    for the block; ``redirect_stdout`` alone misses them, as they hold the console stream they were made with."""
    import logging
    import sys

    loggers = [
        logging.getLogger(),
        *(v for v in logging.Logger.manager.loggerDict.values() if isinstance(v, logging.Logger)),
    ]
    moved = []
    for logger in loggers:
        for handler in logger.handlers:
            if isinstance(handler, logging.StreamHandler) and handler.stream in (sys.__stdout__, sys.__stderr__):
                moved.append((handler, handler.setStream(stream)))
    try:
        yield
    finally:
        for handler, previous in moved:
            handler.setStream(previous)


def _log_path(config: ReportConfig, seed: int, run: _Run | None) -> Path:
    return Path(config.seed_config(seed).out) / "logs" / f"{'pretrain' if run is None else run.name}.log"


def _fit_unit(config: ReportConfig, seed: int, run: _Run | None, threads: int) -> float:
    """One unit of a parallel report, in a child process: the seed's pretraining (``run`` ``None``) or one
    run's fit, test and validation, written to their caches; its output goes to ``seed_<s>/logs/<name>.log``.
    Returns its wall time in seconds."""
    import torch

    start = time.perf_counter()
    torch.set_num_threads(threads)
    seed_exp = config.seed_config(seed)
    log = _log_path(config, seed, run)
    log.parent.mkdir(parents=True, exist_ok=True)
    with (
        open(log, "a", buffering=1) as stream,
        contextlib.redirect_stdout(stream),
        contextlib.redirect_stderr(stream),
        _log_handlers_to(stream),
    ):
        try:
            pretrained = training.pretrain(seed_exp)
            if run is not None:
                _fit_and_validate(config, seed_exp, pretrained, run)
        except BaseException:
            traceback.print_exc()  # into the log, beside the fit's own output
            raise
    return time.perf_counter() - start


def _run_in_parallel(config: ReportConfig, runs: list[_Run]) -> None:
    """Every pretraining and fit of the report in ``config.jobs`` child processes, pretrainings first and a
    seed's runs as soon as its pretraining is done; the results land in the runs' caches. A failed unit stops
    the queue (the running ones finish, so their results are kept) and its error is raised, naming it."""
    import multiprocessing

    import torch

    fits = [run for run in runs if run.same_as is None and run.single_view_of is None]
    threads = max(1, torch.get_num_threads() // config.jobs)
    if config.experiment.data is None:  # built once here, not raced by the children
        from lightning_vtr.data.builder import ensure_embedded_dataset

        ensure_embedded_dataset(**config.experiment.embedded)
    total = len(config.seeds) * (1 + len(fits))
    print(
        f"report: {total} fits on {config.jobs} processes, {threads} torch thread(s) each; "
        f"their output in {Path(config.experiment.out) / 'seed_<s>' / 'logs'}",
        flush=True,
    )
    finished = 0
    context = multiprocessing.get_context("spawn")
    with futures.ProcessPoolExecutor(config.jobs, mp_context=context) as pool:
        pending = {pool.submit(_fit_unit, config, seed, None, threads): (seed, None) for seed in config.seeds}
        while pending:
            done, _ = futures.wait(pending, return_when=futures.FIRST_COMPLETED)
            for future in done:
                seed, run = pending.pop(future)
                name = "pretraining" if run is None else run.name
                try:
                    seconds = future.result()
                except BaseException as error:
                    pool.shutdown(wait=True, cancel_futures=True)
                    log = _log_path(config, seed, run)
                    raise RuntimeError(
                        f"report: seed {seed}, {name} failed ({error!r}); its output is in {log}"
                    ) from error
                finished += 1
                print(f"report: [{finished}/{total}] seed {seed}, {name} done in {seconds / 60:.1f} min", flush=True)
                if run is None:
                    for fit in fits:
                        pending[pool.submit(_fit_unit, config, seed, fit, threads)] = (seed, fit)


def _write_json(path: Path, payload: dict) -> None:
    atomic_write(path, json.dumps(payload, indent=1))  # a killed report never leaves a half-written cache


def _read_json(path: Path) -> dict | None:
    return json.loads(path.read_text()) if path.is_file() else None


def _single_view(run: _Run, exp: ExperimentConfig, source: dict) -> dict:
    """Test the fine-tuned model of ``run.single_view_of`` with 1 input view; cached in ``results.json``."""
    run_dir = Path(exp.out) / run.name
    result_file = run_dir / "results.json"
    if result_file.is_file():
        return json.loads(result_file.read_text())
    model = training.load_run_model(exp, Path(exp.out) / run.single_view_of)
    timer = training.StageTimer()
    start = time.perf_counter()
    results = training.evaluate(model, training.make_datamodule(exp, model, num_views=1), exp, run_dir, timer=timer)
    payload = {
        "strategy": run.strategy,
        "source_run": run.single_view_of,
        "num_views": 1,
        # The model is the source run's: its training time is the one to compare.
        "train_seconds": source["train_seconds"],
        "eval_seconds": time.perf_counter() - start,
        "timing": {k: timer.seconds[k] for k in ("test", "test_steps", "test_data")},
        "results": results,
    }
    _write_json(result_file, payload)
    return payload


def _selection_view_sets(run_dir: Path) -> Any:
    """``(B, n, 2)`` float64 viewpoints (degrees) of every sample the run's callback generated, from its
    ``vtr_selection/*.json`` records in selection order; ``None`` without records."""
    import torch

    records = sorted((run_dir / "vtr_selection").glob("*.json"), key=lambda p: (p.stem != "start", p.stem))
    view_sets = [v for path in records for v in json.loads(path.read_text()).get("view_sets", [])]
    if not view_sets:
        return None
    size = len(view_sets[0])
    return torch.tensor([v for v in view_sets if len(v) == size], dtype=torch.float64)


# ------------------------------------------------------------------------------------------ tables


def _values(payloads: dict[str, dict[int, dict]], run: str, view_set: str, metric: str, seeds: list[int]) -> dict:
    """``{seed: value}`` of one run, view set and metric, for the seeds that have a finite value."""
    out = {}
    for seed in seeds:
        value = _metric(payloads[run][seed]["results"].get(view_set, {}), metric)
        if value is not None and not math.isnan(value):
            out[seed] = float(value)
    return out


def _metric(values: dict[str, float], metric: str) -> float | None:
    """One metric of a view set's results; the best-threshold mIoU is derived from the ``iou@<t>`` values."""
    return best_threshold_iou(values) if metric == BEST_IOU else values.get(metric)


def _estimate(values: Sequence[float]) -> Estimate | None:
    return mean_estimate(values) if values else None


def _table(rows: dict[str, str], payloads: dict[str, dict[int, dict]], metrics: Sequence[str], seeds: list[int]) -> str:
    """A Table-1-layout Markdown table of ``rows`` (title -> run name); ``mean ± 95 % CI half-width`` over
    several seeds (Student t), the value alone with one."""
    means: dict[str, dict[str, dict[str, float]]] = {}
    spreads: dict[str, dict[str, dict[str, float]]] = {}
    for title, run in rows.items():
        means[title], spreads[title] = {}, {}
        for view_set in VIEW_SETS:
            for metric in metrics:
                estimate = _estimate(list(_values(payloads, run, view_set, metric, seeds).values()))
                means[title].setdefault(view_set, {})[metric] = estimate.mean if estimate else math.nan
                spreads[title].setdefault(view_set, {})[metric] = estimate.half_width if estimate else math.nan
    return format_robustness_table(means, std=spreads, metric_names=tuple(metrics))


def _differences(
    rows: dict[str, str], baseline: str, payloads: dict[str, dict[int, dict]], metric: str, seeds: list[int]
) -> dict[str, dict[str, Estimate | None]]:
    """``{title: {view_set: paired difference to baseline}}`` for every row but the baseline's own."""
    out: dict[str, dict[str, Estimate | None]] = {}
    for title, run in rows.items():
        if run == baseline:
            continue
        out[title] = {}
        for view_set in VIEW_SETS:
            treatment = _values(payloads, run, view_set, metric, seeds)
            reference = _values(payloads, baseline, view_set, metric, seeds)
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


def _difference_table(differences: dict[str, dict[str, Estimate | None]]) -> str:
    header = ["Method", *(VIEW_SET_TITLES[v] for v in VIEW_SETS)]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for title, per_set in differences.items():
        lines.append("| " + " | ".join([title, *(_format_difference(per_set[v]) for v in VIEW_SETS)]) + " |")
    return "\n".join(lines)


def _view_statistics(view_sets: Any) -> dict[str, Any]:
    """Pitch-band shares, share of sets with an antipodal pair and mean pairwise angle of ``(B, n, 2)`` sets."""
    return {
        "view_sets": int(view_sets.shape[0]),
        "pitch_histogram": pitch_histogram(view_sets, PITCH_BANDS).tolist(),
        "antipodal_share": antipodal_share(view_sets),
        "triplet_spread": triplet_spread(view_sets),
    }


def _pooled_views(views: dict[int, Any], seeds: list[int]) -> Any:
    import torch

    parts = [views[s] for s in seeds if views.get(s) is not None]
    sizes = {p.shape[1] for p in parts}
    return torch.cat(parts) if parts and len(sizes) == 1 else None


def _view_table(statistics: dict[str, dict[str, Any]]) -> str:
    bands = [
        f"[{lo}, {hi}{']' if i == len(PITCH_BANDS) - 2 else ')'}"
        for i, (lo, hi) in enumerate(zip(PITCH_BANDS, PITCH_BANDS[1:]))
    ]
    header = ["Method", "View sets", *(f"Pitch {b}" for b in bands), "Antipodal pairs", "Mean spread (°)"]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for title, stats in statistics.items():
        cells = [title, str(stats["view_sets"])]
        cells += [f"{100 * share:.1f}" for share in stats["pitch_histogram"]]
        cells += [f"{100 * stats['antipodal_share']:.1f}", f"{stats['triplet_spread']:.1f}"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _equivalent_command(config: ReportConfig) -> str:
    exp = config.experiment
    words = ["lightning-vtr", "report", "--model", exp.model, "--preset", exp.preset]
    if exp.data:
        words += ["--data", exp.data]
    words += ["--out", exp.out, "--seeds", *map(str, config.seeds)]
    words += ["--pretrain-epochs", str(exp.pretrain_epochs), "--finetune-epochs", str(exp.finetune_epochs)]
    words += ["--strategies", ",".join(config.strategies), "--fraction", str(exp.fraction)]
    words += ["--test-triplets", str(exp.test_repeats)]
    if exp.finetune_lr != "cosine":
        words += ["--finetune-lr", exp.finetune_lr]
    if config.ablations:
        words += ["--ablations", ",".join(config.ablations)]
    if config.validation_triplets is not None:
        words += ["--validation-triplets", str(config.validation_triplets)]
    if config.jobs > 1:
        words += ["--jobs", str(config.jobs)]
    return shlex.join(words)


def _write_csv(path: Path, runs: list[_Run], payloads: dict[str, dict[int, dict]], seeds: list[int]) -> None:
    with path.open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["run", "strategy", "seed", "view_set", *_METRICS, "train_seconds"])
        for run in runs:
            for seed in seeds:
                payload = payloads[run.name][seed]
                for view_set in VIEW_SETS:
                    values = payload["results"].get(view_set, {})
                    writer.writerow(
                        [run.name, run.strategy, seed, view_set]
                        + [repr(float(_nan_if_none(_metric(values, m)))) for m in _METRICS]
                        + [f"{payload['train_seconds']:.3f}"]
                    )


def _nan_if_none(value: float | None) -> float:
    return math.nan if value is None else value


def _write_differences_csv(
    path: Path, rows: dict[str, str], payloads: dict[str, dict[int, dict]], seeds: list[int]
) -> None:
    """One row per baseline x run x view set x metric: the paired difference as a fraction, its 95 % CI."""
    with path.open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["baseline", "run", "view_set", "metric", "mean", "ci_low", "ci_high", "seeds", "agree"])
        for baseline in (b for b in BASELINES if b in rows.values()):
            for metric in _METRICS:
                by_title = _differences(rows, baseline, payloads, metric, seeds)
                for title, per_set in by_title.items():
                    for view_set, estimate in per_set.items():
                        if estimate is None:
                            continue
                        writer.writerow(
                            [baseline, rows[title], view_set, metric]
                            + [repr(v) for v in (estimate.mean, estimate.low, estimate.high)]
                            + [estimate.n, estimate.agree]
                        )


def _write_chart(
    path: Path,
    rows: dict[str, str],
    payloads: dict[str, dict[int, dict]],
    seeds: list[int],
    view_statistics: dict[str, dict[str, Any]],
) -> None:
    import matplotlib
    import numpy as np
    from matplotlib.figure import Figure  # no pyplot: no global figure manager, no backend switch

    panels = 2 if view_statistics else 1
    # the legends go under the panels, two entries a line: the figure grows with the rows
    legend_lines = math.ceil(len(rows) / 2)
    fig = Figure(figsize=(8 * panels, 4.2 + 0.2 * legend_lines), dpi=120, layout="constrained")
    axes = fig.subplots(1, panels, squeeze=False)[0]
    ax = axes[0]
    width = 0.8 / max(1, len(rows))
    x = np.arange(len(VIEW_SETS))
    # one colour per strategy in both panels (the view panel has no row for None-VTR), distinct up to 20 rows
    palette = [f"C{i}" for i in range(10)] if len(rows) <= 10 else [matplotlib.colormaps["tab20"](i) for i in range(20)]
    colours = {title: palette[i % len(palette)] for i, title in enumerate(rows)}
    for i, (title, run) in enumerate(rows.items()):
        stats = [_estimate(list(_values(payloads, run, v, "iou@0.4", seeds).values())) for v in VIEW_SETS]
        means = [100 * e.mean if e else math.nan for e in stats]
        errors = [100 * e.half_width if e and math.isfinite(e.half_width) else 0.0 for e in stats]
        several = len(seeds) > 1
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
    spread = f" (mean, 95 % CI over {len(seeds)} seeds)" if len(seeds) > 1 else ""
    ax.set_title(f"Reconstruction IoU per test view set{spread}")
    ax.legend(ncol=2, fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.08))
    ax.grid(axis="y", alpha=0.3)
    if view_statistics:
        ax = axes[1]
        centres = [(lo + hi) / 2 for lo, hi in zip(PITCH_BANDS, PITCH_BANDS[1:])]
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
    fig.savefig(path)


# ------------------------------------------------------------------------------------------ timing

#: Rows of the time split: (label, where the seconds come from).
_FIT_STAGES = (
    ("training steps", "train_steps"),
    ("data loading", "train_data"),
    ("validation", "validation"),
    ("selection + synthesis", "augmentation"),
    ("other (setup, checkpoints)", "fit_other"),
)
_TEST_STAGES = (("model", "test_steps"), ("data loading", "test_data"))


def _stage(timing: dict | None, key: str, fallback: float | None = None) -> float:
    if timing and key in timing:
        return float(timing[key])
    return math.nan if fallback is None else float(fallback)


def _time_split(
    runs: list[_Run], payloads: dict[str, dict[int, dict]], pretraining: dict[int, dict | None], seeds: list[int]
) -> dict[str, Any]:
    """Seconds per stage, summed over seeds: pretraining, fine-tuning and testing (with their parts), and per
    run the mean per seed. Missing measurements (runs cached by an older version) are NaN."""

    def total(values: list[float]) -> float:
        return math.fsum(values) if values and all(math.isfinite(v) for v in values) else math.nan

    def mean(values: list[float]) -> float:
        return total(values) / len(values) if values else math.nan

    split: dict[str, Any] = {"pretraining": {}, "fine_tuning": {}, "testing": {}, "per_run": {}}
    pre = [(pretraining.get(s) or {}).get("seconds") for s in seeds]
    split["pretraining"]["total"] = total([_stage(t, "fit") for t in pre])
    for _, key in _FIT_STAGES:
        split["pretraining"][key] = total([_stage(t, key) for t in pre])
    fitted = [r for r in runs if r.single_view_of is None and r.same_as is None]
    fine = {r.name: [payloads[r.name][s] for s in seeds] for r in fitted}
    split["fine_tuning"]["total"] = total([p.get("train_seconds", math.nan) for ps in fine.values() for p in ps])
    for _, key in _FIT_STAGES:
        split["fine_tuning"][key] = total([_stage(p.get("timing"), key) for ps in fine.values() for p in ps])
    tested = [payloads[r.name][s] for r in runs if r.same_as is None for s in seeds]
    split["testing"]["total"] = total([_stage(p.get("timing"), "test", p.get("eval_seconds")) for p in tested])
    for _, key in _TEST_STAGES:
        split["testing"][key] = total([_stage(p.get("timing"), key) for p in tested])
    for run in runs:
        ps = [payloads[run.name][s] for s in seeds]
        split["per_run"][run.name] = {
            "fine_tuning": mean([p.get("train_seconds", math.nan) for p in ps]),
            **{key: mean([_stage(p.get("timing"), key) for p in ps]) for _, key in _FIT_STAGES},
            "testing": mean([_stage(p.get("timing"), "test", p.get("eval_seconds")) for p in ps]),
        }
        if run.single_view_of is not None:  # no fit of its own
            split["per_run"][run.name].update(
                dict.fromkeys(("fine_tuning", *(key for _, key in _FIT_STAGES)), math.nan)
            )
        if run.same_as is not None:  # counted once, under the run it repeats
            split["per_run"][run.name] = dict.fromkeys(split["per_run"][run.name], math.nan)
    split["measured"] = math.fsum(
        v for v in (split[k]["total"] for k in ("pretraining", "fine_tuning", "testing")) if math.isfinite(v)
    )
    return split


def _finite_or_none(value: Any) -> Any:
    """``value`` with every NaN float replaced by ``None`` (JSON has no NaN)."""
    if isinstance(value, dict):
        return {k: _finite_or_none(v) for k, v in value.items()}
    return None if isinstance(value, float) and math.isnan(value) else value


def _seconds(value: float) -> str:
    return "-" if not math.isfinite(value) else f"{value:.1f}"


def _time_tables(split: dict[str, Any], runs: list[_Run], seeds: list[int]) -> str:
    measured = split["measured"]

    def share(value: float) -> str:
        return f"{100 * value / measured:.1f}" if math.isfinite(value) and measured > 0 else "-"

    lines = ["| Stage | Seconds | Share (%) |", "|---|---|---|"]
    for stage, title, parts in (
        ("pretraining", "Pretraining", _FIT_STAGES),
        ("fine_tuning", "Fine-tuning", _FIT_STAGES),
        ("testing", "Testing", _TEST_STAGES),
    ):
        value = split[stage]["total"]
        lines.append(f"| {title} | {_seconds(value)} | {share(value)} |")
        for label, key in parts:
            if stage == "pretraining" and key == "augmentation":
                continue
            value = split[stage][key]
            lines.append(f"| &nbsp;&nbsp;{label} | {_seconds(value)} | {share(value)} |")
    lines.append(f"| Measured in all | {_seconds(measured)} | 100.0 |")
    per_seed = " per seed" if len(seeds) > 1 else ""
    header = ["Run", f"Fine-tuning (s{per_seed})", *(label for label, _ in _FIT_STAGES), f"Testing (s{per_seed})"]
    lines += ["", "| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for run in runs:
        row = split["per_run"][run.name]
        name = run.name if run.same_as is None else f"{run.name} (= {run.same_as}, fitted once)"
        cells = [name, _seconds(row["fine_tuning"]), *(_seconds(row[key]) for _, key in _FIT_STAGES)]
        lines.append("| " + " | ".join([*cells, _seconds(row["testing"])]) + " |")
    return "\n".join(lines)


# ------------------------------------------------------------------------------------------ entry point


def run_report(config: ReportConfig) -> dict:
    """Run (or resume) the whole comparison and write ``report.md``, ``results.csv``, ``differences.csv``,
    ``report.png`` and ``timing.json``.

    Args:
        config: the report's models, data, budget, strategies and ablations.

    Returns:
        ``{"runs": {run: {seed: results.json payload}}, "markdown": str, "paths": {name: Path},
        "wall_seconds": this call's wall time, "total_wall_seconds": over every call on ``out``,
        "differences": {baseline: {row title: {view_set: Estimate}}} (mIoU, fractions),
        "views": {row title: view statistics}, "time_split": seconds per stage}``.

    Raises:
        ValueError: for an invalid configuration (from :class:`ReportConfig`).
    """
    start = time.perf_counter()
    exp = config.experiment
    out = Path(exp.out)
    out.mkdir(parents=True, exist_ok=True)
    runs = _plan(config)
    if config.jobs > 1:
        _run_in_parallel(config, runs)  # the loop below then reads every fit from its cache
    payloads: dict[str, dict[int, dict]] = {run.name: {} for run in runs}
    validation: dict[str, dict[int, dict]] = {run.name: {} for run in runs if run.single_view_of is None}
    views: dict[str, dict[int, Any]] = {run.name: {} for run in runs if run.single_view_of is None}
    pretraining: dict[int, dict | None] = {}
    for seed in config.seeds:
        seed_exp = config.seed_config(seed)
        pretrained = training.pretrain(seed_exp)
        pretraining[seed] = _read_json(Path(seed_exp.out) / "pretrain" / "timing.json")
        for run in runs:
            if run.same_as is not None:
                payloads[run.name][seed] = payloads[run.same_as][seed]
                views[run.name][seed] = views[run.same_as][seed]
                if config.validation_triplets is not None:
                    validation[run.name][seed] = validation[run.same_as][seed]
                continue
            if run.single_view_of is not None:
                payloads[run.name][seed] = _single_view(run, seed_exp, payloads[run.single_view_of][seed])
                continue
            payloads[run.name][seed], validated = _fit_and_validate(config, seed_exp, pretrained, run)
            views[run.name][seed] = _selection_view_sets(Path(seed_exp.out) / run.name)
            if validated is not None:
                validation[run.name][seed] = {"results": validated}
    wall = time.perf_counter() - start

    seeds = list(config.seeds)
    split = _time_split(runs, payloads, pretraining, seeds)
    timing_file = out / "timing.json"
    timing = _read_json(timing_file) or {"invocations": []}
    timing["invocations"].append(wall)
    timing["split"] = _finite_or_none(split)
    _write_json(timing_file, timing)
    total = sum(timing["invocations"])

    main_rows = {STRATEGY_TITLES[s]: s for s in VARIANTS if s in config.strategies}
    differences = {
        baseline: _differences(main_rows, baseline, payloads, "iou@0.4", seeds)
        for baseline in BASELINES
        if baseline in main_rows.values()
    }
    validation_differences = {}
    if config.validation_triplets is not None:
        validation_differences = {
            baseline: _differences(main_rows, baseline, validation, "iou@0.4", seeds)
            for baseline in BASELINES
            if baseline in main_rows.values()
        }
    view_statistics = {}
    for title, run in main_rows.items():
        pooled = _pooled_views(views.get(run, {}), seeds)
        if pooled is not None:
            view_statistics[title] = _view_statistics(pooled)

    interval = "mean ± 95 % CI over seeds (Student t)" if len(seeds) > 1 else "one seed"
    sections = [
        "# View transformation robustness report",
        "",
        f"Command: `{config.command or _equivalent_command(config)}`",
        "",
        f"Budget: {exp.model} ({exp.preset}) on {exp.data or 'the embedded procedural dataset'}; "
        f"seeds {', '.join(map(str, seeds))}; pretraining {exp.pretrain_epochs} epochs on Aligned, then "
        f"{exp.finetune_epochs} fine-tuning epochs per strategy ({exp.finetune_lr} learning rate); "
        f"{100 * exp.fraction:g} % of training objects given new views per selection; every test object "
        f"tested on {exp.test_repeats} fixed view set(s), the same for every strategy of a seed. "
        f"Total wall time: {total / 60:.1f} min over {len(timing['invocations'])} invocation(s) "
        f"(this one {wall / 60:.1f} min).",
        "",
        f"## Table 1: robustness to view transformations (%, test set; {interval})",
        "",
        _table(main_rows, payloads, _METRICS, seeds),
    ]
    merged = [run for run in runs if run.same_as is not None and run.name in main_rows.values()]
    strategy_of = {run.name: run.strategy for run in runs}
    if merged:
        sections += [
            "",
            "Rows fitted once because their selector and callback arguments are identical: "
            + "; ".join(f"{STRATEGY_TITLES[r.strategy]} = {STRATEGY_TITLES[strategy_of[r.same_as]]}" for r in merged)
            + ".",
        ]
    test_note = (
        "Per seed, each strategy minus {baseline}: the same pretrained model and the same test items. Each cell: "
        "the mean difference, its 95 % CI over seeds (with 2+ seeds) and how many seeds agree with the mean's sign."
    )
    validation_note = (
        f"The same models on the validation objects, each on {config.validation_triplets} fixed view set(s): "
        "choose among strategies here, and read the test-split tables above as the confirmation, so that no "
        "choice is tuned on the test split. Cells as above."
    )
    headed = (
        ("Paired difference to {baseline} (mIoU points)", test_note, differences),
        ("Validation split: paired difference to {baseline} (mIoU points)", validation_note, validation_differences),
    )
    for heading, note, tables in headed:
        for baseline, by_title in tables.items():
            if by_title:
                title = STRATEGY_TITLES[baseline]
                sections += ["", "## " + heading.format(baseline=title), "", note.format(baseline=title), ""]
                sections.append(_difference_table(by_title))
    if view_statistics:
        sections += [
            "",
            "## Where the training views went",
            "",
            "The viewpoints of every generated training sample, pooled over seeds: share (%) per pitch band "
            "(degrees), share (%) of view sets holding an antipodal pair (views at least 165° apart) and the "
            "mean angle between two views of a set.",
            "",
            _view_table(view_statistics),
        ]
    if "k" in config.ablations:
        k_rows = {f"K = {k}": ("error_guided" if k == _MAIN_K else f"error_guided_k{k}") for k in config.k_values}
        sections += ["", "## Ablation: bin interval K (mIoU, %)", "", _table(k_rows, payloads, ("iou@0.4",), seeds)]
    if "pool" in config.ablations:
        pool_rows = {"Ours (with pool)": "error_guided", "Ours (without pool)": "error_guided_no_pool"}
        sections += ["", "## Ablation: viewpoint pool (%)", "", _table(pool_rows, payloads, _METRICS, seeds)]
    if "single_view" in config.ablations:
        single_rows = {"None-VTR (1 view)": "single_view_none", "Ours (1 view)": "single_view_error_guided"}
        sections += ["", "## Ablation: single-view input (%)", "", _table(single_rows, payloads, _METRICS, seeds)]
    sections += [
        "",
        "## Where the time goes",
        "",
        "Seconds summed over seeds, as measured when each run ran (a cached run keeps its first measurement).",
        "",
        _time_tables(split, runs, seeds),
    ]
    markdown = "\n".join(sections) + "\n"

    paths = {
        "markdown": out / "report.md",
        "csv": out / "results.csv",
        "differences": out / "differences.csv",
        "chart": out / "report.png",
        "timing": timing_file,
    }
    atomic_write(paths["markdown"], markdown)
    _write_csv(paths["csv"], runs, payloads, seeds)
    _write_differences_csv(paths["differences"], main_rows, payloads, seeds)
    _write_chart(paths["chart"], main_rows, payloads, seeds, view_statistics)
    return {
        "runs": payloads,
        "markdown": markdown,
        "paths": paths,
        "wall_seconds": wall,
        "total_wall_seconds": total,
        "differences": differences,
        "validation": validation if config.validation_triplets is not None else {},
        "validation_differences": validation_differences,
        "views": view_statistics,
        "time_split": split,
    }
