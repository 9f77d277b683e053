r"""Error-guided view augmentation: at each training epoch's end, find the views a model is weakest at,
synthesize them and train on them next epoch.

One module, past 600 lines, because the callback's hooks, its selection step, its synthesis step and its
saved state act on one object; the selectors, synthesizers and datamodule it drives live elsewhere.
"""

from __future__ import annotations

import ast
import copy
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, cast

import lightning as L
import numpy as np
import torch
import torch.nn.functional as F
from lightning.pytorch.utilities import rank_zero_info, rank_zero_warn
from lightning.pytorch.utilities.exceptions import MisconfigurationException
from lightning.pytorch.utilities.seed import isolate_rng
from torch import Tensor
from tqdm.auto import tqdm

from lightning_vtr.data.dataset import GeneratedSample
from lightning_vtr.protocol import (
    AugmentableDataModule,
    ReconstructionModel,
    check_augmentable_datamodule,
    check_reconstruction_model,
)
from lightning_vtr.selection.base import SelectionContext, ViewSelector
from lightning_vtr.synthesis.base import SynthesisRequest, Synthesizer
from lightning_vtr.utils.validation import check_choice, check_float, check_int, check_probabilities, check_type

__all__ = ["DEFAULT_SEARCH_FRACTION", "DEFAULT_SELECTOR_KWARGS", "RECORD_VERSION", "ErrorGuidedViewAugmentation"]

_STATE_VERSION = 1
DEFAULT_SELECTOR_KWARGS: dict[str, Any] = {"score": "visible", "min_separation": 30.0, "temperature": 10.0}
"""Arguments of the default selector, ``ErrorGuidedSelector(**DEFAULT_SELECTOR_KWARGS)``: the side-aware
``visible`` score, bins within 30 degrees of a chosen one (or its antipode) suppressed, bins sampled by
solid angle x score at temperature 10 (the report's ``visible_tau10_search`` row)."""
DEFAULT_SEARCH_FRACTION = 0.35
"""``search_fraction`` with the default selector: the released code's search, 35 % of the training objects."""
RECORD_VERSION = 1
"""The ``version`` of the per-selection records (``<log dir>/vtr_selection/*.json``)."""
_NOTHING_GENERATED = -2
# Returning logits instead of probabilities is the usual way a model breaks the protocol.
_PROBABILITIES_HINT = (
    "did predict_voxels return logits? apply torch.sigmoid to them (the callback thresholds occupancy "
    "probabilities); non-finite values mean the model diverged"
)


@dataclass
class _Selected:
    index: int  # position in the datamodule's fixed train order
    category: str
    object_id: str
    viewpoints: np.ndarray  # (n, 2) degrees, as chosen by the selector
    error: float  # fraction of voxels wrong at the selection threshold


def _generator(*key: int) -> torch.Generator:
    # One independent stream per (seed, epoch, object, purpose): results cannot depend on how objects
    # are split over processes or batches.
    seed = int(np.random.SeedSequence(list(key)).generate_state(1, dtype=np.uint64)[0] >> 1)
    return torch.Generator().manual_seed(seed)


def _reload_train_dataloader(trainer: L.Trainer) -> None:
    """Have the fit loop rebuild the train loader when the current epoch starts.

    The one place the callback touches a private attribute of Lightning: Lightning has no public "reload
    now". ``FitLoop.setup_data`` rebuilds the train loader when ``current_epoch -
    _last_train_dl_reload_epoch >= reload_dataloaders_every_n_epochs`` and then sets the attribute to the
    current epoch; marking the last reload as long ago makes the loop rebuild it before the epoch's first
    batch, as ``reload_dataloaders_every_n_epochs=1`` does between epochs. ``tests/test_callback_contract.py``
    checks that the attribute exists and has these semantics, so a Lightning release that changes it fails there.
    """
    loop = trainer.fit_loop
    if hasattr(loop, "_last_train_dl_reload_epoch"):
        loop._last_train_dl_reload_epoch = float("-inf")
    else:  # pragma: no cover - a Lightning without the attribute
        rank_zero_warn(
            "ErrorGuidedViewAugmentation could not ask this Lightning version to rebuild the train loader; the "
            "views generated before this epoch are trained on from the next epoch."
        )


def _attached_datamodule(trainer: L.Trainer) -> AugmentableDataModule | None:
    """``trainer.datamodule`` (``None`` when fit got none), as ``setup`` requires it to be.

    Lightning sets the attribute at runtime but its type information does not declare it; ``setup`` checks
    that it satisfies :class:`AugmentableDataModule`, which the cast states.
    """
    return cast("AugmentableDataModule | None", cast(Any, trainer).datamodule)


def _datamodule(trainer: L.Trainer) -> AugmentableDataModule:
    """``trainer.datamodule`` after ``setup``, which refuses a fit without one."""
    dm = _attached_datamodule(trainer)
    assert dm is not None, "ErrorGuidedViewAugmentation.setup refuses a fit without a datamodule"
    return dm


