"""The paper's protocol as functions: pretrain on Aligned, fine-tune with a view strategy, test on all sets.

Used by ``examples/*.py`` and ``lightning-vtr report``. Every run writes ``results.json`` into its own
directory and is skipped when that file exists, so a killed experiment re-run resumes where it stopped.
"""

from __future__ import annotations

import inspect
import json
import math
import time
import warnings
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Any

import lightning as L
import torch

from lightning_vtr.callback import ErrorGuidedViewAugmentation
from lightning_vtr.data import IMAGE_RECIPES
from lightning_vtr.data.datamodule import VTRDataModule
from lightning_vtr.evaluation.tables import results_from_test_output
from lightning_vtr.models.base import VoxelReconstructionModule
from lightning_vtr.models.pix2vox import Pix2VoxPlusPlus
from lightning_vtr.models.registry import MODELS
from lightning_vtr.selection import SELECTORS, make_selector
from lightning_vtr.utils.deprecation import renamed_argument
from lightning_vtr.utils.io import atomic_write
from lightning_vtr.utils.validation import check_choice, check_int

__all__ = [
    "FINETUNE_LR_SCHEDULES",
    "MODELS",
    "STRATEGIES",
    "VARIANTS",
    "CosineFineTuning",
    "ExperimentConfig",
    "StageTimer",
    "StrategyVariant",
    "evaluate",
    "make_datamodule",
    "make_model",
    "make_strategy",
    "pretrain",
    "resolved_strategy",
    "run_strategy",
]

#: Fine-tuning learning-rate schedules (``ExperimentConfig.finetune_lr``).
FINETUNE_LR_SCHEDULES = ("cosine", "constant")
#: The paper's Table 1 strategies, in its row order: ``"none"`` (no augmentation), then every selector of
#: :data:`lightning_vtr.selection.SELECTORS` with its defaults. Each is a name in :data:`VARIANTS`, which
#: :func:`make_strategy` takes.
STRATEGIES: tuple[str, ...] = ("none", *SELECTORS)


@dataclass(frozen=True)
class StrategyVariant:
    """A named view strategy: a selector of :data:`lightning_vtr.selection.SELECTORS` and its settings.

    Attributes:
        selector: the selector's registry name; ``None`` for no augmentation (no callback).
        selector_kwargs: arguments of the selector class.
        callback_kwargs: arguments of :class:`~lightning_vtr.callback.ErrorGuidedViewAugmentation`.
        title: the row title in the report's tables.
    """

    selector: str | None
    selector_kwargs: Mapping[str, Any] = field(default_factory=dict)
    callback_kwargs: Mapping[str, Any] = field(default_factory=dict)
    title: str = ""

    def __post_init__(self) -> None:
        if self.selector is not None:
            check_choice("selector", self.selector, SELECTORS)
        # read-only copies: a registry entry cannot be changed through a caller's dict
        object.__setattr__(self, "selector_kwargs", MappingProxyType(dict(self.selector_kwargs)))
        object.__setattr__(self, "callback_kwargs", MappingProxyType(dict(self.callback_kwargs)))


