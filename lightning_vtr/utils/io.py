"""Every file the package writes goes through these helpers: atomic, and never through a symlink.

A reader, a concurrent writer or a killed process never sees half a file: each write goes to a temporary file
created in the destination's folder with ``O_EXCL`` under an unguessable name (:func:`tempfile.mkstemp`), then
``os.replace`` puts it in place in one step. ``os.replace`` replaces a symlink standing at the destination
instead of following it, so an output folder copied from someone else, whose ``results.csv`` is a link to a
file elsewhere, gets a regular ``results.csv`` and the file elsewhere is left as it was. A file that must be
opened in place (a log appended to) is opened with ``O_NOFOLLOW``, which refuses a symlink.

Writers of other libraries (matplotlib's ``savefig``, PIL's ``Image.save``, ``numpy.save``, trimesh's
``export``, ``csv``) write into the file object :func:`atomic_open` yields, or through :func:`atomic_save`.
CSV files are written by :func:`write_csv`, which escapes cells a spreadsheet would run as a formula.
``tests/test_path_audit.py`` fails on a write call anywhere else in the package.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Callable, Iterable, Iterator, Sequence
from pathlib import Path
from typing import IO, Any

__all__ = [
    "CSV_FORMULA_PREFIXES",
    "STALE_SECONDS",
    "atomic_open",
    "atomic_save",
    "atomic_write",
    "atomic_write_json",
    "csv_cell",
    "csv_text",
    "open_append",
    "probe_writable",
    "remove_stale_temporaries",
    "save_figure",
    "uncsv_cell",
    "write_csv",
]

#: A temporary file of :func:`atomic_open` unchanged for this long belongs to a killed write (a live write
#: keeps touching its file); :func:`remove_stale_temporaries` removes it.
STALE_SECONDS = 60.0


@contextlib.contextmanager
def atomic_open(path: str | os.PathLike, mode: str = "wb", *, fsync: bool = False) -> Iterator[IO]:
    """Open a temporary file beside ``path``; on a clean exit it replaces ``path`` in one step.

    The temporary file lives in the destination directory (``os.replace`` is atomic only within one file
    system) under a unique name, so concurrent writers (dataset shards, DDP ranks) never share one. On an
    exception it is removed and ``path`` is left as it was.

    Args:
        path: the destination; its parent directories are created.
        mode: ``"wb"`` or ``"w"``.
        fsync: flush the data to disk before the rename (survives a power loss, not only a kill).

    Example::

        with atomic_open("results.json", "w") as f:
            json.dump(results, f)
    """
    if mode not in ("wb", "w"):
        raise ValueError(f"`mode` must be 'wb' or 'w', got {mode!r}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        # mkstemp creates 0600; give the file the permissions a plain open() would (a shared cache stays readable)
        os.chmod(tmp, 0o666 & ~_umask())
        with os.fdopen(fd, mode, encoding=None if "b" in mode else "utf-8") as f:
            yield f
            if fsync:
                f.flush()
                os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def atomic_write(path: str | os.PathLike, data: bytes | str, *, fsync: bool = False) -> None:
    """Write ``data`` (bytes, or text as UTF-8) to ``path`` atomically (see :func:`atomic_open`)."""
    with atomic_open(path, "wb", fsync=fsync) as f:
        f.write(data.encode("utf-8") if isinstance(data, str) else data)


def atomic_save(path: str | os.PathLike, save: Callable[[IO[bytes]], Any], *, fsync: bool = False) -> Path:
    """Write ``path`` atomically through ``save``, a function that writes into a binary file object.

    For another library's writer: ``save`` gets the temporary file of :func:`atomic_open` (never ``path``),
    so a symlink at ``path`` is replaced, not followed. Returns ``path``.

    Example::

        atomic_save("mesh.obj", lambda f: mesh.export(f, file_type="obj"))
        atomic_save("grid.npy", lambda f: np.save(f, grid))
    """
    with atomic_open(path, "wb", fsync=fsync) as f:
        save(f)
    return Path(path)


def atomic_write_json(path: str | os.PathLike, payload: Any, *, indent: int | None = 1, **dumps: Any) -> None:
    """Write ``payload`` as JSON (UTF-8) to ``path`` atomically; ``dumps`` go to :func:`json.dumps`."""
    import json

    atomic_write(path, json.dumps(payload, indent=indent, **dumps))


def save_figure(fig: Any, path: str | os.PathLike, **savefig: Any) -> Path:
    """Save a matplotlib figure to ``path`` atomically, in the format of its suffix (``savefig`` options pass on).

    Returns ``path``.
    """
    savefig.setdefault("format", Path(path).suffix.lstrip(".").lower() or "png")
    return atomic_save(path, lambda f: fig.savefig(f, **savefig))


#: First characters that make a spreadsheet read a CSV cell as a formula (OWASP, "CSV injection"); a text cell
#: that starts with one is written with a leading ``'``.
CSV_FORMULA_PREFIXES = ("=", "+", "-", "@", "\t", "\r")


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def csv_cell(value: Any) -> Any:
    """``value`` as a CSV cell a spreadsheet shows as text: a string that starts with ``=``, ``+``, ``-``, ``@``,
    a tab or a carriage return (or ``'`` and then one of them) gets a leading ``'``; numbers (``-0.5``, also
    written as text) and other values are kept. :func:`uncsv_cell` undoes it.

    Example:
        >>> csv_cell("=1+2"), csv_cell("@SUM(A1)"), csv_cell("-0.25"), csv_cell("chair"), csv_cell(-1)
        ("'=1+2", "'@SUM(A1)", '-0.25', 'chair', -1)
    """
    if not isinstance(value, str) or not value:
        return value
    starts = value[1:2] if value[0] == "'" else value[0]
    if starts and starts in CSV_FORMULA_PREFIXES and not _is_number(value):
        return "'" + value
    return value


def uncsv_cell(text: str) -> str:
    """The value :func:`csv_cell` escaped: ``text`` without the leading ``'`` it added.

    Example:
        >>> uncsv_cell("'=1+2"), uncsv_cell("chair"), uncsv_cell("'quoted")
        ('=1+2', 'chair', "'quoted")
    """
    if text[:1] == "'" and csv_cell(text[1:]) == text:
        return text[1:]
    return text


def csv_text(rows: Iterable[Sequence[Any] | dict[str, Any]], header: Sequence[str] | None = None) -> str:
    """CSV text (``\\n`` line ends) of ``rows`` (sequences, or dicts keyed by ``header``), every cell through
    :func:`csv_cell`; floats are written with ``repr`` (all their digits)."""
    import csv
    import io

    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    if header is not None:
        writer.writerow([csv_cell(name) for name in header])
    for row in rows:
        cells = [row.get(name, "") for name in header or ()] if isinstance(row, dict) else row
        writer.writerow([csv_cell(repr(v) if isinstance(v, float) else v) for v in cells])
    return buffer.getvalue()


def write_csv(
    path: str | os.PathLike, rows: Iterable[Sequence[Any] | dict[str, Any]], header: Sequence[str] | None = None
) -> Path:
    """Write :func:`csv_text` of ``rows`` to ``path`` atomically; returns ``path``."""
    atomic_write(path, csv_text(rows, header))
    return Path(path)


def open_append(path: str | os.PathLike) -> IO[str]:
    """Open ``path`` (created if missing) to append UTF-8 text, line-buffered, refusing a symlink there.

    For files written over time (a log), which cannot be replaced whole. ``O_NOFOLLOW`` makes the open fail
    (``OSError`` ``ELOOP``) when ``path`` is a symlink, so the write never lands in the file it points to.
    """
    flags = os.O_WRONLY | os.O_CREAT | os.O_APPEND | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_CLOEXEC", 0)
    try:
        fd = os.open(path, flags, 0o666)
    except OSError as err:
        if Path(path).is_symlink():
            raise OSError(err.errno, "a symlink: refusing to write through it", os.fspath(path)) from None
        raise
    return os.fdopen(fd, "a", buffering=1, encoding="utf-8")


def probe_writable(folder: str | os.PathLike) -> None:
    """Check that files can be created in ``folder``: create an unguessable file there (``O_EXCL``) and remove it.

    Raises:
        OSError: the folder refuses it (permission, read-only, full); the error names ``<folder>/.write-probe``.
    """
    try:
        fd, probe = tempfile.mkstemp(dir=folder, prefix=".write-probe-")
    except OSError as err:
        raise type(err)(err.errno, err.strerror, os.path.join(folder, ".write-probe")) from None
    os.close(fd)
    os.unlink(probe)


def remove_stale_temporaries(directory: str | Path, *, older_than: float = STALE_SECONDS) -> list[Path]:
    """Remove the temporary files killed :func:`atomic_open` writes left under ``directory`` (recursively).

    Only hidden ``.<name>.<random>.tmp`` files unchanged for ``older_than`` seconds are removed, so a
    concurrent writer's (another shard's, another rank's) file in progress is kept. Returns what was removed;
    a file another process removes first is skipped.
    """
    import time

    root = Path(directory)
    if not root.is_dir():
        return []
    limit = time.time() - older_than
    removed = []
    for path in root.rglob(".*.tmp"):
        try:
            if path.is_file() and path.stat().st_mtime < limit:
                path.unlink()
                removed.append(path)
        except FileNotFoundError:
            continue
    return removed
