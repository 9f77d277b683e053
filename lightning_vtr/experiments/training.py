"""The paper's protocol as functions: pretrain on Aligned, fine-tune with a view strategy, test on all sets.

Used by ``examples/*.py`` and ``lightning-vtr report``. Every run writes ``results.json`` into its own
directory and is skipped when that file exists, so a killed experiment re-run resumes where it stopped.
The configuration is :class:`~lightning_vtr.experiments.config.ExperimentConfig`; the named view strategies
are the rows of :data:`~lightning_vtr.experiments.strategies.VARIANTS`.
"""

from __future__ import annotations

import inspect
import json
import math
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any, cast

import lightning as L
import torch

from lightning_vtr.callback import ErrorGuidedViewAugmentation
from lightning_vtr.data.datamodule import VTRDataModule
from lightning_vtr.evaluation.tables import results_from_test_output
from lightning_vtr.experiments.config import FINETUNE_LR_SCHEDULES, ExperimentConfig
from lightning_vtr.experiments.output_files import RUN_RESULTS, VALIDATION, read_output_json, run_remedy
from lightning_vtr.experiments.strategies import (
    STRATEGIES,
    VARIANTS,
    StrategyVariant,
    build_arguments,
    callback_arguments,
    selector_class,
)
from lightning_vtr.models.base import VoxelReconstructionModule
from lightning_vtr.models.pix2vox import Pix2VoxPlusPlus
from lightning_vtr.models.registry import MODELS, check_model, model_class, read_checkpoint
from lightning_vtr.selection import SELECTORS, make_selector
from lightning_vtr.utils.io import atomic_write
from lightning_vtr.utils.paths import join_under
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
    "load_run_model",
    "make_datamodule",
    "make_model",
    "make_strategy",
    "pretrain",
    "resolved_strategy",
    "run_strategy",
    "training_objects",
    "validate_run",
]


class CosineFineTuning(L.Callback):
    """Sets every parameter group's learning rate to ``base * (1 + cos(pi * epoch / epochs)) / 2`` at each
    training epoch's start (epoch 0 at the model's rate, the last one near 0), whatever the optimizer.

    The base rate is the group's ``initial_lr`` (written by any torch scheduler) or its ``lr`` when the
    optimizer is first seen, so a resumed run continues the same curve. The model's own scheduler still
    steps, but this callback overrides its value at every epoch start.

    Args:
        epochs: the epochs the curve spans (the fine-tuning epochs); later epochs stay at factor 0.

    Raises:
        ValueError: ``epochs`` is below 1.
        TypeError: ``epochs`` is not an int.

    Example:
        >>> schedule = CosineFineTuning(4)  # L.Trainer(max_epochs=4, callbacks=[schedule])
        >>> tuple(round(schedule.factor(epoch), 3) for epoch in range(5))
        (1.0, 0.854, 0.5, 0.146, 0.0)
    """

    def __init__(self, epochs: int) -> None:
        self.epochs = check_int("epochs", epochs, minimum=1)

    def factor(self, epoch: int) -> float:
        """The multiplier of the base rates at ``epoch`` (0-based): 1 at epoch 0, 0 from ``epochs`` on.

        Args:
            epoch: the training epoch.

        Returns:
            ``(1 + cos(pi * min(epoch, epochs) / epochs)) / 2``.
        """
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

    Example:
        >>> timer = StageTimer()
        >>> callbacks = [timer, *timer.bracket(L.Callback())]  # L.Trainer(callbacks=callbacks)
        >>> len(callbacks), timer.seconds["fit"]
        (4, 0.0)
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


_WEIGHT_ARGUMENTS = ("backbone_weights", "pretrained_encoder")
"""Model arguments that name pretrained weight files: a fine-tuning run takes every weight from the pretrained
checkpoint instead, so it neither re-reads nor needs those files."""


