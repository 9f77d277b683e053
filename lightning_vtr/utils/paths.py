"""Names read from data become paths only through these checks, and paths written under a folder stay in it.

A dataset, a Pix3D copy or a prediction folder from someone else is untrusted input: a category, an object id
or a view-set name read from its files must be one plain path component, so that ``root / name`` names a file
inside ``root``. Readers call :func:`check_name` / :func:`check_object_key` (and :func:`check_no_case_collisions`
on a whole listing) where they read a name; writers build every path under a user-given folder with
:func:`join_under`, which refuses a result that resolves outside that folder (symlinks included).

A plain component is a non-empty string that is not ``.`` or ``..``, holds no ``/`` or ``\\``, is not an
absolute or drive path (``C:``), holds no NUL or other control character (Unicode category ``Cc``) and does
not start with ``-`` (it would read as an option to a shell tool). Two names of one listing that differ only
in case (``Chair`` and ``chair``) or in Unicode normalization (``é`` as one code point, NFC, or as ``e`` and a
combining accent, NFD) are refused too: on a case-insensitive or normalizing file system (macOS, Windows)
they would be one folder, so one object would overwrite the other.

A name printed to a terminal goes through :func:`printable`, which escapes control and other invisible
characters, so a name holding an ANSI escape sequence cannot rewrite what the terminal shows.
"""

from __future__ import annotations

import os
import unicodedata
from collections.abc import Iterable
from pathlib import Path, PureWindowsPath

__all__ = [
    "RULES",
    "UnsafeNameError",
    "UnsafePathError",
    "check_name",
    "check_no_case_collisions",
    "check_object_key",
    "check_relative_path",
    "join_under",
    "name_rule",
    "printable",
]

#: The rules a plain path component must follow: rule id -> what the rule says (the text of the messages).
RULES: dict[str, str] = {
    "type": "must be a string",
    "empty": "must not be empty",
    "dot": "must not be '.' or '..', which name the folder itself or its parent",
    "separator": "must not contain '/' or '\\', the path separators",
    "absolute": "must not be an absolute or drive path",
    "control": "must not contain NUL or control characters",
    "dash": "must not start with '-', which reads as an option",
    "key": "must be '<category>/<object_id>' with exactly one '/'",
    "case": "must not differ only in case (or Unicode normalization) from another name of the same listing, as "
    "both would be one folder on a case-insensitive file system",
}


class UnsafeNameError(ValueError):
    """A name read from a file is not a plain path component (exit status 1).

    The message is one line, ``"<file>: <entry> <name!r>: <rule>"``.

    Attributes:
        source: the file the name was read from.
        entry: what the name is in that file (``"object key"``, ``"category"``, ``"view set"``, ...).
        name: the name as read.
        rule: the id of the rule it breaks, a key of :data:`RULES`.
        reason: what the rule says, with what in the name breaks it (the message after the name).
    """

    #: ``lightning-vtr``'s exit status for it: a data error (see :mod:`lightning_vtr.errors`).
    exit_status = 1

    def __init__(self, source: str | os.PathLike, entry: str, name: object, rule: str, detail: str = "") -> None:
        self.source = os.fspath(source)
        self.entry = entry
        self.name = name
        self.rule = rule
        self.reason = RULES[rule] + (f" ({detail})" if detail else "")
        super().__init__(f"{self.source}: {entry} {name!r}: {self.reason}")


class UnsafePathError(ValueError):
    """A path joined from a root and names resolves outside the root (exit status 1).

    Attributes:
        root: the folder the path had to stay in.
        path: the joined path that leaves it.
    """

    exit_status = 1

    def __init__(self, root: Path, path: Path) -> None:
        self.root = root
        self.path = path
        super().__init__(
            f"{path}: expected a path inside {root}, found one that resolves to {path.resolve()} "
            "(a name with '..', an absolute name or a symlink that leads out); nothing was written there"
        )


