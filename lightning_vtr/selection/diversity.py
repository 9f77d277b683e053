r"""Choosing the ``n`` angle bins an object is shown from: hard top-``n``, non-maximum suppression, tempered sampling.

The paper keeps the ``n`` highest-scoring bins. Two things go wrong with that alone: the chosen bins can
sit next to each other or face each other (a view and its antipode see mirror-image silhouettes), and one
hard rule cannot be compared with the trivial alternative, uniform random views, on one axis.
:func:`choose_bins` adds both remedies as options:

* **Non-maximum suppression** (``min_separation``): once a bin is chosen, no bin whose centre lies within
  ``min_separation`` degrees of it, or of its antipode, may be chosen. ``0`` suppresses only the antipodal
  bin itself.
* **Tempered sampling** (``temperature`` :math:`\tau`): the bins are drawn without replacement with
  probability :math:`\propto \Omega_b \, s_b^{1/\tau}`, where :math:`\Omega_b` is the bin's solid angle and
  :math:`s_b` its score. :math:`\tau \to 0` recovers the hard top ``n``; :math:`\tau \to \infty` draws bins
  in proportion to their area, i.e. area-uniform random views. One knob spans the two strategies.

Bins are indexed in :func:`~lightning_vtr.geometry.candidate_viewpoints` order; angles are in degrees.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from lightning_vtr.geometry import angle_bins, angular_distance, candidate_viewpoints, check_bin_interval
from lightning_vtr.utils.validation import check_float, check_int

__all__ = ["bin_solid_angles", "choose_bins", "suppression_matrix"]

#: Added to the key of a bin whose score is 0, so that such bins are drawn only when no scored bin is left.
_UNSCORED_PENALTY = 1e12


def bin_solid_angles(k: int = 30) -> Tensor:
    """Solid angle (steradians) of every bin of interval ``K``, shape ``(180/K * 360/K,)``; they sum to 4π.

    A bin spanning pitch ``[a, b]`` and ``K`` degrees of yaw covers ``radians(K) * (sin b - sin a)``.
    """
    k = check_bin_interval(k)
    _, pitch = angle_bins(k)
    low = torch.deg2rad(pitch.to(torch.float64) - k / 2)
    high = torch.deg2rad(pitch.to(torch.float64) + k / 2)
    band = math.radians(k) * (torch.sin(high) - torch.sin(low))  # (180/K,)
    return band.repeat_interleave(360 // k)


def suppression_matrix(k: int = 30, min_separation: float = 0.0) -> Tensor:
    """``(V, V)`` bool: entry ``[i, j]`` says choosing bin ``i`` forbids bin ``j``.

    ``j`` is forbidden when its centre lies within ``min_separation`` degrees of ``i``'s centre or of the
    antipode of ``i``'s centre (the antipodal bin itself is always forbidden). The diagonal is ``True``.
    """
    k = check_bin_interval(k)
    min_separation = check_float("min_separation", min_separation, minimum=0.0, maximum=180.0)
    centres = candidate_viewpoints(k).to(torch.float64)
    distance = angular_distance(centres[:, None], centres[None, :])  # (V, V)
    # half a degree of slack absorbs the acos round-off at exact antipodes and separations
    slack = 0.5
    return (distance <= min_separation + slack) | (distance >= 180.0 - min_separation - slack)


def choose_bins(
    scores: Tensor,
    n: int = 3,
    *,
    k: int = 30,
    min_separation: float | None = None,
    temperature: float | None = None,
    generator: torch.Generator | None = None,
) -> Tensor:
    r"""Indices ``(B, n)`` of the bins to sample views around, in the order they were chosen.

    Args:
        scores: ``(B, V)`` non-negative view scores, ``V = (180/K)(360/K)``.
        n: bins per object, ``1 <= n <= V``.
        k: bin interval ``K`` in degrees (must divide 180).
        min_separation: ``None`` for no suppression; else the non-maximum-suppression angle in degrees
            (see :func:`suppression_matrix`). Where suppression leaves fewer than ``n`` bins, the rest are
            taken in key order among the bins not yet chosen.
        temperature: ``None`` (or 0) for the hard top ``n``; else :math:`\tau > 0` of the tempered
            sampling :math:`P(b) \propto \Omega_b s_b^{1/\tau}`. Bins scoring 0 come after every scored bin.
        generator: CPU generator. The hard rule draws ``(B, V)`` uniforms (the random order of exact ties,
            as :func:`~lightning_vtr.selection.projection.top_bins`); the tempered rule ``(B, V)`` uniforms
            for the Gumbel keys.

    Returns:
        ``(B, n)`` int64 bin indices on the device of ``scores``. Without suppression and temperature this
        equals :func:`~lightning_vtr.selection.projection.top_bins` for the same generator state.
    """
    k = check_bin_interval(k)
    n_bins = (180 // k) * (360 // k)
    if not isinstance(scores, Tensor) or scores.ndim != 2 or scores.shape[1] != n_bins:
        shape = tuple(scores.shape) if isinstance(scores, Tensor) else type(scores).__name__
        raise ValueError(f"`scores` must have shape (B, {n_bins}) for K={k}, got {shape}")
    n = check_int("n", n, minimum=1, maximum=n_bins)
    if temperature is not None:
        temperature = check_float("temperature", temperature, minimum=0.0)
    batch = scores.shape[0]
    values = scores.detach().to("cpu", torch.float64)
    uniforms = torch.rand((batch, n_bins), generator=generator, dtype=torch.float64)

    if not temperature:
        # rank of each bin by (score desc, random priority): a unique key, ties in random order
        shuffled = torch.argsort(uniforms, dim=1)
        by_score = torch.argsort(-values.gather(1, shuffled), dim=1, stable=True)
        order = shuffled.gather(1, by_score)
        keys = torch.empty_like(values).scatter_(1, order, -torch.arange(n_bins, dtype=torch.float64).expand(batch, -1))
    else:
        gumbel = -torch.log(-torch.log(uniforms.clamp(1e-300, 1.0 - 1e-16)))
        log_area = torch.log(bin_solid_angles(k))
        scored = values > 0
        log_score = torch.where(scored, values.clamp_min(1e-300).log() / temperature, torch.zeros_like(values))
        keys = log_area + log_score + gumbel - _UNSCORED_PENALTY * (~scored).to(torch.float64)

    suppress = None if min_separation is None else suppression_matrix(k, min_separation)
    chosen = torch.zeros((batch, n_bins), dtype=torch.bool)
    blocked = torch.zeros((batch, n_bins), dtype=torch.bool)
    picks = []
    rows = torch.arange(batch)
    for _ in range(n):
        allowed = ~(blocked | chosen)
        # a row with nothing allowed falls back to any bin not yet chosen
        allowed = torch.where(allowed.any(1, keepdim=True), allowed, ~chosen)
        pick = keys.masked_fill(~allowed, -math.inf).argmax(1)
        picks.append(pick)
        chosen[rows, pick] = True
        if suppress is not None:
            blocked |= suppress[pick]
    return torch.stack(picks, 1).to(scores.device)