def _all_gather(trainer: L.Trainer, obj: Any) -> list[Any]:
    """Every process's ``obj`` (any picklable object), in global-rank order, on every process.

    ``Strategy.all_gather`` gathers tensors of one shape only; objects go through one
    ``Strategy.broadcast`` per rank (world sizes here are small, the objects a few selections).
    """
    if trainer.world_size == 1:
        return [obj]
    rank = trainer.global_rank
    return [trainer.strategy.broadcast(obj if src == rank else None, src=src) for src in range(trainer.world_size)]


def _trainer_shows_progress(trainer: L.Trainer) -> bool:
    bar = trainer.progress_bar_callback  # None with Trainer(enable_progress_bar=False)
    return bar is not None and not getattr(bar, "is_disabled", False)


def _broadcast(trainer: L.Trainer, obj: Any) -> Any:
    """Global rank 0's ``obj`` on every process."""
    return obj if trainer.world_size == 1 else trainer.strategy.broadcast(obj, src=0)


class ErrorGuidedViewAugmentation(L.Callback):
    r"""Trains a multi-view reconstruction model on the viewpoints it reconstructs worst.

    Before the first training epoch (from the model the fit starts with, e.g. the pretrained one; the
    paper's first inner maximisation) and at the end of every training epoch but the last it

    1. draws a seeded random ``search_fraction`` of the training objects (at least ``min_objects``),
    2. predicts their voxels from their Aligned views (eval mode, no gradients),
    3. asks ``selector`` for new viewpoints (error-guided by default: bins of the viewing sphere sampled by
       solid angle x how much of the error volume :math:`E = |V - V^{gt}|` a camera there would see, tempered,
       away from each other; :meth:`paper` takes the paper's hard top bins of the orthographic projection),
    4. picks ``fraction`` of the training objects among the searched ones to get new views (``generate_for``),
       and with a pool (the error-guided default) stores every searched object's selection per category
       and draws each picked object's view set from its category's pool, by default one found on another
       object (``pool_refresh`` rebuilds the pool from the current model at every selection),
    5. synthesizes images at those viewpoints with ``synthesizer`` (mesh rendering by default;
       Zero-1-to-3 with :class:`~lightning_vtr.synthesis.zero123.Zero123Synthesizer`),
    6. adds the new (images, viewpoints, voxels) samples to the datamodule, which serves them from the
       next epoch on (they accumulate; ``max_samples`` caps them).

    Only the reconstruction model is needed at inference; nothing of this callback is.

    Under mixed precision (``Trainer(precision="bf16-mixed")``, ``"16-mixed"``) the model predicts in the
    Trainer's autocast, as in validation; the error volumes and the selection use those predictions cast to
    float32, and the synthesized images are stored exactly as the synthesizer returns them (uint8).

    Requirements: ``Trainer(reload_dataloaders_every_n_epochs=1)``; a datamodule satisfying
    :class:`~lightning_vtr.protocol.AugmentableDataModule` (``split_records``, ``record``, ``eval_item``,
    ``object_views``, ``add_samples(samples, *, max_total)``, ``transform``, ``generated_samples``;
    :class:`~lightning_vtr.data.VTRDataModule` has them all), which the callback only calls and never
    assigns to; a model satisfying :class:`~lightning_vtr.protocol.ReconstructionModel`.

    Each object's voxel error (the ``mean_error`` logged and recorded, the order of ``generate_for="error"``)
    is the fraction of voxels wrong with the prediction binarised at the selector's ``threshold``
    (:data:`~lightning_vtr.protocol.DEFAULT_THRESHOLD` for selectors that do not binarise).

    Selection records: on global rank 0, every selection writes ``<log dir>/vtr_selection/start.json`` (the
    selection before epoch 0) or ``epoch_<EEEE>.json`` (after epoch ``E``), a JSON object with the fields

    * ``version`` (int): the record format, :data:`RECORD_VERSION` (1);
    * ``epoch`` (int): the epoch whose end made the selection, ``-1`` before epoch 0;
    * ``objects`` (list of str): ``"category/object_id"`` of each object given new views, in train order;
    * ``selected`` (list of ``(n, 2)`` lists): the viewpoints (yaw, pitch in degrees, rounded to 0.001) the
      selector chose for each of ``objects``;
    * ``view_sets`` (list of ``(n, 2)`` lists): the viewpoints each object's new images were synthesized
      at (drawn from the pool when there is one, else equal to ``selected``);
    * ``mean_error`` (float): the mean voxel error of the searched objects (``0.0`` when none);
    * ``searched`` (int): the number of objects searched (predicted and scored).

    A reader should check ``version``; fields may be added without changing it, none removed or redefined.

    Checkpoints: the callback's state (pool, selector state, history, last generated epoch) is saved under
    :attr:`state_key`, which names the selector's class but not the seed; resuming with another ``seed``
    restores it and warns. Checkpoints whose key also names the seed are read too.

    In DDP every rank works on its share of the objects (sharded by global rank in a fixed order); results
    are gathered and merged in that order, so every rank ends the epoch with an identical dataset, and the
    samples equal those of a single-process run. All randomness derives from ``(seed, epoch, object)``, so
    a run resumed from a checkpoint generates exactly what an uninterrupted run does; a generation that the
    checkpoint predates (checkpoints saved at validation end, or a run that ended on its last epoch) is
    caught up when training resumes.

    Args:
        selector: a :class:`~lightning_vtr.selection.base.ViewSelector`; the name of one in
            :data:`lightning_vtr.selection.SELECTORS` (``"error_guided"``, ``"random"``, ``"nature"``,
            ``"viat"``, ``"mvtn"``), built with its defaults (``"error_guided"``: ``ErrorGuidedSelector()``,
            whose defaults are the paper's score); or ``"paper"``, the paper's exact rule (:meth:`paper`).
            Default (``None``): the tempered side-aware rule, ``ErrorGuidedSelector(score="visible",
            min_separation=30.0, temperature=10.0)`` (K = 30, 3 views), searching 35 % of the objects into a
            pool rebuilt at every selection (see ``search_fraction`` and ``pool_refresh``), the best
            error-guided rule measured (``docs/results.md``, "The default rule").
        synthesizer: a :class:`~lightning_vtr.synthesis.base.Synthesizer`; default ``RenderSynthesizer()``.
        fraction: share of training objects given new views per selection (the paper's random update
            strategy: 5 %).
        search_fraction: share of training objects scored per selection; ``None``: 0.35 with the default
            selector (``selector=None``; ``fraction`` if larger), ``fraction`` with a selector given or named
            (the paper's). Scoring
            is cheap next to synthesis, so searching more objects than get new views fills the pool with the
            current model's weak views (the released code searches far more than it generates for).
        generate_for: which searched objects get the new views when ``search_fraction > fraction``:
            ``"random"`` (a seeded random subset, the default: it keeps every category in proportion and does
            not show the same few hard objects again and again; with a pool their views come from the whole
            category anyway) or ``"error"`` (the objects with the largest voxel error first).
        min_objects: lower bound on objects searched and given views per selection.
        use_pool: store selections in a per-category viewpoint pool and sample from it; default: the
            selector's ``uses_pool`` (True for error-guided, False for Random/Nature).
        pool_capacity: view sets kept per category in the pool (``None``: all).
        pool_refresh: empty the pool before each selection, so it holds only what the current model gets
            wrong (the released code rebuilds it every epoch); ``False`` keeps every earlier selection (the
            paper's). ``None``: ``True`` with the default selector, ``False`` with a selector given or named.
        pool_prefer_others: draw a view set found on *another* object of the category when there is one
            (the paper's transferability argument); ``False`` draws among all, the object's own included.
        select_at_start: run the first selection and generation in ``on_train_start``, before epoch 0 trains,
            so every fine-tuning epoch sees selected views; ``False`` waits for the end of epoch 0.
        max_samples: cap on generated samples the datamodule serves (the oldest are dropped), passed to every
            ``add_samples(..., max_total=max_samples)``; ``None``: all. The one owner of the cap:
            ``VTRDataModule`` has no cap of its own.
        batch_size: objects per prediction / synthesis call.
        source_view_set: which view set the objects' current views come from.
        seed: seeds every random choice the callback makes.
        log_images: log a grid of new views and the error sheets of two of the objects given views (input
            views, prediction, truth, error, error projection at the selected views) to every logger, through
            :func:`lightning_vtr.utils.image_logging.log_image` (TensorBoard, W&B, MLflow, Comet; PNG files
            under the run's log directory for the others). ``vtr/samples_generated``, ``vtr/samples_total`` and
            ``vtr/mean_error`` are logged with ``pl_module.log`` (epoch-level) whatever this says.
        progress_bar: show a progress bar while synthesizing (rank 0), when the Trainer shows one
            (``Trainer(enable_progress_bar=False)`` hides it too).

    Raises:
        TypeError: an argument of the wrong type (e.g. a ``selector`` that is neither a ViewSelector nor a name).
        ValueError: on invalid arguments (names the argument and value), e.g. an unknown selector name.
        MisconfigurationException: in ``setup`` when the Trainer, datamodule or model cannot be served; in
            ``on_fit_start`` (one prediction on one training item, before any training) when ``predict_voxels``
            gives another grid than the dataset's voxels (the message names both shapes).
        ValueError: whenever ``predict_voxels`` returns values outside ``[0, 1]`` or non-finite ones (logits are
            the usual cause; the message gives the observed range and the count of non-finite values).

    Example::

        trainer = L.Trainer(max_epochs=20, reload_dataloaders_every_n_epochs=1,
                            callbacks=[ErrorGuidedViewAugmentation()])
        trainer.fit(Pix2VoxPlusPlus(preset="tiny"), datamodule=VTRDataModule(image_size=64))

        # or by registry name, as a YAML config would: ErrorGuidedViewAugmentation(selector="random")
        # the paper's exact rule: ErrorGuidedViewAugmentation.paper(), or selector="paper"
    """

    def __init__(
        self,
        selector: ViewSelector | str | None = None,
        synthesizer: Synthesizer | None = None,
        *,
        fraction: float = 0.05,
        search_fraction: float | None = None,
        generate_for: Literal["random", "error"] = "random",
        min_objects: int = 1,
        use_pool: bool | None = None,
        pool_capacity: int | None = None,
        pool_refresh: bool | None = None,
        pool_prefer_others: bool = True,
        select_at_start: bool = True,
        max_samples: int | None = None,
        batch_size: int = 16,
        source_view_set: str = "aligned",
        seed: int = 0,
        log_images: bool = True,
        progress_bar: bool = True,
    ) -> None:
        fraction = check_float("fraction", fraction, minimum=0.0, maximum=1.0, min_open=True)
        # the default selector comes with the settings it was measured with; a selector given or named keeps
        # the paper's (search as many objects as get views, keep every selection in the pool)
        default_rule = selector is None
        if search_fraction is None:
            search_fraction = max(DEFAULT_SEARCH_FRACTION, fraction) if default_rule else fraction
        search_fraction = check_float("search_fraction", search_fraction, minimum=fraction, maximum=1.0)
        generate_for = check_choice("generate_for", generate_for, ("random", "error"))
        pool_refresh = default_rule if pool_refresh is None else check_type("pool_refresh", pool_refresh, bool)
        pool_prefer_others = check_type("pool_prefer_others", pool_prefer_others, bool)
        select_at_start = check_type("select_at_start", select_at_start, bool)
        min_objects = check_int("min_objects", min_objects, minimum=1)
        if max_samples is not None:
            max_samples = check_int("max_samples", max_samples, minimum=1)
        if pool_capacity is not None:
            pool_capacity = check_int("pool_capacity", pool_capacity, minimum=1)
        batch_size = check_int("batch_size", batch_size, minimum=1)
        # a SeedSequence entropy word: non-negative
        seed = check_int("seed", seed, minimum=0)
        if isinstance(selector, str):
            # a registry name, as YAML configs and the CLI give it; imported here so that importing the
            # callback does not import every selector
            from lightning_vtr.selection.registry import SELECTOR_PRESETS, SELECTORS, make_selector

            selector = make_selector(check_choice("selector", selector, [*SELECTORS, *SELECTOR_PRESETS]))
        elif selector is None:
            from lightning_vtr.selection.error_guided import ErrorGuidedSelector

            selector = ErrorGuidedSelector(**DEFAULT_SELECTOR_KWARGS)
        else:
            check_type("selector", selector, ViewSelector, "lightning_vtr ViewSelector or a registry name")
        if synthesizer is None:
            from lightning_vtr.synthesis.render import RenderSynthesizer

            synthesizer = RenderSynthesizer()
        else:
            check_type("synthesizer", synthesizer, Synthesizer, "lightning_vtr Synthesizer")
        self.selector = selector
        self.synthesizer = synthesizer
        self.fraction = fraction
        self.search_fraction = search_fraction
        self.generate_for = generate_for
        self.min_objects = min_objects
        self.pool_refresh = pool_refresh
        self.select_at_start = select_at_start
        self.use_pool = selector.uses_pool if use_pool is None else bool(use_pool)
        self.max_samples = max_samples
        self.batch_size = batch_size
        self.source_view_set = source_view_set
        self.seed = seed
        self.log_images = log_images
        self.progress_bar = progress_bar
        self.pool = None
        if self.use_pool:
            from lightning_vtr.selection.pool import ViewpointPool

            self.pool = ViewpointPool(
                capacity=pool_capacity, num_views=selector.num_views, prefer_others=pool_prefer_others
            )
        # Last epoch whose samples were generated: -1 is the selection before epoch 0, -2 none yet.
        self.last_epoch = _NOTHING_GENERATED
        self.history: list[dict[str, Any]] = []

    @classmethod
    def paper(cls, **kwargs: Any) -> ErrorGuidedViewAugmentation:
        """The paper's exact rule: ``cls(selector="paper", **kwargs)``.

        The selector is ``"paper"`` of :data:`~lightning_vtr.selection.registry.SELECTOR_PRESETS` (binary error summed over the first-hit map of the orthographic error projection, the hard top 3 of the
        30-degree bins, no suppression); the callback searches as many objects as it gives views
        (``search_fraction = fraction``) and keeps every selection in a per-category pool that prefers other
        objects' view sets (``pool_refresh=False``, ``pool_prefer_others=True``), the first selection made
        from the model the fit starts with (``select_at_start=True``). The report's ``paper`` row.

        Args:
            kwargs: any other argument of the callback (``fraction``, ``synthesizer``, ``seed``, ...); they
                override these settings, the selector excepted.

        Raises:
            TypeError: ``kwargs`` give a ``selector``.

        Example::

            callback = ErrorGuidedViewAugmentation.paper(fraction=0.05, seed=0)
        """
        if "selector" in kwargs:
            raise TypeError("ErrorGuidedViewAugmentation.paper() takes no `selector`: it is the paper's")
        return cls(selector="paper", **kwargs)

    @property
    def state_key(self) -> str:
        """The key of this callback's state in a checkpoint: the class and the selector's class.

        The seed is not part of it, so a run resumed with another seed restores the state (and warns that
        later generations differ); checkpoints whose key also names the seed are read too.
        """
        return self._generate_state_key(selector=type(self.selector).__name__)

    def _seeded_state_key(self, states: dict[Any, Any]) -> Any:
        """The key of this callback's state in ``states`` as saved with the seed in the key, or ``None``."""
        prefix = type(self).__qualname__
        for key in states:
            if not isinstance(key, str) or not key.startswith(prefix + "{"):
                continue
            try:
                fields = ast.literal_eval(key[len(prefix) :])
            except (ValueError, SyntaxError):
                continue
            if (
                isinstance(fields, dict)
                and set(fields) == {"selector", "seed"}
                and fields["selector"] == type(self.selector).__name__
            ):
                return key
        return None

    def on_load_checkpoint(self, trainer: L.Trainer, pl_module: L.LightningModule, checkpoint: dict[str, Any]) -> None:
        # Lightning restores the state saved under `state_key`; a checkpoint written when the key named the
        # seed has it under the old key, which is read here.
        states = checkpoint.get("callbacks") or {}
        if self.state_key in states or self._legacy_state_key in states:
            return
        key = self._seeded_state_key(states)
        if key is not None:
            self.load_state_dict(copy.deepcopy(states[key]))

    # ------------------------------------------------------------------ setup checks
    def setup(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        if stage != "fit":
            return
        # Set by Lightning at runtime but not declared in its type information.
        reload_every = cast(Any, trainer).reload_dataloaders_every_n_epochs
        if reload_every != 1:
            raise MisconfigurationException(
                "ErrorGuidedViewAugmentation adds samples at epoch ends, which the next epoch only sees if the train "
                "dataloader is rebuilt: pass `Trainer(reload_dataloaders_every_n_epochs=1)` "
                f"(got {reload_every})."
            )
        dm = _attached_datamodule(trainer)
        if dm is None:
            raise MisconfigurationException(
                "ErrorGuidedViewAugmentation needs a datamodule satisfying lightning_vtr.protocol.AugmentableDataModule, "
                "but no datamodule was given: pass lightning_vtr.data.VTRDataModule (or your own) as `datamodule=`."
            )
        try:
            check_augmentable_datamodule(dm)
        except TypeError as err:
            raise MisconfigurationException(f"ErrorGuidedViewAugmentation: {err}") from err
        # A synthesizer that cannot serve the training objects (rendering without meshes) fails now, not after epoch 0.
        self.synthesizer.check_serves(dm.split_records("train"), view_set=self.source_view_set)
        try:
            check_reconstruction_model(pl_module)
        except TypeError as err:
            raise MisconfigurationException(str(err)) from err
        if self.selector.num_views != pl_module.num_views:
            rank_zero_warn(
                f"The selector returns {self.selector.num_views} views per sample but the model trains with "
                f"{pl_module.num_views}; generated samples will have {self.selector.num_views} views."
            )

    def on_fit_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        # Here rather than in `setup`: the model is on its device now. One prediction, before any training.
        self._check_model_output(trainer, pl_module)

    @torch.no_grad()
    def _check_model_output(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        """Refuse a model whose ``predict_voxels`` does not give the dataset's voxel grid (one training item)."""
        dm = _datamodule(trainer)
        records = dm.split_records("train")
        if not records:
            return  # `_run` warns that nothing can be generated
        item = dm.eval_item(records[0], self.source_view_set, seed=0)
        was_training = pl_module.training
        pl_module.eval()
        try:
            with isolate_rng():  # a model that draws random numbers here must not shift the training's stream
                predicted = self._predict(pl_module, [item["images"]])
        finally:
            pl_module.train(was_training)
        expected = tuple(item["voxels"].shape)
        if tuple(predicted.shape[1:]) != expected:
            raise MisconfigurationException(
                f"ErrorGuidedViewAugmentation compares predictions with the dataset's voxels, but "
                f"{type(pl_module).__name__}.predict_voxels returned shape {tuple(predicted.shape)} for one training "
                f"item ({item['category']}/{item['object_id']}, images {tuple(item['images'].shape)}) and the "
                f"dataset's voxels have shape {expected}: use a model whose voxel_resolution is {expected[0]} or a "
                f"dataset built at the model's resolution."
            )

    # ------------------------------------------------------------------ hooks
    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        # The generation that serves the epoch about to start: before epoch 0 from the model the fit starts
        # with; after a resume, one the checkpoint predates (ModelCheckpoint saves at validation end; the last
        # epoch of a finished run generates nothing).
        due = trainer.current_epoch - 1
        if due == -1 and not self.select_at_start:
            return
        if self.last_epoch < due:
            if due >= 0:
                rank_zero_info(f"ErrorGuidedViewAugmentation: catching up the generation of epoch {due} after resume")
            self._run(trainer, pl_module, due)
            # Lightning built this epoch's train loader before on_train_start; have it rebuilt so the
            # new samples are trained on in this very epoch.
            _reload_train_dataloader(trainer)

    def on_train_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if trainer.sanity_checking or trainer.should_stop:
            return
        max_epochs = trainer.max_epochs
        if max_epochs is not None and max_epochs >= 0 and trainer.current_epoch >= max_epochs - 1:
            return  # nothing would train on them
        self._run(trainer, pl_module, trainer.current_epoch)

    # ------------------------------------------------------------------ the algorithm
    def _count(self, share: float, num_train: int) -> int:
        return min(num_train, max(self.min_objects, round(share * num_train)))

    def _choose_objects(self, num_train: int, epoch: int) -> list[int]:
        """Indices of the objects searched at ``epoch``, in train order."""
        rng = np.random.default_rng([self.seed, epoch + 1])
        return sorted(rng.choice(num_train, size=self._count(self.search_fraction, num_train), replace=False).tolist())

    def _generation_targets(self, selected: list[_Selected], num_train: int, epoch: int) -> list[_Selected]:
        """The searched objects that get new views at ``epoch``, in train order."""
        count = min(len(selected), self._count(self.fraction, num_train))
        if count == len(selected):
            return selected
        if self.generate_for == "error":  # largest error first; ties by train order
            order = sorted(range(len(selected)), key=lambda j: (-selected[j].error, selected[j].index))
            keep = set(order[:count])
        else:
            rng = np.random.default_rng([self.seed, epoch + 1, 3])
            keep = set(rng.choice(len(selected), size=count, replace=False).tolist())
        return [s for j, s in enumerate(selected) if j in keep]

    def _context(self, trainer: L.Trainer, pl_module: L.LightningModule, requests: list) -> SelectionContext:
        def loss_fn(pred: Tensor, target: Tensor) -> Tensor:
            return F.binary_cross_entropy(pred.clamp(1e-6, 1 - 1e-6), target, reduction="none").flatten(1).mean(1)

        return SelectionContext(
            model=pl_module,
            synthesizer=self.synthesizer,
            requests=requests,
            transform=_datamodule(trainer).transform,
            loss_fn=loss_fn,
            device=pl_module.device,
        )

    @torch.no_grad()
    def _predict(self, pl_module: L.LightningModule, images: list[Tensor]) -> Tensor:
        """``predict_voxels`` over ``images`` (each ``(V, 3, H, W)``) in batches: ``(N, R, R, R)`` float32 probabilities.

        The model runs in the Trainer's precision context, as in validation (autocast under ``bf16-mixed`` /
        ``16-mixed``); its output is cast to float32, so error volumes and view selection are in float32.

        Raises:
            ValueError: the model returned another batch size or anything but finite values in ``[0, 1]``.
        """
        name = f"{type(pl_module).__name__}.predict_voxels"
        preds = []
        for start in range(0, len(images), self.batch_size):
            batch = torch.stack(images[start : start + self.batch_size]).to(pl_module.device)
            with pl_module.trainer.precision_plugin.forward_context():
                # `setup` checked that the model satisfies ReconstructionModel.
                out = cast(ReconstructionModel, pl_module).predict_voxels(batch)
            if not isinstance(out, Tensor) or out.ndim != 4 or out.shape[0] != batch.shape[0]:
                found = tuple(out.shape) if isinstance(out, Tensor) else type(out).__name__
                raise ValueError(
                    f"`{name}` must return occupancy probabilities of shape (B, R, R, R) for images of shape "
                    f"{tuple(batch.shape)}, got {found}"
                )
            preds.append(check_probabilities(name, out.detach().float().cpu(), _PROBABILITIES_HINT))
        return torch.cat(preds)

    def _select(
        self, trainer: L.Trainer, pl_module: L.LightningModule, epoch: int, chosen: list[int]
    ) -> list[_Selected]:
        """Predict the chosen objects (sharded by rank), select their views, return them merged in order."""
        dm = _datamodule(trainer)
        records = dm.split_records("train")
        mine = chosen[trainer.global_rank :: trainer.world_size]
        was_training = pl_module.training
        pl_module.eval()
        try:
            items = [dm.eval_item(records[i], self.source_view_set, seed=epoch + 1) for i in mine]
            predicted = self._predict(pl_module, [it["images"] for it in items]) if items else torch.empty(0)
            target = torch.stack([it["voxels"] for it in items]) if items else torch.empty(0)
            if self.selector.batched:
                return self._select_batched(trainer, pl_module, epoch, mine, predicted, target)
            selected = []
            for row, index in enumerate(mine):
                rec = records[index]
                context = (
                    self._context(trainer, pl_module, [self._request(dm, rec)]) if self.selector.needs_context else None
                )
                views = self.selector.select(
                    predicted[row : row + 1],
                    target[row : row + 1],
                    [rec.category],
                    generator=_generator(self.seed, epoch + 1, index, 0),
                    context=context,
                )[0]
                selected.append(self._selected(rec, index, views, predicted[row], target[row]))
        finally:
            pl_module.train(was_training)
        merged = [s for part in _all_gather(trainer, selected) for s in part]
        return sorted(merged, key=lambda s: s.index)

    def _select_batched(
        self,
        trainer: L.Trainer,
        pl_module: L.LightningModule,
        epoch: int,
        mine: list[int],
        predicted: Tensor,
        target: Tensor,
    ) -> list[_Selected]:
        # Learning selectors see every searched object in one call on rank 0; the selections and the learned
        # state are broadcast so every rank (and rank 0's checkpoint) holds the same selector.
        dm = _datamodule(trainer)
        records = dm.split_records("train")
        parts = _all_gather(trainer, (mine, predicted, target))
        indices = [i for part in parts for i in part[0]]
        order = sorted(range(len(indices)), key=lambda j: indices[j])
        indices = [indices[j] for j in order]
        payload = None
        if trainer.is_global_zero:
            all_pred = torch.cat([p[1] for p in parts if len(p[0])])[order]
            all_target = torch.cat([p[2] for p in parts if len(p[0])])[order]
            recs = [records[i] for i in indices]
            context = None
            if self.selector.needs_context:
                context = self._context(trainer, pl_module, [self._request(dm, r) for r in recs])
            views = self.selector.select(
                all_pred,
                all_target,
                [r.category for r in recs],
                generator=_generator(self.seed, epoch + 1, 0, 2),
                context=context,
            )
            selected = [
                self._selected(r, i, v, p, t) for r, i, v, p, t in zip(recs, indices, views, all_pred, all_target)
            ]
            payload = (selected, self.selector.state_dict())
        payload = _broadcast(trainer, payload)
        if not trainer.is_global_zero:
            self.selector.load_state_dict(payload[1])
        return payload[0]

    def _selected(self, record: Any, index: int, views: Tensor, predicted: Tensor, target: Tensor) -> _Selected:
        # the object's error at the selector's threshold, the one its error volume binarises at
        error = ((predicted >= self.selector.threshold).float() != target).float().mean().item()
        return _Selected(index, record.category, record.object_id, views.detach().cpu().numpy(), error)

    def _request(self, dm: Any, record: Any, targets: Tensor | None = None) -> SynthesisRequest:
        if self.synthesizer.needs_source_images:
            images, viewpoints = dm.object_views(record, self.source_view_set)
        else:  # e.g. mesh rendering: skip decoding every source image of the object
            _, viewpoints = record.views[self.source_view_set]
            images = np.zeros((0, 0, 0, 4), np.uint8)
        return SynthesisRequest(
            object_id=record.object_id,
            category=record.category,
            source_images=images,
            source_viewpoints=torch.as_tensor(viewpoints, dtype=torch.float32),
            target_viewpoints=torch.zeros(0, 2) if targets is None else torch.as_tensor(targets, dtype=torch.float32),
            mesh_path=record.mesh_path,
        )

    def _view_sets(self, epoch: int, searched: list[_Selected], targets: list[_Selected]) -> list[np.ndarray]:
        """The view set each of ``targets`` is shown from; every searched selection goes into the pool first."""
        if self.pool is None:
            return [s.viewpoints for s in targets]
        if self.pool_refresh:
            self.pool.clear()
        for s in searched:
            self.pool.add(s.category, s.object_id, torch.as_tensor(s.viewpoints))
        return [
            self.pool.sample(s.category, s.object_id, generator=_generator(self.seed, epoch + 1, s.index, 1)).numpy()
            for s in targets
        ]

    def _synthesize(
        self, trainer: L.Trainer, epoch: int, selected: list[_Selected], view_sets: list[np.ndarray]
    ) -> list[np.ndarray]:
        dm = _datamodule(trainer)
        records = dm.split_records("train")
        rank, world = trainer.global_rank, trainer.world_size
        mine = list(range(rank, len(selected), world))
        images: dict[int, np.ndarray] = {}
        bar = tqdm(
            total=len(mine),
            desc=f"VTR: synthesizing views (epoch {epoch})",
            disable=not (self.progress_bar and rank == 0 and _trainer_shows_progress(trainer)),
            leave=False,
            dynamic_ncols=True,
        )
        for start in range(0, len(mine), self.batch_size):
            chunk = mine[start : start + self.batch_size]
            requests = [self._request(dm, records[selected[j].index], torch.as_tensor(view_sets[j])) for j in chunk]
            for j, out in zip(chunk, self.synthesizer.synthesize(requests)):
                images[j] = np.asarray(out)
            bar.update(len(chunk))
        bar.close()
        merged: dict[int, np.ndarray] = {}
        for part in _all_gather(trainer, images):
            merged.update(part)
        return [merged[j] for j in range(len(selected))]

    def _run(self, trainer: L.Trainer, pl_module: L.LightningModule, epoch: int) -> None:
        dm = _datamodule(trainer)
        num_train = len(dm.split_records("train"))
        if num_train == 0:
            rank_zero_warn("ErrorGuidedViewAugmentation: the datamodule has no training objects; nothing generated.")
            return
        searched = self._select(trainer, pl_module, epoch, self._choose_objects(num_train, epoch))
        selected = self._generation_targets(searched, num_train, epoch)
        view_sets = self._view_sets(epoch, searched, selected)
        images = self._synthesize(trainer, epoch, selected, view_sets)
        samples = [
            GeneratedSample(s.category, s.object_id, img, np.asarray(vs, dtype=np.float64), epoch)
            for s, vs, img in zip(selected, view_sets, images)
        ]
        dm.add_samples(samples, max_total=self.max_samples)
        trainer.strategy.barrier("ErrorGuidedViewAugmentation.add_samples")
        self.last_epoch = epoch
        record = {
            "version": RECORD_VERSION,
            "epoch": epoch,
            "objects": [f"{s.category}/{s.object_id}" for s in selected],
            "selected": [s.viewpoints.round(3).tolist() for s in selected],
            "view_sets": [np.asarray(v).round(3).tolist() for v in view_sets],
            "mean_error": float(np.mean([s.error for s in searched])) if searched else 0.0,
            "searched": len(searched),
        }
        self.history.append({k: record[k] for k in ("epoch", "mean_error")} | {"samples": len(samples)})
        self._log(trainer, pl_module, record, samples)

    # ------------------------------------------------------------------ logging
    def _log(
        self, trainer: L.Trainer, pl_module: L.LightningModule, record: dict[str, Any], samples: list[GeneratedSample]
    ) -> None:
        total = len(_datamodule(trainer).generated_samples)
        metrics = {
            "vtr/samples_generated": float(len(samples)),
            "vtr/samples_total": float(total),
            "vtr/mean_error": record["mean_error"],
        }
        # Through `pl_module.log`, so every logger gets them and ModelCheckpoint / EarlyStopping can monitor them.
        # Every rank logs (the samples are merged in a fixed order, so the values are equal on every rank);
        # `sync_dist` averages equal values, which keeps them, and keeps Lightning from warning under DDP.
        for name, value in metrics.items():
            pl_module.log(name, value, on_step=False, on_epoch=True, sync_dist=True, batch_size=1)
        # `trainer.log_dir` broadcasts under DDP: every rank must ask for it, before the rank-0 branch.
        log_dir = trainer.log_dir or trainer.default_root_dir
        if not trainer.is_global_zero:
            return
        rank_zero_info(
            f"VTR {'before training' if record['epoch'] < 0 else 'epoch ' + str(record['epoch'])}: "
            f"{len(samples)} samples generated ({total} in total), "
            f"mean voxel error of searched objects {record['mean_error']:.4f}"
        )
        if self.log_images and samples and trainer.loggers:
            from lightning_vtr.utils.image_logging import log_image

            log_image(trainer, "vtr/new_views", _grid(samples[:8]), step=trainer.global_step)
            sheets = self._error_sheets(trainer, pl_module, record)
            log_image(trainer, "vtr/error_sheets", sheets, step=trainer.global_step)
        if log_dir:
            out = Path(log_dir) / "vtr_selection"
            out.mkdir(parents=True, exist_ok=True)
            name = "start" if record["epoch"] < 0 else f"epoch_{record['epoch']:04d}"
            (out / f"{name}.json").write_text(json.dumps(record, indent=1))

    @torch.no_grad()
    def _error_sheets(
        self, trainer: L.Trainer, pl_module: L.LightningModule, record: dict[str, Any], count: int = 2
    ) -> np.ndarray:
        """Sheets (views | prediction | truth | error | error projection at the selected views) of the first
        ``count`` objects given new views, predicted again by the current model (rank 0 only, a few objects)."""
        from lightning_vtr.visualize import object_sheet, stack_sheets

        dm = _datamodule(trainer)
        seed = record["epoch"] + 1  # the views the selection predicted from
        records = [dm.record(*name.split("/", 1)) for name in record["objects"][:count]]
        items = [dm.eval_item(rec, self.source_view_set, seed=seed) for rec in records]
        was_training = pl_module.training
        pl_module.eval()
        try:
            predicted = self._predict(pl_module, [item["images"] for item in items])
        finally:
            pl_module.train(was_training)
        normalize = getattr(dm.transform, "normalize", "auto")
        sheets = [
            object_sheet(
                predicted[i],
                item["voxels"],
                item["images"],
                input_viewpoints=item["viewpoints"],
                selected_viewpoints=record["selected"][i],
                panel_size=96,
                normalize=normalize,
                title=f"{record['objects'][i]} (epoch {record['epoch']}): views selected for it",
            )
            for i, item in enumerate(items)
        ]
        return stack_sheets(sheets)

    # ------------------------------------------------------------------ state
    def state_dict(self) -> dict[str, Any]:
        return {
            "version": _STATE_VERSION,
            "seed": self.seed,
            "last_epoch": self.last_epoch,
            "history": list(self.history),
            "pool": self.pool.state_dict() if self.pool is not None else None,
            "selector": self.selector.state_dict(),
        }

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        if state_dict.get("version", 1) > _STATE_VERSION:
            raise ValueError(
                f"The checkpoint's ErrorGuidedViewAugmentation state has version {state_dict['version']}; "
                f"this lightning_vtr reads versions <= {_STATE_VERSION}. Upgrade lightning_vtr."
            )
        if state_dict.get("seed", self.seed) != self.seed:
            rank_zero_warn(
                f"Resuming ErrorGuidedViewAugmentation with seed={self.seed}, but the checkpoint used "
                f"seed={state_dict['seed']}: later generations will differ from the original run."
            )
        self.last_epoch = int(state_dict.get("last_epoch", _NOTHING_GENERATED))
        self.history = list(state_dict.get("history", []))
        if self.pool is not None and state_dict.get("pool") is not None:
            self.pool.load_state_dict(state_dict["pool"])
        if state_dict.get("selector"):
            self.selector.load_state_dict(state_dict["selector"])


def _grid(samples: list[GeneratedSample]) -> np.ndarray:
    """Rows = samples, columns = views, composited on white: ``(rows*H, cols*W, 3)`` uint8."""
    rows = []
    width = max(s.images.shape[0] for s in samples)
    for s in samples:
        rgba = s.images.astype(np.float32) / 255.0
        rgb = rgba[..., :3] * rgba[..., 3:] + (1.0 - rgba[..., 3:])
        pad = width - rgb.shape[0]
        if pad:
            rgb = np.concatenate([rgb, np.ones((pad, *rgb.shape[1:]), np.float32)])
        rows.append(np.concatenate(list(rgb), axis=1))
    return (np.concatenate(rows, axis=0) * 255).astype(np.uint8)
