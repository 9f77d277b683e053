"""``argparse`` types (each parses one word or raises ``ArgumentTypeError``), shared by the command line and
the experiment flags."""

from __future__ import annotations

import argparse
from collections.abc import Callable, Collection

__all__ = ["at_least", "comma_separated", "positive_int", "ratios", "shard"]


def shard(text: str) -> tuple[int, int]:
    """Parse ``"i/n"`` (0-based shard ``i`` of ``n``)."""
    try:
        index, count = (int(part) for part in text.split("/"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected i/n with integers, e.g. 0/4, got {text!r}") from None
    if count < 1 or not 0 <= index < count:
        raise argparse.ArgumentTypeError(f"shard index must satisfy 0 <= i < n, got {index}/{count}")
    return index, count


def comma_separated(choices: Collection[str] | None = None) -> Callable[[str], list[str]]:
    """The type of a non-empty comma-separated list, each item one of ``choices`` (any word when ``None``)."""

    def parse(text: str) -> list[str]:
        items = [item.strip() for item in text.split(",") if item.strip()]
        if not items:
            raise argparse.ArgumentTypeError(f"expected a comma-separated list, got {text!r}")
        unknown = [item for item in items if choices is not None and item not in choices]
        if unknown:
            raise argparse.ArgumentTypeError(
                f"invalid choice(s) {', '.join(map(repr, unknown))} (choose from {', '.join(choices or ())})"
            )
        return items

    parse.__name__ = "comma-separated list"  # argparse names the type in its error messages
    return parse


def ratios(text: str) -> tuple[float, float, float]:
    """Parse ``"train,val,test"`` ratios, e.g. ``0.7,0.1,0.2``."""
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != 3:
        raise argparse.ArgumentTypeError(f"expected three comma-separated ratios train,val,test, got {text!r}")
    return values


def positive_int(text: str) -> int:
    """Parse an integer >= 1."""
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return value


def at_least(minimum: int) -> Callable[[str], int]:
    """The type of an integer ``>= minimum``.

    Example:
        >>> at_least(2)("3")
        3
    """

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            value = minimum - 1
        if value < minimum:
            what = "a positive integer" if minimum == 1 else f"an integer >= {minimum}"
            raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}")
        return value

    parse.__name__ = "integer"  # argparse names the type in its error messages
    return parse
