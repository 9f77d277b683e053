r"""Error-guided view augmentation: at each training epoch's end, find the views a model is weakest at,
synthesize them and train on them next epoch.

The callback keeps the hooks, the orchestration of a selection round and the saved state; the round's pure
parts, the prediction checks, the collectives and the records live in :mod:`lightning_vtr.augmentation`.
"""

from __future__ import annotations

from collections.abc import Mapping
from types import MappingProxyType
from typing import Any, Literal, cast

import lightning as L
from lightning.pytorch.utilities import rank_zero_info, rank_zero_warn
from lightning.pytorch.utilities.exceptions import MisconfigurationException

from lightning_vtr.augmentation import recording
from lightning_vtr.augmentation.inputs import selection_context, synthesis_request
from lightning_vtr.augmentation.prediction import voxel_grid_mismatch
from lightning_vtr.augmentation.recording import RECORD_VERSION
from lightning_vtr.augmentation.rule import make_pool, rule_mismatch
from lightning_vtr.augmentation.runner import RoundSettings, run_round
from lightning_vtr.protocol import (
    AugmentableDataModule,
    check_augmentable_datamodule,
    check_model_matches_data,
    check_reconstruction_model,
)
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


def _trainer_shows_progress(trainer: L.Trainer) -> bool:
    bar = trainer.progress_bar_callback  # None with Trainer(enable_progress_bar=False)
    return bar is not None and not getattr(bar, "is_disabled", False)


