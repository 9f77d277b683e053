"""The ``argparse`` types of the sub-commands (from :mod:`lightning_vtr.utils.argtypes`) and
:func:`check_output_folder`, the check of every ``--out``."""

from __future__ import annotations

from pathlib import Path

from lightning_vtr.utils.argtypes import comma_separated, positive_int, ratios, shard

__all__ = ["EMBEDDED", "check_output_folder", "comma_separated", "dataset_folder", "positive_int", "ratios", "shard"]

#: The word that names the embedded procedural dataset wherever a command takes a dataset folder (``--data
#: embedded``); a folder of that name is written ``./embedded``.
EMBEDDED = "embedded"


def dataset_folder(data: str | Path, option: str = "--data", *, progress: bool = True, read: bool = True) -> Path:
    """The ShapeNet-VTR folder ``data`` names: the word ``embedded`` for the embedded procedural dataset (built on
    first use, as the examples do), else the folder itself, checked to hold a dataset (its ``metadata.json`` read
    unless ``read`` is false: ``dataset-info --verify`` lists what is wrong with it instead).

    Raises:
        FileNotFoundError: no folder there (a file, or nothing).
        DatasetNotFoundError: a folder without ``metadata.json``; for a folder of datasets (such as the cache
            ``~/.cache/lightning_vtr``) the message names the datasets inside it.
        DatasetFormatError: its ``metadata.json`` is invalid.
    """
    from lightning_vtr.data.format import DatasetNotFoundError, load_metadata

    if str(data) == EMBEDDED:
        from lightning_vtr.data.builder import ensure_embedded_dataset

        return ensure_embedded_dataset(progress=progress)
    path = Path(data).expanduser()
    if not read and not path.is_dir():
        return path  # the caller reports what is there
    if not path.is_dir():
        found = "a file" if path.exists() else "no such folder"
        raise FileNotFoundError(
            f"`{option}` must be a ShapeNet-VTR directory or `{EMBEDDED}`, got {str(data)!r} ({found})"
        )
    if not (path / "metadata.json").is_file():
        inside = sorted(p.name for p in path.iterdir() if (p / "metadata.json").is_file())
        if inside:
            shown = ", ".join(inside[:5]) + (", ..." if len(inside) > 5 else "")
            raise DatasetNotFoundError(
                f"`{option}` {str(data)!r} is a folder of datasets, not a dataset: it holds {shown}; pass one of "
                f"them (e.g. {path / inside[0]}), or `{EMBEDDED}` for the embedded dataset"
            )
    if read:
        load_metadata(path)
    return path


def check_output_folder(out: Path, option: str = "--out", marker: str = "predictions.json") -> Path:
    """``out`` if it is a writable folder that is new, empty or holds an earlier output (``marker``, a file name
    or a glob pattern); nothing is left behind by the check.

    Raises:
        UsageError: ``out`` is a file, or a folder of other files (the message names a few).
        PermissionError: the folder cannot be created or written (a probe file is written and removed, and
            so are the folders created for it).
    """
    import contextlib

    from lightning_vtr.errors import UsageError
    from lightning_vtr.utils.io import probe_writable

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
        probe_writable(out)  # an unguessable O_EXCL file, removed: never a file someone placed there
    finally:
        for folder in missing:  # created only to probe: the command creates them when it writes
            with contextlib.suppress(OSError):
                folder.rmdir()
    return out
