"""The paper's protocol as functions: pretrain on Aligned, fine-tune with a view strategy, test on all sets.

Used by ``examples/*.py`` and ``lightning-vtr report``. Every run writes ``results.json`` into its own
directory and is skipped when that file exists, so a killed experiment re-run resumes where it stopped.
"""

from __future__ import annotations

import json
import math
import time
import warnings
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import lightning as L
import torch

from lightning_vtr.callback import ErrorGuidedViewAugmentation
from lightning_vtr.data.datamodule import VTRDataModule
from lightning_vtr.experiments.tables import results_from_test_output
from lightning_vtr.models.base import VoxelReconstructionModule
from lightning_vtr.models.lrgt import LRGT
from lightning_vtr.models.pix2vox import Pix2VoxPlusPlus
from lightning_vtr.selection import SELECTORS, make_selector
from lightning_vtr.utils.deprecation import renamed_argument
from lightning_vtr.utils.io import atomic_write
from lightning_vtr.utils.validation import check_choice, check_int

__all__ = [
    "FINETUNE_LR_SCHEDULES",
    "MODELS",
    "STRATEGIES",
    "CosineFineTuning",
    "ExperimentConfig",
    "evaluate",
    "make_datamodule",
    "make_model",
    "make_strategy",
    "pretrain",
    "run_strategy",
]

#: Model name (``ExperimentConfig.model``, ``lightning-vtr report --model``) -> model class.
MODELS: dict[str, type[VoxelReconstructionModule]] = {"pix2vox": Pix2VoxPlusPlus, "lrgt": LRGT}
#: Fine-tuning learning-rate schedules (``ExperimentConfig.finetune_lr``).
FINETUNE_LR_SCHEDULES = ("cosine", "constant")
#: View strategy names of :func:`make_strategy`, in the row order of the paper's Table 1: ``"none"`` (no
#: augmentation), then every selector of :data:`lightning_vtr.selection.SELECTORS`.
STRATEGIES: tuple[str, ...] = ("none", *SELECTORS)


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
        fraction: share of training objects searched per epoch by the callback.
        accelerator, devices, precision: passed to the Trainer; ``devices`` given as a string of digits
            (from a command line) becomes an int.
        out: where runs are written.
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
    out: str = "runs/vtr"
    embedded: dict[str, Any] = field(default_factory=dict)
    model_kwargs: dict[str, Any] = field(default_factory=dict)
    trainer_kwargs: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        check_choice("finetune_lr", self.finetune_lr, FINETUNE_LR_SCHEDULES)
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


def make_model(config: ExperimentConfig) -> VoxelReconstructionModule:
    """The model :data:`MODELS` registers as ``config.model``, built with ``preset`` and ``model_kwargs``."""
    return MODELS[check_choice("model", config.model, MODELS)](preset=config.preset, **config.model_kwargs)


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
        embedded=config.embedded,
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
    return L.Trainer(callbacks=callbacks or [], **kwargs)


def evaluate(model: L.LightningModule, dm: VTRDataModule, config: ExperimentConfig, run_dir: Path) -> dict:
    """Test on every view set; returns ``{view_set: {metric: value}}`` (and per-category entries)."""
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
    trainer = L.Trainer(**kwargs)
    return results_from_test_output(trainer.test(model, datamodule=dm, verbose=False))


def pretrain(config: ExperimentConfig) -> Path:
    """Train on Aligned for ``pretrain_epochs``; returns the checkpoint path (reused when it exists)."""
    run_dir = Path(config.out) / "pretrain"
    ckpt = run_dir / "pretrained.ckpt"
    if ckpt.is_file():
        return ckpt
    L.seed_everything(config.seed, workers=True, verbose=False)
    model = make_model(config)
    dm = make_datamodule(config, model)
    # The one checkpoint callback, given to the Trainer so that it adds no default one saving twice.
    checkpoints = L.pytorch.callbacks.ModelCheckpoint(dirpath=run_dir / "checkpoints", save_last=True)
    trainer = _trainer(config, run_dir, config.pretrain_epochs, [checkpoints])
    last = run_dir / "checkpoints" / "last.ckpt"
    trainer.fit(model, datamodule=dm, ckpt_path=str(last) if last.is_file() else None)
    # `pretrained.ckpt` marks the pretraining done, so it must appear whole or not at all. Lightning writes
    # to a path (every rank joins, rank 0 writes), so the checkpoint goes to a scratch file first.
    scratch = run_dir / "pretrained.partial.ckpt"
    trainer.save_checkpoint(scratch, weights_only=True)
    if trainer.is_global_zero:
        atomic_write(ckpt, scratch.read_bytes())
        scratch.unlink()
    trainer.strategy.barrier("pretrained.ckpt")
    return ckpt


