"""Functional voxel IoU / F-score against hand-computed and independent references."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

from lightning_vtr.metrics import voxel_fscore, voxel_iou, voxel_iou_best
from lightning_vtr.metrics.functional import _surface_triangles, check_thresholds, precision_recall, surface_points

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
    assert voxel_iou(g, empty).eq(0).all()
    assert voxel_iou(g * 0.3, g).tolist() == [[1.0, 1.0, 0.0, 0.0]]  # empty below 0.3, not above


def _two_objects() -> tuple[torch.Tensor, torch.Tensor]:
    """Object 0 is best at 0.4 (IoU 1, 0), object 1 at 0.5 (IoU 0.5, 1) of thresholds (0.4, 0.5)."""
    g = torch.zeros(2, 2, 2, 2)
    g[:, 0] = 1  # 4 of 8 cells
    p = torch.zeros(2, 2, 2, 2)
    p[0, 0] = 0.45  # >= 0.4 exactly on the target; nothing >= 0.5
    p[1] = 0.42
    p[1, 0] = 0.9  # >= 0.5 exactly on the target; >= 0.4 everywhere
    return p, g


def test_iou_best_is_max_of_means_not_mean_of_maxima():
    p, g = _two_objects()
    torch.testing.assert_close(voxel_iou(p, g, thresholds=(0.4, 0.5)), torch.tensor([[1.0, 0.0], [0.5, 1.0]]))
    best = voxel_iou_best(p, g, thresholds=(0.4, 0.5))
    assert best.shape == () and best.item() == 0.75  # means (0.75, 0.5); the mean of maxima would be 1
    assert voxel_iou_best(p, g, thresholds=(0.5,)).item() == 0.5
    assert voxel_iou_best(p[1:], g[1:], thresholds=(0.4, 0.5)).item() == 1.0


def test_iou_best_default_thresholds_and_empty():
    p, g = _two_objects()
    # Default (0.2, 0.3, 0.4, 0.5): object 1 predicts every cell up to 0.4, so means (0.75, 0.75, 0.75, 0.5).
    assert voxel_iou_best(p, g).item() == 0.75
    empty = torch.zeros(1, 2, 2, 2)
    assert voxel_iou_best(empty, empty).item() == 1.0
    assert voxel_iou_best(empty, g[:1]).item() == 0.0


def test_iou_errors_name_shapes():
    with pytest.raises(ValueError, match=r"same shape.*\(1, 4, 4, 4\).*\(1, 5, 5, 5\)"):
        voxel_iou(torch.zeros(1, 4, 4, 4), torch.zeros(1, 5, 5, 5))
    with pytest.raises(ValueError, match=r"\(B, R, R, R\)"):
        voxel_iou(torch.zeros(4, 4, 4), torch.zeros(4, 4, 4))
    with pytest.raises(ValueError, match="NaN"):
        voxel_iou(torch.full((1, 2, 2, 2), float("nan")), torch.zeros(1, 2, 2, 2))


CONVENTIONS = ("community", "centred")


def _cube_surface_area(side: int, convention: str) -> float:
    """Area of the marching-cubes surface of a cube of ``side`` cells, in cells squared.

    Both surfaces are a box with flat faces of (side - 1)^2 cells, 45-degree strips along the 12 edges
    and a triangle at each of the 8 corners. At iso 0 (community) the vertices sit on the empty cells
    next to the cube: strips sqrt(2) wide, corner triangles of side sqrt(2); at level 0.5 (centred)
    halfway there: strips sqrt(2) / 2 wide, corner triangles of side sqrt(2) / 2.
    """
    w = math.sqrt(2) if convention == "community" else math.sqrt(2) / 2
    return 6 * (side - 1) ** 2 + 12 * w * (side - 1) + 8 * math.sqrt(3) / 4 * w**2


def _cell(convention: str, res: int = R) -> float:
    return 1 / (res + 1) if convention == "community" else 1 / res


def _table() -> torch.Tensor:
    """A hand-built table: a 16 x 2 x 16 top on four 2 x 12 x 2 legs (thin parts, like ShapeNet objects)."""
    g = torch.zeros(1, R, R, R)
    g[0, 8:24, 14:16, 8:24] = 1
    for a in (8, 22):
        for b in (8, 22):
            g[0, a : a + 2, 2:14, b : b + 2] = 1
    return g


@pytest.mark.parametrize("convention", CONVENTIONS)
def test_surface_of_one_cell_is_the_conventions_octahedron(convention):
    # One occupied cell: each of the 8 marching cubes around it cuts one corner, so the surface is a
    # regular octahedron {x : |x - c|_1 = r}. Community: vertices on the 6 empty neighbours (r = one
    # cell = 1 / (R + 1)), centre at padded index 3 / (R + 1). Centred: r = half a cell = 0.5 / R,
    # centre at the cell centre (2 + 0.5) / R - 0.5.
    g = np.zeros((R, R, R), dtype=bool)
    g[2, 2, 2] = True
    pts = surface_points(g, 2000, np.random.default_rng(0), convention=convention)
    if convention == "community":
        centre, radius = 3 / (R + 1), 1 / (R + 1)
    else:
        centre, radius = 2.5 / R - 0.5, 0.5 / R
    np.testing.assert_allclose(np.abs(pts - centre).sum(1), radius, rtol=1e-9)
    # All 8 faces get samples (uniform by area): each octant of offsets holds about 1/8 of the points.
    octant = ((pts - centre) > 0) @ np.array([1, 2, 4])
    assert np.bincount(octant, minlength=8).min() > 2000 / 8 * 0.7


@pytest.mark.parametrize("convention", CONVENTIONS)
def test_surface_area_of_a_cube(convention):
    g = np.zeros((R, R, R), dtype=bool)
    g[8:24, 8:24, 8:24] = True
    tri = _surface_triangles(g, convention)
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum()
    assert area == pytest.approx(_cube_surface_area(16, convention) * _cell(convention) ** 2, rel=1e-9)


def test_community_surface_matches_pymcubes():
    """What3D's surface is PyMCubes at iso 0 on the padded grid, divided by R + 1: same area and moments."""
    mcubes = pytest.importorskip("mcubes")
    grid = np.random.default_rng(3).random((12, 12, 12)) < 0.4  # many ambiguous cube configurations
    verts, faces = mcubes.marching_cubes(np.pad(grid, 1).astype(np.float64), 0)
    ref = verts[faces.astype(np.int64)] / 13
    ours = _surface_triangles(grid, "community")

    def moments(tri: np.ndarray) -> np.ndarray:
        area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
        s = tri.sum(1)
        second = np.einsum("tvi,tvj->tij", tri, tri) + np.einsum("ti,tj->tij", s, s)
        return np.concatenate([[area.sum()], area @ s / 3, (area[:, None, None] * second / 12).sum(0).ravel()])

    np.testing.assert_allclose(moments(ours), moments(ref), rtol=1e-12, atol=1e-12)


