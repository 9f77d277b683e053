"""The procedural generator: determinism, variety, canonical pose, bounds and voxel occupancy."""

from __future__ import annotations

import numpy as np
import pytest

from lightning_vtr.data.procedural import CATEGORIES, make_object, object_id, object_variant
from lightning_vtr.data.voxelize import voxelize


def test_at_least_eight_categories_including_the_named_ones():
    assert len(CATEGORIES) >= 8
    assert {"chair", "table", "lamp", "airplane", "car", "bench", "sofa"} <= set(CATEGORIES)
    assert list(CATEGORIES) == sorted(CATEGORIES)


def test_object_id_format_and_errors():
    assert object_id("chair", 7) == "chair_0007"
    assert object_id("airplane", 1234) == "airplane_1234"
    with pytest.raises(ValueError, match=r"`category` must be one of 'airplane', .*, got 'spaceship'"):
        make_object("spaceship", 0)
    with pytest.raises(ValueError, match=r"`index` must be an int >= 0, got -1"):
        object_id("chair", -1)
    with pytest.raises(TypeError, match=r"`index` must be an int, got bool True"):
        object_id("chair", True)
    assert object_id("chair", np.int64(3)) == "chair_0003"


@pytest.mark.parametrize("category", CATEGORIES)
def test_deterministic_and_varied(category):
    a, b = make_object(category, 3, seed=5), make_object(category, 3, seed=5)
    np.testing.assert_array_equal(a.vertices, b.vertices)
    np.testing.assert_array_equal(a.faces, b.faces)
    # A different index or seed draws other proportions: the bounding boxes differ.
    for other in (make_object(category, 4, seed=5), make_object(category, 3, seed=6)):
        assert not np.allclose(other.extents, a.extents, atol=1e-3) or other.vertices.shape != a.vertices.shape


@pytest.mark.parametrize("category", CATEGORIES)
def test_normalised_into_unit_cube_and_voxelizes_to_a_solid(category):
    for index in range(3):
        mesh = make_object(category, index)
        lo, hi = mesh.bounds
        assert np.all(lo >= -0.5 - 1e-9) and np.all(hi <= 0.5 + 1e-9)
        np.testing.assert_allclose((lo + hi) / 2, 0.0, atol=1e-9)  # bounding box centred
        assert max(hi - lo) == pytest.approx(1.0)  # longest side 1
        occupancy = voxelize(mesh, 32).mean()
        # Floor lamps are the sparsest (a thin pole): just under 1 %, like ShapeNet lamps.
        assert 0.005 < occupancy < 0.6, f"{category}_{index}: occupancy {occupancy:.3f}"


@pytest.mark.parametrize("category", CATEGORIES)
def test_several_structural_variants(category):
    variants = {object_variant(category, i) for i in range(20)}
    assert len(variants) >= 3, variants


def _vertices(category, index):
    return np.asarray(make_object(category, index).vertices)


def test_chair_upright_with_backrest_behind_the_seat():
    for index in range(8):
        v = _vertices("chair", index)
        # The backrest is the only part above the seat's top-plus-arms; it is on the back side (-X).
        high = v[v[:, 2] > 0.35]
        assert high[:, 0].mean() < -0.05, index
        # The floor contacts (legs or the star base) are at the bottom: z min is -0.5 and the seat
        # (the widest horizontal slab) lies in the lower half of the height.
        assert v[:, 2].min() == pytest.approx(-0.5)


def test_airplane_fuselage_along_x_wings_along_y():
    for index in range(8):
        ext = make_object("airplane", index).extents
        assert ext[0] > 2 * ext[2] and ext[1] > 2 * ext[2], ext
        v = _vertices("airplane", index)
        # The nose cone tip is the only vertex at the front (+X) end, on the fuselage axis (y = 0).
        tip = v[np.argmax(v[:, 0])]
        assert abs(tip[1]) < 1e-6


def test_table_top_covers_more_area_than_its_legs():
    for index in range(8):
        vox = voxelize(make_object("table", index), 32)
        z_occ = np.nonzero(vox.any(axis=(0, 1)))[0]
        top, middle = vox[:, :, z_occ.max()].sum(), vox[:, :, (z_occ.min() + z_occ.max()) // 2].sum()
        assert top > 3 * middle, (index, top, middle)


def test_long_objects_extend_along_their_canonical_axis():
    for index in range(5):
        for category in ("bench", "sofa", "shelf"):
            ext = make_object(category, index).extents
            assert ext[1] >= ext[0], (category, index, ext)  # wide along Y, facing +X
        for category in ("car", "bed"):
            ext = make_object(category, index).extents
            assert ext[0] > ext[1], (category, index, ext)  # long along X
        ext = make_object("lamp", index).extents
        assert ext[2] >= 0.45, ext  # lamps are tall or at least half as tall as their reach


def test_car_wheels_touch_the_ground_and_cabin_is_on_top():
    for index in range(6):
        vox = voxelize(make_object("car", index), 32)
        occ_z = np.nonzero(vox.any(axis=(0, 1)))[0]
        # Top layer (the cabin) is narrower along X than the body's widest layer.
        x_extent = [np.ptp(np.nonzero(vox[:, :, k].any(axis=1))[0]) for k in occ_z]
        assert x_extent[-1] < max(x_extent)
