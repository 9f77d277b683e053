"""The statistics of a strategy comparison: means with confidence intervals, paired differences, view spread.

A comparison between strategies is a claim about a difference, so the report states it as one: for each
seed, the difference between two strategies fine-tuned from the *same* pretrained model and tested on the
*same* items (a paired difference), then the mean of those differences with a Student-t 95 % confidence
interval over seeds and the number of seeds that agree in sign. Viewpoints are ``(yaw, pitch)`` in degrees.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import torch
from scipy import stats
from torch import Tensor

from lightning_vtr.geometry import angular_distance, check_viewpoints
from lightning_vtr.utils.validation import check_float

__all__ = [
    "Estimate",
    "antipodal_share",
    "mean_estimate",
    "paired_difference",
    "pitch_histogram",
    "triplet_spread",
]


@dataclass(frozen=True)
class Estimate:
    """A mean over seeds with its confidence interval.

    Attributes:
        mean: the sample mean.
        half_width: half the width of the confidence interval (``nan`` with one value).
        n: number of values (seeds).
        agree: how many values share the sign of the mean (0 when the mean is 0).

    Example:
        >>> estimate = Estimate(mean=0.02, half_width=0.01, n=3, agree=3)
        >>> round(estimate.low, 3), round(estimate.high, 3), estimate.excludes_zero
        (0.01, 0.03, True)
    """

    mean: float
    half_width: float
    n: int
    agree: int

    @property
    def low(self) -> float:
        """The interval's lower end, ``mean - half_width``."""
        return self.mean - self.half_width

    @property
    def high(self) -> float:
        """The interval's upper end, ``mean + half_width``."""
        return self.mean + self.half_width

    @property
    def excludes_zero(self) -> bool:
        """Whether the interval lies entirely on one side of 0 (``False`` with one value)."""
        return math.isfinite(self.half_width) and (self.low > 0 or self.high < 0)


def mean_estimate(values: Sequence[float], confidence: float = 0.95) -> Estimate:
    """Mean of ``values`` with a two-sided Student-t interval of the given ``confidence``.

    ``half_width = t_{(1 + confidence) / 2, n - 1} * s / sqrt(n)`` with ``s`` the sample standard deviation.

    Args:
        values: one number per seed.
        confidence: the interval's confidence level, in (0, 1).

    Returns:
        An :class:`Estimate` over ``values`` (its ``half_width`` is ``nan`` for one value).

    Raises:
        ValueError: ``values`` is empty, or ``confidence`` is not in (0, 1).
        TypeError: ``confidence`` is not a number.

    Example:
        >>> estimate = mean_estimate([1.0, 2.0, 3.0])
        >>> estimate.mean, round(estimate.half_width, 3), estimate.n, estimate.agree
        (2.0, 2.484, 3, 3)
        >>> mean_estimate([0.5])
        Estimate(mean=0.5, half_width=nan, n=1, agree=1)
    """
    confidence = check_float("confidence", confidence, minimum=0.0, maximum=1.0, min_open=True, max_open=True)
    values = [float(v) for v in values]
    if not values:
        raise ValueError("`values` must hold at least one number, got an empty sequence")
    n = len(values)
    mean = math.fsum(values) / n
    if n == 1:
        half_width = math.nan
    else:
        sd = math.sqrt(math.fsum((v - mean) ** 2 for v in values) / (n - 1))
        half_width = float(stats.t.ppf((1 + confidence) / 2, n - 1)) * sd / math.sqrt(n)
    agree = 0 if mean == 0 else sum(1 for v in values if v * mean > 0)
    return Estimate(mean, half_width, n, agree)


def paired_difference(
    treatment: Mapping[int, float], baseline: Mapping[int, float], confidence: float = 0.95
) -> Estimate:
    """Mean over seeds of ``treatment[seed] - baseline[seed]``, on the seeds both have.

    Args:
        treatment: seed -> the value of the strategy compared.
        baseline: seed -> the value of the strategy it is compared with.
        confidence: the interval's confidence level, in (0, 1).

    Returns:
        The :func:`mean_estimate` of the paired differences.

    Raises:
        ValueError: when the two share no seed, or ``confidence`` is not in (0, 1).
        TypeError: ``confidence`` is not a number.

    Example:
        >>> difference = paired_difference({0: 0.52, 1: 0.55, 2: 0.50}, {0: 0.50, 1: 0.51, 2: 0.49, 3: 0.6})
        >>> round(difference.mean, 4), difference.n, difference.agree
        (0.0233, 3, 3)
    """
    seeds = sorted(set(treatment) & set(baseline))
    if not seeds:
        raise ValueError(
            f"`treatment` and `baseline` must share a seed, got {sorted(treatment)} and {sorted(baseline)}"
        )
    return mean_estimate([treatment[s] - baseline[s] for s in seeds], confidence)


