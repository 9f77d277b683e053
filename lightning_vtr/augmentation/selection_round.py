"""One selection round as pure functions: which objects are searched, which of them get new views, and which view
set each of those is shown from.

Every random choice derives from ``(seed, epoch, object)``, so a round does not depend on how objects are split
over processes or batches, and a resumed run repeats an uninterrupted one. Nothing here needs a Trainer: the
callback predicts the searched objects and asks its selector for their viewpoints in between.

Example:
    >>> from lightning_vtr.selection.pool import ViewpointPool
    >>> searched = search_indices(20, epoch=0, search_fraction=0.35, min_objects=1, seed=0)
    >>> len(searched)
    7
    >>> selections = [Selection(i, "chair", f"c{i}", np.zeros((3, 2)), error=0.1) for i in searched]
    >>> plan = plan_round(selections, 20, epoch=0, fraction=0.1, min_objects=1, generate_for="random", seed=0,
    ...                   pool=ViewpointPool(refresh=True))
    >>> len(plan.targets), len(plan.view_sets)
    (2, 2)
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch

from lightning_vtr.selection.pool import ViewpointPool

__all__ = ["RoundPlan", "Selection", "draw_view_sets", "generation_targets", "plan_round", "search_indices", "stream"]

#: The ``purpose`` of each random stream of a round (the last entry of its key).
SELECT_STREAM, POOL_STREAM, BATCHED_SELECT_STREAM = 0, 1, 2


@dataclass
class Selection:
    """What a round found on one searched object.

    Attributes:
        index: the object's position in the datamodule's fixed train order.
        category: the object's category.
        object_id: the object's id.
        viewpoints: ``(n, 2)`` (yaw, pitch) in degrees, as the selector chose them.
        error: the fraction of the object's voxels the model got wrong (prediction binarised at the selector's
            threshold).

    Example:
        >>> Selection(0, "chair", "c0", np.zeros((3, 2)), error=0.25).error
        0.25
    """

    index: int
    category: str
    object_id: str
    viewpoints: np.ndarray
    error: float


@dataclass
class RoundPlan:
    """What a round synthesizes.

    Attributes:
        targets: the objects given new views, in train order.
        view_sets: the ``(n, 2)`` view set (degrees) each target is synthesized at.

    Example:
        >>> RoundPlan([], []).targets
        []
    """

    targets: list[Selection]
    view_sets: list[np.ndarray]


def stream(*key: int) -> torch.Generator:
    """A ``torch.Generator`` seeded from ``key`` (e.g. ``(seed, epoch + 1, object index, purpose)``).

    One independent stream per key: results cannot depend on how objects are split over processes or batches.

    Args:
        key: non-negative ints.

    Returns:
        A new CPU ``torch.Generator``.

    Example:
        >>> bool(torch.equal(torch.rand(2, generator=stream(0, 1, 5)), torch.rand(2, generator=stream(0, 1, 5))))
        True
    """
    seed = int(np.random.SeedSequence(list(key)).generate_state(1, dtype=np.uint64)[0] >> 1)
    return torch.Generator().manual_seed(seed)


def object_count(share: float, num_train: int, min_objects: int) -> int:
    """``round(share * num_train)`` objects, at least ``min_objects``, at most ``num_train``."""
    return min(num_train, max(min_objects, round(share * num_train)))


def search_indices(num_train: int, epoch: int, *, search_fraction: float, min_objects: int, seed: int) -> list[int]:
    """The train-order indices of the objects searched (predicted and scored) in the round after ``epoch``.

    Args:
        num_train: the number of training objects.
        epoch: the epoch whose end makes the round (``-1``: the round before epoch 0).
        search_fraction: the share of the training objects searched.
        min_objects: the fewest objects searched.
        seed: the callback's seed.

    Returns:
        ``object_count(search_fraction, num_train, min_objects)`` distinct indices, ascending, drawn from
        ``numpy.random.default_rng([seed, epoch + 1])``.

    Example:
        >>> len(search_indices(20, -1, search_fraction=0.35, min_objects=1, seed=0))
        7
    """
    rng = np.random.default_rng([seed, epoch + 1])
    count = object_count(search_fraction, num_train, min_objects)
    return sorted(rng.choice(num_train, size=count, replace=False).tolist())


def generation_targets(
    searched: list[Selection],
    num_train: int,
    epoch: int,
    *,
    fraction: float,
    min_objects: int,
    generate_for: Literal["random", "error"],
    seed: int,
) -> list[Selection]:
    """The searched objects that get new views in the round after ``epoch``, in train order.

    Args:
        searched: the searched objects' selections, in train order.
        num_train: the number of training objects.
        epoch: the epoch whose end makes the round.
        fraction: the share of the training objects given views.
        min_objects: the fewest objects given views.
        generate_for: ``"error"``: those with the largest error (ties by train order); ``"random"``: a subset drawn
            from ``numpy.random.default_rng([seed, epoch + 1, 3])``.
        seed: the callback's seed.

    Returns:
        ``object_count(fraction, num_train, min_objects)`` of ``searched`` (all when fewer were searched).

    Example:
        >>> searched = [Selection(i, "chair", str(i), np.zeros((3, 2)), error=i / 10) for i in range(4)]
        >>> [s.index for s in generation_targets(searched, 20, 0, fraction=0.1, min_objects=1,
        ...                                      generate_for="error", seed=0)]
        [2, 3]
    """
    count = min(len(searched), object_count(fraction, num_train, min_objects))
    if count == len(searched):
        return list(searched)
    if generate_for == "error":
        order = sorted(range(len(searched)), key=lambda j: (-searched[j].error, searched[j].index))
        keep = set(order[:count])
    else:
        rng = np.random.default_rng([seed, epoch + 1, 3])
        keep = set(rng.choice(len(searched), size=count, replace=False).tolist())
    return [s for j, s in enumerate(searched) if j in keep]


def draw_view_sets(
    pool: ViewpointPool | None, searched: list[Selection], targets: list[Selection], epoch: int, *, seed: int
) -> list[np.ndarray]:
    """The view set each of ``targets`` is synthesized at.

    Without a pool, each target's own selection. With one, :meth:`ViewpointPool.start_round` (which empties a
    refreshing pool), then every searched object's selection goes into the pool, then each target draws a set
    from its category's pool with the stream ``(seed, epoch + 1, index, 1)``.

    Args:
        pool: the viewpoint pool (changed), or ``None``.
        searched: the searched objects' selections.
        targets: the objects given views (among ``searched``).
        epoch: the epoch whose end makes the round.
        seed: the callback's seed.

    Returns:
        One ``(n, 2)`` array (degrees) per target.

    Example:
        >>> s = Selection(0, "chair", "c0", np.array([[0.0, 30.0], [90.0, 0.0], [-90.0, 0.0]]), error=0.1)
        >>> draw_view_sets(None, [s], [s], 0, seed=0)[0].tolist()
        [[0.0, 30.0], [90.0, 0.0], [-90.0, 0.0]]
    """
    if pool is None:
        return [s.viewpoints for s in targets]
    pool.start_round()
    for s in searched:
        pool.add(s.category, s.object_id, torch.as_tensor(s.viewpoints))
    return [
        pool.sample(s.category, s.object_id, generator=stream(seed, epoch + 1, s.index, POOL_STREAM)).numpy()
        for s in targets
    ]


def plan_round(
    searched: list[Selection],
    num_train: int,
    epoch: int,
    *,
    fraction: float,
    min_objects: int,
    generate_for: Literal["random", "error"],
    seed: int,
    pool: ViewpointPool | None,
) -> RoundPlan:
    """:func:`generation_targets` then :func:`draw_view_sets`: what the round after ``epoch`` synthesizes.

    Args:
        searched: the selections of the searched objects, in train order.
        num_train: the number of training objects.
        epoch: the epoch whose end makes the round (``-1``: before epoch 0).
        fraction: the share of the training objects given new views.
        min_objects: the fewest objects given views.
        generate_for: ``"random"`` or ``"error"`` (see :func:`generation_targets`).
        seed: the callback's seed.
        pool: the viewpoint pool (changed: the round's selections are added), or ``None``.

    Returns:
        A :class:`RoundPlan`.

    Example:
        >>> s = Selection(0, "chair", "c0", np.zeros((3, 2)), error=0.1)
        >>> plan = plan_round([s], 20, 0, fraction=0.05, min_objects=1, generate_for="random", seed=0, pool=None)
        >>> [t.index for t in plan.targets]
        [0]
    """
    targets = generation_targets(
        searched, num_train, epoch, fraction=fraction, min_objects=min_objects, generate_for=generate_for, seed=seed
    )
    return RoundPlan(targets, draw_view_sets(pool, searched, targets, epoch, seed=seed))
