"""Angle bins: which bin holds a viewpoint, the best bins of a score table, and viewpoints drawn around bins."""

from __future__ import annotations

import torch
from torch import Tensor

from lightning_vtr.geometry import (
    candidate_viewpoints,
    check_bin_interval,
    check_viewpoints,
    sample_gaussian_viewpoints,
    wrap_yaw,
)
from lightning_vtr.selection.volumes import check_tensor_ndim
from lightning_vtr.utils.validation import check_float, check_int

__all__ = ["nearest_bins", "sample_around_bins", "select_views", "top_bins"]


def nearest_bins(viewpoints: Tensor, k: int = 30) -> Tensor:
    """Index in :func:`~lightning_vtr.geometry.candidate_viewpoints` order of the bin holding each viewpoint.

    Bins are the paper's intervals ``[-180 + (i - 1) K, -180 + i K)`` in yaw (after wrapping) and
    ``[-90 + (i - 1) K, -90 + i K)`` in pitch, half-open so a boundary angle belongs to the bin above it;
    pitch 90 belongs to the top bin.

    Args:
        viewpoints: ``(..., 2)`` (yaw, pitch) in degrees.
        k: bin interval in degrees (must divide 180).

    Returns:
        ``(...)`` int64 flat bin indices ``i_pitch * (360 / K) + i_yaw`` (0-based).

    Raises:
        TypeError: ``k`` is not a number.
        ValueError: a ``k`` that does not divide 180, or ``viewpoints`` not ``(..., 2)`` or not finite.

    Example:
        >>> nearest_bins(torch.tensor([[-180.0, -90.0], [0.0, 0.0], [179.0, 90.0]]), k=90)
        tensor([0, 6, 7])
    """
    k = check_bin_interval(k)
    vp = check_viewpoints(viewpoints).to(torch.float64)
    n_yaw, n_pitch = 360 // k, 180 // k
    i_yaw = torch.floor((wrap_yaw(vp[..., 0]) + 180.0) / k).long().clamp(0, n_yaw - 1)
    i_pitch = torch.floor((vp[..., 1].clamp(-90.0, 90.0) + 90.0) / k).long().clamp(0, n_pitch - 1)
    return i_pitch * n_yaw + i_yaw


def top_bins(scores: Tensor, n: int = 3, *, generator: torch.Generator | None = None) -> Tensor:
    """Indices ``(B, n)`` of the ``n`` highest scores per row, best first.

    Exactly equal scores are ordered at random (one uniform per score from ``generator``). Ties are
    common: with a binary error a view and its antipode see mirror-image silhouettes and score the same,
    and a fixed order would always favour the lower-index (southern, western) bin.

    Args:
        scores: ``(B, V)`` view scores, e.g. from :func:`projection_scores`.
        n: how many indices to keep per row, ``1 <= n <= V``.
        generator: the random source of the tie order (``None``: torch's global one).

    Returns:
        ``(B, n)`` int64 column indices into ``scores``, on its device.

    Raises:
        TypeError: ``scores`` is not a tensor or ``n`` is not an int.
        ValueError: ``scores`` is not ``(B, V)`` or ``n`` is not in ``[1, V]``.

    Example:
        >>> top_bins(torch.tensor([[0.1, 0.9, 0.5, 0.7]]), 2)
        tensor([[1, 3]])
    """
    check_tensor_ndim(scores, "scores", 2, "(B, V)")
    check_int("n", n, minimum=1, maximum=scores.shape[1])
    priority = torch.rand(scores.shape, generator=generator, dtype=torch.float64).to(scores.device)
    shuffled = torch.argsort(priority, dim=1)
    by_score = torch.argsort(-scores.detach().to(torch.float64).gather(1, shuffled), dim=1, stable=True)
    return shuffled.gather(1, by_score[:, :n])