def pitch_histogram(viewpoints: Tensor, edges: Sequence[float] = (-90, -60, -30, 0, 30, 60, 90)) -> Tensor:
    """Share of viewpoints ``(..., 2)`` per pitch band ``[edges[i], edges[i + 1])`` (the last band closed).

    Args:
        viewpoints: ``(..., 2)`` (yaw, pitch) in degrees.
        edges: increasing band edges in degrees, from -90 to 90.

    Returns:
        ``(len(edges) - 1,)`` float64 shares summing to 1 (all 0 for no viewpoints).

    Raises:
        ValueError: ``viewpoints`` is not ``(..., 2)`` or holds a NaN / infinite angle.

    Example:
        >>> pitch_histogram(torch.tensor([[0.0, 10.0], [90.0, -45.0], [180.0, 90.0]]), edges=(-90, 0, 90))
        tensor([0.3333, 0.6667], dtype=torch.float64)
    """
    pitch = check_viewpoints(viewpoints).reshape(-1, 2)[:, 1].to(torch.float64).contiguous()
    bounds = torch.as_tensor(edges, dtype=torch.float64)
    index = torch.bucketize(pitch, bounds[1:-1], right=True)
    counts = torch.bincount(index, minlength=len(edges) - 1).to(torch.float64)
    return counts / counts.sum().clamp_min(1.0)


def antipodal_share(view_sets: Tensor, tolerance: float = 15.0) -> float:
    """Share of view sets ``(B, n, 2)`` holding a pair of views at least ``180 - tolerance`` degrees apart.

    Such a pair sees mirror-image silhouettes: the second view adds little the first did not show.

    Args:
        view_sets: ``(B, n, 2)`` (yaw, pitch) in degrees.
        tolerance: how far from opposite (degrees, in [0, 180]) a pair may be.

    Returns:
        The share in [0, 1] (0 for no view sets).

    Raises:
        ValueError: ``view_sets`` is not ``(B, n, 2)`` or holds a NaN / infinite angle, or ``tolerance`` is not
            in [0, 180].
        TypeError: ``tolerance`` is not a number.

    Example:
        >>> antipodal_share(torch.tensor([[[0.0, 0.0], [180.0, 0.0]], [[0.0, 0.0], [30.0, 0.0]]]))
        0.5
    """
    tolerance = check_float("tolerance", tolerance, minimum=0.0, maximum=180.0)
    distance = _pairwise_distances(view_sets)
    if distance.shape[0] == 0:
        return 0.0
    return float((distance.amax(dim=(1, 2)) >= 180.0 - tolerance).to(torch.float64).mean())


def triplet_spread(view_sets: Tensor) -> float:
    """Mean angular distance (degrees) between the views of a set, over all pairs and sets ``(B, n, 2)``.

    Args:
        view_sets: ``(B, n, 2)`` (yaw, pitch) in degrees.

    Returns:
        The mean distance in degrees (0 for no view sets or sets of one view).

    Raises:
        ValueError: ``view_sets`` is not ``(B, n, 2)`` or holds a NaN / infinite angle.

    Example:
        >>> triplet_spread(torch.tensor([[[0.0, 0.0], [180.0, 0.0]], [[0.0, 0.0], [30.0, 0.0]]]))
        105.0
    """
    distance = _pairwise_distances(view_sets)
    n = distance.shape[1]
    if distance.shape[0] == 0 or n < 2:
        return 0.0
    upper = torch.triu(torch.ones(n, n, dtype=torch.bool), diagonal=1)
    return float(distance[:, upper].mean())


def _pairwise_distances(view_sets: Tensor) -> Tensor:
    vp = check_viewpoints(view_sets, "view_sets").to(torch.float64)
    if vp.ndim != 3:
        raise ValueError(f"`view_sets` must have shape (B, n, 2), got {tuple(vp.shape)}")
    return angular_distance(vp[:, :, None], vp[:, None, :])
