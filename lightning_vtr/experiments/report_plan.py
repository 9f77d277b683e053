"""The runs of one seed of ``lightning-vtr report``: the strategies' fine-tunings, then the ablations' runs.

Runs whose selector and callback resolve to the same arguments (e.g. a row of a strategies file that repeats a
shipped rule) are fitted once: the later one is marked :attr:`ReportRun.same_as` the earlier.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field, replace
from typing import Any

from lightning_vtr.experiments import training
from lightning_vtr.experiments.report_config import MAIN_K, ReportConfig

__all__ = ["ReportRun", "plan_runs"]


@dataclass(frozen=True)
class ReportRun:
    """One fine-tuning run (or a single-view evaluation of one) of the report.

    Attributes:
        name: the run's directory and its ``run`` in ``results.csv``.
        strategy: a name of the report's :attr:`~lightning_vtr.experiments.report_config.ReportConfig.variants`.
        selector_kwargs, callback_kwargs: the run's arguments over the strategy's.
        single_view_of: the fine-tuned run a single-view evaluation tests; ``None`` for a fine-tuning.
        same_as: an earlier run whose selector and callback resolve to the same arguments; ``None`` if none.
    """

    name: str
    strategy: str
    selector_kwargs: dict[str, Any] = field(default_factory=dict)
    callback_kwargs: dict[str, Any] = field(default_factory=dict)
    single_view_of: str | None = None
    same_as: str | None = None

    @property
    def fitted(self) -> bool:
        """Whether the run fits a model of its own (neither a single-view test nor a repeat of another run)."""
        return self.single_view_of is None and self.same_as is None


def plan_runs(config: ReportConfig) -> list[ReportRun]:
    """Every run of one seed, in execution order (the order of ``config.variants``, then the ablations), once each.

    Args:
        config: the report's strategies, ablations, K values and arguments.

    Returns:
        The runs; an ablation adds the ``"error_guided"`` run (and ``single_view`` the ``"none"`` run) when the
        strategies lack it.

    Example::

        [run.name for run in plan_runs(ReportConfig(ablations=["pool"]))]  # [..., "error_guided_no_pool"]
    """
    strategies = list(config.strategies)
    if config.ablations and "error_guided" not in strategies:
        strategies.append("error_guided")
    if "single_view" in config.ablations and "none" not in strategies:
        strategies.insert(0, "none")
    variants = config.variants
    base = {s: dict(config.selector_kwargs.get(s, {})) for s in variants}
    runs = [ReportRun(s, s, base[s]) for s in variants if s in strategies]
    if "k" in config.ablations:
        runs += [
            ReportRun(f"error_guided_k{k}", "error_guided", {**base["error_guided"], "k": k})
            for k in config.k_values
            if k != MAIN_K
        ]
    if "pool" in config.ablations:
        runs.append(ReportRun("error_guided_no_pool", "error_guided", base["error_guided"], {"use_pool": False}))
    if "single_view" in config.ablations:
        runs += [ReportRun(f"single_view_{s}", s, single_view_of=s) for s in ("none", "error_guided")]
    return _merge_identical(runs, config)


def _merge_identical(runs: list[ReportRun], config: ReportConfig) -> list[ReportRun]:
    """Mark each fine-tuning run that would train exactly what an earlier one trains as the same run."""
    seen: dict[str, str] = {}
    out = []
    for run in runs:
        if run.single_view_of is None:
            callback_kwargs = {**config.callback_kwargs, **run.callback_kwargs}
            resolved = training.resolved_strategy(
                run.strategy, run.selector_kwargs, callback_kwargs, variants=config.variants
            )
            key = json.dumps(resolved, sort_keys=True, default=repr)
            if key in seen:
                run = replace(run, same_as=seen[key])
            else:
                seen[key] = run.name
        out.append(run)
    return out
