"""The two kinds of error a user can fix, and how ``lightning-vtr`` reports every error it expects.

* :class:`UsageError` (exit status 2): the command line is wrong: a path that does not exist or is of the
  wrong kind, a number out of range, an output folder that holds other files.
* :class:`DataError` (exit status 1): the command line is right but a file it names is not what it must be:
  a truncated checkpoint, a picture PIL cannot read, a checkpoint of another model class.

Both are ``ValueError`` s, so code that catches ``ValueError`` keeps working. :func:`exit_status` and
:func:`one_line` map any expected exception (these, ``FileNotFoundError``, ``PermissionError``, a full disk,
``DatasetFormatError``, ...) to the status and the one-line message ``lightning-vtr`` prints.
"""

from __future__ import annotations

import errno
import os

__all__ = ["EXIT_DATA", "EXIT_USAGE", "EXPECTED_ERRORS", "DataError", "UsageError", "exit_status", "one_line"]

EXIT_USAGE = 2
"""Exit status of a usage error (argparse's own)."""
EXIT_DATA = 1
"""Exit status of a data error: an input file that is not what it must be, or a write the system refused."""


class UsageError(ValueError):
    """The command line is wrong (exit status 2)."""


class DataError(ValueError):
    """A file the command line names is not what it must be (exit status 1)."""


EXPECTED_ERRORS: tuple[type[BaseException], ...] = (ValueError, OSError, RuntimeError, EOFError)
"""The exceptions ``lightning-vtr`` answers with one line instead of a traceback."""


def _image_error() -> tuple[type[BaseException], ...]:
    try:
        from PIL import UnidentifiedImageError
    except ImportError:  # pragma: no cover
        return ()
    return (UnidentifiedImageError,)


def exit_status(err: BaseException) -> int:
    """:data:`EXIT_USAGE` for errors of the command line, :data:`EXIT_DATA` for errors of the data or the system.

    An exception class with an int ``exit_status`` attribute (e.g.
    :class:`~lightning_vtr.data.format.DatasetFormatError`) gives that status. Otherwise :class:`UsageError`, a
    missing file or a path of the wrong kind (``FileNotFoundError``, ``NotADirectoryError``, ``IsADirectoryError``)
    and a plain ``ValueError`` (an argument check) are usage errors; :class:`DataError`, ``RuntimeError``,
    ``EOFError``, a picture PIL cannot identify and any other ``OSError`` (permission, full disk, I/O) are data
    errors.

    Args:
        err: the exception caught.

    Returns:
        The process exit status: :data:`EXIT_USAGE` (2) or :data:`EXIT_DATA` (1), unless the exception's class
        names its own.

    Example:
        >>> exit_status(UsageError("`--views` must be an int >= 1, got 0")), exit_status(DataError("truncated"))
        (2, 1)
        >>> exit_status(FileNotFoundError(2, "No such file or directory", "model.ckpt"))
        2
    """
    own = getattr(type(err), "exit_status", None)  # a class that says, e.g. data.format.DatasetFormatError
    if isinstance(own, int):
        return own
    if isinstance(err, UsageError):
        return EXIT_USAGE
    if isinstance(err, (DataError, RuntimeError, EOFError, *_image_error())):
        return EXIT_DATA
    if isinstance(err, (FileNotFoundError, NotADirectoryError, IsADirectoryError)):
        return EXIT_USAGE
    if isinstance(err, OSError):  # permission, full disk, I/O error: the data or the system
        return EXIT_DATA
    return EXIT_USAGE  # a plain ValueError: an argument check


def one_line(err: BaseException) -> str:
    """The error as one line, the message ``lightning-vtr`` prints instead of a traceback.

    An ``OSError`` from the system names the file, what was expected and what was found; any other message has
    its lines joined. A ``KeyError`` or an empty message is prefixed with the exception's class name.

    Args:
        err: the exception caught.

    Returns:
        The message on one line, never empty.

    Example:
        >>> one_line(ValueError("first line\\n  second line"))
        'first line second line'
        >>> one_line(FileNotFoundError(2, "No such file or directory", "model.ckpt"))
        "'model.ckpt': No such file or directory"
        >>> one_line(KeyError("images"))
        "KeyError: 'images'"
    """
    if isinstance(err, OSError) and err.errno is not None and err.filename is not None and err.strerror:
        where = repr(os.fsdecode(err.filename))
        if err.errno == errno.ENOSPC:
            return f"cannot write {where}: expected free space on its disk, found the disk full (free space, re-run)"
        if err.errno in (errno.EACCES, errno.EPERM, errno.EROFS):
            return f"cannot write {where}: expected a location you may write to, found {err.strerror.lower()}"
        return f"{where}: {err.strerror}"
    if isinstance(err, OSError) and err.errno == errno.ENOSPC:
        return "cannot write the output: expected free space on its disk, found the disk full (free space, re-run)"
    text = " ".join(line.strip() for line in str(err).splitlines() if line.strip())
    if isinstance(err, KeyError) or not text:
        text = f"{type(err).__name__}: {text or 'no message'}"
    return text
