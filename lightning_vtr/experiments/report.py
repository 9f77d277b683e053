r"""The paper's comparison on your data: ``lightning-vtr report`` and :func:`run_report`.

For each seed the report pretrains one model on Aligned (:func:`~lightning_vtr.experiments.training.pretrain`),
fine-tunes a copy with every view strategy under the same budget (no augmentation, Nature, Random,
VIAT, MVTN, error-guided; :func:`~lightning_vtr.experiments.training.run_strategy`), tests each on Aligned /
Hemispherical / Spherical, and runs the paper's ablations of the error-guided method:

* ``k``: bin interval :math:`K \in \{15, 30, 60, 90\}` degrees (the K = 30 run is the main "Ours" run);
* ``pool``: with vs without the per-category viewpoint pool (``use_pool=False``);
* ``single_view``: the "none" and "error_guided" fine-tuned models tested with 1 input view.

It writes into ``out`` (the experiment's, :attr:`ReportConfig.experiment`):

* ``report.md``: a header (command, budget, wall time), Table 1 (rows None-VTR / Nature / Random / VIAT /
  MVTN / Ours, columns view set x mIoU\@0.4 and F-score, in %), then the K, pool and single-view
  ablation tables; with several seeds each cell is ``mean ± std`` (sample standard deviation);
* ``results.csv``: one row per run x seed x view set (``run, strategy, seed, view_set, iou@0.4, fscore,
  train_seconds``), metrics as fractions in [0, 1];
* ``report.png``: mIoU per view set and strategy as grouped bars (error bars: std over seeds);
* ``seed_<s>/<run>/results.json`` and checkpoints of every run, ``timing.json`` (wall time per invocation).

Resumable: a finished run (its ``results.json``), a finished pretraining (``pretrained.ckpt``) and a
finished single-view evaluation are reused, and an interrupted fit resumes from its ``last.ckpt``; so a
killed report re-run only does what is missing.

Default budget (:class:`ReportConfig`, :func:`default_experiment`): tiny Pix2Vox++ on the embedded dataset,
1 seed, 30 pretraining epochs, 10 fine-tuning epochs per strategy, 5 % of training objects searched per
epoch. Planned from measured figures on 2 CPU cores (tiny Pix2Vox++ ~19 samples/s; 210 training objects,
so ~12-15 s per epoch; +1-3 s per epoch for the callback's search and rendering; VIAT renders population x iterations x 3
= 120 views per searched object, ~+25 s per epoch): pretraining ~7 min, 10 fine-tuning runs (6
strategies, 3 extra K, no pool) ~30 min, VIAT's extra search ~4 min, 12 test passes ~4 min: about
45-55 minutes in total, an estimate rather than a measurement. ``lightning-vtr report`` prints the
measured time in ``report.md``.
"""

from __future__ import annotations

import csv
import json
import math
import shlex
import statistics
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from lightning_vtr.experiments import training
from lightning_vtr.experiments.tables import VIEW_SET_TITLES, format_robustness_table
from lightning_vtr.experiments.training import STRATEGIES, ExperimentConfig
from lightning_vtr.protocol import VIEW_SETS
from lightning_vtr.utils.io import atomic_write
from lightning_vtr.utils.validation import check_choice, check_int, check_type

__all__ = ["ABLATIONS", "STRATEGIES", "STRATEGY_TITLES", "ReportConfig", "default_experiment", "run_report"]

#: Row titles of Table 1, per strategy of :data:`STRATEGIES` (the paper's row order).
STRATEGY_TITLES: dict[str, str] = {
    "none": "None-VTR",
    "nature": "Nature",
    "random": "Random",
    "viat": "VIAT",
    "mvtn": "MVTN",
    "error_guided": "Ours",
}
#: The ablations of the error-guided method the report can run.
ABLATIONS: tuple[str, ...] = ("k", "pool", "single_view")
_METRICS = ("iou@0.4", "fscore")
_MAIN_K = 30  # the paper's K; the "error_guided" run uses it