_VISIBLE_NMS = {"score": "visible", "min_separation": 30.0}
# the released code's search: 35 % of the objects scored into a pool rebuilt at every selection
_SEARCHED = {"search_fraction": 0.35, "pool_refresh": True}
# a larger, fresh budget at the default's cost: 20 % of the objects given new views per selection, and only the
# latest selection's samples kept (34 = 20 % of the embedded dataset's 170 training objects), so every epoch
# trains on views chosen from the current model; fewer generated sample-epochs (340) than the default's 440
_FRESH = {"fraction": 0.2, "max_samples": 34}
#: Strategy name -> :class:`StrategyVariant`, in the report's row order: the paper's Table 1 strategies
#: (:data:`STRATEGIES`, each selector with its package defaults, so ``"error_guided"`` is whatever
#: ``ErrorGuidedSelector()`` and ``ErrorGuidedViewAugmentation()`` default to), the second random baseline,
#: the paper's exact rule, and the variants of the error-guided method compared to pick its default:
#:
#: * ``"random"``: angle-uniform views (uniform yaw and pitch, the released code's sampler); ``"random_area"``:
#:   uniform on the sphere;
#: * ``"paper"``: the paper's score (binary error summed over the first-hit map), hard top-n bins, a
#:   per-category pool that keeps every selection and prefers other objects' view sets, the first selection
#:   from the pretrained model, as many objects searched as given views;
#: * ``"released"``: the released code's score (soft error in ground-truth voxels, mean over hit pixels) and
#:   pool (rebuilt every selection, sampled among all objects' sets) and a search over 35 % of the objects;
#: * ``"visible"``: the side-aware score of what a camera would see wrong; ``"visible_nms"``: with non-maximum
#:   suppression of bins within 30 degrees of a chosen one or of its antipode; ``"visible_tau"``: the same
#:   suppression, bins sampled with probability proportional to solid angle x score (temperature 1) instead
#:   of the hard top n; ``"visible_tau3"``: the same at temperature 3 (closer to area-uniform random);
#:   ``"visible_nms_search"``, ``"visible_tau_search"`` and ``"visible_tau3_search"``: ``"visible_nms"``,
#:   ``"visible_tau"`` and ``"visible_tau3"`` searching 35 % of the objects into a pool rebuilt at every selection;
#:   ``"visible_tau10_search"``: the same at temperature 10; ``"visible_tau3_search_own"``: ``"visible_tau3_search"``
#:   sampling each object's view set among all of its category's, its own included; ``"visible_tau3_search_error"``:
#:   ``"visible_tau3_search"`` giving the new views to the searched objects with the largest error;
#:   ``"visible_rel_search"`` and ``"visible_rel_tau_search"``: ``"visible_nms_search"`` and ``"visible_tau_search"``
#:   with scores relative to the category's mean per view (``ErrorGuidedSelector(relative=True)``);
#: * ``"input_nms"`` and ``"input_tau"``: the input-side score (``ErrorGuidedSelector(score="input")``: the model's
#:   loss given the object's image from each bin centre alone) with 30-degree suppression, hard top n and
#:   temperature 1, each object trained on its own selection (no pool);
#: * ``"random_fresh"``, ``"random_area_fresh"``, ``"visible_tau3_search_fresh"`` and ``"visible_tau10_search_fresh"``:
#:   ``"random"``, ``"random_area"``, ``"visible_tau3_search"`` and ``"visible_tau10_search"`` giving 20 % of the
#:   objects new views per selection and keeping only the latest selection's samples (sized for the embedded
#:   dataset), whatever the report's ``fraction``.
#:
#: :func:`make_strategy` and :func:`run_strategy` take these names; their ``selector_kwargs`` and
#: ``callback_kwargs`` go over the variant's.
VARIANTS: dict[str, StrategyVariant] = {
    "none": StrategyVariant(None, title="None-VTR"),
    "nature": StrategyVariant("nature", title="Nature"),
    "random": StrategyVariant("random", {"mode": "angle"}, title="Random"),
    "random_area": StrategyVariant("random", {"mode": "area"}, title="Random (area-uniform)"),
    "viat": StrategyVariant("viat", title="VIAT"),
    "mvtn": StrategyVariant("mvtn", title="MVTN"),
    "error_guided": StrategyVariant("error_guided", title="Ours"),
    "paper": StrategyVariant(
        "error_guided",
        {"score": "paper", "min_separation": None, "temperature": None},
        {
            "use_pool": True,
            "pool_capacity": None,
            "pool_refresh": False,
            "pool_prefer_others": True,
            "select_at_start": True,
            "search_fraction": None,
        },
        title="Ours (paper rule)",
    ),
    "released": StrategyVariant(
        "error_guided",
        {"score": "released"},
        {"pool_refresh": True, "pool_prefer_others": False, "search_fraction": 0.35},
        title="Released-code rule",
    ),
    "visible": StrategyVariant("error_guided", {"score": "visible"}, title="Visible"),
    "visible_nms": StrategyVariant("error_guided", _VISIBLE_NMS, title="Visible + NMS"),
    "visible_tau": StrategyVariant("error_guided", {**_VISIBLE_NMS, "temperature": 1.0}, title="Visible + NMS, tau 1"),
    "visible_tau3": StrategyVariant("error_guided", {**_VISIBLE_NMS, "temperature": 3.0}, title="Visible + NMS, tau 3"),
    "visible_nms_search": StrategyVariant(
        "error_guided",
        _VISIBLE_NMS,
        _SEARCHED,
        title="Visible + NMS, search 35 %",
    ),
    "visible_tau_search": StrategyVariant(
        "error_guided",
        {**_VISIBLE_NMS, "temperature": 1.0},
        _SEARCHED,
        title="Visible + NMS, tau 1, search 35 %",
    ),
    "visible_tau3_search": StrategyVariant(
        "error_guided",
        {**_VISIBLE_NMS, "temperature": 3.0},
        _SEARCHED,
        title="Visible + NMS, tau 3, search 35 %",
    ),
    "visible_tau10_search": StrategyVariant(
        "error_guided",
        {**_VISIBLE_NMS, "temperature": 10.0},
        _SEARCHED,
        title="Visible + NMS, tau 10, search 35 %",
    ),
    "visible_tau3_search_own": StrategyVariant(
        "error_guided",
        {**_VISIBLE_NMS, "temperature": 3.0},
        {**_SEARCHED, "pool_prefer_others": False},
        title="Visible + NMS, tau 3, search 35 %, own sets too",
    ),
    "visible_tau3_search_error": StrategyVariant(
        "error_guided",
        {**_VISIBLE_NMS, "temperature": 3.0},
        {**_SEARCHED, "generate_for": "error"},
        title="Visible + NMS, tau 3, search 35 %, worst objects",
    ),
    "visible_rel_search": StrategyVariant(
        "error_guided",
        {**_VISIBLE_NMS, "relative": True},
        _SEARCHED,
        title="Visible relative to category + NMS, search 35 %",
    ),
    "visible_rel_tau_search": StrategyVariant(
        "error_guided",
        {**_VISIBLE_NMS, "relative": True, "temperature": 1.0},
        _SEARCHED,
        title="Visible relative to category + NMS, tau 1, search 35 %",
    ),
    "input_nms": StrategyVariant(
        "error_guided", {"score": "input", "min_separation": 30.0}, {"use_pool": False}, title="Input + NMS"
    ),
    "input_tau": StrategyVariant(
        "error_guided",
        {"score": "input", "min_separation": 30.0, "temperature": 1.0},
        {"use_pool": False},
        title="Input + NMS, tau 1",
    ),
    "random_fresh": StrategyVariant("random", {"mode": "angle"}, _FRESH, title="Random, 20 % fresh"),
    "random_area_fresh": StrategyVariant("random", {"mode": "area"}, _FRESH, title="Random (area-uniform), 20 % fresh"),
    "visible_tau3_search_fresh": StrategyVariant(
        "error_guided",
        {**_VISIBLE_NMS, "temperature": 3.0},
        {**_SEARCHED, **_FRESH},
        title="Visible + NMS, tau 3, search 35 %, 20 % fresh",
    ),
    "visible_tau10_search_fresh": StrategyVariant(
        "error_guided",
        {**_VISIBLE_NMS, "temperature": 10.0},
        {**_SEARCHED, **_FRESH},
        title="Visible + NMS, tau 10, search 35 %, 20 % fresh",
    ),
}


