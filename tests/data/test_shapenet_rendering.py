"""The ShapeNetRendering / ShapeNetVox32 reader on a small fixture written in that layout."""

from __future__ import annotations

import json

import numpy as np
import pytest
from PIL import Image
from scipy.spatial.transform import Rotation

from lightning_vtr.data.binvox import read_binvox, write_binvox
from lightning_vtr.data.format import DatasetFormatError
from lightning_vtr.data.shapenet_rendering import ShapeNetRenderingSource, r2n2_to_viewpoints, read_rendering_metadata
from lightning_vtr.geometry import camera_center

# (taxonomy id, name, models) and per-model (azimuth, elevation) lines of rendering_metadata.txt.
TAXONOMIES = [("02691156", "aeroplane", ["planeA", "planeB"]), ("03001627", "chair", ["chairA", "chairB"])]
ANGLES = [(0.0, 30.0), (90.0, 25.0), (270.0, 28.5), (181.0, 26.0)]
SPLIT = {"planeA": "train", "planeB": "test", "chairA": "train", "chairB": "val"}


def _voxels_y_up(seed: int) -> np.ndarray:
    """A distinctive 32^3 grid: a slab plus a random speckle, so orientation errors show."""
    v = np.zeros((32, 32, 32), dtype=bool)
    v[2:10, 5:30, 12:14] = True  # thin along z (the Y-up file's front axis)
    v |= np.random.default_rng(seed).random(v.shape) < 0.02
    return v


@pytest.fixture
def layout(tmp_path):
    render_root, vox_root = tmp_path / "ShapeNetRendering", tmp_path / "ShapeNetVox32"
    grids = {}
    for t, (tid, _, models) in enumerate(TAXONOMIES):
        for m, model in enumerate(models):
            rdir = render_root / tid / model / "rendering"
            rdir.mkdir(parents=True)
            lines = [f"{az} {el} 0 0.8{m} 25" for az, el in ANGLES]
            (rdir / "rendering_metadata.txt").write_text("\n".join(lines) + "\n")
            for i in range(len(ANGLES)):
                Image.fromarray(np.full((8, 8, 4), 10 * i, dtype=np.uint8)).save(rdir / f"{i:02d}.png")
            grids[model] = _voxels_y_up(10 * t + m)
            (vox_root / tid / model).mkdir(parents=True)
            write_binvox(vox_root / tid / model / "model.binvox", grids[model], up_axis="z")  # stored as made (Y up)
    split = [
        {
            "taxonomy_id": tid,
            "taxonomy_name": name,
            **{s: [m for m in models if SPLIT[m] == s] for s in ("train", "val", "test")},
        }
        for tid, name, models in TAXONOMIES
    ]
    split_file = tmp_path / "ShapeNet.json"
    split_file.write_text(json.dumps(split))
    return render_root, vox_root, split_file, grids


def _blender_camera_position(azimuth: float, elevation: float, in_plane: float = 0.0) -> np.ndarray:
    """Independent reference: 3D-R2N2's Blender rig puts the camera at (1, 0, 0) on a parent whose XYZ
    Euler rotation is (-in_plane, -elevation, -azimuth); Blender's XYZ Euler is the extrinsic x-y-z rotation."""
    rot = Rotation.from_euler("xyz", [-in_plane, -elevation, -azimuth], degrees=True)
    return rot.apply([1.0, 0.0, 0.0])


def test_conversion_matches_blender_rig():
    az = np.array([0.0, 30.0, 90.0, 135.0, 200.0, 270.0, 359.0])
    el = np.array([30.0, 25.0, -10.0, 60.0, 0.0, 89.0, 27.0])
    vp = r2n2_to_viewpoints(az, el)
    expected = np.stack([_blender_camera_position(a, e) for a, e in zip(az, el)])
    np.testing.assert_allclose(camera_center(vp).numpy(), expected, atol=1e-6)
    # Hand-computed: azimuth 90 is yaw -90 (camera on -Y); azimuth 270 is yaw 90; azimuth 0 is yaw 0.
    np.testing.assert_allclose(
        r2n2_to_viewpoints([0, 90, 270, 180], [30, 25, 28.5, 26]), [[0, 30], [-90, 25], [90, 28.5], [-180, 26]]
    )
    assert np.all((vp[:, 0] >= -180) & (vp[:, 0] < 180))


def test_conversion_rejects_bad_input():
    with pytest.raises(ValueError, match="same length"):
        r2n2_to_viewpoints([0, 1], [0])
    with pytest.raises(ValueError, match="elevation"):
        r2n2_to_viewpoints([0], [95])


def test_read_rendering_metadata(tmp_path):
    path = tmp_path / "rendering_metadata.txt"
    path.write_text("293.7 25.9 0 0.87 25\n10 30 0 0.7 25\n\n")
    np.testing.assert_allclose(read_rendering_metadata(path), [[293.7, 25.9, 0, 0.87, 25], [10, 30, 0, 0.7, 25]])
    path.write_text("293.7 25.9 0 0.87\n")
    with pytest.raises(DatasetFormatError, match="line 1"):
        read_rendering_metadata(path)


def test_records_from_fixture(layout):
    render_root, vox_root, split_file, grids = layout
    records = list(ShapeNetRenderingSource(render_root, vox_root, split_file))
    assert [(r.category, r.object_id, r.split) for r in records] == [
        ("aeroplane", "planeA", "train"),
        ("aeroplane", "planeB", "test"),
        ("chair", "chairA", "train"),
        ("chair", "chairB", "val"),
    ]
    expected_vp = [[0.0, 30.0], [-90.0, 25.0], [90.0, 28.5], [179.0, 26.0]]
    for r in records:
        assert list(r.views) == ["aligned"] and r.mesh_path is None and r.voxel_up_axis == "y"
        paths, vp = r.views["aligned"]
        np.testing.assert_allclose(vp, expected_vp)
        assert [p.name for p in paths] == ["00.png", "01.png", "02.png", "03.png"]
        assert np.asarray(Image.open(paths[2]))[0, 0, 0] == 20
        # Voxels: read in the package's +Z-up frame; the file's +Y (up) becomes +Z, its +Z becomes -Y.
        z_up = read_binvox(r.voxel_path, up_axis=r.voxel_up_axis)
        source = grids[r.object_id]
        for i, j, k in [(3, 10, 12), (5, 29, 13), (9, 5, 12), (0, 0, 0), (20, 7, 31)]:
            assert z_up[i, 31 - k, j] == source[i, j, k]
        assert z_up[2:10, 18:20, 5:30].all()  # the slab, thin along z in the file, is thin along y now


def test_category_filter_and_missing_files(layout):
    render_root, vox_root, split_file, _ = layout
    chairs = ShapeNetRenderingSource(render_root, vox_root, split_file, categories=["03001627"])
    assert {r.category for r in chairs} == {"chair"} and len(chairs) == 2
    with pytest.raises(ValueError, match="sofa"):
        ShapeNetRenderingSource(render_root, vox_root, split_file, categories=["sofa"]).records()
    (vox_root / "03001627" / "chairB" / "model.binvox").unlink()
    with pytest.warns(UserWarning, match="Skipped 1 model"):
        assert len(ShapeNetRenderingSource(render_root, vox_root, split_file)) == 3
    with pytest.raises(DatasetFormatError, match="chairB"):
        ShapeNetRenderingSource(render_root, vox_root, split_file, missing="error").records()
    with pytest.raises(FileNotFoundError, match="voxel_root"):
        ShapeNetRenderingSource(render_root, vox_root / "nope", split_file)
