"""Size limits checked before an untrusted file is decoded: a small file must not expand into gigabytes.

A dataset, an output folder or a picture from someone else may be crafted to expand: a 170 KB PNG whose header
says 12000 x 12000 pixels decodes into 576 MB, a binvox header ``dim 2048 2048 2048`` asks for an 8 GiB grid, a
200 MB ``metadata.json`` takes gigabytes to parse. The readers check what the header (or the file size) says
against these limits first and refuse with one line naming the file, the size and the limit
(:class:`~lightning_vtr.errors.DataError`, exit status 1 in ``lightning-vtr``):

* a JSON file read from a dataset or an output folder (``metadata.json``, ``splits.json``, ``object.json``,
  ``robustness.json``, ...) of at most :func:`max_json_bytes` bytes, 64 MiB unless the environment variable
  ``LIGHTNING_VTR_MAX_JSON_BYTES`` says otherwise;
* a picture of a dataset at most :data:`IMAGE_SIDE_FACTOR` times the dataset's image size per side (a 96 px
  dataset: 768 px), any other picture at most :data:`MAX_IMAGE_SIDE` per side, and never more pixels than
  PIL's decompression-bomb limit (``PIL.Image.MAX_IMAGE_PIXELS``);
* a binvox grid of the resolution the dataset states, and never more than :data:`MAX_VOXEL_SIDE` per side.

Before any of these files is opened, :func:`check_regular_file` makes sure it is a regular file (a FIFO, which
a tar archive keeps, would block the reader forever; a device may never end) and, given the dataset's folder,
that its resolved path lies inside that folder (a symlink leading out of a dataset is not followed).
"""

from __future__ import annotations

import functools
import os
import re
import stat
import warnings
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from PIL import Image

__all__ = [
    "IMAGE_SIDE_FACTOR",
    "MAX_IMAGE_SIDE",
    "MAX_JSON_BYTES",
    "MAX_JSON_BYTES_VARIABLE",
    "MAX_VOXEL_SIDE",
    "check_regular_file",
    "file_kind",
    "image_side_limit",
    "max_json_bytes",
    "open_image",
    "read_json",
]

#: The default largest JSON file read from a dataset or an output folder, in bytes (64 MiB; a
#: ``metadata.json`` of 40,000 objects is about 60 MB).
MAX_JSON_BYTES = 64 * 2**20
#: The environment variable that sets another limit for JSON files, in bytes.
MAX_JSON_BYTES_VARIABLE = "LIGHTNING_VTR_MAX_JSON_BYTES"
#: A dataset's picture may be at most this many times the dataset's image size per side.
IMAGE_SIDE_FACTOR = 8
#: The largest side of a picture whose expected size is unknown (a folder test set, a background folder).
MAX_IMAGE_SIDE = 8192
#: The largest side of a binvox grid read (512: a 128 MiB grid).
MAX_VOXEL_SIDE = 512


def max_json_bytes() -> int:
    """The largest JSON file read, in bytes: ``$LIGHTNING_VTR_MAX_JSON_BYTES`` if set, else :data:`MAX_JSON_BYTES`.

    Raises:
        UsageError: the variable is set to something other than a positive integer.
    """
    text = os.environ.get(MAX_JSON_BYTES_VARIABLE)
    if text is None or not text.strip():
        return MAX_JSON_BYTES
    if not text.strip().isdigit() or int(text) < 1:
        from lightning_vtr.errors import UsageError

        raise UsageError(f"${MAX_JSON_BYTES_VARIABLE} must be a positive number of bytes, got {text!r}")
    return int(text)


def file_kind(mode: int) -> str:
    """What an ``os.stat`` mode is, in words, for a message: ``"a regular file"``, ``"a FIFO (named pipe)"``, ...

    Example:
        >>> import stat
        >>> file_kind(stat.S_IFIFO | 0o644), file_kind(stat.S_IFDIR | 0o755)
        ('a FIFO (named pipe)', 'a folder')
    """
    kinds = (
        (stat.S_ISREG, "a regular file"),
        (stat.S_ISDIR, "a folder"),
        (stat.S_ISFIFO, "a FIFO (named pipe)"),
        (stat.S_ISSOCK, "a socket"),
        (stat.S_ISCHR, "a character device"),
        (stat.S_ISBLK, "a block device"),
    )
    return next((name for test, name in kinds if test(mode)), f"a file of mode {stat.filemode(mode)}")


@functools.lru_cache(maxsize=64)
def _resolved_root(root: str) -> str:
    """``os.path.realpath(root)``, once per root and process."""
    return os.path.realpath(root)


