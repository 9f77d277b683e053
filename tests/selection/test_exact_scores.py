"""The view scores are bit-exact: equal (``torch.equal``, not ``allclose``) to a slow per-view loop.

The reference below projects one object onto one view at a time with plain Python loops (the first hit of a
pixel is the nearest voxel centre in it, depths within 1e-9 tie and go to the lowest flat index) and sums
the hit values one after the other in pixel order, in the volume's float dtype. That is the order the
vectorised scores add in, so float sums must match to the last bit, not only to a tolerance.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from lightning_vtr.geometry import DEFAULT_HALF_EXTENT, candidate_viewpoints, orthographic_pixel_coords, voxel_centers
from lightning_vtr.selection import ErrorGuidedSelector, first_hit
from lightning_vtr.selection.projection import error_volume, projection_scores, visible_error_scores


# ------------------------------------------------------------------------------------ reference
def pixel_coords(views: torch.Tensor, res: int) -> torch.Tensor:
    """``(V, R^3, 3)`` pixel coordinates of the voxel centres, projected in the scores' chunks of views.

    The views include voxel centres exactly on pixel edges, where the last bit of a coordinate decides the pixel;
    on CPUs with wide vector units that bit can depend on how many views one call projects together, so the
    reference takes its coordinates from the same geometry calls as the scores and checks everything after them.
    """
    centres = voxel_centers(res, torch.float64).reshape(-1, 3)
    step = first_hit._TABLE_VIEW_CHUNK
    chunks = [views[s : s + step].double() for s in range(0, len(views), step)]
    return torch.cat([orthographic_pixel_coords(centres, c, res, DEFAULT_HALF_EXTENT) for c in chunks])


def first_hit_voxels(occupied: np.ndarray, coords: list) -> dict[int, int]:
    """``{pixel: voxel}`` of one view: each occupied voxel claims its centre's pixel if it is nearer than the
    current claimant (by more than 1e-9; flat order, so ties keep the lowest index). Image ``R x R`` pixels."""
    res = occupied.shape[0]
    nearest: dict[int, tuple[float, int]] = {}
    for n, is_occupied in enumerate(occupied.reshape(-1).tolist()):
        if not is_occupied:
            continue
        row, col, depth = coords[n]
        r, c = math.floor(row), math.floor(col)
        if not (0 <= r < res and 0 <= c < res):
            continue
        pixel = r * res + c
        if pixel not in nearest or depth < nearest[pixel][0] - 1e-9:
            nearest[pixel] = (depth, n)
    return {pixel: n for pixel, (_, n) in nearest.items()}


def reference_scores(
    occupied: torch.Tensor, values: torch.Tensor, views: torch.Tensor, reduction: str = "sum"
) -> torch.Tensor:
    """``(B, V)``: per object and view, the values of the first hits on ``occupied`` summed in pixel order in
    ``values.dtype`` (then divided by the hit count for ``"mean"``, 0 without a hit)."""
    dtype = values.dtype
    np_dtype = {torch.float32: np.float32, torch.float64: np.float64}[dtype]
    scores = torch.zeros(occupied.shape[0], views.shape[0], dtype=dtype)
    coords = pixel_coords(views, occupied.shape[1]).tolist()
    for b in range(occupied.shape[0]):
        flat_values = values[b].reshape(-1).numpy()
        for v in range(views.shape[0]):
            hits = first_hit_voxels(occupied[b].numpy(), coords[v])
            total = np_dtype(0)
            for pixel in sorted(hits):  # one addition at a time, in pixel order
                total = np_dtype(total + flat_values[hits[pixel]])
            if reduction == "mean":
                total = np_dtype(total / np_dtype(len(hits))) if hits else np_dtype(0)
            scores[b, v] = torch.tensor(total, dtype=dtype)
    return scores


# ------------------------------------------------------------------------------------ objects
def random_objects(res: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Predictions and targets of 4 objects: a ball and a box (solid: the culling path), a sparse random cloud
    (no culling), and a slab, with ~20 % of the predictions wrong and soft probabilities."""
    gen = torch.Generator().manual_seed(seed)
    c = voxel_centers(res, torch.float64)
    ball = (c - torch.tensor([0.05, -0.1, 0.0], dtype=torch.float64)).norm(dim=-1) < 0.4
    box = (c[..., 0] > -0.45) & (c[..., 0] < 0.2) & (c[..., 1].abs() < 0.3) & (c[..., 2] < 0.35)
    cloud = torch.rand(res, res, res, generator=gen, dtype=torch.float64) < 0.12
    slab = ((c @ torch.tensor([0.6, 0.48, 0.64], dtype=torch.float64)).abs() < 0.15) & (c.norm(dim=-1) < 0.45)
    target = torch.stack([ball, box, cloud, slab]).float()
    noise = torch.rand(target.shape, generator=gen)
    wrong = torch.rand(target.shape, generator=gen) < 0.2
    predicted = torch.where(target > 0, 0.55 + 0.45 * noise, 0.35 * noise)
    predicted = torch.where(wrong, 1.0 - predicted, predicted)
    return predicted, target