def test_precision_recall_bounded_query_equals_brute_force():
    rng = np.random.default_rng(0)
    x = rng.random((1500, 3)) * 0.2
    y = x[:1000] + rng.normal(scale=0.006, size=(1000, 3))  # nearest distances straddle d
    d = 0.01
    dist = np.sqrt(((x[:, None] - y[None]) ** 2).sum(-1))
    expected_p = float((dist.min(1) < d).mean())
    expected_r = float((dist.min(0) < d).mean())
    assert 0.05 < expected_p < 0.95 and 0.05 < expected_r < 0.95
    precision, recall = precision_recall(x, y, d)
    assert precision == expected_p
    assert recall == expected_r
    # The bounded query agrees with an unbounded one point for point.
    tree = cKDTree(y)
    unbounded = tree.query(x, k=1)[0] < d
    bounded = tree.query(x, k=1, distance_upper_bound=d)[0] < d
    np.testing.assert_array_equal(bounded, unbounded)


@pytest.mark.parametrize("convention", CONVENTIONS)
def test_fscore_identical_small_object_is_one(convention):
    g = _cube(14, 18)  # side 4 cells: area about 0.1, 8192 samples are far denser than 1 % spacing
    assert voxel_fscore(g, g, convention=convention).item() == pytest.approx(1.0, abs=1e-3)