class ErrorGuidedViewAugmentation(L.Callback):
    r"""Trains a multi-view reconstruction model on the viewpoints it reconstructs worst.

    Before the first training epoch (``select_at_start``, from the model the fit starts with) and at the end of
    every training epoch but the last, a selection round (:func:`lightning_vtr.augmentation.runner.run_round`)

    1. draws a seeded random ``search_fraction`` of the training objects (at least ``min_objects``),
    2. predicts their voxels from their ``source_view_set`` views (eval mode, no gradients, the Trainer's
       precision) and logs their mean voxel error (``vtr/mean_error``),
    3. asks ``selector`` for new viewpoints of each (Random and Nature ignore the predictions),
    4. picks ``fraction`` of the training objects among the searched ones to get views (``generate_for``); with a
       ``pool``, every searched object's selection goes into its category's pool (emptied first when the pool
       refreshes) and each picked object's view set is drawn from it,
    5. synthesizes images at those viewpoints with ``synthesizer``,
    6. adds them to the datamodule (``add_samples``), which serves them from the next epoch on, tagged
       ``view_set="generated"``; they accumulate up to ``max_samples``.

    Every default is a constant: ``ErrorGuidedViewAugmentation()`` is the measured default rule (:meth:`default`),
    :meth:`paper` the paper's. ``print(callback)`` shows every effective setting; they are logged at fit start
    (global rank 0) and written to ``<log dir>/vtr_selection/settings.json`` beside the selection records
    (``docs/records.md``).

    Files: records go under the running Trainer's log directory (``trainer.log_dir``, or ``default_root_dir``
    without a logger); ``VTRDataModule`` writes generated samples under ``<log dir>/vtr_generated``. A resumed run
    reads the samples it restores from the folder the checkpoint names and writes new ones under its own.

    Checkpoints: the pool, the selector's state, the history, the last generated epoch and the :meth:`rule` are
    saved under :attr:`state_key`. Resuming with the same rule is exact (a resumed run generates what an
    uninterrupted one does; another ``seed`` warns). Another rule warns, naming both rules and what differs, and
    starts this callback's state fresh (the datamodule still serves the checkpoint's samples). A checkpoint of
    lightning_vtr 0.3 (no rule stored) is restored as this callback's rule.

    Under DDP every rank predicts and synthesizes its share of the objects and the results are gathered in train
    order: every rank ends with the dataset of a single-process run. All randomness derives from
    ``(seed, epoch, object)`` (:mod:`lightning_vtr.augmentation.selection_round`).

    Args:
        selector: a :class:`~lightning_vtr.selection.base.ViewSelector`, or a name in
            :data:`lightning_vtr.selection.SELECTORS` / :data:`~lightning_vtr.selection.registry.SELECTOR_PRESETS`
            built with its defaults. Default ``"error_guided"``: ``ErrorGuidedSelector()``
            (``ErrorGuidedSelector.default()``: side-aware ``visible`` score, 30-degree suppression, temperature
            10, K = 30, 3 views).
        synthesizer: a :class:`~lightning_vtr.synthesis.base.Synthesizer`. Default ``None``: ``RenderSynthesizer()``
            (the object's mesh rendered).
        fraction: share of the training objects given new views per round. Default 0.05 (the paper's 5 %).
        search_fraction: share of the training objects predicted and scored per round, at least ``fraction``.
            Default 0.35 (scoring is cheap next to synthesis; the extra objects fill the pool).
        generate_for: which searched objects get views: ``"random"`` (a seeded subset, the default) or ``"error"``
            (the largest voxel error first).
        min_objects: fewest objects searched and given views per round. Default 1.
        pool: a :class:`~lightning_vtr.selection.pool.ViewpointPool` (its ``num_views`` the selector's), a mapping
            of its arguments (``capacity``, ``prefer_others``, ``refresh``, ``fallback``; the YAML form), or
            ``None`` (each object trains on its own selection). Default :data:`DEFAULT_POOL` (emptied before each
            round, drawing sets found on other objects); ignored for a selector with ``uses_pool=False`` (Random,
            Nature, VIAT, MVTN), which refuses any other pool.
        select_at_start: run the first round in ``on_train_start``, before epoch 0 trains. Default ``True``.
        max_samples: most generated samples served (the oldest dropped; ``add_samples(..., max_total=)``).
            Default ``None``: all.
        batch_size: objects per prediction / synthesis call. Default 16.
        source_view_set: the view set the objects' input views come from. Default ``"aligned"``.
        seed: seeds every random choice of the callback. Default 0.
        log_images: log a grid of new views and two objects' error sheets to every logger
            (:func:`lightning_vtr.utils.image_logging.log_image`). Default ``True``. ``vtr/samples_generated``,
            ``vtr/samples_total`` and ``vtr/mean_error`` are logged with ``pl_module.log`` regardless.
        progress_bar: show a progress bar while synthesizing (rank 0, when the Trainer shows one). Default ``True``.

    Raises:
        TypeError: an argument of the wrong type (names the argument and the value).
        ValueError: an invalid value (names the argument and the value), e.g. ``search_fraction < fraction``, an
            unknown selector name or a pool with a selector that uses none; and whenever ``predict_voxels``
            returns values outside ``[0, 1]`` or non-finite ones (logits are the usual cause).
        MisconfigurationException: in ``setup`` when the Trainer, datamodule or model cannot be served or the
            model's declared sizes disagree with the datamodule's; in ``on_fit_start`` when ``predict_voxels``
            gives another grid than the dataset's voxels.

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
        if not self.selector.uses_pool and isinstance(pool, Mapping) and dict(pool) == dict(DEFAULT_POOL):
            pool = None  # the default (or a config's copy of it) means "no pool" for a selector that uses none
        self.pool = make_pool(pool, self.selector)
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
            check_model_matches_data(pl_module, dm)
        except (TypeError, ValueError) as err:
            raise MisconfigurationException(f"ErrorGuidedViewAugmentation: {err}") from err
        if self.selector.num_views != pl_module.num_views:
            rank_zero_warn(
                f"The selector returns {self.selector.num_views} views per sample but the model trains with "
                f"{pl_module.num_views}; generated samples will have {self.selector.num_views} views."
            )

    def on_fit_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        # 1. the settings, logged and recorded (the log directory is a collective under DDP: every rank asks)
        log_dir = recording.log_dir(trainer)
        rank_zero_info(f"lightning_vtr: {self!r}")
        if trainer.is_global_zero:
            recording.write_settings(log_dir, repr(self), self.settings())
        # 2. one prediction before any training, now that the model is on its device: the voxel grid must match
        mismatch = voxel_grid_mismatch(pl_module, _datamodule(trainer), self.source_view_set)
        if mismatch is not None:
            raise MisconfigurationException(mismatch)

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

    def _run(self, trainer: L.Trainer, pl_module: L.LightningModule, epoch: int) -> None:
        """The round after ``epoch``: run it, serve its samples, remember it, log it."""
        dm = _datamodule(trainer)
        if not dm.split_records("train"):
            rank_zero_warn("ErrorGuidedViewAugmentation: the datamodule has no training objects; nothing generated.")
            return
        # 1. search, select, plan and synthesize (every rank its share; all end with the same result)
        show_progress = self.progress_bar and trainer.global_rank == 0 and _trainer_shows_progress(trainer)
        result = run_round(
            trainer,
            pl_module,
            dm,
            epoch,
            selector=self.selector,
            synthesizer=self.synthesizer,
            pool=self.pool,
            settings=self._round_settings(),
            show_progress=show_progress,
        )
        # 2. the datamodule serves the new samples from the next train loader on
        dm.add_samples(result.samples, max_total=self.max_samples)
        trainer.strategy.barrier("ErrorGuidedViewAugmentation.add_samples")
        # 3. the state a checkpoint saves
        self.last_epoch = epoch
        self.history.append({"epoch": epoch, "mean_error": result.record["mean_error"], "samples": len(result.samples)})
        # 4. the logged values, images and the round's record
        recording.log_round(
            trainer,
            pl_module,
            dm,
            result.record,
            result.samples,
            log_images=self.log_images,
            source_view_set=self.source_view_set,
            batch_size=self.batch_size,
        )
        # 5. a synthesizer serving the nearest prerendered view says how far it snapped (this process's views)
        pop_snap_angles = getattr(self.synthesizer, "pop_snap_angles", None)
        angles = pop_snap_angles() if callable(pop_snap_angles) else ()
        if len(angles):
            mean = float(sum(angles) / len(angles))
            pl_module.log("vtr/snap_angle_mean", mean, on_step=False, on_epoch=True, batch_size=1)

    def _round_settings(self) -> RoundSettings:
        return RoundSettings(
            fraction=self.fraction,
            search_fraction=self.search_fraction,
            generate_for=self.generate_for,
            min_objects=self.min_objects,
            seed=self.seed,
            batch_size=self.batch_size,
            source_view_set=self.source_view_set,
        )

    def _request(self, dm: Any, record: Any, targets: Any = None) -> SynthesisRequest:
        """The synthesis request for ``record`` at ``targets`` (``(n, 2)`` degrees; ``None``: none)."""
        return synthesis_request(dm, record, self.synthesizer, self.source_view_set, targets)

    def _context(self, trainer: L.Trainer, pl_module: L.LightningModule, requests: list) -> SelectionContext:
        """The context a selector that queries the model (``needs_context``) gets for ``requests``."""
        return selection_context(pl_module, _datamodule(trainer), self.synthesizer, requests)

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
            mismatch = rule_mismatch(state_dict["rule"], self.rule())
            if mismatch is not None:
                rank_zero_warn(mismatch)
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
