"""Functional voxel-reconstruction metrics: IoU at thresholds and the surface F-score.

These hold the math; :mod:`lightning_vtr.metrics` wraps them in torchmetrics ``Metric`` classes
that accumulate per-object scores and sync across processes (DESIGN section 7).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import numpy as np
import torch
from scipy.spatial import cKDTree
from skimage.measure import marching_cubes
from torch import Tensor

from lightning_vtr.utils.validation import check_float, check_int

__all__ = ["DEFAULT_IOU_THRESHOLDS", "check_thresholds", "surface_points", "voxel_fscore", "voxel_iou"]

#: The thresholds of Pix2Vox++'s test protocol; the paper's tables use 0.4.
DEFAULT_IOU_THRESHOLDS: tuple[float, ...] = (0.2, 0.3, 0.4, 0.5)


def _check_pair(preds: Tensor, target: Tensor) -> tuple[Tensor, Tensor]:
    if not isinstance(preds, Tensor) or not isinstance(target, Tensor):
        raise TypeError(f"`preds` and `target` must be tensors, got {type(preds).__name__} and {type(target).__name__}")
    if preds.ndim != 4:
        raise ValueError(f"`preds` must have shape (B, R, R, R), got {tuple(preds.shape)}")
    if preds.shape != target.shape:
        raise ValueError(
            f"`preds` and `target` must have the same shape, got {tuple(preds.shape)} and {tuple(target.shape)}"
        )
    if preds.is_floating_point() and not torch.isfinite(preds).all():
        raise ValueError("`preds` must hold finite probabilities, got NaN or infinite values")
    return preds, target


def check_thresholds(thresholds: Sequence[float], name: str = "thresholds") -> tuple[float, ...]:
    """Binarisation thresholds as a tuple of floats, each in ``[0, 1]`` (the IoU metrics' ``thresholds``).

    Args:
        thresholds: a non-empty sequence of numbers (a 1-d tensor or array works too).
        name: the argument's name in error messages.

    Raises:
        TypeError: ``thresholds`` is not a sequence (a lone number or a string) or holds a non-number.
        ValueError: it is empty or a value lies outside ``[0, 1]``.
    """
    if isinstance(thresholds, (Tensor, np.ndarray)):
        thresholds = thresholds.tolist()
    if isinstance(thresholds, (str, bytes)) or not isinstance(thresholds, Iterable):
        raise TypeError(
            f"`{name}` must be a sequence of numbers in [0, 1], got {type(thresholds).__name__} {thresholds!r}"
        )
    values = tuple(check_float(f"{name}[{i}]", t, minimum=0.0, maximum=1.0) for i, t in enumerate(thresholds))
    if not values:
        raise ValueError(f"`{name}` must be a non-empty sequence of numbers in [0, 1], got {thresholds!r}")
    return values


def voxel_iou(preds: Tensor, target: Tensor, thresholds: Sequence[float] = DEFAULT_IOU_THRESHOLDS) -> Tensor:
    r"""Per-object voxel IoU at several thresholds.

    .. math::
        \mathrm{IoU}_t = \frac{\sum_{ijk} [p_{ijk} \ge t]\, g_{ijk}}{\sum_{ijk} [([p_{ijk} \ge t] + g_{ijk}) \ge 1]}

    Two empty grids agree perfectly and get IoU 1 (the formula alone gives 0 / 0).

    Args:
        preds: occupancy probabilities ``(B, R, R, R)``.
        target: ground-truth occupancy ``(B, R, R, R)``; values ``>= 0.5`` count as occupied.
        thresholds: the ``T`` thresholds ``t``.

    Returns:
        ``(B, T)`` IoU of each object at each threshold, float32.

    Raises:
        TypeError: ``preds`` or ``target`` is not a tensor, or ``thresholds`` is not a sequence of numbers.
        ValueError: the shapes differ or are not ``(B, R, R, R)``, ``preds`` is not finite, or a threshold
            lies outside ``[0, 1]``.

    Example:
        >>> g = torch.zeros(1, 2, 2, 2); g[0, 0] = 1
        >>> p = torch.zeros(1, 2, 2, 2); p[0, 0, 0] = 0.9; p[0, 1, 0] = 0.3
        >>> voxel_iou(p, g, thresholds=(0.2, 0.5))
        tensor([[0.3333, 0.5000]])
    """
    preds, target = _check_pair(preds, target)
    ts = check_thresholds(thresholds)
    gt = (target >= 0.5).flatten(1)  # (B, N)
    p = preds.flatten(1).float()
    binary = p.unsqueeze(1) >= torch.tensor(ts, device=p.device).view(1, -1, 1)  # (B, T, N)
    inter = (binary & gt.unsqueeze(1)).sum(-1).float()
    union = (binary | gt.unsqueeze(1)).sum(-1).float()
    return torch.where(union > 0, inter / union.clamp_min(1), torch.ones_like(union))


def surface_points(occupancy: np.ndarray, num_points: int, rng: np.random.Generator) -> np.ndarray | None:
    """Points sampled uniformly by area on the marching-cubes surface of a binary grid.

    The grid is padded by one empty cell so that objects touching the border still get a closed
    surface, and vertices are mapped to world coordinates in :mod:`lightning_vtr.geometry`'s voxel
    convention (cell ``i`` has its centre at ``(i + 0.5) / R - 0.5``), i.e. the unit cube.

    Args:
        occupancy: boolean ``(R, R, R)`` grid.
        num_points: how many points to sample.
        rng: numpy generator driving the sampling.

    Returns:
        ``(num_points, 3)`` float64 points, or ``None`` if the grid is empty.
    """
    if not occupancy.any():
        return None
    padded = np.pad(occupancy.astype(np.float32), 1)
    verts, faces, _, _ = marching_cubes(padded, level=0.5)
    # Padded index p is cell p - 1, whose centre is at (p - 0.5) / R - 0.5.
    res = np.asarray(occupancy.shape, dtype=np.float64)
    verts = (verts - 0.5) / res - 0.5
    tri = verts[faces]  # (F, 3, 3)
    areas = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    face_idx = rng.choice(len(faces), size=num_points, p=areas / areas.sum())
    # Uniform barycentric sampling: reflect (u, v) outside the triangle back inside.
    uv = rng.random((num_points, 2))
    outside = uv.sum(1) > 1
    uv[outside] = 1 - uv[outside]
    a, b, c = tri[face_idx, 0], tri[face_idx, 1], tri[face_idx, 2]
    return a + uv[:, :1] * (b - a) + uv[:, 1:] * (c - a)


def voxel_fscore(
    preds: Tensor,
    target: Tensor,
    *,
    threshold: float = 0.4,
    num_points: int = 8192,
    distance: float = 0.01,
    seed: int | None = 0,
    generator: np.random.Generator | None = None,
) -> Tensor:
    r"""Per-object F-score at distance ``d`` between the surfaces of two voxel grids.

    The community F-score@1% (Tatarchenko et al. 2019, as used by Pix2Vox++ and the paper):
    binarise, extract each surface by marching cubes in the unit cube, sample ``num_points`` points
    on each, and with :math:`D(x, Y) = \min_{y \in Y} \lVert x - y \rVert`:

    .. math::
        P = \frac{1}{|X|}\sum_{x \in X} [D(x, Y) < d], \quad
        R = \frac{1}{|Y|}\sum_{y \in Y} [D(y, X) < d], \quad
        F = \frac{2PR}{P + R}

    with ``X`` sampled on the prediction and ``Y`` on the ground truth. ``F = 0`` when exactly one
    grid is empty and ``F = 1`` when both are (they agree). Because distances are measured between
    samples, identical surfaces of area ``A`` score about ``1 - exp(-N pi d^2 / A)``, not 1.

    Args:
        preds: occupancy probabilities ``(B, R, R, R)``, binarised at ``threshold``.
        target: ground truth ``(B, R, R, R)``; values ``>= 0.5`` count as occupied.
        threshold: binarisation threshold for ``preds``.
        num_points: points sampled on each surface.
        distance: ``d``, in units of the unit cube (0.01 = 1 %).
        seed: seed of the sampling generator (used when ``generator`` is None).
        generator: a numpy generator to draw from instead of a fresh seeded one.

    Returns:
        ``(B,)`` float32 F-scores in ``[0, 1]``.

    Raises:
        TypeError: a tensor argument is not a tensor, or a number argument is not a number.
        ValueError: the shapes differ or are not ``(B, R, R, R)``, ``preds`` is not finite, ``threshold``
            is outside ``[0, 1]``, ``num_points < 1`` or ``distance <= 0``.
    """
    preds, target = _check_pair(preds, target)
    threshold = check_float("threshold", threshold, minimum=0.0, maximum=1.0)
    num_points = check_int("num_points", num_points, minimum=1)
    distance = check_float("distance", distance, minimum=0.0, min_open=True)
    rng = generator if generator is not None else np.random.default_rng(seed)
    pred_np = (preds.detach() >= threshold).cpu().numpy()
    gt_np = (target.detach() >= 0.5).cpu().numpy()
    scores = []
    for p_grid, g_grid in zip(pred_np, gt_np):
        x = surface_points(p_grid, num_points, rng)
        y = surface_points(g_grid, num_points, rng)
        if x is None or y is None:
            scores.append(1.0 if x is None and y is None else 0.0)
            continue
        precision = float((cKDTree(y).query(x, k=1)[0] < distance).mean())
        recall = float((cKDTree(x).query(y, k=1)[0] < distance).mean())
        total = precision + recall
        scores.append(2 * precision * recall / total if total > 0 else 0.0)
    return torch.tensor(scores, dtype=torch.float32, device=preds.device)