def check_regular_file(path: str | os.PathLike, *, root: str | os.PathLike | None = None) -> None:
    """Refuse to read ``path`` unless it is a regular file (links followed) and, with ``root``, lies inside ``root``.

    Every reader of this module and :func:`~lightning_vtr.data.binvox.read_binvox` call it before opening a file:
    a FIFO (a tar archive keeps them) would block the reader forever, a device may never end.

    Args:
        path: the file about to be read.
        root: the dataset's folder the file belongs to (``None``: no such check): a file whose resolved path
            (``os.path.realpath``, one per call; the root's is computed once) is not inside it, a symlink leading
            out of the dataset, is refused.

    Raises:
        DataError: ``path`` leads out of ``root``, or is a FIFO, a socket, a device or a folder; one line naming
            the file and what it is.
        FileNotFoundError: it does not exist (an ``OSError``, as ``open`` raises).
    """
    from lightning_vtr.errors import DataError

    if root is not None:
        base = _resolved_root(os.fspath(root))
        target = os.path.realpath(path)
        if target != base and not target.startswith(base.rstrip(os.sep) + os.sep):
            raise DataError(f"{os.fspath(path)} is a symbolic link leading out of the dataset (to {target}); not read")
    mode = os.stat(path).st_mode
    if not stat.S_ISREG(mode):
        raise DataError(f"{os.fspath(path)}: a regular file was expected, found {file_kind(mode)}")


def read_json(path: str | os.PathLike, *, root: str | os.PathLike | None = None) -> Any:
    """The parsed JSON file ``path``, after checking its size against :func:`max_json_bytes`.

    Args:
        path: the JSON file.
        root: the dataset's folder it belongs to, if any: a file leading out of it is refused
            (:func:`check_regular_file`).

    Raises:
        DataError: the file is larger than the limit (the message names the file, its size and the limit); it
            is not a regular file, or leads out of ``root`` (:func:`check_regular_file`); it nests deeper than
            Python's recursion limit.
        OSError: the file cannot be read.
        json.JSONDecodeError: it is not JSON (a ``ValueError``).

    Example::

        meta = read_json("data/metadata.json")
    """
    import json

    path = Path(path)
    check_regular_file(path, root=root)
    with open(path, "rb") as f:
        size = os.fstat(f.fileno()).st_size
        limit = max_json_bytes()
        if size > limit:
            from lightning_vtr.errors import DataError

            raise DataError(
                f"{path}: a JSON file of at most {limit} bytes was expected, found {size} bytes "
                f"(set ${MAX_JSON_BYTES_VARIABLE} to read larger files)"
            )
        data = f.read(limit + 1)
    try:
        return json.loads(data)
    except RecursionError:  # a few KB of brackets nest deeper than the parser recurses
        from lightning_vtr.errors import DataError

        raise DataError(f"{path}: not valid JSON (nested deeper than Python's recursion limit)") from None


def image_side_limit(image_size: int | None) -> int:
    """The largest side accepted for a picture of a dataset of ``image_size`` px (:data:`MAX_IMAGE_SIDE` when
    ``None``).

    Example:
        >>> image_side_limit(96), image_side_limit(None)
        (768, 8192)
    """
    return MAX_IMAGE_SIDE if image_size is None else IMAGE_SIDE_FACTOR * int(image_size)


def open_image(
    path: str | os.PathLike, max_side: int | None = None, *, root: str | os.PathLike | None = None
) -> Image.Image:
    """``PIL.Image.open(path)``, refused before any pixel is decoded when its header states a larger picture.

    Args:
        path: the picture.
        max_side: the largest width and height accepted (``None``: :data:`MAX_IMAGE_SIDE`); see
            :func:`image_side_limit`.
        root: the dataset's folder it belongs to, if any: a picture leading out of it is refused
            (:func:`check_regular_file`).

    Returns:
        The opened image, not yet decoded (``.load()``, ``.convert()`` decode it); close it after use.

    Raises:
        DataError: the picture is larger than ``max_side`` per side, or than PIL's decompression-bomb limit;
            the message names the file, its size and the limit; it is not a regular file, or leads out of
            ``root`` (:func:`check_regular_file`).
        OSError: PIL cannot open it (``PIL.UnidentifiedImageError`` is one).
    """
    from PIL import Image

    from lightning_vtr.errors import DataError

    limit = MAX_IMAGE_SIDE if max_side is None else int(max_side)
    check_regular_file(path, root=root)
    try:
        with warnings.catch_warnings():  # PIL warns of a large header; the size is checked just below
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            image = Image.open(path)
    except Image.DecompressionBombError as err:  # the header states more pixels than PIL decodes at all
        found = re.search(r"\((\d+) pixels\)", str(err))
        pixels = f"{found.group(1)} pixels" if found else "more pixels than PIL's limit"
        bomb = 2 * (Image.MAX_IMAGE_PIXELS or 0)  # PIL refuses twice the pixels it warns of
        raise DataError(
            f"{os.fspath(path)}: a picture of at most {limit}x{limit} pixels was expected, found {pixels} "
            f"(more than PIL's decompression-bomb limit of {bomb} pixels); not decoded"
        ) from None
    width, height = image.size
    if width > limit or height > limit:
        image.close()
        raise DataError(
            f"{os.fspath(path)}: a picture of at most {limit}x{limit} pixels was expected, found {width}x{height}; "
            "not decoded"
        )
    return image