def make_model(config: ExperimentConfig, *, fine_tuning: bool = False) -> L.LightningModule:
    """The model :data:`MODELS` registers as ``config.model``, built with ``preset`` and ``model_kwargs``; a class
    path ``module.Class`` (any ``LightningModule`` with the protocol's members and its own ``training_step`` and
    ``configure_optimizers``) is built with ``model_kwargs`` alone.

    ``fine_tuning=True`` builds the model a pretrained checkpoint is loaded into: without the weight-file
    arguments (the checkpoint holds those weights), and Pix2Vox++ with ``BCE(refined)`` only, as VTR fine-tunes
    it (its paper preset pretrains with the two-stage loss), unless ``model_kwargs`` say otherwise.

    Args:
        config: supplies ``model``, ``preset`` and ``model_kwargs``.
        fine_tuning: build the model a pretrained checkpoint is loaded into (see above).

    Returns:
        A new model with its initial weights.

    Raises:
        ValueError: ``config.model`` is neither in :data:`MODELS` nor an importable class path, or the class lacks
            a member of the protocol (:class:`~lightning_vtr.errors.UsageError`, naming what is missing).

    Example:
        >>> model = make_model(ExperimentConfig(model="pix2vox", preset="tiny"))
        >>> type(model).__name__, model.num_views, model.image_size
        ('Pix2VoxPlusPlus', 3, 64)
    """
    if config.model not in MODELS:
        cls = model_class(config.model, "model", training=True)
        return check_model(cls(**config.model_kwargs))
    model_class_ = MODELS[config.model]
    kwargs = dict(config.model_kwargs)
    if fine_tuning:
        for name in _WEIGHT_ARGUMENTS:
            kwargs.pop(name, None)
        if issubclass(model_class_, Pix2VoxPlusPlus):
            kwargs.setdefault("two_stage_loss", False)
    return model_class_(preset=config.preset, **kwargs)


