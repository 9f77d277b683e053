"""The paper's reconstruction error-guided view selector (Sec. "View selection module")."""

from __future__ import annotations

import math
from typing import Literal

import torch
from torch import Tensor

from lightning_vtr.geometry import candidate_viewpoints, check_bin_interval, sample_uniform_viewpoints
from lightning_vtr.selection.base import SelectionContext, ViewSelector
from lightning_vtr.selection.projection import (
    _candidate_scores,
    _check_pair,
    error_volume,
    sample_around_bins,
    top_bins,
)

__all__ = ["ErrorGuidedSelector"]


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
    and ``last_fallback (B,)`` hold the intermediate results for logging and plots.

    Args:
        k: bin interval ``K`` in degrees; must divide 180 (30 gives 72 candidate views).
        num_views: ``n``, views selected per object (the number of input views, 3).
        threshold: binarisation threshold of the prediction (``mode="binary"``).
        mode: ``"binary"`` (paper) or ``"soft"`` error volume, see :func:`error_volume`.
        mask: ``"gt"`` counts only errors inside ground-truth voxels; ``None`` counts all.
        reduction: per-view score, ``"sum"`` (paper) or ``"mean"`` over hit pixels.
        sigma: sampling standard deviation in degrees; ``None`` means ``K / 6``.
        fallback: uniform sampler for objects without error: ``"area"`` (uniform on the sphere) or
            ``"angle"`` (uniform yaw and pitch).
        eps: error values ``<= eps`` are transparent to the projection (matters for ``mode="soft"``).

    Raises:
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
        threshold: float = 0.4,
        mode: Literal["binary", "soft"] = "binary",
        mask: Literal[None, "gt"] = None,
        reduction: Literal["sum", "mean"] = "sum",
        sigma: float | None = None,
        fallback: Literal["area", "angle"] = "area",
        eps: float = 0.0,
    ) -> None:
        self.k = check_bin_interval(k)
        n_candidates = (180 // self.k) * (360 // self.k)
        if isinstance(num_views, bool) or not isinstance(num_views, int) or not 1 <= num_views <= n_candidates:
            raise ValueError(f"`num_views` must be an int in [1, {n_candidates}] for K={self.k}, got {num_views!r}")
        if not (isinstance(threshold, (int, float)) and 0.0 <= threshold <= 1.0):
            raise ValueError(f"`threshold` must lie in [0, 1], got {threshold!r}")
        if mode not in ("binary", "soft"):
            raise ValueError(f"`mode` must be 'binary' or 'soft', got {mode!r}")
        if mask not in (None, "gt"):
            raise ValueError(f"`mask` must be None or 'gt', got {mask!r}")
        if reduction not in ("sum", "mean"):
            raise ValueError(f"`reduction` must be 'sum' or 'mean', got {reduction!r}")
        if sigma is not None and not (isinstance(sigma, (int, float)) and sigma >= 0 and math.isfinite(sigma)):
            raise ValueError(f"`sigma` must be None or a finite number >= 0 (degrees), got {sigma!r}")
        if fallback not in ("area", "angle"):
            raise ValueError(f"`fallback` must be 'area' or 'angle', got {fallback!r}")
        if not (isinstance(eps, (int, float)) and 0.0 <= eps < 1.0):
            raise ValueError(f"`eps` must lie in [0, 1), got {eps!r}")
        self.num_views = num_views
        self.threshold = float(threshold)
        self.mode = mode
        self.mask = mask
        self.reduction = reduction
        self.sigma = self.k / 6.0 if sigma is None else float(sigma)
        self.fallback = fallback
        self.eps = float(eps)
        self.candidates = candidate_viewpoints(self.k)  # (V_c, 2) degrees, pitch-major
        self.last_scores: Tensor | None = None
        self.last_bins: Tensor | None = None
        self.last_fallback: Tensor | None = None

    def error_volume(self, predicted: Tensor, target: Tensor) -> Tensor:
        """``(B, R, R, R)`` error volume with this selector's threshold, mode and mask."""
        return error_volume(predicted, target, threshold=self.threshold, mode=self.mode, mask=self.mask)

    def score_views(self, predicted: Tensor, target: Tensor) -> Tensor:
        """Scores ``(B, V_c)`` of every candidate viewpoint (``candidate_viewpoints(k)`` order)."""
        if self.mode == "binary":
            # the {0, 1} error as bool: skips a float conversion of the grids
            predicted, target = _check_pair(predicted, target)
            errors = (predicted >= self.threshold) != (target >= 0.5)
            if self.mask == "gt":
                errors &= target >= 0.5
        else:
            errors = self.error_volume(predicted, target)
        # equal to view_scores(error_projection(errors, candidates, eps=eps)) without the (B, V, R, R) maps
        return _candidate_scores(
            errors,
            self.candidates.to(errors.device),
            reduction=self.reduction,
            eps=self.eps,
            binary=self.mode == "binary" or None,
        ).to(predicted.dtype)

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
        per object. Random draws, all from ``generator``: the tie order and Gaussian samples of
        :func:`select_views`, then the uniform fallback of the objects without error, in batch order.
        """
        predicted, target = _check_pair(predicted, target)
        if len(categories) != predicted.shape[0]:
            raise ValueError(
                f"`categories` must have one entry per object: got {len(categories)} for a batch of {predicted.shape[0]}"
            )
        # 1. score every candidate view by the error it sees
        scores = self.score_views(predicted, target)
        # 2. keep the best bins (exact ties in random order) and sample around their centres
        bins = top_bins(scores, self.num_views, generator=generator)
        views = sample_around_bins(bins, self.k, sigma=self.sigma, generator=generator).to(torch.get_default_dtype())
        # 3. objects without error: no preferred side, sample uniformly
        no_error = scores.sum(dim=1) <= 0
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
            f"{type(self).__name__}(k={self.k}, num_views={self.num_views}, threshold={self.threshold}, "
            f"mode={self.mode!r}, mask={self.mask!r}, reduction={self.reduction!r}, sigma={self.sigma}, "
            f"fallback={self.fallback!r})"
        )
