"""Atomic file writes: a reader, a concurrent writer or a killed process never sees half a file."""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import IO

__all__ = ["STALE_SECONDS", "atomic_open", "atomic_write", "remove_stale_temporaries"]

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