def make_datamodule(config: ExperimentConfig, model: L.LightningModule, num_views: int | None = None) -> VTRDataModule:
    """The experiment's datamodule.

    Args:
        config: supplies the data, batch size, workers, seed, test repeats, embedded options and recipe.
        model: supplies the view count and image size (unless ``config.image_size`` is set).
        num_views: input views per item; ``None`` takes the model's.

    Returns:
        A :class:`~lightning_vtr.data.datamodule.VTRDataModule`, not set up.

    Example:
        >>> config = ExperimentConfig(batch_size=4)
        >>> dm = make_datamodule(config, make_model(config), num_views=1)
        >>> dm.num_views, dm.batch_size
        (1, 4)
    """
    recipe = config.recipe
    if recipe == "reference":
        declared = getattr(type(model), "image_recipe", None)
        if not isinstance(declared, str):
            raise ValueError(
                f"`recipe` 'reference' takes the model class's `image_recipe`, which {type(model).__name__} does not "
                "define; give a named recipe (plain, pix2vox, lrgt)"
            )
        recipe = declared
    return VTRDataModule(
        config.data,
        num_views=num_views or int(cast(Any, model).num_views),
        image_size=config.image_size or int(cast(Any, model).image_size),
        batch_size=config.batch_size,
        num_workers=config.num_workers,
        seed=config.seed,
        test_repeats=config.test_repeats,
        embedded=config.embedded,
        recipe=recipe,
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
    from lightning_vtr.utils.memory import retain_freed_memory

    silence_lightning_tips()  # Lightning 2.6 advertises two cloud services at every Trainer
    retain_freed_memory()  # CPU steps reuse freed memory instead of faulting it in again (see the function)
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

    Args:
        model: the model to test.
        dm: its datamodule; its ``test_split`` and ``test_repeats`` say which items each view set tests.
        config: supplies the test Trainer's ``accelerator`` and ``trainer_kwargs``; the test runs on one device.
        run_dir: the Trainer's ``default_root_dir``.
        timer: a :class:`StageTimer` that adds the test's time to its ``test`` stages; ``None``: none.

    Returns:
        ``{view_set: {metric: value}}``, per-category entries under ``"<view_set>/<category>"``.

    Example::

        model = load_run_model(config, run_dir)
        results = evaluate(model, make_datamodule(config, model), config, run_dir)
        results["spherical"]["iou@0.4"]
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
    tested = model if isinstance(model, VoxelReconstructionModule) else ProtocolTester(model)
    return results_from_test_output(trainer.test(tested, datamodule=dm, verbose=False))


class ProtocolTester(VoxelReconstructionModule):
    """Any model with ``predict_voxels`` tested as the package's models are: IoU and F-score per view set and
    category, logged under the same keys, so a model of your own gets the same columns in every table.

    Args:
        model: a ``LightningModule`` with ``predict_voxels``, ``image_size``, ``num_views`` and
            ``voxel_resolution``.

    Example::

        L.Trainer().test(ProtocolTester(my_model), datamodule=dm)
    """

    def __init__(self, model: L.LightningModule) -> None:
        declared = cast(Any, model)  # the protocol's attributes, which LightningModule does not declare
        super().__init__(int(declared.image_size), int(declared.num_views), int(declared.voxel_resolution))
        self.model = model

    def reconstruct(self, images: torch.Tensor) -> dict[str, torch.Tensor]:
        return {"voxels": cast(Any, self.model).predict_voxels(images)}

    def loss(self, outputs: dict[str, torch.Tensor], target: torch.Tensor) -> torch.Tensor:
        raise NotImplementedError("ProtocolTester only tests")


def pretrain(config: ExperimentConfig) -> Path:
    """Train on Aligned for ``pretrain_epochs``; returns the checkpoint path (reused when it exists).

    Beside the checkpoint, ``timing.json`` holds the fit's :class:`StageTimer` stages (seconds; the part
    after the last resume when the fit was interrupted).

    Args:
        config: the experiment; the run lives in ``<config.out>/pretrain`` and resumes from its ``last.ckpt``.

    Returns:
        The path of ``<config.out>/pretrain/pretrained.ckpt`` (weights only).

    Raises:
        ValueError: ``config.model`` is not in :data:`MODELS`.
        lightning_vtr.utils.paths.UnsafePathError: ``<config.out>/pretrain`` resolves outside ``config.out`` (a
            symlink leading out).

    Example::

        config = ExperimentConfig(pretrain_epochs=2, finetune_epochs=2, out="runs/demo")
        ckpt = pretrain(config)  # runs/demo/pretrain/pretrained.ckpt
    """
    run_dir = join_under(config.out, "pretrain")
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
    if resumed:  # an earlier output is data: read as tensors and plain containers, never as a full pickle
        read_checkpoint(last, _EARLIER_OUTPUT, remedy=_REMEDY)
    trainer.fit(model, datamodule=dm, ckpt_path=str(last) if resumed else None, weights_only=True)
    if trainer.is_global_zero:
        _write_timing(run_dir / "timing.json", timer, resumed=resumed)
    # `pretrained.ckpt` marks the pretraining done, so it must appear whole or not at all. Lightning writes
    # to a path (every rank joins, rank 0 writes), so the checkpoint goes to a scratch file first.
    scratch = run_dir / "pretrained.partial.ckpt"
    if trainer.is_global_zero:
        scratch.unlink(missing_ok=True)  # Lightning opens the path itself: never a link an earlier output left there
    trainer.strategy.barrier("pretrained.partial.ckpt")
    trainer.save_checkpoint(scratch, weights_only=True)
    if trainer.is_global_zero:
        atomic_write(ckpt, scratch.read_bytes())
        scratch.unlink()
    trainer.strategy.barrier("pretrained.ckpt")
    return ckpt


#: How the messages name a checkpoint of an earlier output folder that the run resumes from.
_EARLIER_OUTPUT = "a checkpoint of the earlier output in `--out`"
#: What the messages advise for a checkpoint of an earlier output that is not one this package wrote.
_REMEDY = "delete it, or use another `--out`, to train it again"


def _state_dict(checkpoint: Path) -> dict[str, Any]:
    """The ``state_dict`` of a checkpoint this module wrote, read with ``weights_only=True``.

    Raises:
        DataError: the file is not a checkpoint torch reads as tensors and plain containers (one line naming it
            and, for a full pickle, the globals it holds).
    """
    from lightning_vtr.errors import DataError

    state = read_checkpoint(checkpoint, _EARLIER_OUTPUT, remedy=_REMEDY).get("state_dict")
    if not isinstance(state, dict):
        raise DataError(f"{_EARLIER_OUTPUT} must hold a state_dict, got {str(checkpoint)!r}: {_REMEDY}")
    return state


def _write_timing(path: Path, timer: StageTimer, **extra: Any) -> None:
    atomic_write(path, json.dumps({"seconds": timer.seconds, **extra}, indent=1))


def training_objects(config: ExperimentConfig) -> int:
    """The number of training objects of the experiment's dataset (its ``metadata.json``).

    Args:
        config: ``data`` names the dataset; ``None`` is the embedded one (built with ``embedded`` when missing).

    Returns:
        How many objects the dataset's ``train`` split holds (170 for the embedded dataset's defaults).

    Raises:
        DatasetNotFoundError: ``config.data`` holds no ``metadata.json``.

    Example::

        training_objects(ExperimentConfig(data="/data/shapenet_vtr"))
    """
    from lightning_vtr.data.format import load_metadata

    if config.data is None:
        from lightning_vtr.data.builder import ensure_embedded_dataset

        root = Path(ensure_embedded_dataset(**config.embedded))
    else:
        root = Path(config.data).expanduser()
    return sum(1 for info in load_metadata(root)["objects"].values() if info.get("split") == "train")


def make_strategy(
    name: str,
    config: ExperimentConfig,
    synthesizer: Any = None,
    selector_kwargs: dict[str, Any] | None = None,
    callback_kwargs: dict[str, Any] | None = None,
    *,
    train_objects: int | None = None,
    variants: dict[str, StrategyVariant] | None = None,
) -> L.Callback | None:
    """The callback of a named view strategy (``None`` for ``"none"``).

    Args:
        name: a name in ``variants``: ``"none"``, a strategy of the paper's Table 1 (``"nature"``,
            ``"random"``, ``"viat"``, ``"mvtn"``, ``"paper"``), ``"random_area"``, ``"error_guided"`` (the
            default rule) or a row of a strategies file of yours.
        config: supplies ``fraction`` and ``seed`` of the callback, and the dataset of a row's
            ``max_samples_fraction``.
        synthesizer: the callback's synthesizer (``None``: mesh rendering); a row that names its own
            (:attr:`~lightning_vtr.experiments.strategies.StrategyVariant.synthesizer`) uses that one instead.
        selector_kwargs: arguments of the selector class, over the variant's (e.g. ``{"k": 15}`` for
            error-guided).
        callback_kwargs: arguments of :class:`~lightning_vtr.callback.ErrorGuidedViewAugmentation`, over the
            variant's and the config's (e.g. ``{"use_pool": False}``).
        train_objects: the dataset's training objects, for a row's ``max_samples_fraction``; ``None`` counts
            them (:func:`training_objects`) when the row needs it.
        variants: the named strategies (:func:`~lightning_vtr.experiments.strategies.load_variants`); default
            :data:`VARIANTS`.

    Returns:
        An :class:`~lightning_vtr.callback.ErrorGuidedViewAugmentation`, or ``None`` for a row without selector.

    Raises:
        ValueError: ``name`` is not in ``variants``.

    Example::

        callback = make_strategy("error_guided", ExperimentConfig(fraction=0.1), selector_kwargs={"k": 15})
    """
    variants = VARIANTS if variants is None else variants
    variant = variants[check_choice("name", name, variants)]
    if variant.selector is None:
        return None
    arguments = build_arguments({**variant.selector_kwargs, **(selector_kwargs or {})})
    if variant.selector in SELECTORS:
        selector = make_selector(variant.selector, **arguments)
    else:
        selector = selector_class(variant.selector)(**arguments)
    options = {"fraction": config.fraction, "seed": config.seed, **variant.callback_kwargs, **(callback_kwargs or {})}
    if variant.max_samples_fraction is not None and "max_samples" not in options:
        options["max_samples"] = variant.max_samples(
            training_objects(config) if train_objects is None else train_objects
        )
    options = callback_arguments(selector.uses_pool, options)
    if variant.synthesizer is not None:  # the row's own synthesizer is part of its strategy
        synthesizer = variant.make_synthesizer()
    return ErrorGuidedViewAugmentation(selector=selector, synthesizer=synthesizer, **options)


def resolved_strategy(
    name: str,
    selector_kwargs: dict[str, Any] | None = None,
    callback_kwargs: dict[str, Any] | None = None,
    *,
    variants: dict[str, StrategyVariant] | None = None,
) -> dict[str, Any] | None:
    """Every argument :func:`make_strategy` would give the selector and the callback, defaults filled in.

    Two strategies with equal resolved forms train the same run (e.g. a row of your strategies file that repeats a
    shipped rule), so the report fits it once. A row's ``max_samples_fraction`` stays a fraction
    (``callback_kwargs["max_samples_fraction"]``) unless ``callback_kwargs`` give ``max_samples``.

    Args:
        name: a name in ``variants``.
        selector_kwargs: as for :func:`make_strategy`.
        callback_kwargs: as for :func:`make_strategy`.
        variants: the named strategies; default :data:`VARIANTS`.

    Returns:
        ``{"selector": name, "selector_kwargs": {...}, "callback_kwargs": {...}}``; ``None`` for a row without
        selector.

    Raises:
        ValueError: ``name`` is not in ``variants``.

    Example:
        >>> resolved_strategy("none") is None
        True
        >>> resolved = resolved_strategy("random", callback_kwargs={"fraction": 0.1})
        >>> callback_kwargs = resolved["callback_kwargs"]
        >>> resolved["selector"], callback_kwargs["search_fraction"]
        ('random', 0.1)
    """
    variants = VARIANTS if variants is None else variants
    variant = variants[check_choice("name", name, variants)]
    if variant.selector is None:
        return None
    cls = selector_class(variant.selector)
    selector = inspect.signature(cls).bind_partial(**{**variant.selector_kwargs, **(selector_kwargs or {})})
    selector.apply_defaults()
    options = {**variant.callback_kwargs, **(callback_kwargs or {})}
    capped = variant.max_samples_fraction is not None and "max_samples" not in options
    options.setdefault("fraction", inspect.signature(ErrorGuidedViewAugmentation).parameters["fraction"].default)
    callback = inspect.signature(ErrorGuidedViewAugmentation).bind_partial(
        **callback_arguments(bool(cast(Any, cls).uses_pool), options)
    )
    callback.apply_defaults()
    arguments = {k: v for k, v in callback.arguments.items() if k not in ("selector", "synthesizer", "pool")}
    pool = callback.arguments["pool"] or {}  # in the rows' vocabulary (strategies.POOL_KEYS)
    arguments["use_pool"] = bool(pool)
    arguments["pool_capacity"] = pool.get("capacity", options.get("pool_capacity"))
    arguments["pool_refresh"] = pool.get("refresh", bool(options.get("pool_refresh") or False))
    arguments["pool_prefer_others"] = pool.get("prefer_others", bool(options.get("pool_prefer_others", True)))
    if capped:
        arguments["max_samples_fraction"] = variant.max_samples_fraction
    resolved = {"selector": variant.selector, "selector_kwargs": dict(selector.arguments), "callback_kwargs": arguments}
    if variant.synthesizer is not None:  # a row's own synthesizer makes another run
        resolved["synthesizer"] = {"class_path": variant.synthesizer["class_path"],
                                   "init_args": dict(variant.synthesizer.get("init_args") or {})}  # fmt: skip
    return resolved


_PLACEMENT = frozenset({"out", "accelerator", "devices", "num_workers"})
"""ExperimentConfig fields that say where and on what a run happens, not what it measures."""


_DISPLAY_TRAINER_KWARGS = frozenset({"enable_progress_bar"})
"""``trainer_kwargs`` that change what a run shows, not what it measures (``lightning-vtr report --no-progress``)."""


def _comparable(config: ExperimentConfig) -> dict[str, Any]:
    """``config`` as it reads back from ``results.json``."""
    return json.loads(json.dumps(asdict(config), default=str))


def _measured(config: dict[str, Any]) -> dict[str, Any]:
    """A :func:`_comparable` config without the ``trainer_kwargs`` that only change what a run shows."""
    trainer_kwargs = config.get("trainer_kwargs")
    if not isinstance(trainer_kwargs, dict):
        return config
    return {**config, "trainer_kwargs": {k: v for k, v in trainer_kwargs.items() if k not in _DISPLAY_TRAINER_KWARGS}}


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
    variants: dict[str, StrategyVariant] | None = None,
) -> dict:
    """Fine-tune the pretrained model with one view strategy and test it; cached in ``results.json``.

    The run lives in ``<config.out>/<run_name or name>``; its final weights in ``checkpoints/last.ckpt``.
    Without ``callback``, :func:`make_strategy` builds it from ``name`` (a name in :data:`VARIANTS`),
    ``synthesizer``, ``selector_kwargs`` and ``callback_kwargs``.

    Args:
        name: a name in :data:`VARIANTS` (the payload's ``strategy``, and the run's directory name unless
            ``run_name`` is given).
        config: the experiment; the run lives under ``config.out``.
        pretrained: the checkpoint of :func:`pretrain` the model starts from.
        run_name: the run's directory under ``config.out``; ``None``: ``name``.
        callback: the view-augmentation callback; ``None``: :func:`make_strategy` builds it from ``name``.
        synthesizer: the callback's synthesizer when ``callback`` is ``None`` (``None``: mesh rendering).
        selector_kwargs: as for :func:`make_strategy`, when ``callback`` is ``None``.
        callback_kwargs: as for :func:`make_strategy`, when ``callback`` is ``None``.
        variants: the named strategies ``name`` is looked up in; default :data:`VARIANTS`.

    Returns:
        The ``results.json`` payload: ``strategy``, ``config``, ``train_seconds`` (the fit),
        ``eval_seconds`` (the test), ``timing`` (:class:`StageTimer` stages of both, seconds; for the part
        after the last resume when the fit was interrupted), ``generated_samples`` and ``results``
        (``{view_set: {metric: value}}``, per-category entries under ``"<view_set>/<category>"``).

    Raises:
        ValueError: the run's cached ``results.json`` was written with another configuration (fields other than
            ``out``, ``accelerator``, ``devices``, ``num_workers`` and ``trainer_kwargs["enable_progress_bar"]``
            differ), ``name`` is not in
            :data:`VARIANTS` (without ``callback``), or ``config.model`` is not in :data:`MODELS`.
        DataError: the cached ``results.json`` is not valid JSON or a field has another type than this function
            writes (:data:`~lightning_vtr.experiments.output_files.RUN_RESULTS`); the one line names the file and
            the field.
        lightning_vtr.utils.paths.UnsafePathError: the run's directory resolves outside ``config.out`` (a symlink
            leading out).

    Example::

        config = ExperimentConfig(pretrain_epochs=2, finetune_epochs=2, out="runs/demo")
        payload = run_strategy("random", config, pretrain(config))
        payload["results"]["spherical"]["iou@0.4"]
    """
    run_dir = join_under(config.out, run_name or name)
    result_file = run_dir / "results.json"
    cached = read_output_json(result_file, RUN_RESULTS, run_remedy(run_dir))
    if cached is not None:
        # A cache is only a result of *this* configuration: refuse one written under another. Where the
        # run lives and what hardware it used do not change what it measures.
        current, saved = _measured(_comparable(config)), cached.get("config", {})
        # a field added in a later version, absent from an older cache, measured its default
        saved = _measured({**{k: v for k, v in _comparable(ExperimentConfig()).items() if k not in saved}, **saved})
        changed = sorted(k for k in (current.keys() | saved.keys()) - _PLACEMENT if current.get(k) != saved.get(k))
        if changed:
            raise ValueError(
                f"{result_file} was written with another configuration (differs in {changed}); use another `out` "
                "directory or delete that run to re-train it"
            )
        return cached
    L.seed_everything(config.seed, workers=True, verbose=False)
    model = make_model(config, fine_tuning=True)
    model.load_state_dict(_state_dict(pretrained))
    dm = make_datamodule(config, model)
    if callback is None:
        callback = make_strategy(name, config, synthesizer, selector_kwargs, callback_kwargs, variants=variants)
    checkpoints = L.pytorch.callbacks.ModelCheckpoint(dirpath=run_dir / "checkpoints", save_last=True)
    timer = StageTimer()
    callbacks = [timer, *timer.bracket(callback), checkpoints]
    if config.finetune_lr == "cosine":
        callbacks.append(CosineFineTuning(config.finetune_epochs))
    trainer = _trainer(config, run_dir, config.finetune_epochs, callbacks)
    last = run_dir / "checkpoints" / "last.ckpt"
    if last.is_file():
        read_checkpoint(last, _EARLIER_OUTPUT, remedy=_REMEDY)
    start = time.perf_counter()
    trainer.fit(model, datamodule=dm, ckpt_path=str(last) if last.is_file() else None, weights_only=True)
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


