"""The paper's reconstruction error-guided view selector (Sec. "View selection module")."""

from __future__ import annotations

from typing import Any, Literal

import torch
from torch import Tensor

from lightning_vtr.geometry import candidate_viewpoints, check_bin_interval, sample_uniform_viewpoints
from lightning_vtr.protocol import DEFAULT_THRESHOLD
from lightning_vtr.selection.base import SelectionContext, ViewSelector, check_categories
from lightning_vtr.selection.bins import sample_around_bins
from lightning_vtr.selection.diversity import choose_bins
from lightning_vtr.selection.scores import (
    SCORES,
    ProjectionScore,
    ScoreSetup,
    ViewScore,
    rows_by_category,
)
from lightning_vtr.selection.volumes import check_volume_pair, error_volume
from lightning_vtr.utils.validation import check_choice, check_float, check_int, check_type

__all__ = ["SCORES", "ErrorGuidedSelector", "relative_to_category"]


def relative_to_category(scores: Tensor, categories: list[str]) -> Tensor:
    """``(B, V)`` view scores over their category's mean per view, taken over the objects with any error.

    A view no object of the category scores above 0 gets 0; an object without error keeps its zeros. An object
    alone in its category gets 1 wherever it sees error.
    """
    check_categories(categories, scores.shape[0])
    relative = torch.zeros_like(scores)
    for rows in rows_by_category(categories).values():
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

    For every object: score every bin-centre viewpoint of interval ``K``
    (:func:`~lightning_vtr.geometry.candidate_viewpoints`) by the error it sees (``score``), choose
    ``num_views`` bins (``min_separation``, ``temperature``), and sample each final viewpoint from
    :math:`\mathcal{N}(\text{bin centre}, \sigma = \text{spread} \cdot K)` in yaw and pitch (degrees), yaw wrapped and pitch clamped.
    An object with no error (all scores 0) has no preferred view and gets ``num_views`` uniform viewpoints
    instead (``fallback`` mode of :func:`~lightning_vtr.geometry.sample_uniform_viewpoints`).

    ``ErrorGuidedSelector()`` is the package's default rule, the same as :meth:`default`: the ``"visible"``
    score, bins within 30 degrees of a chosen one (or its antipode) suppressed, bins drawn at temperature 10.
    The paper's rule (the ``"paper"`` score, the hard top ``num_views`` bins) is :meth:`paper`.

    The selections are meant for the per-category :class:`~lightning_vtr.selection.pool.ViewpointPool`
    (``uses_pool = True``). After :meth:`select`, ``last_scores (B, V_c)``, ``last_bins (B, num_views)``
    and ``last_fallback (B,)`` hold the intermediate results for logging and plots (``last_scores``: the
    relative scores with ``relative=True``).

    The view scores (``score``: a name of :data:`~lightning_vtr.selection.scores.SCORES`, built with its
    defaults, or a score object with its own options; see :mod:`lightning_vtr.selection.scores`):

    * ``"paper"`` (:class:`~lightning_vtr.selection.scores.PaperScore`): binary error at ``threshold``, summed
      over the first-hit map of the error volume: the area of the error's silhouette.
    * ``"released"`` (:class:`~lightning_vtr.selection.scores.ReleasedScore`, the authors' released code): soft
      error inside ground-truth voxels, mean over hit pixels.
    * ``"visible"`` (:class:`~lightning_vtr.selection.scores.VisibleScore`): what a camera at that viewpoint
      would see wrong, on the surface of prediction and truth together. Side-aware by construction.
    * a :class:`~lightning_vtr.selection.scores.ViewScore` object of your own: a score with
      ``needs_context`` gets a :class:`~lightning_vtr.selection.base.SelectionContext` (the selector's
      ``needs_context`` is then ``True``); one with ``per_category`` makes the selector ``batched``; its
      :meth:`~lightning_vtr.selection.scores.ViewScore.state_dict` is the selector's state.

    Which bins are kept (see :func:`~lightning_vtr.selection.diversity.choose_bins`): non-maximum suppression
    keeps chosen bins apart and never picks an antipode of a chosen bin; a temperature samples bins with
    probability :math:`\propto` solid angle :math:`\times s^{1/\tau}`, from the hard top-n (:math:`\tau \to 0`)
    to area-uniform random bins (:math:`\tau \to \infty`); ``None`` for both gives the hard top ``num_views``.

    Args:
        score: ``"visible"`` (default), ``"paper"``, ``"released"``, or a
            :class:`~lightning_vtr.selection.scores.ViewScore` object (e.g. ``ReleasedScore(eps=0.1)``).
        k: ``30`` (default): bin interval ``K`` in degrees; must divide 180 (30 gives 72 candidate views).
        num_views: ``3`` (default): ``n``, views selected per object (the number of input views).
        threshold: ``0.4`` (default, :data:`~lightning_vtr.protocol.DEFAULT_THRESHOLD`): binarisation threshold
            of the prediction.
        min_separation: ``30.0`` (default): the angle in degrees within which a chosen bin (or its antipode)
            forbids other bins; ``0`` forbids only the antipode; ``None`` for no suppression.
        temperature: ``10.0`` (default): :math:`\tau > 0` of the tempered sampling; ``None`` for the hard top
            ``n``.
        spread: ``0.16666666666666666`` (default, ``1 / 6``): standard deviation of the draws around a bin
            centre, as a fraction of the bin interval: ``sigma = spread * K`` degrees (the paper's ``K / 6``).
        fallback: ``"area"`` (default: uniform on the sphere) or ``"angle"`` (uniform yaw and pitch): the
            uniform sampler of objects without error.
        relative: ``False`` (default). ``True`` divides each object's score of a view by the mean score of
            that view over the objects of its category in the call (those with any error), so the bins are
            chosen by where this object is worse than its category. The selector is then ``batched``: the
            callback scores all searched objects in one call (on rank 0 under DDP). Not for a ``per_category``
            score.

    Raises:
        TypeError: an argument of the wrong type (named in the message, with its value).
        ValueError: naming the argument and the bad value, e.g. ``K`` not dividing 180.

    Example::

        selector = ErrorGuidedSelector(k=30)  # the default rule at K = 30
        print(selector)  # ErrorGuidedSelector(score='visible', k=30, num_views=3, ...)
        views = selector.select(predicted, target, categories, generator=torch.Generator().manual_seed(0))
        views.shape  # (B, 3, 2), degrees
        paper = ErrorGuidedSelector.paper()  # the paper's rule
        released = ErrorGuidedSelector(score=ReleasedScore(eps=0.1), min_separation=None, temperature=None)
    """

    uses_pool = True

    def __init__(
        self,
        score: Literal["paper", "released", "visible"] | ViewScore = "visible",
        k: int = 30,
        num_views: int = 3,
        threshold: float = DEFAULT_THRESHOLD,
        min_separation: float | None = 30.0,
        temperature: float | None = 10.0,
        spread: float = 1 / 6,
        fallback: Literal["area", "angle"] = "area",
        relative: bool = False,
    ) -> None:
        if isinstance(score, ViewScore):
            self.score_options: ViewScore = score
        else:
            self.score_options = SCORES[check_choice("score", score, SCORES)]()
        self.k = check_bin_interval(k)
        # at most one view per candidate bin: the views are drawn around distinct best bins
        n_candidates = (180 // self.k) * (360 // self.k)
        self.num_views = check_int("num_views", num_views, minimum=1, maximum=n_candidates)
        self.threshold = check_float("threshold", threshold, minimum=0.0, maximum=1.0)
        self.min_separation = (
            None
            if min_separation is None
            else check_float("min_separation", min_separation, minimum=0.0, maximum=180.0)
        )
        self.temperature = None if temperature is None else check_float("temperature", temperature, minimum=0.0)
        self.spread = check_float("spread", spread, minimum=0.0)
        #: The standard deviation in degrees of the draws around a bin centre, ``spread * k``.
        # as K / (1 / spread): the default gives K / 6.0 exactly, the paper's sigma to the last bit
        self.sigma = self.k / (1.0 / self.spread) if self.spread > 0 else 0.0
        self.fallback = check_choice("fallback", fallback, ("area", "angle"))
        self.relative = check_type("relative", relative, bool)
        if self.score_options.per_category and self.relative:
            # every object of a category gets the category's map: relative to the category it would be all ones
            raise ValueError(
                f"`relative=True` does not apply to score={self.score!r}, which scores a category, not an object"
            )
        # relative scores compare an object with the others, a per-category score pools a category's objects: the callback
        # must pass them all in one call
        self.batched = self.relative or self.score_options.per_category
        # a score with a context renders views and queries the model
        self.needs_context = self.score_options.needs_context
        self.candidates = candidate_viewpoints(self.k)  # (V_c, 2) degrees, pitch-major
        self.last_scores: Tensor | None = None
        self.last_bins: Tensor | None = None
        self.last_fallback: Tensor | None = None

    @property
    def score(self) -> str:
        """The score's name (``score_options.name``); its options are :attr:`score_options`."""
        return self.score_options.name

    @classmethod
    def default(cls, **kwargs: Any) -> ErrorGuidedSelector:
        """The package's default rule: ``score="visible"``, ``min_separation=30.0``, ``temperature=10.0``.

        Args:
            kwargs: other constructor arguments (``k``, ``num_views``, ...), over the rule's.
        """
        return cls(**{"score": "visible", "min_separation": 30.0, "temperature": 10.0, **kwargs})

    @classmethod
    def paper(cls, **kwargs: Any) -> ErrorGuidedSelector:
        """The paper's rule: ``score="paper"``, no suppression, the hard top ``num_views`` bins.

        Args:
            kwargs: other constructor arguments (``k``, ``num_views``, ...), over the rule's.
        """
        return cls(**{"score": "paper", "min_separation": None, "temperature": None, **kwargs})

    def _setup(self) -> ScoreSetup:
        return ScoreSetup(
            k=self.k, candidates=self.candidates, num_views=self.num_views, sigma=self.sigma, threshold=self.threshold
        )

    def error_volume(self, predicted: Tensor, target: Tensor) -> Tensor:
        """``(B, R, R, R)`` error volume at this selector's threshold, binary, every error kept.

        A :class:`~lightning_vtr.selection.scores.ProjectionScore` takes its own ``mode`` and ``mask``.
        """
        options = self.score_options
        mode: Literal["binary", "soft"] = options.mode if isinstance(options, ProjectionScore) else "binary"
        mask: Literal["gt"] | None = "gt" if isinstance(options, ProjectionScore) and options.mask == "gt" else None
        return error_volume(predicted, target, threshold=self.threshold, mode=mode, mask=mask)

    def score_views(
        self,
        predicted: Tensor,
        target: Tensor,
        context: SelectionContext | None = None,
        *,
        categories: list[str] | None = None,
        generator: torch.Generator | None = None,
    ) -> Tensor:
        """Scores ``(B, V_c)`` of every candidate viewpoint (``candidate_viewpoints(k)`` order), before
        ``relative``.

        Args:
            predicted: ``(B, R, R, R)`` occupancy probabilities.
            target: ``(B, R, R, R)`` ground-truth occupancy.
            context: the model and synthesizer, for a score with ``needs_context``.
            categories: one category per object; needed by a ``per_category`` score (``None``: every object
                alone).
            generator: the random source of a score that draws (e.g. the objects and views it measures).

        Raises:
            ValueError: a ``per_category`` score without ``categories``; a missing or incomplete context for a
                score with ``needs_context``.
        """
        predicted, target = check_volume_pair(predicted, target)
        if categories is None:
            if self.score_options.per_category:
                raise ValueError(
                    f"score={self.score!r} scores a category from several of its objects: pass `categories` "
                    "(one per object)"
                )
            categories = ["object"] * predicted.shape[0]
        check_categories(categories, predicted.shape[0])
        return self.score_options(predicted, target, categories, self._setup(), context, generator)

    def state_dict(self) -> dict[str, Any]:
        """The score's learned state (its ``state_dict()``; empty for the shipped scores)."""
        return self.score_options.state_dict()

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore what :meth:`state_dict` returned.

        Raises:
            ValueError: the score refuses ``state`` (e.g. saved per-bin values of another length than this
                selector's ``V_c`` bins).
        """
        self.score_options.load_state_dict(state, self._setup())

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
        scores = self.score_views(predicted, target, context, categories=categories, generator=generator)
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

    def settings(self) -> dict[str, Any]:
        """The effective settings: ``score`` (its name), the score's own options, then the selector's.

        Example:
            >>> ErrorGuidedSelector.paper().settings()["score"], ErrorGuidedSelector.paper().settings()["mode"]
            ('paper', 'binary')
        """
        return {
            "score": self.score,
            **self.score_options.settings(),
            "k": self.k,
            "num_views": self.num_views,
            "threshold": self.threshold,
            "min_separation": self.min_separation,
            "temperature": self.temperature,
            "spread": self.spread,
            "fallback": self.fallback,
            "relative": self.relative,
        }

    def __repr__(self) -> str:
        """``ErrorGuidedSelector(score=VisibleScore(mode='binary'), k=30, ...)``: every effective setting."""
        options = self.score_options.settings()
        own = {name: value for name, value in self.settings().items() if name != "score" and name not in options}
        items = ", ".join(f"{name}={value!r}" for name, value in own.items())
        return f"{type(self).__name__}(score={self.score_options!r}, {items})"