def __getattr__(name: str) -> Any:
    if name == "MODEL_CLASSES":  # the model names before 0.2
        warnings.warn(
            "`MODEL_CLASSES` is deprecated and will be removed in 0.3; use the keys of `MODELS`.",
            DeprecationWarning,
            stacklevel=2,
        )
        return tuple(MODELS)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


@dataclass
class ExperimentConfig:
    """One experiment's budget and settings.

    Attributes:
        model: a name in :data:`MODELS` (``"pix2vox"`` or ``"lrgt"``).
        preset: the model preset (``"tiny"`` on a laptop, ``"paper"`` for the published configuration).
        data: a ShapeNet-VTR directory; ``None`` uses the embedded procedural dataset.
        pretrain_epochs: epochs on Aligned before any view strategy (the paper's pre-trained model).
        finetune_epochs: epochs of fine-tuning, the same for every strategy (including none).
        batch_size, num_workers, seed: as usual. ``image_size`` ``None`` takes the preset's.
        fraction: share of training objects the callback gives new views per selection (its ``fraction``).
        accelerator, devices, precision: passed to the Trainer; ``devices`` given as a string of digits
            (from a command line) becomes an int.
        out: where runs are written.
        recipe: the training images' recipe (``VTRDataModule(recipe=...)``): ``"plain"`` (composite on white,
            ImageNet normalisation; the default, as in 0.1), ``"reference"`` (the model's published recipe, its
            class's ``image_recipe``: ``"pix2vox"`` or ``"lrgt"``) or a name of
            :data:`~lightning_vtr.data.IMAGE_RECIPES`.
        test_repeats: view sets per test object, each a fixed choice of the model's ``num_views`` views of the
            tested view set (``VTRDataModule(test_repeats=...)``); the same for every strategy of a seed, so
            differences between strategies are paired. More repeats cut the variance of a test mean cheaply.
        embedded: options of the embedded procedural dataset (``data=None``).
        finetune_lr: learning-rate schedule of fine-tuning, the same for every strategy: ``"cosine"``
            anneals each parameter group's rate from the model's own value to 0 over ``finetune_epochs``
            (:class:`CosineFineTuning`), so the tested weights are not one noisy step of a constant rate;
            ``"constant"`` keeps the model's scheduler.
        model_kwargs: extra arguments of the model class.
        trainer_kwargs: extra ``L.Trainer`` arguments of every fit and test (e.g. ``limit_train_batches``);
            they override this module's defaults, except ``devices=1`` of the evaluation.
    """

    model: str = "pix2vox"
    preset: str = "tiny"
    data: str | None = None
    pretrain_epochs: int = 12
    finetune_epochs: int = 12
    batch_size: int = 16
    num_workers: int = 0
    image_size: int | None = None
    fraction: float = 0.05
    seed: int = 0
    accelerator: str = "auto"
    devices: int | str = 1
    precision: str = "32-true"
    finetune_lr: str = "cosine"
    test_repeats: int = 1
    recipe: str = "plain"
    out: str = "runs/vtr"
    embedded: dict[str, Any] = field(default_factory=dict)
    model_kwargs: dict[str, Any] = field(default_factory=dict)
    trainer_kwargs: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        check_choice("finetune_lr", self.finetune_lr, FINETUNE_LR_SCHEDULES)
        check_choice("recipe", self.recipe, ("reference", *IMAGE_RECIPES))
        check_int("test_repeats", self.test_repeats, minimum=1)
        if isinstance(self.devices, str) and self.devices.isdigit():
            self.devices = int(self.devices)


