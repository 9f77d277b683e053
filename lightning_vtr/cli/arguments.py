"""``argparse`` types shared by the sub-commands (each parses one word or raises ``ArgumentTypeError``), and
:func:`check_output_folder`, the check of every ``--out``."""

from __future__ import annotations

import argparse
from collections.abc import Callable, Collection
from pathlib import Path

__all__ = ["check_output_folder", "comma_separated", "positive_int", "ratios", "shard"]


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


def check_output_folder(out: Path, option: str = "--out", marker: str = "predictions.json") -> Path:
    """``out`` if it is a writable folder that is new, empty or holds an earlier output (``marker``, a file name
    or a glob pattern); nothing is left behind by the check.

    Raises:
        UsageError: ``out`` is a file, or a folder of other files (the message names a few).
        PermissionError: the folder cannot be created or written (a probe file is written and removed, and
            so are the folders created for it).
    """
    import contextlib
    import os

    from lightning_vtr.errors import UsageError

    out = Path(out).expanduser()
    if out.exists() and not out.is_dir():
        raise UsageError(f"`{option}` must be a folder (new, empty or an earlier output), got {str(out)!r} (a file)")
    if out.is_dir() and not any(out.glob(marker)):
        others = sorted(p.name for p in out.iterdir() if not p.name.startswith("."))
        if others:
            shown = ", ".join(others[:3]) + (", ..." if len(others) > 3 else "")
            raise UsageError(
                f"`{option}` must be a new or empty folder or an earlier output (with {marker}), got {str(out)!r} "
                f"holding {len(others)} other {'entry' if len(others) == 1 else 'entries'} ({shown}); choose another folder"
            )
    missing = [p for p in (out, *out.parents) if not p.exists()]
    out.mkdir(parents=True, exist_ok=True)
    try:
        probe = out / f".write-probe-{os.getpid()}"
        with open(probe, "wb") as f:
            f.write(b"")
        probe.unlink()
    finally:
        for folder in missing:  # created only to probe: the command creates them when it writes
            with contextlib.suppress(OSError):
                folder.rmdir()
    return out
