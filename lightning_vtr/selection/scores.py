"""The view scores of :class:`~lightning_vtr.selection.error_guided.ErrorGuidedSelector`, one class per score.

A score rates every candidate viewpoint (bin centre) of every object: ``(B, V_c)``, higher where the model
should see more. Each class holds the options that apply to its score alone; the selector holds what every
score shares (bin interval, threshold, how bins are chosen). :data:`SCORES` names them for configs.

Example:
    >>> from lightning_vtr.selection import ErrorGuidedSelector
    >>> ErrorGuidedSelector(score=ReleasedScore(eps=0.1)).score_options.settings()
    {'mode': 'soft', 'mask': 'gt', 'reduction': 'mean', 'eps': 0.1}
"""

from __future__ import annotations

import abc
import dataclasses
from typing import Any, ClassVar, Literal

import torch
from torch import Tensor

from lightning_vtr.selection.base import SelectionContext
from lightning_vtr.selection.projection import projection_scores, soft_error_scores, visible_error_scores
from lightning_vtr.selection.volumes import check_volume_pair
from lightning_vtr.utils.validation import check_choice, check_float

__all__ = [
    "SCORES",
    "PaperScore",
    "ProjectionScore",
    "ReleasedScore",
    "ScoreSetup",
    "ViewScore",
    "VisibleScore",
    "rows_by_category",
]


def rows_by_category(categories: list[str]) -> dict[str, list[int]]:
    """The batch rows of each category, categories in order of first appearance.

    Args:
        categories: the category of each batch row.

    Returns:
        ``{category: [row, ...]}``, in order of first appearance.

    Example:
        >>> rows_by_category(["chair", "table", "chair"])
        {'chair': [0, 2], 'table': [1]}
    """
    rows_of: dict[str, list[int]] = {}
    for row, category in enumerate(categories):
        rows_of.setdefault(category, []).append(row)
    return rows_of


@dataclasses.dataclass(frozen=True)
class ScoreSetup:
    """What a score takes from its selector: the bins, the views per object and the threshold.

    Attributes:
        k: bin interval ``K`` in degrees.
        candidates: ``(V_c, 2)`` bin-centre viewpoints in degrees (``candidate_viewpoints(k)``).
        num_views: views the selector draws around a chosen bin.
        sigma: standard deviation in degrees of those draws.
        threshold: occupancy threshold of the predictions.

    Example:
        >>> from lightning_vtr.geometry import candidate_viewpoints
        >>> setup = ScoreSetup(k=30, candidates=candidate_viewpoints(30), num_views=3, sigma=5.0, threshold=0.4)
        >>> setup.candidates.shape  # 12 yaw x 6 pitch bins
        torch.Size([72, 2])
    """

    k: int
    candidates: Tensor
    num_views: int
    sigma: float
    threshold: float


class ViewScore(abc.ABC):
    """One view score: ``(B, V_c)`` ratings of the candidate viewpoints of a batch of objects.

    A subclass sets :attr:`name` and the class attributes below, implements :meth:`__call__` and
    :meth:`settings` (its constructor arguments), and overrides :meth:`state_dict` / :meth:`load_state_dict`
    if it learns across calls.

    Example:
        >>> class TopDown(ViewScore):  # prefers views from above, whatever the error
        ...     name = "top_down"
        ...     def __call__(self, predicted, target, categories, setup, context=None, generator=None):
        ...         return (setup.candidates[:, 1] + 90.0).expand(len(predicted), -1)
        ...     def settings(self):
        ...         return {}
        >>> TopDown()
        TopDown()
    """

    #: The score's name in :data:`SCORES` (``ErrorGuidedSelector(score=name)``).
    name: ClassVar[str]
    #: Whether the score renders views and queries the model (needs a :class:`SelectionContext`).
    needs_context: ClassVar[bool] = False
    #: Whether the score rates a category from several of its objects rather than each object alone; the
    #: selector is then ``batched`` and cannot be ``relative``.
    per_category: ClassVar[bool] = False

    @abc.abstractmethod
    def __call__(
        self,
        predicted: Tensor,
        target: Tensor,
        categories: list[str],
        setup: ScoreSetup,
        context: SelectionContext | None = None,
        generator: torch.Generator | None = None,
    ) -> Tensor:
        """Scores ``(B, V_c)`` for predictions / targets ``(B, R, R, R)``, ``>= 0``, ``setup.candidates`` order."""

    @abc.abstractmethod
    def settings(self) -> dict[str, Any]:
        """The score's constructor arguments, as plain JSON values."""

    def state_dict(self) -> dict[str, Any]:
        """Learned state to checkpoint (empty for the scores that keep none)."""
        return {}

    def load_state_dict(self, state: dict[str, Any], setup: ScoreSetup) -> None:  # noqa: B027 (stateless: no-op)
        """Restore what :meth:`state_dict` returned."""

    def __repr__(self) -> str:
        items = ", ".join(f"{name}={value!r}" for name, value in self.settings().items())
        return f"{type(self).__name__}({items})"

    def __eq__(self, other: object) -> bool:
        return isinstance(other, ViewScore) and type(other) is type(self) and other.settings() == self.settings()

    def __hash__(self) -> int:
        return hash((type(self).__name__, repr(self)))