class CosineFineTuning(L.Callback):
    """Sets every parameter group's learning rate to ``base * (1 + cos(pi * epoch / epochs)) / 2`` at each
    training epoch's start (epoch 0 at the model's rate, the last one near 0), whatever the optimizer.

    The base rate is the group's ``initial_lr`` (written by any torch scheduler) or its ``lr`` when the
    optimizer is first seen, so a resumed run continues the same curve. The model's own scheduler still
    steps, but this callback overrides its value at every epoch start.
    """

    def __init__(self, epochs: int) -> None:
        self.epochs = check_int("epochs", epochs, minimum=1)

    def factor(self, epoch: int) -> float:
        return 0.5 * (1.0 + math.cos(math.pi * min(epoch, self.epochs) / self.epochs))

    def on_train_epoch_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        factor = self.factor(trainer.current_epoch)
        for optimizer in trainer.optimizers:
            for group in optimizer.param_groups:
                group.setdefault("initial_lr", group["lr"])
                group["lr"] = group["initial_lr"] * factor


class StageTimer(L.Callback):
    """Wall time per stage of the fits and tests it watches, in :attr:`seconds` (accumulated over calls).

    Stages: ``fit`` (the whole ``trainer.fit``), ``train_steps`` (training batches: forward, backward,
    optimizer), ``train_data`` (the rest of the training epochs: fetching and collating batches, loader
    rebuilds), ``validation``, ``augmentation`` (the hooks of the callbacks between :meth:`bracket`'s two
    markers: an augmentation callback's selection and synthesis), ``fit_other`` (what remains of ``fit``:
    setup, checkpoints, other hooks); ``test`` (the whole ``trainer.test``), ``test_steps`` (test batches) and
    ``test_data`` (the rest of ``test``: loading the test items). Give it to the Trainer before the callback
    it brackets.
    """

    STAGES = (
        "fit",
        "train_steps",
        "train_data",
        "validation",
        "augmentation",
        "fit_other",
        "test",
        "test_steps",
        "test_data",
    )

    def __init__(self) -> None:
        self.seconds: dict[str, float] = dict.fromkeys(self.STAGES, 0.0)
        self._started: dict[str, float] = {}
        self._epoch_seconds = 0.0

    def _start(self, key: str) -> None:
        self._started[key] = time.perf_counter()

    def _stop(self, key: str) -> float:
        start = self._started.pop(key, None)
        return 0.0 if start is None else time.perf_counter() - start

    def bracket(self, callback: L.Callback | None) -> list[L.Callback]:
        """``[opening marker, callback, closing marker]``: the time ``callback``'s ``on_train_start`` and
        ``on_train_epoch_end`` take counts as ``augmentation`` (``[]`` for ``None``)."""
        if callback is None:
            return []
        return [_Marker(self, opening=True), callback, _Marker(self, opening=False)]

    def on_fit_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._epoch_seconds = 0.0
        self._fit_stages = {k: self.seconds[k] for k in ("train_steps", "validation", "augmentation")}
        self._start("fit")

    def on_fit_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        fit = self._stop("fit")
        spent = {k: self.seconds[k] - self._fit_stages[k] for k in self._fit_stages}
        train_data = max(0.0, self._epoch_seconds - spent["train_steps"] - spent["validation"])
        self.seconds["fit"] += fit
        self.seconds["train_data"] += train_data
        self.seconds["fit_other"] += max(0.0, fit - train_data - sum(spent.values()))

    def on_train_epoch_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._start("epoch")

    def on_train_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._epoch_seconds += self._stop("epoch")

    def on_train_batch_start(
        self, trainer: L.Trainer, pl_module: L.LightningModule, batch: Any, batch_idx: int
    ) -> None:
        self._start("train_steps")

    def on_train_batch_end(
        self, trainer: L.Trainer, pl_module: L.LightningModule, outputs: Any, batch: Any, batch_idx: int
    ) -> None:
        self.seconds["train_steps"] += self._stop("train_steps")

    def on_validation_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if not trainer.sanity_checking:
            self._start("validation")

    def on_validation_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self.seconds["validation"] += self._stop("validation")

    def on_test_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._test_steps = self.seconds["test_steps"]
        self._start("test")

    def on_test_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        test = self._stop("test")
        self.seconds["test"] += test
        self.seconds["test_data"] += max(0.0, test - (self.seconds["test_steps"] - self._test_steps))

    def on_test_batch_start(
        self, trainer: L.Trainer, pl_module: L.LightningModule, batch: Any, batch_idx: int, dataloader_idx: int = 0
    ) -> None:
        self._start("test_steps")

    def on_test_batch_end(
        self,
        trainer: L.Trainer,
        pl_module: L.LightningModule,
        outputs: Any,
        batch: Any,
        batch_idx: int,
        dataloader_idx: int = 0,
    ) -> None:
        self.seconds["test_steps"] += self._stop("test_steps")


