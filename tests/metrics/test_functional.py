"""Functional voxel IoU / F-score against hand-computed and independent references."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from lightning_vtr.metrics import voxel_fscore, voxel_iou
from lightning_vtr.metrics.functional import check_thresholds

R = 32


def _cube(lo: int, hi: int, shift: int = 0) -> torch.Tensor:
    g = torch.zeros(1, R, R, R)
    g[0, lo + shift : hi + shift, lo:hi, lo:hi] = 1
    return g


def _reference_iou(p: np.ndarray, g: np.ndarray, t: float) -> float:
    inter = union = 0
    for a, b in zip((p >= t).ravel(), (g >= 0.5).ravel()):
        inter += int(a and b)
        union += int(a or b)
    return inter / union


def test_iou_hand_made_grid():
    g = torch.zeros(1, 2, 2, 2)
    g[0, 0] = 1  # 4 occupied cells
    p = torch.zeros(1, 2, 2, 2)
    p[0, 0, 0, 0], p[0, 0, 0, 1], p[0, 1, 0, 0] = 0.9, 0.35, 0.25
    iou = voxel_iou(p, g, thresholds=(0.2, 0.3, 0.4, 0.5))
    # t=0.2: 3 predicted (2 hits) -> 2 / 5; t=0.3: 2 hits / 4; t>=0.4: 1 hit / 4.
    torch.testing.assert_close(iou, torch.tensor([[2 / 5, 2 / 4, 1 / 4, 1 / 4]]))


def test_iou_matches_reference_on_random_grids():
    gen = torch.Generator().manual_seed(0)
    p = torch.rand(3, 6, 6, 6, generator=gen)
    g = (torch.rand(3, 6, 6, 6, generator=gen) > 0.6).float()
    iou = voxel_iou(p, g)
    for b in range(3):
        for j, t in enumerate((0.2, 0.3, 0.4, 0.5)):
            assert iou[b, j].item() == pytest.approx(_reference_iou(p[b].numpy(), g[b].numpy(), t), abs=1e-6)


def test_iou_identical_disjoint_and_empty():
    g = _cube(4, 12)
    assert voxel_iou(g, g).eq(1).all()
    assert voxel_iou(_cube(20, 28), g).eq(0).all()
    empty = torch.zeros_like(g)
    assert voxel_iou(empty, empty).eq(1).all()  # both empty: defined as agreement
    assert voxel_iou(empty, g).eq(0).all()


def test_iou_errors_name_shapes():
    with pytest.raises(ValueError, match=r"same shape.*\(1, 4, 4, 4\).*\(1, 5, 5, 5\)"):
        voxel_iou(torch.zeros(1, 4, 4, 4), torch.zeros(1, 5, 5, 5))
    with pytest.raises(ValueError, match=r"\(B, R, R, R\)"):
        voxel_iou(torch.zeros(4, 4, 4), torch.zeros(4, 4, 4))
    with pytest.raises(ValueError, match="NaN"):
        voxel_iou(torch.full((1, 2, 2, 2), float("nan")), torch.zeros(1, 2, 2, 2))


def test_fscore_identical_small_object_is_one():
    g = _cube(14, 18)  # side 0.125: area 0.094, 8192 samples are far denser than 1 % spacing
    assert voxel_fscore(g, g).item() == pytest.approx(1.0, abs=1e-3)


def test_fscore_identical_large_object_matches_sampling_density():
    # With N uniform samples on area A, a sample's nearest other-set sample lies within d with
    # probability 1 - exp(-N pi d^2 / A) (Poisson approximation; edges lower it slightly).
    g = _cube(8, 24)  # side 0.5, area about 6 * 0.25 = 1.5 (marching cubes bevels the edges)
    expected = 1 - math.exp(-8192 * math.pi * 0.01**2 / 1.5)
    assert voxel_fscore(g, g).item() == pytest.approx(expected, abs=0.03)


def test_fscore_empty_and_disjoint():
    g = _cube(4, 12)
    empty = torch.zeros_like(g)
    assert voxel_fscore(empty, g).item() == 0.0
    assert voxel_fscore(g, empty).item() == 0.0
    assert voxel_fscore(empty, empty).item() == 1.0
    assert voxel_fscore(_cube(20, 28), g).item() == 0.0  # surfaces 8 cells = 0.25 apart


def test_fscore_shifted_cube_band():
    # A 16-cell cube shifted by one cell (1/32 > d): only the four side faces keep coinciding
    # over 15/16 of their area, so about 4 * 15/16 / 6 = 0.63 of each surface is within d
    # (plus thin strips near edges), times the sampling factor of the identical case (about 0.82).
    g = _cube(8, 24)
    score = voxel_fscore(_cube(8, 24, shift=1), g).item()
    assert 0.45 <= score <= 0.62


def test_fscore_threshold_binarises_prediction():
    g = _cube(14, 18)
    assert voxel_fscore(g * 0.45, g, threshold=0.4).item() == pytest.approx(1.0, abs=1e-3)
    assert voxel_fscore(g * 0.45, g, threshold=0.5).item() == 0.0


def test_fscore_seeded():
    g, p = _cube(8, 24), _cube(8, 24, shift=1)
    assert voxel_fscore(p, g, seed=3).item() == voxel_fscore(p, g, seed=3).item()


def test_fscore_argument_errors():
    g = _cube(14, 18)
    with pytest.raises(ValueError, match="^`num_points` must be an int >= 1, got 0$"):
        voxel_fscore(g, g, num_points=0)
    with pytest.raises(TypeError, match="^`num_points` must be an int, got float 10.0$"):
        voxel_fscore(g, g, num_points=10.0)
    with pytest.raises(ValueError, match="^`distance` must be a number > 0, got 0.0$"):
        voxel_fscore(g, g, distance=0.0)
    with pytest.raises(ValueError, match=r"^`threshold` must be a number in \[0, 1\], got 1.5$"):
        voxel_fscore(g, g, threshold=1.5)


def test_check_thresholds():
    assert check_thresholds((0.2, 1)) == (0.2, 1.0)
    assert check_thresholds(torch.tensor([0.5])) == (0.5,)
    with pytest.raises(ValueError, match=r"^`thresholds\[1\]` must be a number in \[0, 1\], got 1.5$"):
        check_thresholds([0.4, 1.5])
    with pytest.raises(
        ValueError, match=r"^`thresholds` must be a non-empty sequence of numbers in \[0, 1\], got \(\)$"
    ):
        check_thresholds(())
    with pytest.raises(TypeError, match=r"^`thresholds` must be a sequence of numbers in \[0, 1\], got float 0.4$"):
        check_thresholds(0.4)
    with pytest.raises(TypeError, match=r"^`thresholds\[0\]` must be a number, got str 'a'$"):
        check_thresholds(["a"])
