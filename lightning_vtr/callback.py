r"""Error-guided view augmentation: at each training epoch's end, find the views a model is weakest at,
synthesize them and train on them next epoch.

The callback keeps the hooks, the orchestration of a selection round and the saved state; the round's pure
parts, the prediction checks, the collectives and the records live in :mod:`lightning_vtr.augmentation`.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from types import MappingProxyType
from typing import Any, Literal, cast

import lightning as L
import numpy as np
import torch
from lightning.pytorch.utilities import rank_zero_info, rank_zero_warn
from lightning.pytorch.utilities.exceptions import MisconfigurationException
from lightning.pytorch.utilities.seed import isolate_rng
from torch import Tensor
from tqdm.auto import tqdm

from lightning_vtr.augmentation import recording
from lightning_vtr.augmentation import selection_round as rounds
from lightning_vtr.augmentation.distributed import broadcast_from_zero, sharded_map
from lightning_vtr.augmentation.inputs import selection_context, synthesis_request
from lightning_vtr.augmentation.prediction import predict_probabilities
from lightning_vtr.augmentation.recording import RECORD_VERSION
from lightning_vtr.augmentation.selection_round import Selection
from lightning_vtr.data.dataset import GeneratedSample
from lightning_vtr.protocol import AugmentableDataModule, check_augmentable_datamodule, check_reconstruction_model
from lightning_vtr.selection.base import SelectionContext, ViewSelector
from lightning_vtr.selection.pool import ViewpointPool
from lightning_vtr.synthesis.base import SynthesisRequest, Synthesizer
from lightning_vtr.utils.validation import check_choice, check_float, check_int, check_type

__all__ = ["DEFAULT_POOL", "PAPER_POOL", "RECORD_VERSION", "ErrorGuidedViewAugmentation"]

_STATE_VERSION = 2  # 1: lightning_vtr 0.3 (no rule stored); 2: the rule is stored with the state
DEFAULT_POOL: Mapping[str, Any] = MappingProxyType({"capacity": None, "prefer_others": True, "refresh": True})
"""``pool`` of the default rule: a pool emptied before every round, drawing sets found on other objects."""
PAPER_POOL: Mapping[str, Any] = MappingProxyType({"capacity": None, "prefer_others": True, "refresh": False})
"""``pool`` of the paper's rule (:meth:`ErrorGuidedViewAugmentation.paper`): every round's sets kept."""
_NOTHING_GENERATED = -2


def _reload_train_dataloader(trainer: L.Trainer) -> None:
    """Have the fit loop rebuild the train loader when the current epoch starts.

    The one place the callback touches a private attribute of Lightning: Lightning has no public "reload now".
    ``FitLoop.setup_data`` rebuilds the train loader when ``current_epoch - _last_train_dl_reload_epoch >=
    reload_dataloaders_every_n_epochs``; marking the last reload as long ago makes the loop rebuild it before the
    epoch's first batch. ``tests/test_callback_contract.py`` checks that the attribute exists and has these
    semantics, so a Lightning release that changes it fails there.
    """
    loop = trainer.fit_loop
    if hasattr(loop, "_last_train_dl_reload_epoch"):
        loop._last_train_dl_reload_epoch = float("-inf")
    else:  # pragma: no cover - a Lightning without the attribute
        rank_zero_warn(
            "ErrorGuidedViewAugmentation could not ask this Lightning version to rebuild the train loader; the "
            "views generated before this epoch are trained on from the next epoch."
        )


def _datamodule(trainer: L.Trainer) -> AugmentableDataModule:
    """``trainer.datamodule`` (set by Lightning at run time, not declared in its types); ``setup`` checked it."""
    return cast(AugmentableDataModule, cast(Any, trainer).datamodule)


def _log_dir(trainer: L.Trainer) -> str:
    """The run's own log directory (``default_root_dir`` without a logger); every rank must call it under DDP."""
    return str(trainer.log_dir or trainer.default_root_dir)