class ProjectionScore(ViewScore):
    """The error volume's first-hit projection onto each bin centre, reduced over its pixels.

    The error :math:`E = |V - V^{gt}|` (``mode``; ``mask="gt"`` keeps the errors inside ground-truth voxels) is
    projected onto every candidate view (first hit along each ray of the voxels above ``eps``) and each view's
    map is reduced (``"sum"`` or ``"mean"`` over hit pixels; 0 for an empty map). :class:`PaperScore` and
    :class:`ReleasedScore` are its two named settings.

    Args:
        mode: ``"binary"`` (default: error at the selector's threshold, each hit worth 1) or ``"soft"``.
        mask: ``"none"`` (default: every error) or ``"gt"`` (errors inside ground-truth voxels only).
        reduction: ``"sum"`` (default) or ``"mean"`` over hit pixels.
        eps: ``0.0`` (default): error values ``<= eps`` are transparent to the projection (matters for
            ``mode="soft"``).

    Raises:
        TypeError: an argument of the wrong type.
        ValueError: naming the argument and the bad value.

    Example:
        >>> ProjectionScore(reduction="mean")
        ProjectionScore(mode='binary', mask='none', reduction='mean', eps=0.0)
    """

    name: ClassVar[str] = "projection"

    def __init__(
        self,
        mode: Literal["binary", "soft"] = "binary",
        mask: Literal["none", "gt"] = "none",
        reduction: Literal["sum", "mean"] = "sum",
        eps: float = 0.0,
    ) -> None:
        self.mode: Literal["binary", "soft"] = check_choice("mode", mode, ("binary", "soft"))
        self.mask: Literal["none", "gt"] = check_choice("mask", mask, ("none", "gt"))
        self.reduction = check_choice("reduction", reduction, ("sum", "mean"))
        self.eps = check_float("eps", eps, minimum=0.0, maximum=1.0, max_open=True)

    def settings(self) -> dict[str, Any]:
        """``mode``, ``mask``, ``reduction`` and ``eps``."""
        return {"mode": self.mode, "mask": self.mask, "reduction": self.reduction, "eps": self.eps}

    def __call__(
        self,
        predicted: Tensor,
        target: Tensor,
        categories: list[str],
        setup: ScoreSetup,
        context: SelectionContext | None = None,
        generator: torch.Generator | None = None,
    ) -> Tensor:
        """Scores ``(B, V_c)``, dtype of ``predicted`` (``categories``, ``context``, ``generator`` unused)."""
        predicted, target = check_volume_pair(predicted, target)
        candidates = setup.candidates.to(predicted.device)
        mask: Literal["gt"] | None = "gt" if self.mask == "gt" else None
        if self.mode == "soft":
            # the soft error does not depend on the threshold: scored without building the error volume first
            return soft_error_scores(
                predicted, target, candidates, mask=mask, reduction=self.reduction, eps=self.eps
            ).to(predicted.dtype)
        # the {0, 1} error as bool: skips a float conversion of the grids
        errors = (predicted >= setup.threshold) != (target >= 0.5)
        if mask == "gt":
            errors &= target >= 0.5
        # equal to view_scores(error_projection(errors, candidates, eps=eps)) without the (B, V, R, R) maps
        return projection_scores(errors, candidates, reduction=self.reduction, eps=self.eps, binary=True).to(
            predicted.dtype
        )