class _Marker(L.Callback):
    """One side of :meth:`StageTimer.bracket`: opens or closes the timer's ``augmentation`` stage."""

    def __init__(self, timer: StageTimer, opening: bool) -> None:
        self.timer, self.opening = timer, opening

    def _mark(self) -> None:
        if self.opening:
            self.timer._start("augmentation")
        else:
            self.timer.seconds["augmentation"] += self.timer._stop("augmentation")

    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._mark()

    def on_train_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._mark()

    @property
    def state_key(self) -> str:  # two markers of one timer in a Trainer need distinct keys
        return self._generate_state_key(opening=self.opening)


#: Model arguments that name pretrained weight files: a fine-tuning run takes every weight from the pretrained
#: checkpoint instead, so it neither re-reads nor needs those files.
_WEIGHT_ARGUMENTS = ("backbone_weights", "pretrained_encoder")


def make_model(config: ExperimentConfig, *, fine_tuning: bool = False) -> VoxelReconstructionModule:
    """The model :data:`MODELS` registers as ``config.model``, built with ``preset`` and ``model_kwargs``.

    ``fine_tuning=True`` builds the model a pretrained checkpoint is loaded into: without the weight-file
    arguments (the checkpoint holds those weights), and Pix2Vox++ with ``BCE(refined)`` only, as VTR fine-tunes
    it (its paper preset pretrains with the two-stage loss), unless ``model_kwargs`` say otherwise.
    """
    model_class = MODELS[check_choice("model", config.model, MODELS)]
    kwargs = dict(config.model_kwargs)
    if fine_tuning:
        for name in _WEIGHT_ARGUMENTS:
            kwargs.pop(name, None)
        if issubclass(model_class, Pix2VoxPlusPlus):
            kwargs.setdefault("two_stage_loss", False)
    return model_class(preset=config.preset, **kwargs)


def make_datamodule(
    config: ExperimentConfig,
    model: L.LightningModule,
    num_views: int | None = None,
    *,
    n_views: int | None = None,
) -> VTRDataModule:
    """The experiment's datamodule; ``num_views`` ``None`` takes the model's (tests with another count need it).

    ``n_views`` is the deprecated name of ``num_views`` (removed in 0.3).
    """
    num_views = renamed_argument("n_views", n_views, "num_views", num_views)
    return VTRDataModule(
        config.data,
        num_views=num_views or model.num_views,
        image_size=config.image_size or model.image_size,
        batch_size=config.batch_size,
        num_workers=config.num_workers,
        seed=config.seed,
        test_repeats=config.test_repeats,
        embedded=config.embedded,
        recipe=type(model).image_recipe if config.recipe == "reference" else config.recipe,
    )


