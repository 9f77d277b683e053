"""The ``argparse`` types of the sub-commands (from :mod:`lightning_vtr.utils.argtypes`) and
:func:`check_output_folder`, the check of every ``--out``."""

from __future__ import annotations

from pathlib import Path

from lightning_vtr.utils.argtypes import comma_separated, positive_int, ratios, shard

__all__ = ["check_output_folder", "comma_separated", "positive_int", "ratios", "shard"]


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
