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

__all__ = ["SELECTORS", "SELECTOR_PRESETS", "make_selector"]

SELECTORS: dict[str, type[ViewSelector]] = {
    "nature": NatureSelector,
    "random": RandomSelector,
    "viat": VIATSelector,
    "mvtn": MVTNSelector,
    "error_guided": ErrorGuidedSelector,
}
"""Strategy name -> selector class, in the row order of the paper's Table 1 ("none", no augmentation,
is the harness's baseline and has no selector)."""

#: Named settings of a selector: name -> (a name in :data:`SELECTORS`, its arguments). ``"paper"`` is the
#: paper's exact rule: binary error summed over the first-hit map, the hard top n bins, no suppression of
#: neighbouring bins (``ErrorGuidedSelector.paper()``). ``ErrorGuidedViewAugmentation(selector="paper")`` gives this
#: selector alone; the paper's whole rule, with its callback settings, is
#: :meth:`~lightning_vtr.callback.ErrorGuidedViewAugmentation.paper`.
SELECTOR_PRESETS: dict[str, tuple[str, dict[str, Any]]] = {
    "paper": ("error_guided", {"score": "paper", "min_separation": None, "temperature": None}),
}


def make_selector(name: str, **kwargs: Any) -> ViewSelector:
    """The selector registered as ``name``, built with ``kwargs``.

    Args:
        name: a name in :data:`SELECTORS` (the class with its defaults) or in :data:`SELECTOR_PRESETS` (its
            class with the preset's arguments).
        kwargs: arguments of the selector class; over a preset's.

    Returns:
        A new instance of the registered :class:`~lightning_vtr.selection.base.ViewSelector` subclass.

    Raises:
        ValueError: ``name`` is in neither :data:`SELECTORS` nor :data:`SELECTOR_PRESETS`.

    Example:
        >>> selector = make_selector("paper")  # ErrorGuidedSelector(score="paper", min_separation=None, ...)
        >>> type(selector).__name__, selector.score
        ('ErrorGuidedSelector', 'paper')
        >>> make_selector("random", mode="area").mode
        'area'
    """
    check_choice("name", name, [*SELECTORS, *SELECTOR_PRESETS])
    if name in SELECTOR_PRESETS:
        base, preset = SELECTOR_PRESETS[name]
        return SELECTORS[base](**{**preset, **kwargs})
    return SELECTORS[name](**kwargs)
