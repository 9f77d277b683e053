"""A griffe extension for the docs build: the package's docstrings cite names with reStructuredText roles
(``:class:`~lightning_vtr.data.VTRDataModule```, ``:func:`f```, ``:math:`E```), which Markdown would show
as written. Each role becomes inline code holding the name as the role's tilde form shows it."""

from __future__ import annotations

import re
from typing import Any

import griffe

_ROLE = re.compile(r":(?:py:)?(class|func|meth|mod|data|attr|exc|obj|const|math|paramref|ref):`(~?)([^`]+)`")


def _replace(match: re.Match[str]) -> str:
    role, tilde, target = match.groups()
    if role != "math" and tilde:
        target = target.rsplit(".", 1)[-1]
    return f"`{target}`"


class RstRoles(griffe.Extension):
    """Rewrites the roles of every docstring griffe loads."""

    def on_instance(self, *, obj: Any, **kwargs: Any) -> None:
        if obj.docstring is not None:
            obj.docstring.value = _ROLE.sub(_replace, obj.docstring.value)
