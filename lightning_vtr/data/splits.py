"""How the dataset builder splits each category's objects into train / validation / test."""

from __future__ import annotations

import zlib
from collections.abc import Sequence
from typing import Any

import numpy as np

__all__ = ["MIN_OBJECTS_FOR_SPLITS", "empty_split_warning", "split_counts", "split_objects", "stable_int"]


def stable_int(*parts: Any) -> int:
    """A seed from ``parts`` that every process computes alike (crc32: ``hash()`` of a str is salted per process).

    Example:
        >>> stable_int("chair", 3) == stable_int("chair", 3)
        True
    """
    return zlib.crc32("/".join(str(p) for p in parts).encode())


#: The fewest objects a category needs for one validation and one test object besides its training objects.
MIN_OBJECTS_FOR_SPLITS = 3


def split_counts(n: int, ratios: Sequence[float]) -> list[int]:
    """``[train, val, test]`` object counts of a category of ``n`` objects split ``ratios``.

    The counts are the rounded ratios, except that with at least :data:`MIN_OBJECTS_FOR_SPLITS` objects a
    validation or test split with a positive ratio that rounds to 0 objects takes one object from the
    largest other split (train on ties). Counts that give both at least one object are the rounded ones.
    """
    counts = [round(ratios[0] * n), round(ratios[1] * n)]
    counts.append(n - sum(counts))
    if n >= MIN_OBJECTS_FOR_SPLITS:
        for part in (1, 2):
            if ratios[part] > 0 and counts[part] == 0:
                donor = max((i for i in range(3) if counts[i] > 1), key=lambda i: (counts[i], -i))
                counts[donor] -= 1
                counts[part] += 1
    return counts


def split_objects(keys: list[tuple[str, str]], ratios: Sequence[float], seed: int) -> dict[str, dict[str, list[str]]]:
    """Split each category's objects ``ratios`` (train, val, test) with a permutation seeded per category
    (counts from :func:`split_counts`)."""
    out: dict[str, dict[str, list[str]]] = {}
    for category in sorted({c for c, _ in keys}):
        ids = sorted(o for c, o in keys if c == category)
        order = np.random.default_rng([seed, stable_int(category)]).permutation(len(ids))
        n_train, n_val, _ = split_counts(len(ids), ratios)
        shuffled = [ids[i] for i in order]
        out[category] = {
            "train": sorted(shuffled[:n_train]),
            "val": sorted(shuffled[n_train : n_train + n_val]),
            "test": sorted(shuffled[n_train + n_val :]),
        }
    return out


def empty_split_warning(splits: dict[str, dict[str, list[str]]], ratios: Sequence[float]) -> str | None:
    """One line naming the categories left without a validation or test object their ratio asks for."""
    short = []
    for category, parts in sorted(splits.items()):
        empty = [name for name, ratio in zip(("val", "test"), ratios[1:]) if ratio > 0 and not parts[name]]
        if empty:
            total = sum(len(ids) for ids in parts.values())
            short.append(f"{category} ({total} objects, no {' or '.join(empty)})")
    if not short:
        return None
    return (
        f"build_dataset: too few objects for a validation and a test object (a category needs at least "
        f"{MIN_OBJECTS_FOR_SPLITS}): {', '.join(short)}; build more objects of these categories"
    )
