"""The paper's reconstruction error-guided view selector (Sec. "View selection module")."""

from __future__ import annotations

import dataclasses
from typing import Any, Literal

import torch
from torch import Tensor

from lightning_vtr.geometry import candidate_viewpoints, check_bin_interval, sample_uniform_viewpoints
from lightning_vtr.metrics.functional import voxel_iou
from lightning_vtr.protocol import DEFAULT_THRESHOLD
from lightning_vtr.selection.base import SelectionContext, ViewSelector, check_categories, view_set_losses
from lightning_vtr.selection.diversity import choose_bins
from lightning_vtr.selection.projection import (
    _soft_error_scores,
    check_volume_pair,
    error_volume,
    projection_scores,
    sample_around_bins,
    visible_error_scores,
)
from lightning_vtr.utils.validation import check_choice, check_float, check_int, check_type

__all__ = ["OBJECT_SCORES", "SCORES", "ErrorGuidedSelector", "relative_to_category"]

#: The view scores, as ``(error mode, mask, reduction)`` of the error projection; ``"visible"`` projects the
#: surface of prediction and truth together instead of the error alone (see :func:`visible_error_scores`).
SCORES: dict[str, tuple[Literal["binary", "soft"], Literal["gt"] | None, Literal["sum", "mean"]]] = {
    "paper": ("binary", None, "sum"),  # the paper: binary error, summed first-hit map
    "released": ("soft", "gt", "mean"),  # the authors' released code: soft error inside GT, mean over hits
    "visible": ("binary", None, "sum"),  # ours: the error on the surface a camera sees, summed
    "input": ("binary", None, "sum"),  # ours: the model's loss given that view as input (no projection)
    "map": ("binary", None, "sum"),  # ours: the category's measured failure map (no projection)
}
#: The scores computed for one object alone from its prediction (and, for ``"input"``, its rendered views);
#: ``"map"`` is a property of a category, measured over several of its objects.
OBJECT_SCORES: tuple[str, ...] = ("paper", "released", "visible", "input")


def _rows_by_category(categories: list[str]) -> dict[str, list[int]]:
    """The batch rows of each category, categories in order of first appearance."""
    rows_of: dict[str, list[int]] = {}
    for row, category in enumerate(categories):
        rows_of.setdefault(category, []).append(row)
    return rows_of


def relative_to_category(scores: Tensor, categories: list[str]) -> Tensor:
    """``(B, V)`` view scores over their category's mean per view, taken over the objects with any error.

    A view no object of the category scores above 0 gets 0; an object without error keeps its zeros. An object
    alone in its category gets 1 wherever it sees error.
    """
    check_categories(categories, scores.shape[0])
    relative = torch.zeros_like(scores)
    for rows in _rows_by_category(categories).values():
        index = torch.tensor(rows, device=scores.device)
        group = scores.index_select(0, index)
        erring = group[group.sum(1) > 0]
        if len(erring) == 0:
            continue
        mean = erring.mean(0)
        relative.index_copy_(0, index, torch.where(mean > 0, group / mean.clamp_min(torch.finfo(mean.dtype).tiny), 0))
    return relative