def _trainer_shows_progress(trainer: L.Trainer) -> bool:
    bar = trainer.progress_bar_callback  # None with Trainer(enable_progress_bar=False)
    return bar is not None and not getattr(bar, "is_disabled", False)


def _make_pool(pool: ViewpointPool | Mapping[str, Any] | None, selector: ViewSelector) -> ViewpointPool | None:
    if pool is None:
        return None
    if not selector.uses_pool:
        if isinstance(pool, Mapping) and dict(pool) == dict(DEFAULT_POOL):  # the default (or a config's copy of it)
            return None
        raise ValueError(
            f"`pool` must be None with {type(selector).__name__}, which draws each object's views itself "
            f"(uses_pool=False), got {pool!r}: pass pool=None"
        )
    if isinstance(pool, Mapping):
        unknown = sorted(set(pool) - {"capacity", "prefer_others", "refresh", "fallback", "num_views"})
        if unknown:
            raise TypeError(
                f"`pool` as a mapping takes ViewpointPool's arguments (capacity, prefer_others, refresh, fallback), "
                f"got unknown keys {unknown}"
            )
        pool = ViewpointPool(**{"num_views": selector.num_views, **pool})
    check_type("pool", pool, ViewpointPool, "ViewpointPool, a mapping of its arguments or None")
    if pool.num_views != selector.num_views:
        raise ValueError(
            f"`pool` holds view sets of {pool.num_views} views but the selector {type(selector).__name__} returns "
            f"{selector.num_views}: pass ViewpointPool(num_views={selector.num_views}, ...)"
        )
    return pool


def _describe_rule(rule: Mapping[str, Any]) -> str:
    selector = ", ".join(f"{k}={v!r}" for k, v in dict(rule.get("selector_settings") or {}).items())
    rest = ", ".join(f"{k}={v!r}" for k, v in rule.items() if k not in ("selector", "selector_settings"))
    return f"{rule.get('selector')}({selector}) with {rest}"


def _rule_differences(old: Mapping[str, Any], new: Mapping[str, Any], prefix: str = "") -> list[str]:
    out = []
    for key in [*old, *(k for k in new if k not in old)]:
        a, b = old.get(key), new.get(key)
        if isinstance(a, Mapping) and isinstance(b, Mapping):
            out += _rule_differences(a, b, f"{prefix}{key}.")
        elif json.dumps(a, sort_keys=True) != json.dumps(b, sort_keys=True):
            out.append(f"{prefix}{key} ({a!r} in the checkpoint, {b!r} now)")
    return out