def _trainer(config: ExperimentConfig, run_dir: Path, epochs: int, callbacks: list | None = None) -> L.Trainer:
    kwargs: dict[str, Any] = dict(
        max_epochs=epochs,
        accelerator=config.accelerator,
        devices=config.devices,
        precision=config.precision,
        default_root_dir=str(run_dir),
        reload_dataloaders_every_n_epochs=1,
        logger=L.pytorch.loggers.CSVLogger(str(run_dir), name="", version=""),
        enable_checkpointing=True,
        enable_model_summary=False,
        num_sanity_val_steps=0,
        log_every_n_steps=5,
        deterministic=False,
    )
    kwargs.update(config.trainer_kwargs)
    from lightning_vtr.utils.feedback import EpochSummary, silence_lightning_tips

    silence_lightning_tips()  # Lightning 2.6 advertises two cloud services at every Trainer
    # a line per epoch (epoch, train loss, val IoU, time) instead of minutes of silence between epochs
    return L.Trainer(callbacks=[*(callbacks or []), EpochSummary()], **kwargs)


def evaluate(
    model: L.LightningModule,
    dm: VTRDataModule,
    config: ExperimentConfig,
    run_dir: Path,
    *,
    timer: StageTimer | None = None,
) -> dict:
    """Test on every view set; returns ``{view_set: {metric: value}}`` (and per-category entries).

    ``timer`` (a :class:`StageTimer`) adds the test's time to its ``test`` stages.
    """
    kwargs: dict[str, Any] = dict(
        accelerator=config.accelerator,
        default_root_dir=str(run_dir),
        logger=False,
        enable_model_summary=False,
        enable_progress_bar=False,
    )
    kwargs.update(config.trainer_kwargs)
    # One process: a DistributedSampler would pad the test set with duplicates and bias the means.
    kwargs["devices"] = 1
    if timer is not None:
        kwargs["callbacks"] = [*kwargs.get("callbacks", []), timer]
    from lightning_vtr.utils.feedback import silence_lightning_tips

    silence_lightning_tips()
    trainer = L.Trainer(**kwargs)
    return results_from_test_output(trainer.test(model, datamodule=dm, verbose=False))


def pretrain(config: ExperimentConfig) -> Path:
    """Train on Aligned for ``pretrain_epochs``; returns the checkpoint path (reused when it exists).

    Beside the checkpoint, ``timing.json`` holds the fit's :class:`StageTimer` stages (seconds; the part
    after the last resume when the fit was interrupted).
    """
    run_dir = Path(config.out) / "pretrain"
    ckpt = run_dir / "pretrained.ckpt"
    if ckpt.is_file():
        return ckpt
    L.seed_everything(config.seed, workers=True, verbose=False)
    model = make_model(config)
    dm = make_datamodule(config, model)
    # The one checkpoint callback, given to the Trainer so that it adds no default one saving twice.
    checkpoints = L.pytorch.callbacks.ModelCheckpoint(dirpath=run_dir / "checkpoints", save_last=True)
    timer = StageTimer()
    trainer = _trainer(config, run_dir, config.pretrain_epochs, [timer, checkpoints])
    last = run_dir / "checkpoints" / "last.ckpt"
    resumed = last.is_file()
    trainer.fit(model, datamodule=dm, ckpt_path=str(last) if resumed else None)
    if trainer.is_global_zero:
        _write_timing(run_dir / "timing.json", timer, resumed=resumed)
    # `pretrained.ckpt` marks the pretraining done, so it must appear whole or not at all. Lightning writes
    # to a path (every rank joins, rank 0 writes), so the checkpoint goes to a scratch file first.
    scratch = run_dir / "pretrained.partial.ckpt"
    trainer.save_checkpoint(scratch, weights_only=True)
    if trainer.is_global_zero:
        atomic_write(ckpt, scratch.read_bytes())
        scratch.unlink()
    trainer.strategy.barrier("pretrained.ckpt")
    return ckpt


def _write_timing(path: Path, timer: StageTimer, **extra: Any) -> None:
    atomic_write(path, json.dumps({"seconds": timer.seconds, **extra}, indent=1))


