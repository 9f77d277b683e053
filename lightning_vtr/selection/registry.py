"""The one registry of view strategies, by the names the harness, the CLI and YAML configs use."""

from __future__ import annotations

from typing import Any

from lightning_vtr.selection.base import ViewSelector
from lightning_vtr.selection.error_guided import ErrorGuidedSelector
from lightning_vtr.selection.mvtn import MVTNSelector
from lightning_vtr.selection.nature import NatureSelector
from lightning_vtr.selection.random_selector import RandomSelector
from lightning_vtr.selection.viat import VIATSelector
from lightning_vtr.utils.validation import check_choice

__all__ = ["SELECTORS", "make_selector"]

#: Strategy name -> selector class, in the row order of the paper's Table 1 ("none", no augmentation,
#: is the harness's baseline and has no selector).
SELECTORS: dict[str, type[ViewSelector]] = {
    "nature": NatureSelector,
    "random": RandomSelector,
    "viat": VIATSelector,
    "mvtn": MVTNSelector,
    "error_guided": ErrorGuidedSelector,
}


def make_selector(name: str, **kwargs: Any) -> ViewSelector:
    """The selector registered as ``name``, built with ``kwargs``.

    Raises:
        ValueError: ``name`` is not in :data:`SELECTORS`.
    """
    return SELECTORS[check_choice("name", name, SELECTORS)](**kwargs)