def name_rule(name: object) -> tuple[str, str] | None:
    """The rule ``name`` breaks as a plain path component, or ``None`` if it is one.

    Returns:
        ``(rule id, detail)``: the key of :data:`RULES` and what in ``name`` breaks it (may be empty).

    Example:
        >>> name_rule("chair"), name_rule("..")
        (None, ('dot', ''))
    """
    if not isinstance(name, str):
        return "type", f"found {type(name).__name__}"
    if not name:
        return "empty", ""
    if name in (".", ".."):
        return "dot", ""
    for i, char in enumerate(name):
        if unicodedata.category(char) == "Cc":
            return "control", f"found {char!r} at index {i}"
    for sep in ("/", "\\"):
        if sep in name:
            return "separator", f"found {sep!r} at index {name.index(sep)}"
    if os.path.isabs(name) or PureWindowsPath(name).drive:
        return "absolute", ""
    if name.startswith("-"):
        return "dash", ""
    return None


def check_name(name: str, *, source: str | os.PathLike, entry: str) -> str:
    """``name`` if it is one plain path component (see the module docstring), else :class:`UnsafeNameError`.

    Args:
        name: the name as read.
        source: the file it was read from (named in the message).
        entry: what the name is in that file, e.g. ``"category"`` or ``"view set"``.

    Returns:
        ``name`` unchanged.

    Raises:
        UnsafeNameError: ``"<source>: <entry> <name!r>: <rule>"``.

    Example:
        >>> check_name("chair", source="metadata.json", entry="category")
        'chair'
        >>> check_name("../x", source="metadata.json", entry="category")
        Traceback (most recent call last):
        ...
        lightning_vtr.utils.paths.UnsafeNameError: metadata.json: category '../x': must not contain '/' or '\\', the path separators (found '/' at index 2)
    """
    broken = name_rule(name)
    if broken is not None:
        raise UnsafeNameError(source, entry, name, *broken)
    return name


def check_object_key(key: str, *, source: str | os.PathLike, entry: str) -> tuple[str, str]:
    """``(category, object_id)`` of a key ``'<category>/<object_id>'`` whose two parts are plain components.

    Args:
        key: the key as read, e.g. ``"chair/c0"``.
        source: the file it was read from.
        entry: what the key is in that file, e.g. ``"object key"``.

    Returns:
        ``(category, object_id)``.

    Raises:
        UnsafeNameError: the key has not exactly one ``/`` or a part is not a plain component; the message
            names the part and the rule.

    Example:
        >>> check_object_key("chair/c0", source="metadata.json", entry="object key")
        ('chair', 'c0')
    """
    if not isinstance(key, str):
        raise UnsafeNameError(source, entry, key, "type", f"found {type(key).__name__}")
    if key.startswith(("/", "\\")) or PureWindowsPath(key).drive:
        raise UnsafeNameError(source, entry, key, "absolute")
    if any(part in (".", "..") for part in key.split("/")):
        raise UnsafeNameError(source, entry, key, "dot", "its part '..'" if ".." in key.split("/") else "its part '.'")
    if key.count("/") != 1:
        raise UnsafeNameError(source, entry, key, "key", f"found {key.count('/')}")
    category, object_id = key.split("/")
    for part, value in (("category", category), ("object id", object_id)):
        broken = name_rule(value)
        if broken is not None:
            rule, detail = broken
            raise UnsafeNameError(source, entry, key, rule, f"its {part} {value!r}" + (f", {detail}" if detail else ""))
    return category, object_id


def check_relative_path(path: str, *, source: str | os.PathLike, entry: str) -> str:
    """``path`` if it is a relative path of plain components separated by ``/`` (e.g. ``"img/chair/0001.png"``).

    Args:
        path: the path as read from a file.
        source: the file it was read from.
        entry: what the path is in that file, e.g. ``"key 'img'"``.

    Returns:
        ``path`` unchanged.

    Raises:
        UnsafeNameError: ``path`` is absolute, or one of its components is not a plain component.

    Example:
        >>> check_relative_path("img/chair/0001.png", source="pix3d.json", entry="key 'img'")
        'img/chair/0001.png'
    """
    if not isinstance(path, str):
        raise UnsafeNameError(source, entry, path, "type", f"found {type(path).__name__}")
    if path.startswith(("/", "\\")) or PureWindowsPath(path).drive:
        raise UnsafeNameError(source, entry, path, "absolute")
    for part in path.split("/"):
        broken = name_rule(part)
        if broken is not None:
            rule, detail = broken
            raise UnsafeNameError(source, entry, path, rule, f"its part {part!r}" + (f", {detail}" if detail else ""))
    return path