def make_strategy(
    name: str,
    config: ExperimentConfig,
    synthesizer: Any = None,
    selector_kwargs: dict[str, Any] | None = None,
    callback_kwargs: dict[str, Any] | None = None,
) -> L.Callback | None:
    """The callback of a named view strategy of :data:`VARIANTS` (``None`` for ``"none"``).

    Args:
        name: a name in :data:`VARIANTS`: ``"none"``, a strategy of the paper's Table 1 (``"nature"``,
            ``"random"``, ``"viat"``, ``"mvtn"``, ``"error_guided"``), ``"random_area"``, ``"paper"`` or a
            variant of the error-guided method (``"released"``, ``"visible"``, ...).
        config: supplies ``fraction`` and ``seed`` of the callback.
        synthesizer: the callback's synthesizer (``None``: mesh rendering).
        selector_kwargs: arguments of the selector class, over the variant's (e.g. ``{"k": 15}`` for
            error-guided).
        callback_kwargs: arguments of :class:`~lightning_vtr.callback.ErrorGuidedViewAugmentation`, over the
            variant's and the config's (e.g. ``{"use_pool": False}``).

    Raises:
        ValueError: ``name`` is not in :data:`VARIANTS`.
    """
    variant = VARIANTS[check_choice("name", name, VARIANTS)]
    if variant.selector is None:
        return None
    selector = make_selector(variant.selector, **{**variant.selector_kwargs, **(selector_kwargs or {})})
    options = {"fraction": config.fraction, "seed": config.seed, **variant.callback_kwargs, **(callback_kwargs or {})}
    return ErrorGuidedViewAugmentation(selector=selector, synthesizer=synthesizer, **options)


def resolved_strategy(
    name: str, selector_kwargs: dict[str, Any] | None = None, callback_kwargs: dict[str, Any] | None = None
) -> dict[str, Any] | None:
    """Every argument :func:`make_strategy` would give the selector and the callback, defaults filled in.

    Two strategies with equal resolved forms train the same run (the callback's default and ``"paper"`` while the
    default is the paper's rule), so the report fits it once. ``None`` for ``"none"``.

    Raises:
        ValueError: ``name`` is not in :data:`VARIANTS`.
    """
    variant = VARIANTS[check_choice("name", name, VARIANTS)]
    if variant.selector is None:
        return None
    selector_class = SELECTORS[variant.selector]
    selector = inspect.signature(selector_class).bind_partial(**{**variant.selector_kwargs, **(selector_kwargs or {})})
    selector.apply_defaults()
    options = {**variant.callback_kwargs, **(callback_kwargs or {})}
    callback = inspect.signature(ErrorGuidedViewAugmentation).bind_partial(**options)
    callback.apply_defaults()
    arguments = {k: v for k, v in callback.arguments.items() if k not in ("selector", "synthesizer")}
    if arguments.get("use_pool") is None:  # the callback's default: the selector's preference
        arguments["use_pool"] = selector_class.uses_pool
    if arguments.get("search_fraction") is None:  # the callback's default: search as many as given views
        arguments["search_fraction"] = arguments["fraction"]
    return {"selector": variant.selector, "selector_kwargs": dict(selector.arguments), "callback_kwargs": arguments}


#: ExperimentConfig fields that say where and on what a run happens, not what it measures.
_PLACEMENT = frozenset({"out", "accelerator", "devices", "num_workers"})


def _comparable(config: ExperimentConfig) -> dict[str, Any]:
    """``config`` as it reads back from ``results.json``."""
    return json.loads(json.dumps(asdict(config), default=str))


