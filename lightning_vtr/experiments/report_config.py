"""What ``lightning-vtr report`` runs: :class:`ReportConfig`, its default experiment and the report's names.

Every field of :class:`ReportConfig` marked with :func:`~lightning_vtr.experiments.config.flag` is a flag of
``lightning-vtr report`` (``validation_repeats`` is ``--validation-repeats``), as are those of its
:class:`~lightning_vtr.experiments.config.ExperimentConfig` but ``seed``.
"""

from __future__ import annotations

import pickle
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from lightning_vtr.experiments.config import ExperimentConfig, flag
from lightning_vtr.experiments.strategies import STRATEGIES
from lightning_vtr.utils.paths import join_under

if TYPE_CHECKING:
    from lightning_vtr.experiments.strategies import StrategyVariant

__all__ = [
    "ABLATIONS",
    "AUTO_JOBS",
    "BASELINES",
    "MAIN_STRATEGIES",
    "METRICS",
    "PITCH_BANDS",
    "REPORT_EXPERIMENT",
    "STRATEGIES",
    "STRATEGY_TITLES",
    "ReportConfig",
    "auto_jobs",
    "default_experiment",
]

MAIN_STRATEGIES: tuple[str, ...] = ("none", "random", "random_area", "paper", "error_guided")
"""The report's default rows, what a user chooses between: no augmentation, Random as the paper draws it
(angle-uniform), area-uniform Random, the paper's rule and the package's default rule
(``ErrorGuidedViewAugmentation()``). Any other name of :data:`~lightning_vtr.experiments.strategies.VARIANTS` is
opt-in."""
BASELINES: tuple[str, ...] = ("none", "random")
"""The strategies every other one is compared with, seed by seed (when the report runs them)."""
ABLATIONS: tuple[str, ...] = ("k", "pool", "single_view")
"""The ablations of the error-guided method the report can run (none by default)."""
PITCH_BANDS: tuple[int, ...] = (-90, -60, -30, 0, 30, 60, 90)
"""Pitch bands (degrees) of the view-distribution table and chart."""
METRICS: tuple[str, ...] = ("iou@0.4", "iou_best", "fscore")
"""The metrics of Table 1, ``results.csv`` and ``differences.csv`` (``"iou_best"`` is
:data:`lightning_vtr.evaluation.tables.BEST_IOU`, written out so that ``--help`` imports no torch)."""
MAIN_K = 30
"""The paper's bin interval K (degrees); the ``"error_guided"`` run uses it."""
REPORT_EXPERIMENT: dict[str, Any] = {
    "out": "runs/report",
    "pretrain_epochs": 30,
    "finetune_epochs": 10,
    "test_repeats": 4,
}
"""The report's budget over :class:`~lightning_vtr.experiments.config.ExperimentConfig`'s defaults."""


def default_experiment(**changes: Any) -> ExperimentConfig:
    """The report's default experiment: :data:`REPORT_EXPERIMENT` over ExperimentConfig's defaults, then ``changes``.

    Args:
        changes: fields of :class:`~lightning_vtr.experiments.config.ExperimentConfig`.

    Returns:
        Tiny Pix2Vox++ on the embedded dataset, 30 pretraining and 10 fine-tuning epochs, batch size 8, every test
        object on 4 view sets, written to ``runs/report``, with ``changes``.

    Example::

        run_report(ReportConfig(default_experiment(data="/data/shapenet_vtr", out="runs/shapenet"), seeds=[0, 1, 2]))
    """
    return ExperimentConfig(**{**REPORT_EXPERIMENT, **changes})


AUTO_JOBS = 4
"""The most fits :func:`auto_jobs` runs at once."""


def auto_jobs(experiment: ExperimentConfig) -> int:
    """How many fits ``lightning-vtr report`` runs at once unless ``--jobs`` says: one per torch thread, at
    most :data:`AUTO_JOBS`, when the fits run on the CPU with one device; else 1.

    On a CPU, small models train faster as several one-thread fits side by side than as one fit with all
    threads; each fit's numbers then are those of its thread count (``torch.get_num_threads() // jobs``).

    Args:
        experiment: the report's experiment (its ``accelerator`` and ``devices``).

    Returns:
        The number of fits at once, at least 1.

    Example:
        >>> import torch
        >>> auto_jobs(default_experiment(accelerator="gpu"))
        1
        >>> auto_jobs(default_experiment(accelerator="cpu")) == min(AUTO_JOBS, torch.get_num_threads())
        True
    """
    import torch

    accelerator = experiment.accelerator
    on_cpu = accelerator == "cpu" or (
        accelerator == "auto" and not torch.cuda.is_available() and not torch.backends.mps.is_available()
    )
    if not on_cpu or str(experiment.devices) != "1":
        return 1
    return max(1, min(AUTO_JOBS, torch.get_num_threads()))