def check_no_case_collisions(names: Iterable[str], *, source: str | os.PathLike, entry: str) -> None:
    """Refuse two names of one listing that differ only in case (one folder on a case-insensitive file system).

    Names are compared after ``unicodedata.normalize("NFC", name).casefold()``, so two spellings of one name
    in different Unicode normal forms (NFC ``"\u00e9"`` and NFD ``"e\u0301"``) collide as well. Object keys
    ``'<category>/<object_id>'`` are compared part by part: two categories that differ only in case collide,
    and so do two object ids of one category.

    Raises:
        UnsafeNameError: the second name of the first colliding pair, with the first named in the message.

    Example:
        >>> check_no_case_collisions(["chair/a", "Chair/b"], source="metadata.json", entry="object key")
        Traceback (most recent call last):
        ...
        lightning_vtr.utils.paths.UnsafeNameError: metadata.json: object key 'Chair/b': must not differ only in case (or Unicode normalization) from another name of the same listing, as both would be one folder on a case-insensitive file system (its category 'Chair' against 'chair/a')
    """
    seen: dict[str, tuple[str, str]] = {}  # casefolded prefix -> (prefix as written, full name)
    for name in names:
        parts = name.split("/")
        for depth in range(1, len(parts) + 1):
            prefix = "/".join(parts[:depth])
            folded = unicodedata.normalize("NFC", prefix).casefold()
            first = seen.setdefault(folded, (prefix, name))
            if first[0] != prefix:
                what = f"its category {prefix!r}" if depth < len(parts) else "it"
                raise UnsafeNameError(source, entry, name, "case", f"{what} against {first[1]!r}")


def printable(text: str) -> str:
    """``text`` with every character a terminal would not show as itself escaped as ``repr`` escapes it.

    Control characters (ESC of an ANSI escape sequence, a carriage return, a newline), format characters
    (a right-to-left override) and other non-printable characters become ``\\x1b``, ``\\r``, ``\\u202e``, ...;
    letters of any script and spaces are kept.

    Example:
        >>> printable("chair\\x1b[2Jx"), printable("Stühle")
        ('chair\\\\x1b[2Jx', 'Stühle')
    """
    if text.isprintable():
        return text
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)


def join_under(root: str | os.PathLike, *parts: str, replace_link: bool = False) -> Path:
    """``root`` joined with ``parts``; refused if the result does not resolve to a path inside ``root``.

    Both sides are resolved (symlinks followed, ``..`` collapsed) before the comparison, so a part with
    ``..``, an absolute part or a symlink inside ``root`` that points out of it is refused. ``root`` itself
    may be a symlink. The returned path is the unresolved join, so messages show the path the user expects.

    Args:
        root: the folder every written path must stay in (an output folder, a dataset root).
        parts: the names to append; each may hold ``/`` (e.g. a checked ``'<category>/<object_id>'`` key).
        replace_link: the last part names a file the caller writes whole through :mod:`lightning_vtr.utils.io`
            (``os.replace``), which replaces a symlink standing there instead of following it: that symlink
            is not followed here either, so an earlier output whose files are links is written again with
            regular files. Its folders are still resolved and checked.

    Returns:
        ``Path(root, *parts)``.

    Raises:
        UnsafePathError: the result resolves to ``root``'s parent or anywhere else outside ``root``.

    Example:
        >>> join_under("out", "chair", "c0").as_posix()
        'out/chair/c0'
        >>> join_under("out", "chair/../../etc")
        Traceback (most recent call last):
        ...
        lightning_vtr.utils.paths.UnsafePathError: ...
    """
    base = Path(root)
    path = base.joinpath(*parts)
    resolved_root = base.resolve()
    if replace_link and path.name not in ("", ".", ".."):
        resolved = path.parent.resolve() / path.name
    else:
        resolved = path.resolve()
    if resolved != resolved_root and resolved_root not in resolved.parents:
        raise UnsafePathError(base, path)
    return path