def test_fscore_identical_large_object_matches_sampling_density():
    # Centred draws triangles independently: with N uniform samples on area A, a sample's nearest
    # other-set sample lies within d with probability 1 - exp(-N pi d^2 / A) (Poisson approximation;
    # edges lower it slightly).
    area = _cube_surface_area(16, "centred") / R**2  # 1.4443
    expected = 1 - math.exp(-8192 * math.pi * 0.01**2 / area)
    assert expected == pytest.approx(0.8317, abs=1e-4)
    g = _cube(8, 24)
    assert voxel_fscore(g, g, convention="centred").item() == pytest.approx(expected, abs=0.01)
    # Community stratifies by area like Open3D <= 0.18, so both sample sets put the same number of
    # points on each triangle and match more often than the Poisson figure (0.8244 for its area
    # 1.4798). What3D/LegoFormer's own code under Open3D 0.18 scores 0.8814 +- 0.0006 (30 seeds).
    assert voxel_fscore(g, g, convention="community").item() == pytest.approx(0.881, abs=0.01)


def test_community_sampling_is_stratified_by_area():
    # Open3D <= 0.18: the first k triangles get round(N * their share of the area) points in all, so
    # each face of a cube gets a sixth of the points up to the strips and corners, whatever the seed.
    g = np.zeros((R, R, R), dtype=bool)
    g[8:24, 8:24, 8:24] = True
    for seed in range(3):
        pts = surface_points(g, 6000, np.random.default_rng(seed))
        on_face = np.isclose(pts[:, 0], 8 / (R + 1)) & (np.abs(pts[:, 1:] - 16.5 / (R + 1)) < 7.5 / (R + 1)).all(1)
        share = 15**2 / _cube_surface_area(16, "community")
        assert abs(on_face.sum() - 6000 * share) <= 2  # rounding only; independent draws vary by +-30


def test_fscore_default_is_community():
    g, p = _cube(8, 24), _cube(8, 24, shift=1)
    assert voxel_fscore(p, g).item() == voxel_fscore(p, g, convention="community").item()
    assert voxel_fscore(p, g).item() != voxel_fscore(p, g, convention="centred").item()


@pytest.mark.parametrize("convention", CONVENTIONS)
def test_fscore_empty_and_disjoint(convention):
    g = _cube(4, 12)
    empty = torch.zeros_like(g)
    assert voxel_fscore(empty, g, convention=convention).item() == 0.0  # exactly one empty: 0
    assert voxel_fscore(g, empty, convention=convention).item() == 0.0
    assert voxel_fscore(empty, empty, convention=convention).item() == 1.0  # both empty: they agree
    # A prediction below the threshold everywhere is empty too.
    assert voxel_fscore(g * 0.3, g, threshold=0.4, convention=convention).item() == 0.0
    assert voxel_fscore(_cube(20, 28), g, convention=convention).item() == 0.0  # 8 cells apart
    # Mixed batch: each object gets its own rule.
    batch = voxel_fscore(torch.cat([empty, g, empty]), torch.cat([empty, g, g]), convention=convention)
    assert batch[0].item() == 1.0 and batch[1].item() > 0.99 and batch[2].item() == 0.0