def select_views(
    scores: Tensor,
    k: int = 30,
    n: int = 3,
    *,
    generator: torch.Generator | None = None,
    sigma: float | None = None,
) -> Tensor:
    """Sample ``n`` viewpoints per object around its ``n`` best-scoring candidate bins.

    The ``n`` highest scores are kept (:func:`top_bins`: exact ties in random order); each final viewpoint
    is drawn from ``N(bin centre, sigma)`` independently in yaw and pitch, then yaw is wrapped into
    ``[-180, 180)`` and pitch clamped into ``[-90, 90]``. Objects whose scores are all zero are not
    special-cased here (see :class:`ErrorGuidedSelector` for the uniform fallback). Random draws from
    ``generator``: ``(B, V)`` uniforms for the tie order, then ``(B, n, 2)`` normals.

    Args:
        scores: ``(B, V)`` with ``V = (180 / K) * (360 / K)`` in
            :func:`~lightning_vtr.geometry.candidate_viewpoints` order.
        k: bin interval ``K`` in degrees (must divide 180).
        n: views per object, ``1 <= n <= V``.
        generator: CPU generator.
        sigma: standard deviation in degrees; ``None`` means the paper's ``K / 6``.

    Returns:
        ``(B, n, 2)`` (yaw, pitch) in degrees, best bin first, on the device of ``scores``.

    Raises:
        TypeError: ``scores`` is not a tensor, or ``n`` / ``sigma`` has the wrong type.
        ValueError: a bad ``k``, ``scores`` not ``(B, V)`` for that ``k``, ``n`` out of range or ``sigma < 0``.

    Example:
        With ``K = 90`` there are 8 bins; ``sigma=0`` returns the centres of the best two:

        >>> select_views(torch.arange(8.0)[None], k=90, n=2, sigma=0.0)
        tensor([[[135.,  45.],
                 [ 45.,  45.]]])
        >>> select_views(torch.rand(4, 8), k=90, generator=torch.Generator().manual_seed(0)).shape
        torch.Size([4, 3, 2])
    """
    k = check_bin_interval(k)
    candidates = candidate_viewpoints(k)
    expected = f"(B, {candidates.shape[0]}) for K={k}"
    check_tensor_ndim(scores, "scores", 2, expected)
    if scores.shape[1] != candidates.shape[0]:
        raise ValueError(f"`scores` must have shape {expected}, got {tuple(scores.shape)}")
    sigma = k / 6.0 if sigma is None else check_float("sigma", sigma, minimum=0.0)
    best = top_bins(scores, n, generator=generator)  # (B, n)
    return sample_around_bins(best, k, sigma=sigma, generator=generator).to(
        scores.dtype if scores.is_floating_point() else torch.get_default_dtype()
    )


def sample_around_bins(
    bins: Tensor, k: int = 30, *, sigma: float | None = None, generator: torch.Generator | None = None
) -> Tensor:
    """Viewpoints ``(..., 2)`` in degrees drawn from ``N(centre of bin, sigma)`` for flat bin indices ``(...)``.

    Yaw and pitch are drawn independently; yaw is then wrapped into ``[-180, 180)`` and pitch clamped into
    ``[-90, 90]``.

    Args:
        bins: ``(...)`` integer flat bin indices in :func:`~lightning_vtr.geometry.candidate_viewpoints` order
            (as :func:`nearest_bins` and :func:`top_bins` return them).
        k: bin interval ``K`` in degrees (must divide 180).
        sigma: standard deviation in degrees; ``None`` means the paper's ``K / 6``.
        generator: the random source (``None``: torch's global one).

    Returns:
        ``(..., 2)`` float64 (yaw, pitch) in degrees, on the device of ``bins``.

    Raises:
        TypeError: ``k`` or ``sigma`` is not a number.
        ValueError: a bad ``k`` or a negative ``sigma``.

    Example:
        >>> sample_around_bins(torch.tensor([0, 6]), 90, sigma=0.0)  # the bins' centres
        tensor([[-135.,  -45.],
                [  45.,   45.]], dtype=torch.float64)
    """
    k = check_bin_interval(k)
    sigma = k / 6.0 if sigma is None else check_float("sigma", sigma, minimum=0.0)
    centres = candidate_viewpoints(k).to(bins.device, torch.float64)[bins]
    return sample_gaussian_viewpoints(centres, sigma, generator=generator)
