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

from lightning_vtr.metrics.functional import voxel_iou
from lightning_vtr.selection.base import SelectionContext, check_categories, view_set_losses
from lightning_vtr.selection.bins import sample_around_bins
from lightning_vtr.selection.projection import _soft_error_scores, projection_scores, visible_error_scores
from lightning_vtr.selection.volumes import check_volume_pair
from lightning_vtr.utils.validation import check_choice, check_float, check_int

__all__ = [
    "OBJECT_SCORES",
    "SCORES",
    "InputScore",
    "MapScore",
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
            return _soft_error_scores(
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


def _check_context(context: SelectionContext | None, names: tuple[str, ...], score: str, what: str) -> None:
    if context is None or any(getattr(context, name) is None for name in names):
        raise ValueError(
            f"ErrorGuidedSelector(score={score!r}) needs a SelectionContext with {', '.join(names)}: {what}; the "
            "ErrorGuidedViewAugmentation callback passes one"
        )


class InputScore(ViewScore):
    """The model's loss when it is given the object's image from that bin centre, alone.

    Every bin centre is synthesized and predicted from (a one-view set of
    :func:`~lightning_vtr.selection.base.view_set_losses`: one synthesizer call, model batches of at most
    ``model_batch_size``), so it needs a :class:`~lightning_vtr.selection.base.SelectionContext`: ``V_c``
    images and single-view predictions per object (72 at ``K = 30``).

    Args:
        model_batch_size: ``72`` (default): most single-view predictions per model call.

    Raises:
        TypeError, ValueError: ``model_batch_size`` is not an int ``>= 1``.
    """

    name: ClassVar[str] = "input"
    needs_context: ClassVar[bool] = True

    def __init__(self, model_batch_size: int = 72) -> None:
        self.model_batch_size = check_int("model_batch_size", model_batch_size, minimum=1)

    def settings(self) -> dict[str, Any]:
        """``model_batch_size``."""
        return {"model_batch_size": self.model_batch_size}

    @torch.no_grad()
    def __call__(
        self,
        predicted: Tensor,
        target: Tensor,
        categories: list[str],
        setup: ScoreSetup,
        context: SelectionContext | None = None,
        generator: torch.Generator | None = None,
    ) -> Tensor:
        """Losses ``(B, V_c)``, clamped at 0, dtype of ``predicted``.

        Raises:
            ValueError: no context (or one without model, synthesizer, transform or loss), a request count
                other than ``B``, or a synthesizer that returns another number of objects or images.
        """
        _check_context(
            context,
            ("model", "synthesizer", "transform", "loss_fn"),
            self.name,
            "it renders every candidate view and scores the model's loss on it",
        )
        assert context is not None
        batch, n_views = target.shape[0], setup.candidates.shape[0]
        if batch == 0:
            return target.new_zeros((0, n_views), dtype=predicted.dtype)
        # every bin centre is a one-view set: (B, V_c, 1, 2)
        sets = setup.candidates[None, :, None].expand(batch, -1, -1, -1)
        losses = view_set_losses(sets, target.float(), context, self.model_batch_size)
        return losses.float().clamp_min(0.0).to(predicted.dtype)


class MapScore(ViewScore):
    r"""The category's measured failure map: where the model fails on views of the category's objects.

    Per call, for up to ``objects`` objects of each category (the first of a seeded shuffle of the call's
    objects of that category), the model's :math:`1 - \mathrm{IoU}` (at the selector's threshold) given
    ``num_views`` views drawn around each bin centre, as the selector draws them around a chosen bin, is
    averaged over the category and blended into :attr:`category_maps` (``momentum``; a category's first
    measurement is taken whole). Every object of a category gets its category's map rescaled to ``[0, 1]``
    (worst bin 1, best bin 0; a flat map scores 0), so that a temperature acts on how the bins differ, not on
    the model's overall level. Each measured object costs ``V_c * num_views`` rendered images and ``V_c``
    predictions. The maps are the score's state (:meth:`state_dict`).

    Args:
        objects: ``2`` (default): the most objects of each category measured per call.
        momentum: ``0.3`` (default): weight of a call's measurement in the blended map, in ``(0, 1]``.
        model_batch_size: ``72`` (default): most view sets per model call.

    Raises:
        TypeError, ValueError: naming the argument and the bad value.
    """

    name: ClassVar[str] = "map"
    needs_context: ClassVar[bool] = True
    per_category: ClassVar[bool] = True

    def __init__(self, objects: int = 2, momentum: float = 0.3, model_batch_size: int = 72) -> None:
        self.objects = check_int("objects", objects, minimum=1)
        self.momentum = check_float("momentum", momentum, minimum=0.0, maximum=1.0, min_open=True)
        self.model_batch_size = check_int("model_batch_size", model_batch_size, minimum=1)
        #: Each category's blended failure map, ``(V_c,)`` float32 mean loss per bin.
        self.category_maps: dict[str, Tensor] = {}

    def settings(self) -> dict[str, Any]:
        """``objects``, ``momentum`` and ``model_batch_size``."""
        return {"objects": self.objects, "momentum": self.momentum, "model_batch_size": self.model_batch_size}

    @torch.no_grad()
    def __call__(
        self,
        predicted: Tensor,
        target: Tensor,
        categories: list[str],
        setup: ScoreSetup,
        context: SelectionContext | None = None,
        generator: torch.Generator | None = None,
    ) -> Tensor:
        """``(B, V_c)`` float32: each object's category map, rescaled to ``[0, 1]``.

        ``predicted`` is not used. ``generator`` draws the measured objects (a shuffle per category, in order of
        first appearance), then the views around the bins.

        Raises:
            ValueError: no context, or one without model, synthesizer or transform.
        """
        check_categories(categories, target.shape[0])
        _check_context(
            context,
            ("model", "synthesizer", "transform"),
            self.name,
            "it renders views around every bin and measures the model's IoU on them",
        )
        assert context is not None
        n_bins = setup.candidates.shape[0]
        rows_of = rows_by_category(categories)
        measured: dict[str, list[int]] = {}
        for category, rows in rows_of.items():
            order = torch.randperm(len(rows), generator=generator)[: self.objects]
            measured[category] = [rows[i] for i in sorted(order.tolist())]
        chosen = [row for rows in measured.values() for row in rows]
        if chosen:
            bins = torch.arange(n_bins)[None, :, None].expand(len(chosen), n_bins, setup.num_views)
            sets = sample_around_bins(bins, setup.k, sigma=setup.sigma, generator=generator).to(torch.float32)
            threshold = setup.threshold

            def iou_loss(pred: Tensor, reference: Tensor) -> Tensor:
                return 1.0 - voxel_iou(pred.float(), reference.float(), thresholds=(threshold,))[:, 0]

            measuring = dataclasses.replace(
                context, requests=[context.requests[row] for row in chosen], loss_fn=iou_loss
            )
            losses = view_set_losses(sets, target[chosen].float(), measuring, self.model_batch_size).float()
            start = 0
            for category, rows in measured.items():
                new = losses[start : start + len(rows)].mean(0)
                start += len(rows)
                old = self.category_maps.get(category)
                self.category_maps[category] = new if old is None else old + self.momentum * (new - old)
        scores = target.new_zeros((target.shape[0], n_bins), dtype=torch.float32)
        for category, rows in rows_of.items():
            loss = self.category_maps[category]
            spread = loss.max() - loss.min()
            if spread > 0:
                scores[rows] = ((loss - loss.min()) / spread).to(scores.device)
        return scores

    def state_dict(self) -> dict[str, Any]:
        """The blended category maps."""
        return {"category_maps": {name: m.clone() for name, m in self.category_maps.items()}}

    def load_state_dict(self, state: dict[str, Any], setup: ScoreSetup) -> None:
        """Restore the category maps :meth:`state_dict` returned.

        Raises:
            ValueError: a map of another length than the selector's ``V_c`` bins.
        """
        maps = state.get("category_maps", {})
        n_bins = setup.candidates.shape[0]
        for name, value in maps.items():
            if tuple(value.shape) != (n_bins,):
                raise ValueError(
                    f"The saved failure map of category {name!r} has shape {tuple(value.shape)}; this selector "
                    f"(k={setup.k}) has {n_bins} bins"
                )
        self.category_maps = {name: torch.as_tensor(value).float().clone() for name, value in maps.items()}


#: Score name -> score class with its defaults (``ErrorGuidedSelector(score=name)``).
SCORES: dict[str, type[ViewScore]] = {
    "paper": PaperScore,
    "released": ReleasedScore,
    "visible": VisibleScore,
    "input": InputScore,
    "map": MapScore,
}
#: The scores computed for one object alone from its prediction (and, for ``"input"``, its rendered views);
#: ``"map"`` is a property of a category, measured over several of its objects.
OBJECT_SCORES: tuple[str, ...] = ("paper", "released", "visible", "input")