VIEWS = {
    "k60": candidate_viewpoints(60),
    # a few views off the bin centres too: yaw 0 / pitch 0 put voxel centres exactly on pixel edges and in
    # depth ties, and uneven octant groups exercise the padded buffer columns
    "mixed": torch.cat(
        [candidate_viewpoints(90), torch.tensor([[0.0, 0.0], [90.0, 0.0], [30.0, 90.0], [12.0, -37.0], [-45.0, 35.0]])]
    ),
}


# -------------------------------------------------------------------------------------- tests
@pytest.mark.parametrize("views", list(VIEWS))
@pytest.mark.parametrize("res", [7, 10])
@pytest.mark.parametrize("reduction", ["sum", "mean"])
def test_projection_scores_equal_the_loop_reference_exactly(res, reduction, views):
    predicted, target = random_objects(res, seed=res)
    vp = VIEWS[views]
    # the paper's error: binary (hit counts), as bool and as float; the released one: soft, inside the truth
    binary = error_volume(predicted, target, mode="binary")
    soft = error_volume(predicted, target, mode="soft", mask="gt")
    for volumes, flag in ((binary > 0, True), (binary, None), (soft, None), (soft.double(), None)):
        values = volumes.float() if volumes.dtype == torch.bool else volumes
        expected = reference_scores(volumes > 0, values, vp, reduction)
        got = projection_scores(volumes, vp, reduction=reduction, binary=flag)
        assert got.dtype == expected.dtype
        assert torch.equal(got, expected), (volumes.dtype, flag, (got - expected).abs().max())


@pytest.mark.parametrize("views", list(VIEWS))
@pytest.mark.parametrize("res", [7, 10])
@pytest.mark.parametrize("mode", ["binary", "soft"])
def test_visible_scores_equal_the_loop_reference_exactly(res, mode, views):
    predicted, target = random_objects(res, seed=100 + res)
    vp = VIEWS[views]
    surface = (predicted >= 0.4) | (target >= 0.5)
    errors = error_volume(predicted, target, mode=mode)
    got = visible_error_scores(predicted, target, vp, threshold=0.4, mode=mode)
    assert torch.equal(got, reference_scores(surface, errors, vp)), got - reference_scores(surface, errors, vp)


@pytest.mark.parametrize("score", ["paper", "released", "visible"])
def test_selector_scores_equal_the_loop_reference_exactly(score):
    predicted, target = random_objects(8, seed=7)
    selector = ErrorGuidedSelector.paper(k=60, score=score)
    gt = target >= 0.5
    if score == "visible":
        expected = reference_scores((predicted >= 0.4) | gt, ((predicted >= 0.4) != gt).float(), selector.candidates)
    elif score == "released":
        soft = (predicted - target).abs() * gt
        expected = reference_scores(soft > 0, soft, selector.candidates, "mean")
    else:
        errors = ((predicted >= 0.4) != gt).float()
        expected = reference_scores(errors > 0, errors, selector.candidates)
    assert torch.equal(selector.score_views(predicted, target), expected)


def test_scores_do_not_depend_on_the_chunking(monkeypatch):
    # Objects are scored in chunks bounded by pairs and buffer slots; one object per chunk must change nothing.
    predicted, target = random_objects(10, seed=3)
    views = VIEWS["mixed"]
    soft = error_volume(predicted, target, mode="soft", mask="gt")
    whole = (
        projection_scores(soft, views, reduction="mean"),
        projection_scores(soft > 0, views, binary=True),
        visible_error_scores(predicted, target, views),
        visible_error_scores(predicted, target, views, mode="soft"),
    )
    monkeypatch.setattr(first_hit, "_SCORE_CHUNK_PAIRS", 1)
    monkeypatch.setattr(first_hit, "_SCORE_CHUNK_SLOTS", 1)
    chunked = (
        projection_scores(soft, views, reduction="mean"),
        projection_scores(soft > 0, views, binary=True),
        visible_error_scores(predicted, target, views),
        visible_error_scores(predicted, target, views, mode="soft"),
    )
    for one, other in zip(whole, chunked):
        assert torch.equal(one, other)


@pytest.mark.parametrize("mask", [None, "gt"])
@pytest.mark.parametrize("reduction", ["sum", "mean"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64, torch.float16])
def test_soft_error_scores_equal_the_two_step_form_exactly(mask, reduction, dtype):
    # The selector's soft scores write the error straight into the summed rows; they must equal scoring the
    # error volume, bit for bit, also with eps, a NaN and half precision (which takes the two-step form).
    from lightning_vtr.selection.projection import soft_error_scores

    predicted, target = random_objects(9, seed=21)
    predicted, target = predicted.to(dtype), target.to(dtype)
    predicted[1, 2, 3, 4] = float("nan")
    views = VIEWS["mixed"]
    for eps in (0.0, 0.25):
        errors = error_volume(predicted, target, mode="soft", mask=mask)
        expected = projection_scores(errors, views, reduction=reduction, eps=eps, binary=False)
        got = soft_error_scores(predicted, target, views, mask=mask, reduction=reduction, eps=eps)
        assert got.dtype == expected.dtype
        assert torch.equal(got, expected)
