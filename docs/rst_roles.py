"""A griffe extension for the docs build: the package's docstrings use a little reStructuredText, which
Markdown would show as written. Every docstring griffe loads is rewritten before it is rendered:

* roles (``:class:`~lightning_vtr.data.VTRDataModule```, ``:func:`f```) become inline code holding the name as
  the role's tilde form shows it; ``:math:`E``` becomes inline math (``$E$``, rendered by arithmatex and MathJax);
* a ``.. math::`` directive and its indented block become a display-math block (``$$ ... $$``);
* ``Example::`` (or ``Examples::``) and its indented block become an ``Example:`` section holding a fenced
  ``python`` block, so it is highlighted; an ``Example:`` section of ``>>>`` lines becomes a fenced ``pycon``
  block (Markdown would read ``>>>`` as quotes); any other paragraph ending in ``::`` keeps one ``:`` and its
  indented literal block becomes a fenced ``text`` block.

The package's ``.py`` files stay as they are: this runs in the docs build only (``mkdocs.yml``, the
mkdocstrings python handler's ``extensions``).
"""

from __future__ import annotations

import re
from typing import Any

import griffe

_ROLE = re.compile(r":(?:py:)?(class|func|meth|mod|data|attr|exc|obj|const|math|paramref|ref):`(~?)([^`]+)`")
_MATH = re.compile(r"^(?P<indent>[ \t]*)\.\. math::[ \t]*(?P<rest>.*)$")
_LITERAL = re.compile(r"^(?P<indent>[ \t]*)(?P<text>.*?)::[ \t]*$")
_EXAMPLE_TITLES = {"example", "examples"}


def _replace_role(match: re.Match[str]) -> str:
    role, tilde, target = match.groups()
    if role == "math":
        return f"${target}$"
    if tilde:
        target = target.rsplit(".", 1)[-1]
    return f"`{target}`"


def _width(line: str) -> int:
    return len(line) - len(line.lstrip())


def _block(lines: list[str], start: int, indent: int) -> tuple[list[str], int]:
    """The indented block after line ``start - 1``: blank lines and lines indented past ``indent``, dedented,
    blank lines at either end dropped; and the index of the first line after it."""
    end = start
    while end < len(lines) and (not lines[end].strip() or _width(lines[end]) > indent):
        end += 1
    while end > start and not lines[end - 1].strip():
        end -= 1  # trailing blank lines belong to what follows
    body = lines[start:end]
    depth = min((_width(line) for line in body if line.strip()), default=indent)
    block = [line[depth:] if line.strip() else "" for line in body]
    while block and not block[0]:
        block.pop(0)
    return block, end


def rewrite(docstring: str) -> str:
    """``docstring`` with its reST roles, ``.. math::`` directives and ``::`` literal blocks as Markdown.

    Example:
        >>> print(rewrite("Example::\\n\\n    f(1)\\n"))
        Example:
            ```python
            f(1)
            ```
    """
    lines = docstring.splitlines()
    out: list[str] = []
    i = 0
    while i < len(lines):
        line = lines[i]
        math = _MATH.match(line)
        literal = None if math or line.lstrip().startswith("..") else _LITERAL.match(line)
        if math:
            pad = math.group("indent")
            block, i = _block(lines, i + 1, len(pad))
            first = [math.group("rest")] if math.group("rest").strip() else []
            out += ["", f"{pad}$$", *(f"{pad}{text}" for text in first + block), f"{pad}$$", ""]
            continue
        title = line.strip()
        if title.rstrip(":").lower() in _EXAMPLE_TITLES and title.endswith(":") and not title.endswith("::"):
            pad = line[: _width(line)]
            block, end = _block(lines, i + 1, len(pad))
            if block and block[0].startswith(">>>"):  # a doctest: a highlighted console session
                inner = pad + "    "
                out += [line, f"{inner}```pycon", *(f"{inner}{code}" if code else "" for code in block), f"{inner}```"]
                i = end
                continue
        if literal and i + 1 < len(lines):
            pad, text = literal.group("indent"), literal.group("text")
            block, end = _block(lines, i + 1, len(pad))
            if block:
                i = end
                if text.strip().lower() in _EXAMPLE_TITLES:
                    inner = pad + "    "
                    out += [f"{pad}{text.strip()}:", f"{inner}```python"]
                    out += [f"{inner}{code}" if code else "" for code in block] + [f"{inner}```"]
                else:
                    if text.strip():
                        out += [f"{pad}{text.rstrip()}:", ""]
                    out += [f"{pad}```text", *(f"{pad}{code}" if code else "" for code in block), f"{pad}```"]
                continue
        out.append(line)
        i += 1
    return _ROLE.sub(_replace_role, "\n".join(out))


class RstRoles(griffe.Extension):
    """Rewrites every docstring griffe loads with :func:`rewrite`."""

    def on_instance(self, *, obj: Any, **kwargs: Any) -> None:
        if obj.docstring is not None:
            obj.docstring.value = rewrite(obj.docstring.value)