class PaperScore(ProjectionScore):
    """The paper's score: binary error, summed over the first-hit map (:class:`ProjectionScore`'s defaults).

    Every hit is worth 1, so a view's score is the area of the error's silhouette, the same for a view and
    its antipode.

    Args:
        mode: ``"binary"`` (default) or ``"soft"``.
        mask: ``"none"`` (default) or ``"gt"``.
        reduction: ``"sum"`` (default) or ``"mean"``.
        eps: ``0.0`` (default): transparency threshold of the projection.

    Example:
        >>> from lightning_vtr.selection import ErrorGuidedSelector
        >>> ErrorGuidedSelector.paper().score_options
        PaperScore(mode='binary', mask='none', reduction='sum', eps=0.0)
    """

    name: ClassVar[str] = "paper"


class ReleasedScore(ProjectionScore):
    """The authors' released code's score: soft error inside ground-truth voxels, mean over hit pixels.

    Side-aware: it averages the error on the visible ground-truth surface.

    Args:
        mode: ``"soft"`` (default) or ``"binary"``.
        mask: ``"gt"`` (default) or ``"none"``.
        reduction: ``"mean"`` (default) or ``"sum"``.
        eps: ``0.0`` (default): transparency threshold of the projection.

    Example:
        >>> ReleasedScore()
        ReleasedScore(mode='soft', mask='gt', reduction='mean', eps=0.0)
    """

    name: ClassVar[str] = "released"

    def __init__(
        self,
        mode: Literal["binary", "soft"] = "soft",
        mask: Literal["none", "gt"] = "gt",
        reduction: Literal["sum", "mean"] = "mean",
        eps: float = 0.0,
    ) -> None:
        super().__init__(mode=mode, mask=mask, reduction=reduction, eps=eps)


class VisibleScore(ViewScore):
    """What a camera at each bin centre would see wrong (side-aware).

    The first hit along each ray on the union of predicted (at the selector's threshold) and ground-truth
    occupancy, valued by the error there, summed over pixels
    (:func:`~lightning_vtr.selection.projection.visible_error_scores`).

    Args:
        mode: ``"binary"`` (default: the error is 1 where prediction and truth disagree) or ``"soft"``
            (``|predicted - target|`` at the visible voxel).

    Raises:
        ValueError: an unknown ``mode``.

    Example:
        >>> from lightning_vtr.selection import ErrorGuidedSelector
        >>> ErrorGuidedSelector().score_options  # the default rule's score
        VisibleScore(mode='binary')
    """

    name: ClassVar[str] = "visible"

    def __init__(self, mode: Literal["binary", "soft"] = "binary") -> None:
        self.mode = check_choice("mode", mode, ("binary", "soft"))

    def settings(self) -> dict[str, Any]:
        """``mode``."""
        return {"mode": self.mode}

    def __call__(
        self,
        predicted: Tensor,
        target: Tensor,
        categories: list[str],
        setup: ScoreSetup,
        context: SelectionContext | None = None,
        generator: torch.Generator | None = None,
    ) -> Tensor:
        """Scores ``(B, V_c)``, dtype of ``predicted`` (``categories``, ``context``, ``generator`` unused)."""
        predicted, target = check_volume_pair(predicted, target)
        return visible_error_scores(
            predicted, target, setup.candidates.to(predicted.device), threshold=setup.threshold, mode=self.mode
        )


SCORES: dict[str, type[ViewScore]] = {
    "paper": PaperScore,
    "released": ReleasedScore,
    "visible": VisibleScore,
}
"""Score name -> score class, built with its defaults by ``ErrorGuidedSelector(score=name)``."""