class ErrorGuidedViewAugmentation(L.Callback):
    r"""Trains a multi-view reconstruction model on the viewpoints it reconstructs worst.

    Before the first training epoch (from the model the fit starts with; ``select_at_start``) and at the end of
    every training epoch but the last, a selection round

    1. draws a seeded random ``search_fraction`` of the training objects (at least ``min_objects``),
    2. predicts their voxels from their ``source_view_set`` views (eval mode, no gradients, the Trainer's
       precision) and logs their mean voxel error (``vtr/mean_error``),
    3. asks ``selector`` for new viewpoints of each (every selector is given the predictions; Random and Nature
       ignore them),
    4. picks ``fraction`` of the training objects among the searched ones to get new views (``generate_for``);
       with a ``pool``, every searched object's selection goes into the per-category pool (emptied first when the
       pool refreshes) and each picked object's view set is drawn from its category's pool,
    5. synthesizes images at those viewpoints with ``synthesizer``,
    6. adds the new samples to the datamodule (``add_samples``), which serves them from the next epoch on (tagged
       ``view_set="generated"``; they accumulate, ``max_samples`` caps them).

    Every default below is a constant: ``ErrorGuidedViewAugmentation()`` is the measured default rule,
    :meth:`default` names it and :meth:`paper` is the paper's. ``print(callback)`` shows every effective setting;
    the callback logs them at fit start (global rank 0) and writes them to ``<log dir>/vtr_selection/settings.json``
    beside the selection records (``docs/records.md``).

    Files: records go under the running Trainer's log directory (``trainer.log_dir``, or ``default_root_dir``
    without a logger); generated samples are written by the datamodule (``VTRDataModule``: under
    ``<log dir>/vtr_generated`` of the running Trainer). A resumed run reads the samples it restores from the folder
    the checkpoint names and writes new ones under its own log directory.

    Checkpoints: the state (pool, selector state, history, last generated epoch, and the rule: the selector's class
    and :meth:`~lightning_vtr.selection.base.ViewSelector.settings` with the callback settings that change what is
    stored, see :meth:`rule`) is saved under :attr:`state_key`. Resuming with the same rule restores it exactly (a
    resumed run generates what an uninterrupted one does; another ``seed`` restores it and warns). Resuming with
    another rule warns, naming both rules and what differs, and starts this callback's state fresh (the datamodule
    still serves the samples the checkpoint lists). A checkpoint of lightning_vtr 0.3 (which stored no rule) is
    restored as this callback's rule.

    In DDP every rank predicts and synthesizes its share of the objects; results are gathered in train order, so
    every rank ends with an identical dataset equal to a single-process run's. All randomness derives from
    ``(seed, epoch, object)`` (:mod:`lightning_vtr.augmentation.selection_round`).

    Args:
        selector: a :class:`~lightning_vtr.selection.base.ViewSelector`, or a name in
            :data:`lightning_vtr.selection.SELECTORS` / :data:`~lightning_vtr.selection.registry.SELECTOR_PRESETS`
            built with its defaults. Default ``"error_guided"``: ``ErrorGuidedSelector()``, the measured default
            selector (``ErrorGuidedSelector.default()``: side-aware ``visible`` score, 30-degree suppression,
            temperature 10, K = 30, 3 views).
        synthesizer: a :class:`~lightning_vtr.synthesis.base.Synthesizer`. Default ``None``: ``RenderSynthesizer()``
            (the object's mesh rendered).
        fraction: share of the training objects given new views per round. Default 0.05 (the paper's 5 %).
        search_fraction: share of the training objects searched (predicted and scored) per round; at least
            ``fraction``. Default 0.35. Scoring is cheap next to synthesis, so searching more objects than get views
            fills the pool with the current model's weak views.
        generate_for: which searched objects get views when more are searched than get views: ``"random"`` (a seeded
            random subset, the default) or ``"error"`` (the largest voxel error first).
        min_objects: fewest objects searched and given views per round. Default 1.
        pool: the per-category viewpoint pool: a :class:`~lightning_vtr.selection.pool.ViewpointPool` (used as is;
            its ``num_views`` must be the selector's), a mapping of its arguments (``capacity``, ``prefer_others``,
            ``refresh``, ``fallback``; YAML configs give this form; ``num_views`` is the selector's), or ``None`` (no
            pool: each object trains on its own selection). Default :data:`DEFAULT_POOL`: all sets kept within a
            round, emptied before each round (``refresh=True``), drawing sets found on other objects.
            A selector with ``uses_pool=False`` (Random, Nature, VIAT, MVTN) draws no pool: the default is ignored
            for it (its ``repr`` shows ``pool=None``) and any other pool is refused.
        select_at_start: run the first round in ``on_train_start``, before epoch 0 trains. Default ``True``.
        max_samples: most generated samples the datamodule serves (the oldest dropped), passed as every
            ``add_samples(..., max_total=max_samples)``. Default ``None``: all.
        batch_size: objects per prediction / synthesis call. Default 16.
        source_view_set: the view set the objects' input views come from. Default ``"aligned"``.
        seed: seeds every random choice the callback makes. Default 0.
        log_images: log a grid of new views and the error sheets of two objects to every logger
            (:func:`lightning_vtr.utils.image_logging.log_image`). Default ``True``. The values
            ``vtr/samples_generated``, ``vtr/samples_total`` and ``vtr/mean_error`` are logged with
            ``pl_module.log`` whatever this says.
        progress_bar: show a progress bar while synthesizing (rank 0, when the Trainer shows one). Default ``True``.

    Raises:
        TypeError: an argument of the wrong type (names the argument and the value).
        ValueError: an invalid value (names the argument and the value), e.g. ``search_fraction < fraction``, an
            unknown selector name, or a pool with a selector that uses none.
        MisconfigurationException: in ``setup`` when the Trainer, datamodule or model cannot be served; in
            ``on_fit_start`` when ``predict_voxels`` gives another grid than the dataset's voxels.
        ValueError: whenever ``predict_voxels`` returns values outside ``[0, 1]`` or non-finite ones (logits are the
            usual cause).

    Example::

        trainer = L.Trainer(max_epochs=20, reload_dataloaders_every_n_epochs=1,
                            callbacks=[ErrorGuidedViewAugmentation()])
        trainer.fit(Pix2VoxPlusPlus(preset="tiny"), datamodule=VTRDataModule())

        ErrorGuidedViewAugmentation.paper()  # the paper's rule
        ErrorGuidedViewAugmentation(RandomSelector())  # area-uniform Random
    """

    def __init__(
        self,
        selector: ViewSelector | str = "error_guided",
        synthesizer: Synthesizer | None = None,
        *,
        fraction: float = 0.05,
        search_fraction: float = 0.35,
        generate_for: Literal["random", "error"] = "random",
        min_objects: int = 1,
        pool: ViewpointPool | Mapping[str, Any] | None = DEFAULT_POOL,
        select_at_start: bool = True,
        max_samples: int | None = None,
        batch_size: int = 16,
        source_view_set: str = "aligned",
        seed: int = 0,
        log_images: bool = True,
        progress_bar: bool = True,
    ) -> None:
        self.fraction = check_float("fraction", fraction, minimum=0.0, maximum=1.0, min_open=True)
        self.search_fraction = check_float("search_fraction", search_fraction, minimum=0.0, maximum=1.0)
        if self.search_fraction < self.fraction:
            raise ValueError(
                f"`search_fraction` must be >= `fraction` ({self.fraction}): the objects given views are among the "
                f"searched ones, got {self.search_fraction}; pass search_fraction={self.fraction} to search only them"
            )
        self.generate_for = check_choice("generate_for", generate_for, ("random", "error"))
        self.min_objects = check_int("min_objects", min_objects, minimum=1)
        self.select_at_start = check_type("select_at_start", select_at_start, bool)
        self.max_samples = None if max_samples is None else check_int("max_samples", max_samples, minimum=1)
        self.batch_size = check_int("batch_size", batch_size, minimum=1)
        self.source_view_set = check_type("source_view_set", source_view_set, str)
        self.seed = check_int("seed", seed, minimum=0)  # a SeedSequence entropy word: non-negative
        self.log_images = check_type("log_images", log_images, bool)
        self.progress_bar = check_type("progress_bar", progress_bar, bool)
        if isinstance(selector, str):
            # a registry name, as YAML configs and the CLI give it; imported here so that importing the callback
            # does not import every selector
            from lightning_vtr.selection.registry import SELECTOR_PRESETS, SELECTORS, make_selector

            selector = make_selector(check_choice("selector", selector, [*SELECTORS, *SELECTOR_PRESETS]))
        self.selector: ViewSelector = check_type(
            "selector", selector, ViewSelector, "lightning_vtr ViewSelector or a registry name"
        )
        if synthesizer is None:
            from lightning_vtr.synthesis.render import RenderSynthesizer

            synthesizer = RenderSynthesizer()
        self.synthesizer: Synthesizer = check_type("synthesizer", synthesizer, Synthesizer, "lightning_vtr Synthesizer")
        self.pool = _make_pool(pool, self.selector)
        # Last epoch whose samples were generated: -1 is the round before epoch 0, -2 none yet.
        self.last_epoch = _NOTHING_GENERATED
        self.history: list[dict[str, Any]] = []

    @classmethod
    def default(cls, **kwargs: Any) -> ErrorGuidedViewAugmentation:
        """The measured default rule, ``cls(**kwargs)``: ``ErrorGuidedSelector.default()``, 35 % of the objects
        searched into a pool emptied before every round (:data:`DEFAULT_POOL`), 5 % given views.

        Args:
            kwargs: any other argument of the callback (``fraction``, ``synthesizer``, ``seed``, ...).

        Raises:
            TypeError: ``kwargs`` give a ``selector``.
        """
        if "selector" in kwargs:
            raise TypeError("ErrorGuidedViewAugmentation.default() takes no `selector`: it is the default rule's")
        from lightning_vtr.selection.error_guided import ErrorGuidedSelector

        return cls(selector=ErrorGuidedSelector.default(), **kwargs)

    @classmethod
    def paper(cls, **kwargs: Any) -> ErrorGuidedViewAugmentation:
        """The paper's rule: ``ErrorGuidedSelector.paper()`` (binary error summed over the first-hit map, the hard
        top 3 of the 30-degree bins, no suppression), as many objects searched as given views (``search_fraction =
        fraction``, 5 % by default) and a pool that keeps every round's sets and prefers other objects' sets
        (:data:`PAPER_POOL`), the first round made from the model the fit starts with.

        Args:
            kwargs: any other argument of the callback; ``search_fraction`` and ``pool`` override the preset's.

        Raises:
            TypeError: ``kwargs`` give a ``selector``.

        Example::

            callback = ErrorGuidedViewAugmentation.paper(fraction=0.1, seed=0)  # 10 % searched and given views
        """
        if "selector" in kwargs:
            raise TypeError("ErrorGuidedViewAugmentation.paper() takes no `selector`: it is the paper's")
        from lightning_vtr.selection.error_guided import ErrorGuidedSelector

        kwargs.setdefault("search_fraction", kwargs.get("fraction", 0.05))
        kwargs.setdefault("pool", PAPER_POOL)
        return cls(selector=ErrorGuidedSelector.paper(), **kwargs)

    # ------------------------------------------------------------------ settings
    def settings(self) -> dict[str, Any]:
        """Every effective setting, JSON-serialisable: the selector's class and settings, the synthesizer's class,
        the pool's settings (``None`` without a pool) and the callback's own arguments."""
        return {
            "selector": type(self.selector).__name__,
            "selector_settings": self.selector.settings(),
            "synthesizer": type(self.synthesizer).__name__,
            "fraction": self.fraction,
            "search_fraction": self.search_fraction,
            "generate_for": self.generate_for,
            "min_objects": self.min_objects,
            "pool": None if self.pool is None else self.pool.settings(),
            "select_at_start": self.select_at_start,
            "max_samples": self.max_samples,
            "batch_size": self.batch_size,
            "source_view_set": self.source_view_set,
            "seed": self.seed,
            "log_images": self.log_images,
            "progress_bar": self.progress_bar,
        }

    def rule(self) -> dict[str, Any]:
        """What the saved state belongs to: the selector's class and settings and the callback settings that change
        what is stored (``fraction``, ``search_fraction``, ``generate_for``, ``min_objects``, ``pool``,
        ``select_at_start``, ``source_view_set``). Not the seed, the synthesizer, ``max_samples`` or the logging."""
        keep = ("selector", "selector_settings", "fraction", "search_fraction", "generate_for", "min_objects", "pool")
        settings = self.settings()
        return {k: settings[k] for k in (*keep, "select_at_start", "source_view_set")}

    def __repr__(self) -> str:
        items = {**self.settings(), "selector": self.selector, "synthesizer": type(self.synthesizer).__name__}
        items.pop("selector_settings")
        items["pool"] = self.pool
        text = ", ".join(
            f"{k}={v}" if k in ("selector", "synthesizer", "pool") else f"{k}={v!r}" for k, v in items.items()
        )
        return f"{type(self).__name__}({text})"

    @property
    def state_key(self) -> str:
        """The key of this callback's state in a checkpoint: the class and the selector's class (the key of 0.3).

        The rule is stored inside the state (:meth:`rule`), and checked when it is loaded.
        """
        return self._generate_state_key(selector=type(self.selector).__name__)

    # ------------------------------------------------------------------ setup checks
    def setup(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        if stage != "fit":
            return
        reload_every = cast(Any, trainer).reload_dataloaders_every_n_epochs  # not declared in Lightning's types
        if reload_every != 1:
            raise MisconfigurationException(
                "ErrorGuidedViewAugmentation adds samples at epoch ends, which the next epoch only sees if the train "
                "dataloader is rebuilt: pass `Trainer(reload_dataloaders_every_n_epochs=1)` "
                f"(got {reload_every})."
            )
        dm = cast(Any, trainer).datamodule
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
        log_dir = _log_dir(trainer)  # a collective under DDP: every rank asks
        rank_zero_info(f"lightning_vtr: {self!r}")
        if trainer.is_global_zero:
            recording.write_settings(log_dir, repr(self), self.settings())
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
        predicted = self._predict(pl_module, [item["images"]], isolated=True)
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
        # The round that serves the epoch about to start: before epoch 0 from the model the fit starts with; after a
        # resume, one the checkpoint predates (ModelCheckpoint saves at validation end; the last epoch of a finished
        # run generates nothing).
        due = trainer.current_epoch - 1
        if due == -1 and not self.select_at_start:
            return
        if self.last_epoch < due:
            if due >= 0:
                rank_zero_info(f"ErrorGuidedViewAugmentation: catching up the generation of epoch {due} after resume")
            self._run(trainer, pl_module, due)
            # Lightning built this epoch's train loader before on_train_start: have it rebuilt with the new samples.
            _reload_train_dataloader(trainer)

    def on_train_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if trainer.sanity_checking or trainer.should_stop:
            return
        max_epochs = trainer.max_epochs
        if max_epochs is not None and max_epochs >= 0 and trainer.current_epoch >= max_epochs - 1:
            return  # nothing would train on them
        self._run(trainer, pl_module, trainer.current_epoch)

    # ------------------------------------------------------------------ one round
    def _run(self, trainer: L.Trainer, pl_module: L.LightningModule, epoch: int) -> None:
        dm = _datamodule(trainer)
        num_train = len(dm.split_records("train"))
        if num_train == 0:
            rank_zero_warn("ErrorGuidedViewAugmentation: the datamodule has no training objects; nothing generated.")
            return
        chosen = rounds.search_indices(
            num_train, epoch, search_fraction=self.search_fraction, min_objects=self.min_objects, seed=self.seed
        )
        searched = self._select(trainer, pl_module, epoch, chosen)
        plan = rounds.plan_round(
            searched,
            num_train,
            epoch,
            fraction=self.fraction,
            min_objects=self.min_objects,
            generate_for=self.generate_for,
            seed=self.seed,
            pool=self.pool,
        )
        images = self._synthesize(trainer, epoch, plan)
        samples = [
            GeneratedSample(s.category, s.object_id, img, np.asarray(vs, dtype=np.float64), epoch)
            for s, vs, img in zip(plan.targets, plan.view_sets, images)
        ]
        dm.add_samples(samples, max_total=self.max_samples)
        trainer.strategy.barrier("ErrorGuidedViewAugmentation.add_samples")
        self.last_epoch = epoch
        record = recording.selection_record(epoch, plan.targets, plan.view_sets, searched)
        self.history.append({"epoch": epoch, "mean_error": record["mean_error"], "samples": len(samples)})
        self._log(trainer, pl_module, record, samples)

    def _predict(self, pl_module: L.LightningModule, images: list[Tensor], isolated: bool = False) -> Tensor:
        """``predict_probabilities`` in eval mode (restoring the mode after); ``isolated`` keeps the RNG untouched."""
        was_training = pl_module.training
        pl_module.eval()
        try:
            if not isolated:
                return predict_probabilities(pl_module, images, self.batch_size)
            with isolate_rng():  # a model that draws random numbers here must not shift the training's stream
                return predict_probabilities(pl_module, images, self.batch_size)
        finally:
            pl_module.train(was_training)

    def _select(
        self, trainer: L.Trainer, pl_module: L.LightningModule, epoch: int, chosen: list[int]
    ) -> list[Selection]:
        """Predict the chosen objects (sharded by rank), select their views, return them merged in train order."""
        dm = _datamodule(trainer)
        records = dm.split_records("train")
        was_training = pl_module.training
        pl_module.eval()  # selectors that query the model (VIAT, MVTN, the input score) see it in eval mode
        try:
            if self.selector.batched:
                return self._select_batched(trainer, pl_module, epoch, chosen)

            def select(mine: list[int]) -> list[Selection]:
                predicted, target = self._predict_objects(dm, pl_module, mine, epoch)
                out = []
                for row, index in enumerate(mine):
                    rec = records[index]
                    views = self.selector.select(
                        predicted[row : row + 1],
                        target[row : row + 1],
                        [rec.category],
                        generator=rounds.stream(self.seed, epoch + 1, index, rounds.SELECT_STREAM),
                        context=self._context(dm, pl_module, [rec]),
                    )[0]
                    out.append(self._selection(rec, index, views, predicted[row], target[row]))
                return out

            return sharded_map(trainer, chosen, select)
        finally:
            pl_module.train(was_training)

    def _predict_objects(self, dm: Any, pl_module: L.LightningModule, indices: list[int], epoch: int) -> tuple:
        """``(predicted, target)`` ``(N, R, R, R)`` of the training objects ``indices`` (views drawn for ``epoch``)."""
        records = dm.split_records("train")
        items = [dm.eval_item(records[i], self.source_view_set, seed=epoch + 1) for i in indices]
        if not items:
            return torch.empty(0), torch.empty(0)
        predicted = predict_probabilities(pl_module, [it["images"] for it in items], self.batch_size)
        return predicted, torch.stack([it["voxels"] for it in items])

    def _select_batched(
        self, trainer: L.Trainer, pl_module: L.LightningModule, epoch: int, chosen: list[int]
    ) -> list[Selection]:
        # Learning selectors see every searched object in one call on rank 0; the selections and the learned state
        # are broadcast so every rank (and rank 0's checkpoint) holds the same selector.
        dm = _datamodule(trainer)
        records = dm.split_records("train")
        parts = sharded_map(trainer, chosen, lambda mine: list(zip(*self._predict_objects(dm, pl_module, mine, epoch))))
        payload = None
        if trainer.is_global_zero:
            recs = [records[i] for i in chosen]
            predicted = torch.stack([p for p, _ in parts]) if parts else torch.empty(0)
            target = torch.stack([t for _, t in parts]) if parts else torch.empty(0)
            views = self.selector.select(
                predicted,
                target,
                [r.category for r in recs],
                generator=rounds.stream(self.seed, epoch + 1, 0, rounds.BATCHED_SELECT_STREAM),
                context=self._context(dm, pl_module, recs),
            )
            selected = [self._selection(*a) for a in zip(recs, chosen, views, predicted, target)]
            payload = (selected, self.selector.state_dict())
        payload = broadcast_from_zero(trainer, payload)
        if not trainer.is_global_zero:
            self.selector.load_state_dict(payload[1])
        return payload[0]

    def _selection(self, record: Any, index: int, views: Tensor, predicted: Tensor, target: Tensor) -> Selection:
        # the object's error at the selector's threshold, the one its error volume binarises at
        error = ((predicted >= self.selector.threshold).float() != target).float().mean().item()
        return Selection(index, record.category, record.object_id, views.detach().cpu().numpy(), error)

    def _context(self, dm: Any, pl_module: L.LightningModule, recs: list) -> SelectionContext | None:
        if not self.selector.needs_context:
            return None
        requests = [self._request(dm, r) for r in recs]
        return selection_context(pl_module, dm, self.synthesizer, requests)

    def _request(self, dm: Any, record: Any, targets: Tensor | np.ndarray | None = None) -> SynthesisRequest:
        return synthesis_request(dm, record, self.synthesizer, self.source_view_set, targets)

    def _synthesize(self, trainer: L.Trainer, epoch: int, plan: rounds.RoundPlan) -> list[np.ndarray]:
        dm = _datamodule(trainer)
        records = dm.split_records("train")
        bar = tqdm(
            desc=f"VTR: synthesizing views (epoch {epoch})",
            disable=not (self.progress_bar and trainer.global_rank == 0 and _trainer_shows_progress(trainer)),
            leave=False,
            dynamic_ncols=True,
        )

        def synthesize(mine: list[int]) -> list[np.ndarray]:
            bar.reset(total=len(mine))
            out = []
            for start in range(0, len(mine), self.batch_size):
                chunk = mine[start : start + self.batch_size]
                requests = [self._request(dm, records[plan.targets[j].index], plan.view_sets[j]) for j in chunk]
                out += [np.asarray(images) for images in self.synthesizer.synthesize(requests)]
                bar.update(len(chunk))
            return out

        try:
            return sharded_map(trainer, list(range(len(plan.targets))), synthesize)
        finally:
            bar.close()

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
        # Every rank logs equal values; `sync_dist` keeps them and keeps Lightning from warning under DDP.
        for name, value in metrics.items():
            pl_module.log(name, value, on_step=False, on_epoch=True, sync_dist=True, batch_size=1)
        log_dir = _log_dir(trainer)  # a collective under DDP: every rank asks, before the rank-0 branch
        if not trainer.is_global_zero:
            return
        rank_zero_info(
            f"VTR {'before training' if record['epoch'] < 0 else 'epoch ' + str(record['epoch'])}: "
            f"{len(samples)} samples generated ({total} in total), "
            f"mean voxel error of searched objects {record['mean_error']:.4f}"
        )
        if self.log_images and samples and trainer.loggers:
            from lightning_vtr.utils.image_logging import log_image

            log_image(trainer, "vtr/new_views", recording.new_views_grid(samples[:8]), step=trainer.global_step)
            sheets = recording.error_sheets(
                pl_module,
                _datamodule(trainer),
                record,
                source_view_set=self.source_view_set,
                batch_size=self.batch_size,
            )
            log_image(trainer, "vtr/error_sheets", sheets, step=trainer.global_step)
        recording.write_record(log_dir, record)

    # ------------------------------------------------------------------ state
    def state_dict(self) -> dict[str, Any]:
        return {
            "version": _STATE_VERSION,
            "rule": self.rule(),
            "seed": self.seed,
            "last_epoch": self.last_epoch,
            "history": list(self.history),
            "pool": self.pool.state_dict() if self.pool is not None else None,
            "selector": self.selector.state_dict(),
        }

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        version = state_dict.get("version", 1)
        if version > _STATE_VERSION:
            raise ValueError(
                f"The checkpoint's ErrorGuidedViewAugmentation state has version {version}; this lightning_vtr "
                f"reads versions <= {_STATE_VERSION}. Upgrade lightning_vtr."
            )
        if version >= 2:
            saved, rule = state_dict["rule"], self.rule()
            differences = _rule_differences(saved, rule)
            if differences:
                rank_zero_warn(
                    f"ErrorGuidedViewAugmentation: the checkpoint's state belongs to the rule {_describe_rule(saved)}; "
                    f"this callback runs {_describe_rule(rule)}. They differ in {'; '.join(differences)}. Starting "
                    "this callback's state fresh (empty pool, no history); the datamodule keeps serving the samples "
                    "the checkpoint lists. Resume with the checkpoint's rule to continue its state."
                )
                return
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
