"""Running the report's plan: every seed's pretraining, fits, tests and validations, in this process or in
``ReportConfig.jobs`` child processes. Every result is cached in its run's directory
(:func:`~lightning_vtr.experiments.training.run_strategy`), so a killed report re-run only does what is missing.
"""

from __future__ import annotations

import contextlib
import json
import time
import traceback
from concurrent import futures
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from lightning_vtr.experiments import training
from lightning_vtr.experiments.config import ExperimentConfig
from lightning_vtr.experiments.output_files import (
    PRETRAIN_TIMING,
    RUN_RESULTS,
    SELECTION_RECORD,
    read_output_json,
    run_remedy,
)
from lightning_vtr.experiments.report_config import ReportConfig
from lightning_vtr.experiments.report_plan import ReportRun
from lightning_vtr.utils.io import atomic_write, open_append
from lightning_vtr.utils.paths import join_under

__all__ = ["ReportResults", "execute_runs", "single_view", "write_json"]


@dataclass
class ReportResults:
    """What the runs of a report gave, per run name and seed.

    Attributes:
        payloads: ``{run: {seed: results.json payload}}`` (a repeated run shares its source's).
        validation: ``{run: {seed: {"results": validation results}}}`` when the report validates.
        views: ``{run: {seed: (B, n, 2) viewpoints of the generated samples, or None}}`` of the fine-tunings.
        pretraining: ``{seed: the pretraining's timing.json, or None}``.
    """

    payloads: dict[str, dict[int, dict]] = field(default_factory=dict)
    validation: dict[str, dict[int, dict]] = field(default_factory=dict)
    views: dict[str, dict[int, Any]] = field(default_factory=dict)
    pretraining: dict[int, dict | None] = field(default_factory=dict)


def execute_runs(config: ReportConfig, runs: list[ReportRun]) -> ReportResults:
    """Pretrain every seed and run (or read from their caches) all of ``runs``.

    Args:
        config: the report; ``config.jobs`` > 1 fits in child processes first, then reads every fit's cache.
        runs: the plan (:func:`~lightning_vtr.experiments.report_plan.plan_runs`).

    Returns:
        The runs' results per run name and seed.

    Raises:
        RuntimeError: a fit of a parallel report failed (the message names it and its log).
    """
    for seed in config.seeds:  # a folder of an earlier output that leads out of it is refused before any fit
        for name in ("pretrain", "logs", *(run.name for run in runs)):
            join_under(config.seed_config(seed).out, name)
    if config.jobs > 1:
        _run_in_parallel(config, runs)
    results = ReportResults(
        payloads={run.name: {} for run in runs},
        validation={run.name: {} for run in runs if run.single_view_of is None},
        views={run.name: {} for run in runs if run.single_view_of is None},
    )
    for seed in config.seeds:
        _run_seed(config, runs, seed, results)
    return results


def _run_seed(config: ReportConfig, runs: list[ReportRun], seed: int, results: ReportResults) -> None:
    """One seed's pretraining and runs, in plan order, into ``results``."""
    seed_exp = config.seed_config(seed)
    pretrained = training.pretrain(seed_exp)
    timing = Path(seed_exp.out) / "pretrain" / "timing.json"
    results.pretraining[seed] = read_output_json(
        timing,
        PRETRAIN_TIMING,
        f"delete that file ({timing}); the report then shows the pretraining's times as unknown",
    )
    payloads, views, validation = results.payloads, results.views, results.validation
    for run in runs:
        if run.same_as is not None:
            payloads[run.name][seed] = payloads[run.same_as][seed]
            views[run.name][seed] = views[run.same_as][seed]
            if config.validation_repeats is not None:
                validation[run.name][seed] = validation[run.same_as][seed]
        elif run.single_view_of is not None:
            payloads[run.name][seed] = single_view(run, seed_exp, payloads[run.single_view_of][seed])
        else:
            payloads[run.name][seed], validated = _fit_and_validate(config, seed_exp, pretrained, run)
            views[run.name][seed] = _selection_view_sets(join_under(seed_exp.out, run.name))
            if validated is not None:
                validation[run.name][seed] = {"results": validated}


def _fit_and_validate(
    config: ReportConfig, seed_exp: ExperimentConfig, pretrained: Path, run: ReportRun
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
        variants=config.variants,
    )
    if config.validation_repeats is None:
        return payload, None
    return payload, training.validate_run(seed_exp, join_under(seed_exp.out, run.name), config.validation_repeats)


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


def _log_path(config: ReportConfig, seed: int, run: ReportRun | None) -> Path:
    return join_under(config.seed_config(seed).out, "logs", f"{'pretrain' if run is None else run.name}.log")


def _fit_unit(config: ReportConfig, seed: int, run: ReportRun | None, threads: int) -> float:
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
        open_append(log) as stream,
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


def _run_in_parallel(config: ReportConfig, runs: list[ReportRun]) -> None:
    """Every pretraining and fit of the report in ``config.jobs`` child processes, pretrainings first and a
    seed's runs as soon as its pretraining is done; the results land in the runs' caches. A failed unit stops
    the queue (the running ones finish, so their results are kept) and its error is raised, naming it."""
    import multiprocessing

    import torch

    fits = [run for run in runs if run.fitted]
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
        pending: dict[futures.Future[float], tuple[int, ReportRun | None]] = {
            pool.submit(_fit_unit, config, seed, None, threads): (seed, None) for seed in config.seeds
        }
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


def write_json(path: Path, payload: dict) -> None:
    atomic_write(path, json.dumps(payload, indent=1))  # a killed report never leaves a half-written cache


def single_view(run: ReportRun, exp: ExperimentConfig, source: dict) -> dict:
    """Test the fine-tuned model of ``run.single_view_of`` with 1 input view; cached in ``results.json``."""
    assert run.single_view_of is not None, "single_view tests single-view runs only"
    run_dir = join_under(exp.out, run.name)
    result_file = run_dir / "results.json"
    cached = read_output_json(result_file, RUN_RESULTS, run_remedy(run_dir))
    if cached is not None:
        return cached
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
    write_json(result_file, payload)
    return payload


def _selection_view_sets(run_dir: Path) -> Any:
    """``(B, n, 2)`` float64 viewpoints (degrees) of every sample the run's callback generated, from its
    ``vtr_selection/*.json`` records in selection order; ``None`` without records."""
    import torch

    records = sorted((run_dir / "vtr_selection").glob("*.json"), key=lambda p: (p.stem != "start", p.stem))
    remedy = run_remedy(run_dir)
    view_sets = [v for path in records for v in read_output_json(path, SELECTION_RECORD, remedy).get("view_sets", [])]
    if not view_sets:
        return None
    size = len(view_sets[0])
    return torch.tensor([v for v in view_sets if len(v) == size], dtype=torch.float64)
