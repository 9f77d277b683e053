"""One selection round on a running Trainer: predict and score the searched objects, plan the round, synthesize.

:func:`run_round` is what the callback calls at an epoch's end; :func:`select_objects` and
:func:`synthesize_round` are its two sharded steps, :func:`~lightning_vtr.augmentation.selection_round.plan_round`
the pure step between them. Every process calls them with the same arguments; each works on its share of the
objects (:func:`~lightning_vtr.augmentation.distributed.sharded_map`) and all end with the same results, a
single-process run's.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import lightning as L
import numpy as np
import torch
from torch import Tensor
from tqdm.auto import tqdm

from lightning_vtr.augmentation import recording
from lightning_vtr.augmentation.distributed import broadcast_from_zero, sharded_map
from lightning_vtr.augmentation.inputs import selection_context, synthesis_request
from lightning_vtr.augmentation.prediction import predict_probabilities
from lightning_vtr.augmentation.selection_round import (
    BATCHED_SELECT_STREAM,
    SELECT_STREAM,
    RoundPlan,
    Selection,
    plan_round,
    search_indices,
    stream,
)
from lightning_vtr.data.dataset import GeneratedSample
from lightning_vtr.protocol import AugmentableDataModule
from lightning_vtr.selection.base import SelectionContext, ViewSelector, check_selection
from lightning_vtr.selection.pool import ViewpointPool
from lightning_vtr.synthesis.base import Synthesizer

__all__ = [
    "RoundResult",
    "RoundSettings",
    "object_selection",
    "predict_objects",
    "run_round",
    "select_objects",
    "synthesize_round",
]


@dataclass(frozen=True)
class RoundSettings:
    """The callback settings a round reads (the callback's arguments of the same names).

    Attributes:
        fraction: share of the training objects given new views.
        search_fraction: share of the training objects predicted and scored.
        generate_for: which searched objects get views, ``"random"`` or ``"error"``.
        min_objects: fewest objects searched and given views.
        seed: seeds every random choice of the round.
        batch_size: objects per prediction / synthesis call.
        source_view_set: the view set the objects' input views come from.

    Example:
        >>> RoundSettings(fraction=0.05, search_fraction=0.35, generate_for="random", min_objects=1, seed=0,
        ...               batch_size=16, source_view_set="aligned").search_fraction
        0.35
    """

    fraction: float
    search_fraction: float
    generate_for: Literal["random", "error"]
    min_objects: int
    seed: int
    batch_size: int
    source_view_set: str


@dataclass
class RoundResult:
    """What a round produced.

    Attributes:
        searched: every searched object's selection, in train order.
        plan: the objects given views and their view sets.
        samples: one generated sample per target, for ``add_samples``.
        record: the round's :func:`~lightning_vtr.augmentation.recording.selection_record`.

    Example::

        result = run_round(trainer, model, dm, 0, selector=selector, synthesizer=synthesizer, pool=None,
                           settings=settings, show_progress=False)
        result.record["mean_error"]
    """

    searched: list[Selection]
    plan: RoundPlan
    samples: list[GeneratedSample]
    record: dict[str, Any]


def predict_objects(
    pl_module: L.LightningModule, dm: AugmentableDataModule, indices: list[int], epoch: int, settings: RoundSettings
) -> tuple[Tensor, Tensor]:
    """The predictions and ground truth of the training objects at ``indices``.

    The model runs in the mode it is in (:func:`select_objects` sets eval mode).

    Args:
        pl_module: the model, attached to a Trainer.
        dm: the datamodule.
        indices: train-order indices of the objects.
        epoch: the round's epoch: the input views are ``dm.eval_item(record, settings.source_view_set,
            seed=epoch + 1)``'s.
        settings: the round's settings (``source_view_set``, ``batch_size``).

    Returns:
        ``(predicted, target)``, each ``(N, R, R, R)`` float32 on the CPU (empty without indices).

    Example::

        predicted, target = predict_objects(model, dm, [0, 3], epoch=0, settings=settings)
    """
    records = dm.split_records("train")
    items = [dm.eval_item(records[i], settings.source_view_set, seed=epoch + 1) for i in indices]
    if not items:
        return torch.empty(0), torch.empty(0)
    predicted = predict_probabilities(pl_module, [it["images"] for it in items], settings.batch_size)
    return predicted, torch.stack([it["voxels"] for it in items])


def object_selection(
    record: Any, index: int, views: Tensor, predicted: Tensor, target: Tensor, threshold: float
) -> Selection:
    """The :class:`~lightning_vtr.augmentation.selection_round.Selection` of one object.

    Args:
        record: the object's record (``category``, ``object_id``).
        index: its train-order index.
        views: ``(n, 2)`` viewpoints the selector chose, degrees.
        predicted: ``(R, R, R)`` occupancy probabilities.
        target: ``(R, R, R)`` ground-truth occupancy.
        threshold: the selector's threshold (the one its error volume binarises at).

    Returns:
        The selection; its ``error`` is the fraction of voxels where ``predicted >= threshold`` differs from
        ``target``.

    Example:
        >>> from types import SimpleNamespace
        >>> record = SimpleNamespace(category="chair", object_id="a")
        >>> object_selection(record, 0, torch.zeros(3, 2), torch.full((2, 2, 2), 0.35), torch.ones(2, 2, 2), 0.3).error
        0.0
    """
    error = ((predicted >= threshold).float() != target).float().mean().item()
    return Selection(index, record.category, record.object_id, views.detach().cpu().numpy(), error)


def _context(
    selector: ViewSelector,
    pl_module: L.LightningModule,
    dm: AugmentableDataModule,
    synthesizer: Synthesizer,
    records: list[Any],
    source_view_set: str,
) -> SelectionContext | None:
    if not selector.needs_context:
        return None
    requests = [synthesis_request(dm, r, synthesizer, source_view_set) for r in records]
    return selection_context(pl_module, dm, synthesizer, requests)


def select_objects(
    trainer: L.Trainer,
    pl_module: L.LightningModule,
    dm: AugmentableDataModule,
    selector: ViewSelector,
    synthesizer: Synthesizer,
    indices: list[int],
    epoch: int,
    settings: RoundSettings,
) -> list[Selection]:
    """Predict the training objects at ``indices`` and ask ``selector`` for their viewpoints.

    The model is in eval mode meanwhile (selectors that query it see it so), its mode restored after. Every
    selection is checked as soon as ``select`` returns (:func:`~lightning_vtr.selection.base.check_selection`). A selector
    with ``batched=False`` sees one object at a time, each process its share, with the random stream
    ``(seed, epoch + 1, index, 0)``; a ``batched`` one (a learning selector) sees every object in one call on
    global rank 0 with the stream ``(seed, epoch + 1, 0, 2)``, and its learned state is broadcast so every process
    holds the same selector.

    Args:
        trainer: the running Trainer (its ranks and collectives).
        pl_module: the model.
        dm: the datamodule.
        selector: chooses the viewpoints (its state changes when it learns).
        synthesizer: renders the views of a selector that queries the model (``needs_context``).
        indices: train-order indices of the objects, ascending, the same on every process.
        epoch: the epoch whose end makes the round (``-1``: before epoch 0).
        settings: the round's settings (``seed``, ``batch_size``, ``source_view_set``).

    Returns:
        One :class:`~lightning_vtr.augmentation.selection_round.Selection` per index, in order, on every process.

    Example::

        searched = select_objects(trainer, model, dm, selector, synthesizer, [0, 3], epoch=0, settings=settings)
    """
    records = dm.split_records("train")
    was_training = pl_module.training
    pl_module.eval()
    try:
        if not selector.batched:

            def select(mine: list[int]) -> list[Selection]:
                predicted, target = predict_objects(pl_module, dm, mine, epoch, settings)
                out = []
                for row, index in enumerate(mine):
                    rec = records[index]
                    views = selector.select(
                        predicted[row : row + 1],
                        target[row : row + 1],
                        [rec.category],
                        generator=stream(settings.seed, epoch + 1, index, SELECT_STREAM),
                        context=_context(selector, pl_module, dm, synthesizer, [rec], settings.source_view_set),
                    )
                    views = check_selection(selector, views, 1)[0]
                    out.append(object_selection(rec, index, views, predicted[row], target[row], selector.threshold))
                return out

            return sharded_map(trainer, indices, select)

        parts = sharded_map(
            trainer, indices, lambda mine: list(zip(*predict_objects(pl_module, dm, mine, epoch, settings)))
        )
        payload: tuple[list[Selection] | None, Any] | None = None
        if trainer.is_global_zero:
            recs = [records[i] for i in indices]
            predicted = torch.stack([p for p, _ in parts]) if parts else torch.empty(0)
            target = torch.stack([t for _, t in parts]) if parts else torch.empty(0)
            views = selector.select(
                predicted,
                target,
                [r.category for r in recs],
                generator=stream(settings.seed, epoch + 1, 0, BATCHED_SELECT_STREAM),
                context=_context(selector, pl_module, dm, synthesizer, recs, settings.source_view_set),
            )
            try:
                views = check_selection(selector, views, len(recs))
            except ValueError as error:  # every process raises it, rather than the others waiting for rank 0
                payload = (None, str(error))
            else:
                found = [object_selection(*a, selector.threshold) for a in zip(recs, indices, views, predicted, target)]
                payload = (found, selector.state_dict())
        payload = broadcast_from_zero(trainer, payload)
        if payload[0] is None:
            raise ValueError(payload[1])
        if not trainer.is_global_zero:
            selector.load_state_dict(payload[1])
        return payload[0]
    finally:
        pl_module.train(was_training)


def synthesize_round(
    trainer: L.Trainer,
    dm: AugmentableDataModule,
    synthesizer: Synthesizer,
    plan: RoundPlan,
    epoch: int,
    settings: RoundSettings,
    *,
    show_progress: bool,
) -> list[np.ndarray]:
    """Images of every target of ``plan`` at its view set, ``settings.batch_size`` objects per synthesizer call.

    Args:
        trainer: the running Trainer (its ranks and collectives).
        dm: the datamodule (the targets' records and source views).
        synthesizer: makes the images.
        plan: the round's plan.
        epoch: the epoch whose end makes the round (for the progress bar's title).
        settings: the round's settings (``batch_size``, ``source_view_set``).
        show_progress: show a progress bar on this process.

    Returns:
        One ``(n, H, W, 4)`` uint8 array per target, in order, on every process.

    Example::

        images = synthesize_round(trainer, dm, RenderSynthesizer(), plan, 0, settings, show_progress=False)
    """
    records = dm.split_records("train")
    bar = tqdm(
        desc=f"VTR: synthesizing views (epoch {epoch})", disable=not show_progress, leave=False, dynamic_ncols=True
    )

    def synthesize(mine: list[int]) -> list[np.ndarray]:
        bar.reset(total=len(mine))
        out = []
        for start in range(0, len(mine), settings.batch_size):
            chunk = mine[start : start + settings.batch_size]
            requests = [
                synthesis_request(
                    dm, records[plan.targets[j].index], synthesizer, settings.source_view_set, plan.view_sets[j]
                )
                for j in chunk
            ]
            out += [np.asarray(images) for images in synthesizer.synthesize(requests)]
            bar.update(len(chunk))
        return out

    try:
        return sharded_map(trainer, list(range(len(plan.targets))), synthesize)
    finally:
        bar.close()


def run_round(
    trainer: L.Trainer,
    pl_module: L.LightningModule,
    dm: AugmentableDataModule,
    epoch: int,
    *,
    selector: ViewSelector,
    synthesizer: Synthesizer,
    pool: ViewpointPool | None,
    settings: RoundSettings,
    show_progress: bool,
) -> RoundResult:
    """The round after ``epoch``: search, select, plan, synthesize.

    1. :func:`~lightning_vtr.augmentation.selection_round.search_indices`: which objects are searched;
    2. :func:`select_objects`: their predictions and selections;
    3. :func:`~lightning_vtr.augmentation.selection_round.plan_round`: which get views, from which view sets
       (``pool`` changes);
    4. :func:`synthesize_round`: their images.

    Args:
        trainer: the running Trainer.
        pl_module: the model.
        dm: the datamodule, with at least one training object.
        epoch: the epoch whose end makes the round (``-1``: before epoch 0).
        selector: chooses the viewpoints.
        synthesizer: makes the images.
        pool: the viewpoint pool, or ``None``.
        settings: the round's settings.
        show_progress: show a progress bar while synthesizing on this process.

    Returns:
        A :class:`RoundResult`; the datamodule is not changed.

    Example::

        result = run_round(trainer, model, dm, 0, selector=selector, synthesizer=synthesizer, pool=None,
                           settings=settings, show_progress=False)
        dm.add_samples(result.samples)
    """
    num_train = len(dm.split_records("train"))
    chosen = search_indices(
        num_train, epoch, search_fraction=settings.search_fraction, min_objects=settings.min_objects, seed=settings.seed
    )
    searched = select_objects(trainer, pl_module, dm, selector, synthesizer, chosen, epoch, settings)
    plan = plan_round(
        searched,
        num_train,
        epoch,
        fraction=settings.fraction,
        min_objects=settings.min_objects,
        generate_for=settings.generate_for,
        seed=settings.seed,
        pool=pool,
    )
    images = synthesize_round(trainer, dm, synthesizer, plan, epoch, settings, show_progress=show_progress)
    samples = [
        GeneratedSample(s.category, s.object_id, img, np.asarray(vs, dtype=np.float64), epoch)
        for s, vs, img in zip(plan.targets, plan.view_sets, images)
    ]
    record = recording.selection_record(epoch, plan.targets, plan.view_sets, searched)
    return RoundResult(searched, plan, samples, record)