def default_experiment(**changes: Any) -> ExperimentConfig:
    """The report's default experiment with ``changes``: tiny Pix2Vox++ on the embedded dataset, 30 pretraining
    and 10 fine-tuning epochs, batch size 8, written to ``runs/report`` (see the module docstring for the time).

    Example::

        run_report(ReportConfig(default_experiment(data="/data/shapenet_vtr", out="runs/shapenet"), seeds=[0, 1, 2]))
    """
    defaults = {"out": "runs/report", "pretrain_epochs": 30, "finetune_epochs": 10, "batch_size": 8}
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
        seeds: one full comparison per seed (pretraining included); several give mean ± std.
        strategies: the rows of Table 1 (any of :data:`STRATEGIES`).
        ablations: which of :data:`ABLATIONS` to run (they add the "error_guided" run, and
            ``single_view`` the "none" run, when ``strategies`` lacks them).
        k_values: bin intervals of the K ablation, degrees (each must divide 180).
        selector_kwargs: per strategy name, arguments of its selector (e.g. ``{"viat": {"population": 4}}``).
        callback_kwargs: arguments of every strategy's
            :class:`~lightning_vtr.callback.ErrorGuidedViewAugmentation` (e.g. ``{"progress_bar": False}``).
        synthesizer: the callbacks' synthesizer (``None``: mesh rendering).
        command: the command line shown in the header (``None``: the equivalent ``lightning-vtr report``).
    """

    experiment: ExperimentConfig = field(default_factory=default_experiment)
    seeds: Sequence[int] = (0,)
    strategies: Sequence[str] = STRATEGIES
    ablations: Sequence[str] = ABLATIONS
    k_values: Sequence[int] = (15, 30, 60, 90)
    selector_kwargs: dict[str, dict[str, Any]] = field(default_factory=dict)
    callback_kwargs: dict[str, Any] = field(default_factory=dict)
    synthesizer: Any = None
    command: str | None = None

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
            raise ValueError(f"`strategies` must name at least one of {list(STRATEGIES)}, got []")
        for strategy in self.strategies:
            check_choice("strategies", strategy, STRATEGIES)
        for ablation in self.ablations:
            check_choice("ablations", ablation, ABLATIONS)
        bad = [k for k in self.k_values if 180 % k]
        if bad:
            raise ValueError(f"`k_values` must divide 180 (degrees), got {bad}")
        for strategy in self.selector_kwargs:
            check_choice("selector_kwargs", strategy, STRATEGIES)

    def seed_config(self, seed: int) -> ExperimentConfig:
        """The :class:`~lightning_vtr.experiments.training.ExperimentConfig` of every run of ``seed``."""
        return replace(self.experiment, seed=seed, out=str(Path(self.experiment.out) / f"seed_{seed}"))


@dataclass(frozen=True)
class _Run:
    """One fine-tuning run (or a single-view evaluation of one) of the report."""

    name: str  # directory and CSV ``run`` name
    strategy: str
    selector_kwargs: dict[str, Any] = field(default_factory=dict)
    callback_kwargs: dict[str, Any] = field(default_factory=dict)
    single_view_of: str | None = None  # the fine-tuned run a single-view evaluation tests


def _plan(config: ReportConfig) -> list[_Run]:
    """Every run of one seed, in execution order, without duplicates."""
    strategies = list(config.strategies)
    if config.ablations and "error_guided" not in strategies:
        strategies.append("error_guided")
    if "single_view" in config.ablations and "none" not in strategies:
        strategies.insert(0, "none")
    base = {s: dict(config.selector_kwargs.get(s, {})) for s in STRATEGIES}
    runs = [_Run(s, s, base[s]) for s in STRATEGIES if s in strategies]
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
    return runs


def _write_json(path: Path, payload: dict) -> None:
    atomic_write(path, json.dumps(payload, indent=1))  # a killed report never leaves a half-written cache


def _single_view(run: _Run, exp: ExperimentConfig, source: dict) -> dict:
    """Test the fine-tuned model of ``run.single_view_of`` with 1 input view; cached in ``results.json``."""
    import torch

    run_dir = Path(exp.out) / run.name
    result_file = run_dir / "results.json"
    if result_file.is_file():
        return json.loads(result_file.read_text())
    ckpt = Path(exp.out) / run.single_view_of / "checkpoints" / "last.ckpt"
    if not ckpt.is_file():
        raise FileNotFoundError(f"single-view evaluation needs the fine-tuned checkpoint {ckpt}, which does not exist")
    model = training.make_model(exp)
    model.load_state_dict(torch.load(ckpt, map_location="cpu", weights_only=False)["state_dict"])
    start = time.perf_counter()
    results = training.evaluate(model, training.make_datamodule(exp, model, num_views=1), exp, run_dir)
    payload = {
        "strategy": run.strategy,
        "source_run": run.single_view_of,
        "num_views": 1,
        # The model is the source run's: its training time is the one to compare.
        "train_seconds": source["train_seconds"],
        "eval_seconds": time.perf_counter() - start,
        "results": results,
    }
    _write_json(result_file, payload)
    return payload


# ------------------------------------------------------------------------------------------ tables


def _aggregate(values: list[float]) -> tuple[float, float]:
    """Mean and sample standard deviation (0 for one value; NaN entries ignored)."""
    values = [v for v in values if v is not None and not math.isnan(v)]
    if not values:
        return math.nan, math.nan
    return statistics.fmean(values), statistics.stdev(values) if len(values) > 1 else 0.0


def _table(rows: dict[str, str], payloads: dict[str, dict[int, dict]], metrics: Sequence[str], seeds: list[int]) -> str:
    """A Table-1-layout Markdown table of ``rows`` (title -> run name); ``mean ± std`` with several seeds."""
    means: dict[str, dict[str, dict[str, float]]] = {}
    stds: dict[str, dict[str, dict[str, float]]] = {}
    for title, run in rows.items():
        means[title], stds[title] = {}, {}
        for view_set in VIEW_SETS:
            for metric in metrics:
                values = [payloads[run][s]["results"].get(view_set, {}).get(metric, math.nan) for s in seeds]
                mean, std = _aggregate(values)
                means[title].setdefault(view_set, {})[metric] = mean
                stds[title].setdefault(view_set, {})[metric] = std
    return format_robustness_table(means, std=stds if len(seeds) > 1 else None, metric_names=tuple(metrics))


def _equivalent_command(config: ReportConfig) -> str:
    exp = config.experiment
    words = ["lightning-vtr", "report", "--model", exp.model, "--preset", exp.preset]
    if exp.data:
        words += ["--data", exp.data]
    words += ["--out", exp.out, "--seeds", *map(str, config.seeds)]
    words += ["--pretrain-epochs", str(exp.pretrain_epochs), "--finetune-epochs", str(exp.finetune_epochs)]
    words += ["--strategies", ",".join(config.strategies), "--fraction", str(exp.fraction)]
    if exp.finetune_lr != "cosine":
        words += ["--finetune-lr", exp.finetune_lr]
    if not config.ablations:
        words.append("--no-ablations")
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
                        + [repr(float(values.get(m, math.nan))) for m in _METRICS]
                        + [f"{payload['train_seconds']:.3f}"]
                    )


def _write_chart(path: Path, rows: dict[str, str], payloads: dict[str, dict[int, dict]], seeds: list[int]) -> None:
    import numpy as np
    from matplotlib.figure import Figure  # no pyplot: no global figure manager, no backend switch

    fig = Figure(figsize=(8, 4.2), dpi=120, layout="tight")
    ax = fig.subplots()
    width = 0.8 / max(1, len(rows))
    x = np.arange(len(VIEW_SETS))
    for i, (title, run) in enumerate(rows.items()):
        stats = [
            _aggregate([payloads[run][s]["results"].get(v, {}).get("iou@0.4", math.nan) for s in seeds])
            for v in VIEW_SETS
        ]
        means = [100 * m for m, _ in stats]
        errors = [100 * e for _, e in stats] if len(seeds) > 1 else None
        ax.bar(x - 0.4 + (i + 0.5) * width, means, width, yerr=errors, capsize=3 if errors else 0, label=title)
    ax.set_xticks(x, [VIEW_SET_TITLES[v] for v in VIEW_SETS])
    ax.set_ylabel("mIoU@0.4 (%)")
    spread = f" (mean ± std, {len(seeds)} seeds)" if len(seeds) > 1 else ""
    ax.set_title(f"Reconstruction IoU per test view set{spread}")
    ax.legend(ncol=3, fontsize=8)
    ax.grid(axis="y", alpha=0.3)
    fig.savefig(path)


# ------------------------------------------------------------------------------------------ entry point


def run_report(config: ReportConfig) -> dict:
    """Run (or resume) the whole comparison and write ``report.md``, ``results.csv`` and ``report.png``.

    Args:
        config: the report's models, data, budget, strategies and ablations.

    Returns:
        ``{"runs": {run: {seed: results.json payload}}, "markdown": str, "paths": {name: Path},
        "wall_seconds": this call's wall time, "total_wall_seconds": over every call on ``out``}``.

    Raises:
        ValueError: for an invalid configuration (from :class:`ReportConfig`).
    """
    start = time.perf_counter()
    exp = config.experiment
    out = Path(exp.out)
    out.mkdir(parents=True, exist_ok=True)
    runs = _plan(config)
    payloads: dict[str, dict[int, dict]] = {run.name: {} for run in runs}
    for seed in config.seeds:
        seed_exp = config.seed_config(seed)
        pretrained = training.pretrain(seed_exp)
        for run in runs:
            if run.single_view_of is not None:
                payloads[run.name][seed] = _single_view(run, seed_exp, payloads[run.single_view_of][seed])
                continue
            payloads[run.name][seed] = training.run_strategy(
                run.strategy,
                seed_exp,
                pretrained,
                run_name=run.name,
                synthesizer=config.synthesizer,
                selector_kwargs=run.selector_kwargs,
                callback_kwargs={**config.callback_kwargs, **run.callback_kwargs},
            )
    wall = time.perf_counter() - start

    timing_file = out / "timing.json"
    timing = json.loads(timing_file.read_text()) if timing_file.is_file() else {"invocations": []}
    timing["invocations"].append(wall)
    _write_json(timing_file, timing)
    total = sum(timing["invocations"])

    seeds = list(config.seeds)
    main_rows = {STRATEGY_TITLES[s]: s for s in STRATEGIES if s in config.strategies}
    sections = [
        "# View transformation robustness report",
        "",
        f"Command: `{config.command or _equivalent_command(config)}`",
        "",
        f"Budget: {exp.model} ({exp.preset}) on {exp.data or 'the embedded procedural dataset'}; "
        f"seeds {', '.join(map(str, seeds))}; pretraining {exp.pretrain_epochs} epochs on Aligned, then "
        f"{exp.finetune_epochs} fine-tuning epochs per strategy ({exp.finetune_lr} learning rate); "
        f"{100 * exp.fraction:g} % of training objects "
        f"searched per epoch. Total wall time: {total / 60:.1f} min over {len(timing['invocations'])} invocation(s) "
        f"(this one {wall / 60:.1f} min).",
        "",
        "## Table 1: robustness to view transformations (%, test set)",
        "",
        _table(main_rows, payloads, _METRICS, seeds),
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
    markdown = "\n".join(sections) + "\n"

    paths = {"markdown": out / "report.md", "csv": out / "results.csv", "chart": out / "report.png"}
    paths["markdown"].write_text(markdown)
    _write_csv(paths["csv"], runs, payloads, seeds)
    _write_chart(paths["chart"], main_rows, payloads, seeds)
    return {"runs": payloads, "markdown": markdown, "paths": paths, "wall_seconds": wall, "total_wall_seconds": total}
