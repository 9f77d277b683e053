"""Sharding a selection round's work over the processes of a distributed Trainer, and gathering the results.

Every function takes the Trainer and goes through ``trainer.strategy`` for its collectives, so it works with any
strategy Lightning offers; with one process they return at once.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any, TypeVar

import lightning as L

__all__ = ["all_gather_objects", "broadcast_from_zero", "shard", "sharded_map"]

T = TypeVar("T")


def shard(items: Sequence[T], rank: int, world_size: int) -> list[T]:
    """The items process ``rank`` of ``world_size`` works on: every ``world_size``-th, from position ``rank``.

    Args:
        items: the same sequence on every process.
        rank: this process's global rank.
        world_size: the number of processes.

    Returns:
        ``list(items[rank::world_size])``.

    Example:
        >>> shard([10, 11, 12, 13, 14], rank=1, world_size=2)
        [11, 13]
    """
    return list(items[rank::world_size])


def all_gather_objects(trainer: L.Trainer, obj: Any) -> list[Any]:
    """Every process's ``obj`` (any picklable object), in global-rank order, on every process.

    ``Strategy.all_gather`` gathers tensors of one shape only; objects go through one ``Strategy.broadcast`` per
    rank (world sizes here are small, the objects a few selections).

    Args:
        trainer: the running Trainer (its ``world_size``, ``global_rank`` and ``strategy``).
        obj: this process's object.

    Returns:
        ``[obj of rank 0, obj of rank 1, ...]``; ``[obj]`` with one process.

    Example::

        parts = all_gather_objects(trainer, my_selections)  # every rank's list, in rank order
    """
    if trainer.world_size == 1:
        return [obj]
    rank = trainer.global_rank
    return [trainer.strategy.broadcast(obj if src == rank else None, src=src) for src in range(trainer.world_size)]


def broadcast_from_zero(trainer: L.Trainer, obj: Any) -> Any:
    """Global rank 0's ``obj`` on every process.

    Args:
        trainer: the running Trainer.
        obj: the object (only rank 0's is used).

    Returns:
        Rank 0's ``obj``.

    Example::

        payload = broadcast_from_zero(trainer, payload if trainer.is_global_zero else None)
    """
    return obj if trainer.world_size == 1 else trainer.strategy.broadcast(obj, src=0)


def sharded_map(trainer: L.Trainer, items: Sequence[T], work: Callable[[list[T]], list[Any]]) -> list[Any]:
    """``work`` over ``items``, each process doing its :func:`shard`; every process gets all results, in item order.

    Args:
        trainer: the running Trainer (its global rank, world size and strategy).
        items: the same sequence on every process.
        work: maps a process's shard to one result per item, in order.

    Returns:
        One result per item of ``items``, in order, on every process (a single-process run's results).

    Example::

        images = sharded_map(trainer, list(range(len(targets))), synthesize_these)
    """
    rank, world = trainer.global_rank, trainer.world_size
    parts = all_gather_objects(trainer, work(shard(items, rank, world)))
    out: list[Any] = [None] * len(items)
    for r, part in enumerate(parts):
        for p, result in enumerate(part):
            out[r + p * world] = result
    return out
