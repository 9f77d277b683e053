"""View selection: the paper's error-guided selector and viewpoint pool, and the comparison strategies."""

from __future__ import annotations

from typing import TYPE_CHECKING

from lightning_vtr.utils.exports import lazy_exports

if TYPE_CHECKING:  # what type checkers, IDEs and the API reference read
    from lightning_vtr.selection.base import SelectionContext, ViewSelector, check_categories
    from lightning_vtr.selection.bins import nearest_bins, sample_around_bins, select_views, top_bins
    from lightning_vtr.selection.differentiable_projection import soft_error_projection
    from lightning_vtr.selection.error_guided import ErrorGuidedSelector
    from lightning_vtr.selection.mvtn import MVTNSelector
    from lightning_vtr.selection.nature import NatureSelector
    from lightning_vtr.selection.pool import ViewpointPool
    from lightning_vtr.selection.projection import (
        error_projection,
        projection_scores,
        view_scores,
        visible_error_scores,
    )
    from lightning_vtr.selection.random_selector import RandomSelector
    from lightning_vtr.selection.registry import SELECTORS, make_selector
    from lightning_vtr.selection.scores import (
        SCORES,
        PaperScore,
        ProjectionScore,
        ReleasedScore,
        ViewScore,
        VisibleScore,
    )
    from lightning_vtr.selection.viat import VIATSelector
    from lightning_vtr.selection.volumes import check_volume_pair, check_volumes, error_volume
else:  # at run time each name is imported from its module on first use
    __getattr__, __dir__ = lazy_exports(
        __name__,
        {
            "lightning_vtr.selection.base": ["SelectionContext", "ViewSelector", "check_categories"],
            "lightning_vtr.selection.bins": ["nearest_bins", "sample_around_bins", "select_views", "top_bins"],
            "lightning_vtr.selection.differentiable_projection": ["soft_error_projection"],
            "lightning_vtr.selection.error_guided": ["ErrorGuidedSelector"],
            "lightning_vtr.selection.mvtn": ["MVTNSelector"],
            "lightning_vtr.selection.nature": ["NatureSelector"],
            "lightning_vtr.selection.pool": ["ViewpointPool"],
            "lightning_vtr.selection.projection": [
                "error_projection",
                "projection_scores",
                "view_scores",
                "visible_error_scores",
            ],
            "lightning_vtr.selection.random_selector": ["RandomSelector"],
            "lightning_vtr.selection.registry": ["SELECTORS", "make_selector"],
            "lightning_vtr.selection.scores": [
                "SCORES",
                "PaperScore",
                "ProjectionScore",
                "ReleasedScore",
                "ViewScore",
                "VisibleScore",
            ],
            "lightning_vtr.selection.viat": ["VIATSelector"],
            "lightning_vtr.selection.volumes": ["check_volume_pair", "check_volumes", "error_volume"],
        },
    )

__all__ = [
    "SCORES",
    "SELECTORS",
    "ErrorGuidedSelector",
    "MVTNSelector",
    "NatureSelector",
    "PaperScore",
    "ProjectionScore",
    "RandomSelector",
    "ReleasedScore",
    "SelectionContext",
    "VIATSelector",
    "ViewScore",
    "ViewSelector",
    "ViewpointPool",
    "VisibleScore",
    "check_categories",
    "check_volume_pair",
    "check_volumes",
    "error_projection",
    "error_volume",
    "make_selector",
    "nearest_bins",
    "projection_scores",
    "sample_around_bins",
    "select_views",
    "soft_error_projection",
    "top_bins",
    "view_scores",
    "visible_error_scores",
]