def test_fscore_community_surface_lies_half_a_cell_further_out():
    # Two single cells 3 cells apart (R = 8), d = 1.5 cells. Centred octahedra (radius 0.5 cell)
    # are 2 cells apart, beyond d: F = 0 exactly. Community octahedra (radius 1 cell) are 1 cell
    # apart, so the facing parts are within d: 0 < F < 1.
    res = 8
    p, g = torch.zeros(1, res, res, res), torch.zeros(1, res, res, res)
    p[0, 2, 4, 4] = g[0, 5, 4, 4] = 1
    centred = voxel_fscore(p, g, distance=1.5 / res, convention="centred").item()
    community = voxel_fscore(p, g, distance=1.5 / (res + 1), convention="community").item()
    assert centred == 0.0
    assert 0.05 < community < 0.2
    # With d above the largest possible distance (the two octahedra span 5 cells) everything matches.
    assert voxel_fscore(p, g, distance=6 / (res + 1), convention="community").item() == 1.0


@pytest.mark.parametrize(("convention", "low", "high"), [("community", 0.50, 0.55), ("centred", 0.49, 0.55)])
def test_fscore_shifted_cube_band(convention, low, high):
    # A 16-cell cube shifted by one cell (more than d in both conventions): the faces across the
    # shift never match; the 4 side faces (14 x 15 cells in common) and the 4 strips along the
    # shift (14 cells) keep coinciding. Community: (4 * 14 * 15 + 4 * 14 * sqrt 2) / 1611.5 = 0.570
    # of the surface, centred: (840 + 4 * 14 * sqrt 2 / 2) / 1479.0 = 0.595, times the identical
    # case's sampling factor (0.881, 0.832) gives 0.50 and 0.495, plus thin bands within d of the
    # shifted edges. Means over 30 seeds: 0.527 and 0.521; What3D/LegoFormer's code: 0.526.
    g = _cube(8, 24)
    score = voxel_fscore(_cube(8, 24, shift=1), g, convention=convention).item()
    assert low <= score <= high


def _ball(radius: float) -> torch.Tensor:
    i = torch.arange(R, dtype=torch.float64) - 15.5
    return ((i.view(-1, 1, 1) ** 2 + i.view(1, -1, 1) ** 2 + i.view(1, 1, -1) ** 2) <= radius**2).float()[None]


def test_fscore_conventions_differ_by_a_few_hundredths():
    # Identical balls of radius 10 cells, 3 seeds: community 0.896 (What3D/LegoFormer's code: 0.896),
    # centred 0.860. On a 16-cell cube 0.882 vs 0.832, on the thin table 0.949 vs 0.945.
    g = _ball(10.0)
    community = np.mean([voxel_fscore(g, g, seed=s).item() for s in range(3)])
    centred = np.mean([voxel_fscore(g, g, seed=s, convention="centred").item() for s in range(3)])
    assert community == pytest.approx(0.8955, abs=0.005)
    assert centred == pytest.approx(0.8598, abs=0.005)
    table = _table()
    diff = voxel_fscore(table, table).item() - voxel_fscore(table, table, convention="centred").item()
    assert abs(diff) < 0.015


def test_fscore_threshold_binarises_prediction():
    g = _cube(14, 18)
    assert voxel_fscore(g * 0.45, g, threshold=0.4).item() == pytest.approx(1.0, abs=1e-3)
    assert voxel_fscore(g * 0.45, g, threshold=0.5).item() == 0.0
    assert voxel_fscore(g * 0.4, g, threshold=0.4).item() == pytest.approx(1.0, abs=1e-3)  # >= t counts


def test_fscore_seeded():
    g, p = _cube(8, 24), _cube(8, 24, shift=1)
    assert voxel_fscore(p, g, seed=3).item() == voxel_fscore(p, g, seed=3).item()
    gen = np.random.default_rng(3)
    assert voxel_fscore(p, g, generator=gen).item() == voxel_fscore(p, g, seed=3).item()


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
    with pytest.raises(ValueError, match="^`convention` must be one of 'community', 'centred', got 'what3d'$"):
        voxel_fscore(g, g, convention="what3d")
    with pytest.raises(ValueError, match="^`convention` must be one of 'community', 'centred', got 'centered'$"):
        surface_points(g[0].bool().numpy(), 10, np.random.default_rng(0), convention="centered")


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
