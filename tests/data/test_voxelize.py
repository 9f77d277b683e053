"""Solid voxelization: grid convention, filled interiors, unions, open and thin meshes."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from lightning_vtr.data.voxelize import surface_voxels, voxelize
from lightning_vtr.geometry import voxel_centers


def _box(extents, centre=(0.0, 0.0, 0.0)) -> trimesh.Trimesh:
    return trimesh.creation.box(extents=extents).apply_translation(centre)


def test_box_occupies_exactly_the_cells_it_crosses():
    # R = 10: cells are 0.1 wide with boundaries at -0.5 + 0.1 i. A box x in [-0.27, 0.13],
    # y in [-0.05, 0.35], z in [0.02, 0.18] crosses cells x 2..6, y 4..8, z 5..6 (hand-computed).
    vox = voxelize(_box((0.40, 0.40, 0.16), (-0.07, 0.15, 0.10)), 10)
    expected = np.zeros((10, 10, 10), bool)
    expected[2:7, 4:9, 5:7] = True
    np.testing.assert_array_equal(vox, expected)
    # Without filling only the surface remains: a box 4-5 cells thick has an empty core.
    shell = voxelize(_box((0.4, 0.4, 0.4), (0.01, 0.01, 0.01)), 10, fill=False)
    assert not shell[4:7, 4:7, 4:7].any() and shell[3, 5, 5] and shell[7, 5, 5]  # x in [-0.19, 0.21]: cells 3..7
    assert voxelize(_box((0.4, 0.4, 0.4), (0.01, 0.01, 0.01)), 10)[3:8, 3:8, 3:8].all()


def test_index_order_is_x_y_z():
    # A thin rod along +y at x ~ 0.3, z ~ -0.3 must occupy V[i, :, k] with i, k from voxel_centers.
    vox = voxelize(_box((0.05, 0.9, 0.05), (0.31, 0.0, -0.31)), 16)
    centres = voxel_centers(16).numpy()
    occupied = centres[vox]
    assert np.abs(occupied[:, 0] - 0.31).max() < 1 / 16 and np.abs(occupied[:, 2] + 0.31).max() < 1 / 16
    assert np.ptp(occupied[:, 1]) > 0.8


def test_sphere_is_solid_and_close_to_its_volume():
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.4)
    vox = voxelize(sphere, 32)
    centres = voxel_centers(32).numpy()
    r = np.linalg.norm(centres, axis=-1)
    assert vox[r < 0.4 - 1 / 32].all()  # the whole interior is filled
    assert not vox[r > 0.4 + 2 / 32].any()  # nothing far outside
    # Cells crossed by the surface count, so the volume is between the inner and the outer estimate.
    cell = (1 / 32) ** 3
    assert 4 / 3 * np.pi * 0.4**3 <= vox.sum() * cell <= 4 / 3 * np.pi * (0.4 + 0.5 / 32 * 1.8) ** 3


def test_overlapping_parts_stay_solid():
    # Two intersecting closed boxes: ray parity would call their overlap "outside".
    union = trimesh.util.concatenate(
        [_box((0.6, 0.2, 0.2), (0.01, 0.01, 0.01)), _box((0.2, 0.6, 0.2), (0.01, 0.01, 0.01))]
    )
    vox = voxelize(union, 20)
    assert vox[10, 10, 10]  # the centre lies inside both boxes
    reference = voxelize(_box((0.6, 0.2, 0.2), (0.01, 0.01, 0.01)), 20) | voxelize(
        _box((0.2, 0.6, 0.2), (0.01, 0.01, 0.01)), 20
    )
    np.testing.assert_array_equal(vox, reference)


def test_flipped_faces_and_small_holes_do_not_matter():
    box = _box((0.5, 0.5, 0.5), (0.013, 0.013, 0.013))
    solid = voxelize(box, 16)
    flipped = box.copy()
    flipped.invert()
    np.testing.assert_array_equal(voxelize(flipped, 16), solid)
    # A hole smaller than a cell is covered by the cells around its rim: the sphere stays solid.
    holed = trimesh.creation.icosphere(subdivisions=5, radius=0.4)
    holed.update_faces(np.arange(len(holed.faces)) != 0)  # one triangle ~0.02 wide, below the cell size 1/16
    assert not holed.is_watertight
    np.testing.assert_array_equal(
        voxelize(holed, 16), voxelize(trimesh.creation.icosphere(subdivisions=5, radius=0.4), 16)
    )


def test_open_shape_stays_open_and_thin_parts_survive():
    # An open-topped tray (bottom and four walls, all one-sided planes): no cavity is enclosed.
    plane = trimesh.creation.box(extents=(0.6, 0.6, 0.002))
    parts = [plane.copy().apply_translation((0, 0, -0.2))]
    for angle, axis in [(np.pi / 2, (1, 0, 0)), (np.pi / 2, (0, 1, 0))]:
        for sign in (-1, 1):
            wall = plane.copy().apply_transform(trimesh.transformations.rotation_matrix(angle, axis))
            offset = np.cross(axis, (0, 0, 1)) * 0.3 * sign
            parts.append(wall.apply_translation(offset + np.array([0.0, 0.0, 0.1])))
    tray = trimesh.util.concatenate(parts)
    vox = voxelize(tray, 20)
    assert not vox[10, 10, 10]  # the inside of the tray is empty, not filled
    assert vox[10, 10, 6]  # the bottom, 0.002 thick (1/25 of a cell), is still there


def test_geometry_outside_the_cube_is_clipped_and_errors():
    vox = voxelize(_box((2.0, 0.1, 0.1)), 8)
    assert vox[:, 3:5, 3:5].all() and vox.sum() == 8 * 4
    with pytest.raises(ValueError, match=r"`resolution` must be an int >= 1, got 0"):
        voxelize(_box((0.5, 0.5, 0.5)), 0)
    with pytest.raises(TypeError, match=r"`resolution` must be an int, got float 8.0"):
        voxelize(_box((0.5, 0.5, 0.5)), 8.0)
    with pytest.raises(ValueError, match="no triangles"):
        voxelize(trimesh.Trimesh(), 8)
    with pytest.raises(TypeError, match=r"`mesh` must be a trimesh.Trimesh, got ndarray"):
        surface_voxels(np.zeros((3, 3)), 8)