class ErrorGuidedSelector(ViewSelector):
    r"""Pick the viewpoints that see the most reconstruction error.

    For every object: :math:`E = |V - V^{gt}|`; the first-hit orthographic projection of ``E`` onto every
    bin-centre viewpoint of interval ``K`` (:func:`~lightning_vtr.geometry.candidate_viewpoints`); score
    :math:`s_v = \sum_{pixels} P_v`; keep the ``num_views`` best bins; sample each final viewpoint from
    :math:`\mathcal{N}(\text{bin centre}, \sigma = K / 6)` in yaw and pitch (degrees), yaw wrapped and pitch
    clamped. An object with no error (all scores 0) has no preferred view and gets ``num_views`` uniform
    viewpoints instead (``fallback`` mode of :func:`~lightning_vtr.geometry.sample_uniform_viewpoints`).

    The selections are meant for the per-category :class:`~lightning_vtr.selection.pool.ViewpointPool`
    (``uses_pool = True``). After :meth:`select`, ``last_scores (B, V_c)``, ``last_bins (B, num_views)``
    and ``last_fallback (B,)`` hold the intermediate results for logging and plots (``last_scores``: the
    relative scores with ``relative=True``).

    The view score (``score``):

    * ``"paper"`` (the paper, and the default): binary error at ``threshold``, summed over the first-hit
      map. Every hit is worth 1, so a view's score is the area of the error's silhouette, the same for a
      view and its antipode.
    * ``"released"`` (the authors' released code): soft error :math:`|V - V^{gt}|` inside ground-truth
      voxels, mean over hit pixels (0 for an empty map). Side-aware: it averages the error on the visible
      ground-truth surface.
    * ``"visible"`` (ours): what a camera at that viewpoint would see wrong. The first hit along each ray on
      the union of predicted and ground-truth occupancy, valued by the (binary) error there, summed
      (:func:`~lightning_vtr.selection.projection.visible_error_scores`). Side-aware by construction.
    * ``"input"`` (ours, the input side): the model's reconstruction loss when it is *given* the object's
      image from that viewpoint, alone. Every bin centre is synthesized and predicted from, so the selector
      needs a :class:`~lightning_vtr.selection.base.SelectionContext` (``needs_context`` is then ``True``):
      ``V_c`` images and single-view predictions per object (72 at ``K = 30``). It asks which input views
      the model fails on, where the other scores ask where its output from the training views is wrong.
    * ``"map"`` (ours, the category's measured failure map): the model's loss :math:`1 - \mathrm{IoU}` (at
      ``threshold``) given ``num_views`` views drawn around each bin centre, as the selector draws them around
      a chosen bin, measured on up to ``map_objects`` objects of each category per call and averaged over the
      category; the maps of successive calls are blended (``map_momentum``). Every object of a category gets
      its category's map, rescaled to ``[0, 1]`` (worst bin 1, best bin 0) so that a temperature acts on how
      the bins differ, not on the model's overall level. It needs a context as ``"input"`` does and is
      ``batched`` (all searched objects in one call); :attr:`category_maps` holds the blended maps and is
      saved with the callback's state. Why: on the embedded dataset the failure map of a category's training
      objects predicts where a new object of that category fails (Spearman correlation about 0.6), where the
      per-object scores do not (0.2 or less).

    Which bins are kept (``min_separation``, ``temperature``; see
    :func:`~lightning_vtr.selection.diversity.choose_bins`): by default the hard top ``num_views``;
    non-maximum suppression keeps chosen bins apart and never picks an antipode of a chosen bin; a
    temperature samples bins with probability :math:`\propto` solid angle :math:`\times s^{1/\tau}`, from
    the hard top-n (:math:`\tau \to 0`) to area-uniform random bins (:math:`\tau \to \infty`).

    Args:
        k: bin interval ``K`` in degrees; must divide 180 (30 gives 72 candidate views).
        num_views: ``n``, views selected per object (the number of input views, 3).
        score: ``"paper"``, ``"released"``, ``"visible"`` or ``"input"`` (see above).
        threshold: binarisation threshold of the prediction (:data:`~lightning_vtr.protocol.DEFAULT_THRESHOLD`).
        min_separation: ``None`` for no suppression; else the angle in degrees within which a chosen bin
            (or its antipode) forbids other bins. ``0`` forbids only the antipode.
        temperature: ``None`` for the hard top ``n``; else :math:`\tau > 0` of the tempered sampling.
        mode: override of the score's error volume, ``"binary"`` or ``"soft"`` (see :func:`error_volume`).
        mask: override of the score's mask: ``"gt"`` counts only errors inside ground-truth voxels,
            ``"none"`` every error.
        reduction: override of the score's per-view reduction, ``"sum"`` or ``"mean"`` over hit pixels.
            ``None`` (the default) for ``mode``, ``mask`` and ``reduction`` takes the value of ``score``;
            ``score="visible"`` takes ``mode`` only; ``score="input"`` takes none of them.
        sigma: sampling standard deviation in degrees; ``None`` means ``K / 6``.
        fallback: uniform sampler for objects without error: ``"area"`` (uniform on the sphere) or
            ``"angle"`` (uniform yaw and pitch).
        eps: error values ``<= eps`` are transparent to the projection (matters for ``mode="soft"``).
        map_objects: for ``score="map"``: the most objects of each category whose views are rendered and
            predicted per call (the first of a seeded shuffle of the call's objects of that category); each costs
            ``V_c * num_views`` rendered images and ``V_c`` predictions.
        map_momentum: for ``score="map"``: weight of a call's new measurement in a category's blended map
            (``1``: only the latest; the first measurement of a category is taken whole).
        relative: ``True`` (ours) divides each object's score of a view by the mean score of that view over
            the objects of its category in the call (those with any error), so the bins are chosen by where
            this object is worse than its category, not by the views every object of it gets wrong. The
            selector is then ``batched``: the callback scores all searched objects in one call (on rank 0
            under DDP), so a selection depends on the (seed, epoch) and the searched set, not on the object
            alone.
        model_batch_size: most single-view predictions per model call for ``score="input"``.

    Raises:
        TypeError: an argument of the wrong type (named in the message, with its value).
        ValueError: naming the argument and the bad value, e.g. ``K`` not dividing 180.

    Example::

        selector = ErrorGuidedSelector(k=30, num_views=3)
        views = selector.select(predicted, target, categories, generator=torch.Generator().manual_seed(0))
        views.shape  # (B, 3, 2), degrees
    """

    uses_pool = True

    def __init__(
        self,
        k: int = 30,
        num_views: int = 3,
        score: Literal["paper", "released", "visible", "input", "map"] = "paper",
        threshold: float = DEFAULT_THRESHOLD,
        min_separation: float | None = None,
        temperature: float | None = None,
        mode: Literal["binary", "soft"] | None = None,
        mask: Literal["gt", "none"] | None = None,
        reduction: Literal["sum", "mean"] | None = None,
        sigma: float | None = None,
        fallback: Literal["area", "angle"] = "area",
        eps: float = 0.0,
        relative: bool = False,
        model_batch_size: int = 72,
        map_objects: int = 2,
        map_momentum: float = 0.3,
    ) -> None:
        self.k = check_bin_interval(k)
        # at most one view per candidate bin: the views are drawn around distinct best bins
        n_candidates = (180 // self.k) * (360 // self.k)
        self.num_views = check_int("num_views", num_views, minimum=1, maximum=n_candidates)
        self.score = check_choice("score", score, SCORES)
        self.threshold = check_float("threshold", threshold, minimum=0.0, maximum=1.0)
        self.min_separation = (
            None
            if min_separation is None
            else check_float("min_separation", min_separation, minimum=0.0, maximum=180.0)
        )
        self.temperature = None if temperature is None else check_float("temperature", temperature, minimum=0.0)
        if score == "visible" and (mask is not None or reduction is not None):
            # the visible score values every visible voxel and sums: a mask or a mean would change what it means
            raise ValueError(
                f"`mask` and `reduction` do not apply to score='visible', got mask={mask!r}, reduction={reduction!r}"
            )
        if score in ("input", "map") and (mode is not None or mask is not None or reduction is not None):
            # the input and map scores are the model's loss, not a projection of an error volume
            raise ValueError(
                f"`mode`, `mask` and `reduction` do not apply to score={score!r}, got "
                f"mode={mode!r}, mask={mask!r}, reduction={reduction!r}"
            )
        if score == "map" and relative:
            # every object of a category gets the category's map: relative to the category it would be all ones
            raise ValueError("`relative=True` does not apply to score='map', which scores a category, not an object")
        default_mode, default_mask, default_reduction = SCORES[score]
        self.mode = check_choice("mode", default_mode if mode is None else mode, ("binary", "soft"))
        mask = default_mask if mask is None else check_choice("mask", mask, ("gt", "none"))
        self.mask = None if mask == "none" else mask
        self.reduction = check_choice(
            "reduction", default_reduction if reduction is None else reduction, ("sum", "mean")
        )
        self.sigma = self.k / 6.0 if sigma is None else check_float("sigma", sigma, minimum=0.0)
        self.fallback = check_choice("fallback", fallback, ("area", "angle"))
        self.eps = check_float("eps", eps, minimum=0.0, maximum=1.0, max_open=True)
        self.relative = check_type("relative", relative, bool)
        # relative scores compare an object with the others, the map pools a category's objects: the callback
        # must pass them all in one call
        self.batched = self.relative or self.score == "map"
        # the input and map scores render views and query the model
        self.needs_context = self.score in ("input", "map")
        self.model_batch_size = check_int("model_batch_size", model_batch_size, minimum=1)
        self.map_objects = check_int("map_objects", map_objects, minimum=1)
        self.map_momentum = check_float("map_momentum", map_momentum, minimum=0.0, maximum=1.0, min_open=True)
        #: ``score="map"``: each category's blended failure map, ``(V_c,)`` float32 mean loss per bin.
        self.category_maps: dict[str, Tensor] = {}
        self.candidates = candidate_viewpoints(self.k)  # (V_c, 2) degrees, pitch-major
        self.last_scores: Tensor | None = None
        self.last_bins: Tensor | None = None
        self.last_fallback: Tensor | None = None

    def error_volume(self, predicted: Tensor, target: Tensor) -> Tensor:
        """``(B, R, R, R)`` error volume with this selector's threshold, mode and mask."""
        return error_volume(predicted, target, threshold=self.threshold, mode=self.mode, mask=self.mask)

    def score_views(self, predicted: Tensor, target: Tensor, context: SelectionContext | None = None) -> Tensor:
        """Scores ``(B, V_c)`` of every candidate viewpoint (``candidate_viewpoints(k)`` order).

        ``context`` is needed by ``score="input"`` only (see :meth:`input_scores`). ``score="map"`` scores
        categories, not objects: :meth:`select` measures and applies it (see :meth:`map_scores`).

        Raises:
            ValueError: ``score="map"``; or, for ``score="input"``, a missing or incomplete context.
        """
        if self.score == "map":
            raise ValueError(
                "score='map' scores a category from several of its objects: call select() or map_scores(), "
                "not score_views()"
            )
        if self.score == "input":
            return self.input_scores(target, context).to(predicted.dtype)
        if self.score == "visible":
            predicted, target = check_volume_pair(predicted, target)
            return visible_error_scores(
                predicted, target, self.candidates.to(predicted.device), threshold=self.threshold, mode=self.mode
            )
        if self.mode == "binary":
            # the {0, 1} error as bool: skips a float conversion of the grids
            predicted, target = check_volume_pair(predicted, target)
            errors = (predicted >= self.threshold) != (target >= 0.5)
            if self.mask == "gt":
                errors &= target >= 0.5
        else:
            # the soft error does not depend on the threshold: scored without building the error volume first
            return _soft_error_scores(
                predicted,
                target,
                self.candidates.to(predicted.device),
                mask=self.mask,
                reduction=self.reduction,
                eps=self.eps,
            ).to(predicted.dtype)
        # equal to view_scores(error_projection(errors, candidates, eps=eps)) without the (B, V, R, R) maps
        return projection_scores(
            errors,
            self.candidates.to(errors.device),
            reduction=self.reduction,
            eps=self.eps,
            binary=self.mode == "binary",
        ).to(predicted.dtype)

    @torch.no_grad()
    def input_scores(self, target: Tensor, context: SelectionContext | None) -> Tensor:
        """``(B, V_c)`` loss of the model given each object's image from each bin centre as its only view.

        Every bin centre is a one-view set of :func:`~lightning_vtr.selection.base.view_set_losses`: one
        synthesizer call for all of them, ``(N, 1, 3, h, w)`` model batches of at most ``model_batch_size``.

        Raises:
            ValueError: no context (or one without model, synthesizer, transform or loss), a request count
                other than ``B``, or a synthesizer that returns another number of objects or images.
        """
        if context is None or any(
            getattr(context, name) is None for name in ("model", "synthesizer", "transform", "loss_fn")
        ):
            raise ValueError(
                "ErrorGuidedSelector(score='input') needs a SelectionContext with model, synthesizer, transform "
                "and loss_fn: it renders every candidate view and scores the model's loss on it; the "
                "ErrorGuidedViewAugmentation callback passes one"
            )
        batch, n_views = target.shape[0], self.candidates.shape[0]
        if batch == 0:
            return target.new_zeros((0, n_views), dtype=torch.float32)
        # every bin centre is a one-view set: (B, V_c, 1, 2)
        sets = self.candidates[None, :, None].expand(batch, -1, -1, -1)
        losses = view_set_losses(sets, target.float(), context, self.model_batch_size)
        return losses.float().clamp_min(0.0)

    @torch.no_grad()
    def map_scores(
        self,
        target: Tensor,
        categories: list[str],
        context: SelectionContext | None,
        generator: torch.Generator | None = None,
    ) -> Tensor:
        r"""``(B, V_c)`` scores of ``score="map"``: each object's category map, rescaled to ``[0, 1]``.

        Measures, for up to ``map_objects`` objects of each category in the call, the model's
        :math:`1 - \mathrm{IoU}` given ``num_views`` views drawn around every bin centre (one synthesizer call,
        model batches of at most ``model_batch_size`` sets), averages them per category and blends the result
        into :attr:`category_maps` (``map_momentum``). A category's map is then rescaled to ``[0, 1]`` between
        its best and worst bin; a flat map scores 0 everywhere (no preferred bin).

        Args:
            target: ``(B, R, R, R)`` ground-truth occupancy of the objects of ``context.requests``.
            categories: the category of each object.
            context: the model, synthesizer, transform and one request per object (its loss is not used).
            generator: draws the measured objects (a shuffle per category, in order of first appearance),
                then the views around the bins.

        Raises:
            ValueError: no context, or one without model, synthesizer or transform.
        """
        check_categories(categories, target.shape[0])
        if context is None or any(getattr(context, name) is None for name in ("model", "synthesizer", "transform")):
            raise ValueError(
                "ErrorGuidedSelector(score='map') needs a SelectionContext with model, synthesizer and transform: "
                "it renders views around every bin and measures the model's IoU on them; the "
                "ErrorGuidedViewAugmentation callback passes one"
            )
        n_bins = self.candidates.shape[0]
        rows_of = _rows_by_category(categories)
        measured: dict[str, list[int]] = {}
        for category, rows in rows_of.items():
            order = torch.randperm(len(rows), generator=generator)[: self.map_objects]
            measured[category] = [rows[i] for i in sorted(order.tolist())]
        chosen = [row for rows in measured.values() for row in rows]
        if chosen:
            bins = torch.arange(n_bins)[None, :, None].expand(len(chosen), n_bins, self.num_views)
            sets = sample_around_bins(bins, self.k, sigma=self.sigma, generator=generator).to(torch.float32)
            threshold = self.threshold

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
                self.category_maps[category] = new if old is None else old + self.map_momentum * (new - old)
        scores = target.new_zeros((target.shape[0], n_bins), dtype=torch.float32)
        for category, rows in rows_of.items():
            loss = self.category_maps[category]
            spread = loss.max() - loss.min()
            if spread > 0:
                scores[rows] = ((loss - loss.min()) / spread).to(scores.device)
        return scores

    def state_dict(self) -> dict[str, Any]:
        """``score="map"``: the blended category maps (empty for the other scores, which keep no state)."""
        if self.score != "map":
            return {}
        return {"category_maps": {name: m.clone() for name, m in self.category_maps.items()}}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore the category maps :meth:`state_dict` returned.

        Raises:
            ValueError: a map of another length than this selector's ``V_c`` bins.
        """
        maps = state.get("category_maps", {})
        for name, value in maps.items():
            if tuple(value.shape) != (self.candidates.shape[0],):
                raise ValueError(
                    f"The saved failure map of category {name!r} has shape {tuple(value.shape)}; this selector "
                    f"(k={self.k}) has {self.candidates.shape[0]} bins"
                )
        self.category_maps = {name: torch.as_tensor(value).float().clone() for name, value in maps.items()}

    def select(
        self,
        predicted: Tensor,
        target: Tensor,
        categories: list[str],
        generator: torch.Generator | None = None,
        context: SelectionContext | None = None,
    ) -> Tensor:
        """Viewpoints ``(B, num_views, 2)`` in degrees for predictions / targets ``(B, R, R, R)``.

        An empty batch (``B = 0``, e.g. a DDP rank with no object this epoch) returns an empty
        ``(0, num_views, 2)`` tensor. ``categories`` is checked for length only; the selection itself is
        per object. Random draws, all from ``generator``: the ``(B, V_c)`` uniforms of
        :func:`~lightning_vtr.selection.diversity.choose_bins`, the Gaussian samples around the bins, then the
        uniform fallback of the objects without error, in batch order.
        """
        predicted, target = check_volume_pair(predicted, target)
        check_categories(categories, predicted.shape[0])
        # 1. score every candidate view by the error it sees (or by its category's measured failures)
        if self.score == "map":
            scores = self.map_scores(target, categories, context, generator)
        else:
            scores = self.score_views(predicted, target, context)
        no_error = scores.sum(dim=1) <= 0
        if self.relative:
            scores = relative_to_category(scores, categories)
        # 2. choose bins (the best, apart from each other, or tempered draws) and sample around their centres
        bins = choose_bins(
            scores,
            self.num_views,
            k=self.k,
            min_separation=self.min_separation,
            temperature=self.temperature,
            generator=generator,
        )
        views = sample_around_bins(bins, self.k, sigma=self.sigma, generator=generator).to(torch.get_default_dtype())
        # 3. objects without error: no preferred side, sample uniformly
        count = int(no_error.sum())
        if count:
            uniform = sample_uniform_viewpoints(count * self.num_views, mode=self.fallback, generator=generator)
            views[no_error] = uniform.view(count, self.num_views, 2).to(views)
        self.last_scores = scores.detach()
        self.last_bins = bins
        self.last_fallback = no_error
        return views

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(k={self.k}, num_views={self.num_views}, score={self.score!r}, "
            f"threshold={self.threshold}, min_separation={self.min_separation}, temperature={self.temperature}, "
            f"mode={self.mode!r}, mask={self.mask!r}, reduction={self.reduction!r}, sigma={self.sigma}, "
            f"fallback={self.fallback!r}, relative={self.relative}, model_batch_size={self.model_batch_size}, "
            f"map_objects={self.map_objects}, map_momentum={self.map_momentum})"
        )
