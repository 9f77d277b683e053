"""Research view scores of :class:`lightning_vtr.selection.ErrorGuidedSelector`: the input-side and category-map
scores, as :class:`lightning_vtr.selection.ViewScore` subclasses.

Pass an instance as the selector's ``score``, in Python or in a strategies file (``research/strategies.yaml``)::

    from lightning_vtr.selection import ErrorGuidedSelector
    from research.scores import MapScore

    selector = ErrorGuidedSelector(score=MapScore(objects=2), min_separation=30.0, temperature=None)

Both render views and query the model (``needs_context``), so they need the
:class:`~lightning_vtr.selection.SelectionContext` that
:class:`~lightning_vtr.callback.ErrorGuidedViewAugmentation` passes.
"""

from __future__ import annotations

import dataclasses
from typing import Any, ClassVar

import torch
from torch import Tensor

from lightning_vtr.metrics.functional import voxel_iou
from lightning_vtr.selection import SelectionContext, ViewScore, check_categories, sample_around_bins
from lightning_vtr.selection.base import view_set_losses
from lightning_vtr.selection.scores import ScoreSetup, rows_by_category
from lightning_vtr.utils.validation import check_float, check_int

__all__ = ["InputScore", "MapScore"]


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