def run_strategy(
    name: str,
    config: ExperimentConfig,
    pretrained: Path,
    *,
    run_name: str | None = None,
    callback: L.Callback | None = None,
    synthesizer: Any = None,
    selector_kwargs: dict[str, Any] | None = None,
    callback_kwargs: dict[str, Any] | None = None,
) -> dict:
    """Fine-tune the pretrained model with one view strategy and test it; cached in ``results.json``.

    The run lives in ``<config.out>/<run_name or name>``; its final weights in ``checkpoints/last.ckpt``.
    Without ``callback``, :func:`make_strategy` builds it from ``name`` (a name in :data:`VARIANTS`),
    ``synthesizer``, ``selector_kwargs`` and ``callback_kwargs``.

    Returns:
        The ``results.json`` payload: ``strategy``, ``config``, ``train_seconds`` (the fit),
        ``eval_seconds`` (the test), ``timing`` (:class:`StageTimer` stages of both, seconds; for the part
        after the last resume when the fit was interrupted), ``generated_samples`` and ``results``
        (``{view_set: {metric: value}}``, per-category entries under ``"<view_set>/<category>"``).
    """
    run_dir = Path(config.out) / (run_name or name)
    result_file = run_dir / "results.json"
    if result_file.is_file():
        cached = json.loads(result_file.read_text())
        # A cache is only a result of *this* configuration: refuse one written under another. Where the
        # run lives and what hardware it used do not change what it measures.
        current, saved = _comparable(config), cached.get("config", {})
        # a field added in a later version, absent from an older cache, measured its default
        saved = {**{k: v for k, v in _comparable(ExperimentConfig()).items() if k not in saved}, **saved}
        changed = sorted(k for k in (current.keys() | saved.keys()) - _PLACEMENT if current.get(k) != saved.get(k))
        if changed:
            raise ValueError(
                f"{result_file} was written with another configuration (differs in {changed}); use another `out` "
                "directory or delete that run to re-train it"
            )
        return cached
    L.seed_everything(config.seed, workers=True, verbose=False)
    model = make_model(config, fine_tuning=True)
    model.load_state_dict(torch.load(pretrained, map_location="cpu", weights_only=False)["state_dict"])
    dm = make_datamodule(config, model)
    if callback is None:
        callback = make_strategy(name, config, synthesizer, selector_kwargs, callback_kwargs)
    checkpoints = L.pytorch.callbacks.ModelCheckpoint(dirpath=run_dir / "checkpoints", save_last=True)
    timer = StageTimer()
    callbacks = [timer, *timer.bracket(callback), checkpoints]
    if config.finetune_lr == "cosine":
        callbacks.append(CosineFineTuning(config.finetune_epochs))
    trainer = _trainer(config, run_dir, config.finetune_epochs, callbacks)
    last = run_dir / "checkpoints" / "last.ckpt"
    start = time.perf_counter()
    trainer.fit(model, datamodule=dm, ckpt_path=str(last) if last.is_file() else None)
    train_seconds = time.perf_counter() - start
    start = time.perf_counter()
    results = evaluate(model, dm, config, run_dir, timer=timer)
    eval_seconds = time.perf_counter() - start
    payload = {
        "strategy": name,
        "config": _comparable(config),
        "train_seconds": train_seconds,
        "eval_seconds": eval_seconds,
        "timing": dict(timer.seconds),
        "generated_samples": len(dm.generated_samples),
        "results": results,
    }
    atomic_write(result_file, json.dumps(payload, indent=1))
    return payload


def load_run_model(config: ExperimentConfig, run_dir: Path) -> VoxelReconstructionModule:
    """The experiment's model with the final weights of a fitted run (``run_dir/checkpoints/last.ckpt``).

    Raises:
        FileNotFoundError: the run has no ``checkpoints/last.ckpt`` (it was not fitted by :func:`run_strategy`).
    """
    checkpoint = Path(run_dir) / "checkpoints" / "last.ckpt"
    if not checkpoint.is_file():
        raise FileNotFoundError(f"{checkpoint} does not exist: the run was not fitted by run_strategy")
    model = make_model(config, fine_tuning=True)
    model.load_state_dict(torch.load(checkpoint, map_location="cpu", weights_only=False)["state_dict"])
    return model


def validate_run(config: ExperimentConfig, run_dir: Path, repeats: int) -> dict:
    """Test the final weights of a fine-tuning run on the *validation* split's view sets; cached.

    Loads ``run_dir/checkpoints/last.ckpt`` (written by :func:`run_strategy`) into the experiment's model and
    tests it on every view set of the validation objects, each on ``repeats`` fixed view sets (the same for
    every strategy of a seed). Choosing a strategy on these numbers leaves the test split untouched.

    Returns:
        ``{view_set: {metric: value}}`` as :func:`evaluate` gives, cached in ``run_dir/validation.json`` (a
        cache written with another ``repeats`` is recomputed).

    Raises:
        FileNotFoundError: the run has no ``checkpoints/last.ckpt`` (it was not fitted by :func:`run_strategy`).
    """
    check_int("repeats", repeats, minimum=1)
    run_dir = Path(run_dir)
    cache = run_dir / "validation.json"
    if cache.is_file():
        cached = json.loads(cache.read_text())
        if cached.get("repeats") == repeats:
            return cached["results"]
    model = load_run_model(config, run_dir)
    dm = make_datamodule(config, model)
    dm.test_split, dm.test_repeats = "val", repeats
    results = evaluate(model, dm, config, run_dir)
    atomic_write(cache, json.dumps({"repeats": repeats, "results": results}, indent=1))
    return results
