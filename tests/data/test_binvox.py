"""binvox I/O: axis order against the spec, trimesh's independent implementation and a hand-written file."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from trimesh.exchange.binvox import load_binvox

from lightning_vtr.data.binvox import read_binvox, voxels_to_y_up, voxels_to_z_up, write_binvox
from lightning_vtr.data.mesh import convert_up_axis, normalize_mesh
from lightning_vtr.data.voxelize import voxelize


def _random_grid(shape=(6, 6, 6), seed=0, p=0.4) -> np.ndarray:
    return np.random.default_rng(seed).random(shape) < p


def test_hand_written_file_follows_the_spec(tmp_path):
    # dim 2 2 2 with only voxel (x=1, y=0, z=1) set. The spec lists y fastest, then z, then x:
    # flat position x*4 + z*2 + y = 4 + 2 + 0 = 6, i.e. runs: six 0s, one 1, one 0.
    path = tmp_path / "one.binvox"
    path.write_bytes(b"#binvox 1\ndim 2 2 2\ntranslate -0.5 -0.5 -0.5\nscale 1\ndata\n" + bytes([0, 6, 1, 1, 0, 1]))
    vox, translate, scale = read_binvox(path, return_transform=True)
    expected = np.zeros((2, 2, 2), bool)
    expected[1, 0, 1] = True
    np.testing.assert_array_equal(vox, expected)
    assert translate == (-0.5, -0.5, -0.5) and scale == 1.0
    # ... and our writer produces exactly these bytes after its header.
    write_binvox(tmp_path / "ours.binvox", expected)
    assert (tmp_path / "ours.binvox").read_bytes().split(b"data\n", 1)[1] == bytes([0, 6, 1, 1, 0, 1])


def test_long_runs_split_at_255(tmp_path):
    vox = np.zeros((8, 8, 8), bool)  # 512 zeros -> runs of 255, 255, 2
    vox[7, 7, 7] = True  # the last voxel in file order (x=7, z=7, y=7)
    write_binvox(tmp_path / "a.binvox", vox)
    body = (tmp_path / "a.binvox").read_bytes().split(b"data\n", 1)[1]
    assert body == bytes([0, 255, 0, 255, 0, 1, 1, 1])
    np.testing.assert_array_equal(read_binvox(tmp_path / "a.binvox"), vox)


@pytest.mark.parametrize("shape", [(6, 6, 6), (3, 4, 5)])
def test_round_trip(tmp_path, shape):
    vox = _random_grid(shape)
    write_binvox(tmp_path / "ours.binvox", vox)
    out = read_binvox(tmp_path / "ours.binvox")
    assert out.dtype == bool and out.shape == shape
    np.testing.assert_array_equal(out, vox)


@pytest.mark.parametrize("size", [5, 12])
def test_agreement_with_trimesh(tmp_path, size):
    # trimesh's binvox code (xzy order) is the independent implementation; it handles cubic grids only.
    vox = _random_grid((size,) * 3, seed=size)
    write_binvox(tmp_path / "ours.binvox", vox)
    with open(tmp_path / "ours.binvox", "rb") as f:
        np.testing.assert_array_equal(load_binvox(f).matrix, vox)
    (tmp_path / "theirs.binvox").write_bytes(trimesh.voxel.VoxelGrid(vox).export(file_type="binvox"))
    np.testing.assert_array_equal(read_binvox(tmp_path / "theirs.binvox"), vox)


def test_header_translate_scale_are_written(tmp_path):
    write_binvox(tmp_path / "a.binvox", _random_grid(), translate=(0.1, -0.2, 0.3), scale=2.5)
    text = (tmp_path / "a.binvox").read_bytes().split(b"data\n")[0].decode()
    assert "dim 6 6 6" in text and "translate 0.1 -0.2 0.3" in text and "scale 2.5" in text
    _, translate, scale = read_binvox(tmp_path / "a.binvox", return_transform=True)
    assert translate == (0.1, -0.2, 0.3) and scale == 2.5


def test_y_up_conversion_matches_mesh_conversion(tmp_path):
    # A chiral, non-grid-aligned shape in a +Y-up frame (ShapeNet style).
    boxes = [
        ((0.8, 0.17, 0.23), (0.1, 0.02, -0.05)),
        ((0.19, 0.57, 0.21), (-0.2, 0.2, 0.07)),
        ((0.15, 0.2, 0.41), (0.25, -0.1, 0.2)),
    ]
    mesh_y_up = normalize_mesh(
        trimesh.util.concatenate([trimesh.creation.box(extents=e).apply_translation(c) for e, c in boxes])
    )
    mesh_y_up.apply_translation([0.013, -0.007, 0.011])  # avoid faces on voxel boundaries
    path = tmp_path / "model.binvox"
    write_binvox(path, voxelize(mesh_y_up, 16))  # a ShapeNetVox32-like file: stored in the +Y-up frame
    expected = voxelize(convert_up_axis(mesh_y_up, "y"), 16)
    assert expected.sum() > 50
    np.testing.assert_array_equal(read_binvox(path, up_axis="y"), expected)
    # Writing with up_axis="y" is the inverse of reading with it.
    write_binvox(tmp_path / "back.binvox", expected, up_axis="y")
    np.testing.assert_array_equal(read_binvox(tmp_path / "back.binvox"), voxelize(mesh_y_up, 16))


def test_up_axis_helpers_hand_computed():
    grid = np.zeros((4, 4, 4), bool)
    grid[1, 3, 0] = True  # +Y-up frame: near the top (y index 3), at the back (z index 0)
    # (x, y, z) -> (x, -z, y): index (i, j, k) -> (i, R-1-k, j) = (1, 3, 3): top (z=3), at +y (j=3).
    out = voxels_to_z_up(grid)
    assert list(zip(*np.nonzero(out))) == [(1, 3, 3)]
    np.testing.assert_array_equal(voxels_to_y_up(out), grid)


def test_bad_files_raise_naming_the_file(tmp_path):
    cases = {
        "notbinvox.binvox": b"hello\n",
        "nodata.binvox": b"#binvox 1\ndim 2 2 2\n",
        "baddim.binvox": b"#binvox 1\ndim 2 two 2\ndata\n\x00\x08",
        "short.binvox": b"#binvox 1\ndim 2 2 2\ndata\n\x00\x07",
        "odd.binvox": b"#binvox 1\ndim 2 2 2\ndata\n\x00\x08\x01",
    }
    for name, content in cases.items():
        (tmp_path / name).write_bytes(content)
        with pytest.raises(ValueError, match=name):
            read_binvox(tmp_path / name)
    with pytest.raises(ValueError, match=r"`up_axis` must be one of 'y', 'z', got 'x'"):
        read_binvox(tmp_path / "short.binvox", up_axis="x")


def test_write_is_atomic_and_validates(tmp_path):
    with pytest.raises(ValueError, match="voxels"):
        write_binvox(tmp_path / "a.binvox", np.zeros((4, 4)))
    with pytest.raises(ValueError, match=r"`scale` must be a number > 0, got 0.0"):
        write_binvox(tmp_path / "a.binvox", np.zeros((2, 2, 2)), scale=0)
    with pytest.raises(TypeError, match=r"`translate` must be three numbers, got 'abc'"):
        write_binvox(tmp_path / "a.binvox", np.zeros((2, 2, 2)), translate="abc")
    with pytest.raises(ValueError, match=r"`up_axis` must be one of 'y', 'z', got 'x'"):
        write_binvox(tmp_path / "a.binvox", np.zeros((2, 2, 2)), up_axis="x")
    write_binvox(tmp_path / "sub" / "a.binvox", np.ones((2, 2, 2)))
    assert [p.name for p in (tmp_path / "sub").iterdir()] == ["a.binvox"]  # no temporary left behind