def make_strategy(
    name: str,
    config: ExperimentConfig,
    synthesizer: Any = None,
    selector_kwargs: dict[str, Any] | None = None,
    callback_kwargs: dict[str, Any] | None = None,
) -> L.Callback | None:
    """The callback for a view strategy name (``"none"`` -> ``None``).

    Args:
        name: one of :data:`STRATEGIES`: ``"none"`` or a selector name of
            :data:`lightning_vtr.selection.SELECTORS` (``"nature"``, ``"random"``, ``"viat"``, ``"mvtn"``,
            ``"error_guided"``).
        config: supplies ``fraction`` and ``seed`` of the callback.
        synthesizer: the callback's synthesizer (``None``: mesh rendering).
        selector_kwargs: arguments of the selector class (e.g. ``{"k": 15}`` for error-guided).
        callback_kwargs: further arguments of
            :class:`~lightning_vtr.callback.ErrorGuidedViewAugmentation` (e.g. ``{"use_pool": False}``).

    Raises:
        ValueError: ``name`` is not in :data:`STRATEGIES`.
    """
    if check_choice("name", name, STRATEGIES) == "none":
        return None
    selector = make_selector(name, **(selector_kwargs or {}))
    options = {"fraction": config.fraction, "seed": config.seed, **(callback_kwargs or {})}
    return ErrorGuidedViewAugmentation(selector=selector, synthesizer=synthesizer, **options)


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
    Without ``callback``, :func:`make_strategy` builds it from ``name``, ``synthesizer``,
    ``selector_kwargs`` and ``callback_kwargs``.
    """
    run_dir = Path(config.out) / (run_name or name)
    result_file = run_dir / "results.json"
    if result_file.is_file():
        cached = json.loads(result_file.read_text())
        # A cache is only a result of *this* configuration: refuse one written under another. Where the
        # run lives and what hardware it used do not change what it measures.
        current, saved = _comparable(config), cached.get("config", {})
        changed = sorted(k for k in (current.keys() | saved.keys()) - _PLACEMENT if current.get(k) != saved.get(k))
        if changed:
            raise ValueError(
                f"{result_file} was written with another configuration (differs in {changed}); use another `out` "
                "directory or delete that run to re-train it"
            )
        return cached
    L.seed_everything(config.seed, workers=True, verbose=False)
    model = make_model(config)
    model.load_state_dict(torch.load(pretrained, map_location="cpu", weights_only=False)["state_dict"])
    dm = make_datamodule(config, model)
    if callback is None:
        callback = make_strategy(name, config, synthesizer, selector_kwargs, callback_kwargs)
    checkpoints = L.pytorch.callbacks.ModelCheckpoint(dirpath=run_dir / "checkpoints", save_last=True)
    callbacks = [c for c in (callback, checkpoints) if c is not None]
    if config.finetune_lr == "cosine":
        callbacks.append(CosineFineTuning(config.finetune_epochs))
    trainer = _trainer(config, run_dir, config.finetune_epochs, callbacks)
    last = run_dir / "checkpoints" / "last.ckpt"
    start = time.perf_counter()
    trainer.fit(model, datamodule=dm, ckpt_path=str(last) if last.is_file() else None)
    train_seconds = time.perf_counter() - start
    results = evaluate(model, dm, config, run_dir)
    payload = {
        "strategy": name,
        "config": _comparable(config),
        "train_seconds": train_seconds,
        "generated_samples": len(dm.generated_samples),
        "results": results,
    }
    atomic_write(result_file, json.dumps(payload, indent=1))
    return payload