@dataclass
class ReportConfig:
    """What the report trains and where it writes: one experiment, repeated per seed and per strategy.

    Attributes:
        experiment: model, data, budget and Trainer settings of every run
            (:class:`~lightning_vtr.experiments.config.ExperimentConfig`; default :func:`default_experiment`).
            Its ``out`` is the report's directory (runs go to ``out/seed_<s>/``, tables, CSV and chart to
            ``out``) and its ``seed`` is replaced by each of ``seeds`` (:meth:`seed_config`). The report needs
            ``pretrain_epochs`` and ``finetune_epochs`` of at least 1.
        seeds: one full comparison per seed (pretraining included); several give means with 95 %
            confidence intervals and paired differences.
        strategies: the rows, names of :attr:`variants` (default :data:`MAIN_STRATEGIES`).
        strategies_file: a YAML file of strategy rows of your own
            (:func:`~lightning_vtr.experiments.strategies.load_variants`; a row's selector a registry name or
            ``{class_path, init_args}``), added to the shipped rows (a row with a shipped row's name replaces it);
            ``None``: the shipped rows.
        only_strategies_file: use the rows of ``strategies_file`` alone, not the shipped ones.
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
        validation_repeats: also test every fine-tuned model on the *validation* objects, each on this many
            fixed view sets (:func:`~lightning_vtr.experiments.training.validate_run`), and add the paired
            differences there to ``report.md``: the place to choose among strategies, so the test split only
            confirms. ``None`` (the default): off.
        reference: a name in ``strategies`` every other row is also compared with, seed by seed, beside
            :data:`BASELINES` (e.g. the callback's default, to compare a method of your own with it); ``None``: the
            baselines only.
        maps: also measure each row's viewpoint robustness map (:mod:`~lightning_vtr.experiments.report_maps`):
            every seed's final model of the row on ``map_objects`` test objects, view sets around every bin of
            the ``map_k``-degree grid; written to ``out/maps/``.
        map_k: the maps' bin interval in degrees (divides 180; 30 gives 72 bins, 90 gives 8).
        map_objects: test objects per seed the maps measure, spread over the categories.
        jobs: fits run at once, each in its own (spawned) process with ``torch.get_num_threads() // jobs``
            torch threads (at least 1): every seed's pretraining first, then its runs as soon as it is done.
            Their output goes to ``seed_<s>/logs/<run>.log``; the report prints a line per finished fit, then
            builds the tables from the runs' caches as usual. Results equal a one-process report's at the same
            thread count per fit (a fit's numbers depend on its thread count). Needs ``devices`` 1 and a
            picklable ``synthesizer``. Default 1: everything in this process. ``lightning-vtr report``'s default
            is :func:`auto_jobs`: one fit per torch thread on a CPU, at most :data:`AUTO_JOBS`.

    Raises:
        ValueError: an unknown strategy or ablation, no or repeated seeds, a K that does not divide 180, a count
            below 1, or ``jobs`` > 1 with several devices or an unpicklable synthesizer.
        TypeError: ``experiment`` is not an ExperimentConfig, or a seed is not an int.

    Example::

        ReportConfig(default_experiment(out="runs/r"), seeds=[0, 1], strategies=["none", "random_area", "error_guided"])
    """

    experiment: ExperimentConfig = field(default_factory=default_experiment)
    seeds: Sequence[int] = field(
        default=(0, 1, 2), metadata=flag("seeds; each pretrains its own model, several give confidence intervals")
    )
    strategies: Sequence[str] = field(
        default=MAIN_STRATEGIES,
        metadata=flag("comma-separated rows (--list-strategies lists them)", comma_separated=True),
    )
    strategies_file: str | None = field(
        default=None,
        metadata=flag(
            "a YAML file of your strategy rows (selector: a registry name or {class_path, init_args}), added to "
            "the shipped rows; name them in --strategies",
            default_text="the shipped rows only",
        ),
    )
    only_strategies_file: bool = field(
        default=False, metadata=flag("use the --strategies-file rows alone, not the shipped ones")
    )
    ablations: Sequence[str] = field(
        default=(),
        metadata=flag(
            f"comma-separated ablations of the error-guided method to run, among {','.join(ABLATIONS)}",
            choices=ABLATIONS,
            comma_separated=True,
        ),
    )
    k_values: Sequence[int] = (15, 30, 60, 90)
    selector_kwargs: dict[str, dict[str, Any]] = field(default_factory=dict)
    callback_kwargs: dict[str, Any] = field(default_factory=dict)
    synthesizer: Any = None
    command: str | None = None
    validation_repeats: int | None = field(
        default=None,
        metadata=flag(
            "also test every fine-tuned model on the validation objects, each on this many fixed view sets, and "
            "print the paired differences there: choose strategies on those, not on the test split",
            minimum=1,
            default_text="off",
        ),
    )
    jobs: int = field(
        default=1,
        metadata=flag(
            "fits run at once, each in its own process with (torch threads // N) threads; output per fit in "
            "OUT/seed_<s>/logs",
            minimum=1,
            default_text=f"one per torch thread, at most {AUTO_JOBS}, for CPU fits on one device; else 1",
        ),
    )

    reference: str | None = field(
        default=None,
        metadata=flag(
            "also compare every row with this one, seed by seed (a name in --strategies), as with None-VTR and Random",
            default_text="None-VTR and Random only",
        ),
    )
    maps: bool = field(
        default=False,
        metadata=flag("also measure the viewpoint robustness map of each strategy's final model (OUT/maps/)"),
    )
    map_k: int = field(default=30, metadata=flag("bin interval of --maps, in degrees, dividing 180", minimum=1))
    map_objects: int = field(
        default=8, metadata=flag("test objects per seed of --maps, spread over the categories", minimum=1)
    )

    def __post_init__(self) -> None:
        from lightning_vtr.utils.validation import check_choice, check_int, check_type

        check_type("experiment", self.experiment, ExperimentConfig)
        for name in ("pretrain_epochs", "finetune_epochs"):
            check_int(f"experiment.{name}", getattr(self.experiment, name), minimum=1)
        self.seeds = [check_int("seeds", s) for s in self.seeds]
        self.strategies = list(self.strategies)
        self.ablations = list(self.ablations)
        self.k_values = [check_int("k_values", k, minimum=1) for k in self.k_values]
        if not self.seeds or len(set(self.seeds)) != len(self.seeds):
            raise ValueError(f"`seeds` must be a non-empty list of distinct seeds, got {self.seeds}")
        if self.only_strategies_file and self.strategies_file is None:
            raise ValueError("`only_strategies_file` needs a `strategies_file`")
        variants = self.variants
        if not self.strategies:
            raise ValueError(f"`strategies` must name at least one of {list(variants)}, got []")
        for strategy in self.strategies:
            check_choice("strategies", strategy, variants)
        for ablation in self.ablations:
            check_choice("ablations", ablation, ABLATIONS)
        bad = [k for k in self.k_values if 180 % k]
        if bad:
            raise ValueError(f"`k_values` must divide 180 (degrees), got {bad}")
        for strategy in self.selector_kwargs:
            check_choice("selector_kwargs", strategy, variants)
        if self.validation_repeats is not None:
            check_int("validation_repeats", self.validation_repeats, minimum=1)
        if self.reference is not None:
            check_choice("reference", self.reference, self.strategies)
        check_int("map_objects", self.map_objects, minimum=1)
        if 180 % check_int("map_k", self.map_k, minimum=1):
            raise ValueError(f"`map_k` must divide 180 (degrees), got {self.map_k}")
        if check_int("jobs", self.jobs, minimum=1) > 1:
            if self.experiment.devices != 1:
                raise ValueError(
                    f"`jobs` > 1 runs one-device fits side by side; got jobs={self.jobs} with "
                    f"experiment.devices={self.experiment.devices!r} (use jobs=1 for multi-device fits)"
                )
            try:
                pickle.dumps(self.synthesizer)
            except Exception as error:
                raise ValueError(
                    f"`jobs` > 1 sends the synthesizer to child processes, but {type(self.synthesizer).__name__} "
                    f"cannot be pickled ({error}); use jobs=1"
                ) from error

    @property
    def variants(self) -> dict[str, StrategyVariant]:
        """The named strategies the rows come from: the shipped rows and ``strategies_file``'s
        (:func:`~lightning_vtr.experiments.strategies.report_variants`), read once per file."""
        return _variants(self.strategies_file, self.only_strategies_file)

    def titles(self) -> dict[str, str]:
        """Row title per strategy name of :attr:`variants`."""
        return {name: variant.title for name, variant in self.variants.items()}

    def seed_config(self, seed: int) -> ExperimentConfig:
        """The :class:`~lightning_vtr.experiments.config.ExperimentConfig` of every run of ``seed``."""
        return replace(self.experiment, seed=seed, out=str(join_under(self.experiment.out, f"seed_{seed}")))


_VARIANTS_READ: dict[tuple[str | None, bool], dict[str, StrategyVariant]] = {}


def _variants(path: str | None, only: bool) -> dict[str, StrategyVariant]:
    from lightning_vtr.experiments.strategies import report_variants

    key = (None if path is None else str(Path(path).expanduser().resolve()), only)
    if key not in _VARIANTS_READ:
        _VARIANTS_READ[key] = report_variants(path, replace=only)
    return _VARIANTS_READ[key]


def __getattr__(name: str) -> Any:
    # the shipped rows import the selectors (torch): read on first use, so `lightning-vtr report --help` stays light
    if name == "STRATEGY_TITLES":
        from lightning_vtr.experiments.strategies import VARIANTS

        return {key: variant.title for key, variant in VARIANTS.items()}
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


if TYPE_CHECKING:
    STRATEGY_TITLES: dict[str, str]
    """Row title per name of :data:`~lightning_vtr.experiments.strategies.VARIANTS` (the shipped rows), read on
    first use."""