def load_run_model(config: ExperimentConfig, run_dir: Path) -> L.LightningModule:
    """The experiment's model with the final weights of a fitted run (``run_dir/checkpoints/last.ckpt``).

    Args:
        config: the experiment the run belongs to (its ``model``, ``preset`` and ``model_kwargs``).
        run_dir: the run's directory, ``<config.out>/<run name>``.

    Returns:
        The model as :func:`make_model` builds it with ``fine_tuning=True``, holding the run's final weights
        (on the CPU).

    Raises:
        FileNotFoundError: the run has no ``checkpoints/last.ckpt`` (it was not fitted by :func:`run_strategy`).

    Example::

        model = load_run_model(config, Path(config.out) / "random")
    """
    checkpoint = Path(run_dir) / "checkpoints" / "last.ckpt"
    if not checkpoint.is_file():
        raise FileNotFoundError(f"{checkpoint} does not exist: the run was not fitted by run_strategy")
    model = make_model(config, fine_tuning=True)
    model.load_state_dict(_state_dict(checkpoint))
    return model


def validate_run(config: ExperimentConfig, run_dir: Path, repeats: int) -> dict:
    """Test the final weights of a fine-tuning run on the *validation* split's view sets; cached.

    Loads ``run_dir/checkpoints/last.ckpt`` (written by :func:`run_strategy`) into the experiment's model and
    tests it on every view set of the validation objects, each on ``repeats`` fixed view sets (the same for
    every strategy of a seed). Choosing a strategy on these numbers leaves the test split untouched.

    Args:
        config: the experiment the run belongs to.
        run_dir: the run's directory, ``<config.out>/<run name>``.
        repeats: fixed view sets per validation object (at least 1).

    Returns:
        ``{view_set: {metric: value}}`` as :func:`evaluate` gives, cached in ``run_dir/validation.json`` (a
        cache written with another ``repeats`` is recomputed).

    Raises:
        FileNotFoundError: the run has no ``checkpoints/last.ckpt`` (it was not fitted by :func:`run_strategy`).
        ValueError: ``repeats`` is below 1.
        TypeError: ``repeats`` is not an int.
        DataError: the cached ``validation.json`` is not valid JSON or a field has another type than this function
            writes; the one line names the file and the field.

    Example::

        results = validate_run(config, Path(config.out) / "random", repeats=4)
        results["spherical"]["iou@0.4"]
    """
    check_int("repeats", repeats, minimum=1)
    run_dir = Path(run_dir)
    cache = run_dir / "validation.json"
    cached = read_output_json(cache, VALIDATION, f"delete that file ({cache}) to validate the run again")
    if cached is not None and cached["repeats"] == repeats:
        return cached["results"]
    model = load_run_model(config, run_dir)
    dm = make_datamodule(config, model)
    dm.test_split, dm.test_repeats = "val", repeats
    results = evaluate(model, dm, config, run_dir)
    atomic_write(cache, json.dumps({"repeats": repeats, "results": results}, indent=1))
    return results
