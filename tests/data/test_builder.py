"""The ShapeNet-VTR builder and its CLI: view sets, content, splits, resume, shards, errors, sources."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

from lightning_vtr.data.binvox import read_binvox
from lightning_vtr.data.builder import build_dataset, ensure_embedded_dataset, finalize_dataset, view_set_viewpoints
from lightning_vtr.data.format import load_metadata, object_dir, scan_dataset
from lightning_vtr.data.procedural import make_object
from lightning_vtr.data.voxelize import voxelize

SMALL = dict(categories=["chair", "table"], objects_per_category=3, image_size=32, views_per_set=4, progress=False)


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    root = tmp_path_factory.mktemp("small_vtr")
    report = build_dataset(root, **SMALL)
    return root, report


# ------------------------------------------------------------------------------------------ view sets


def test_aligned_view_set_hand_computed():
    views = view_set_viewpoints("chair", "chair_0000", views_per_set=4, aligned_pitch=30.0)
    np.testing.assert_allclose(views["aligned"], [[0, 30], [90, 30], [-180, 30], [-90, 30]])
    views = view_set_viewpoints("chair", "chair_0000", views_per_set=24, aligned_pitch=-10.0)
    np.testing.assert_allclose(views["aligned"][:3], [[0, -10], [15, -10], [30, -10]])
    assert views["aligned"].shape == (24, 2)


def test_random_view_sets_are_seeded_per_object_and_area_uniform():
    a = view_set_viewpoints("chair", "chair_0001", views_per_set=24, seed=0)
    np.testing.assert_array_equal(
        a["spherical"], view_set_viewpoints("chair", "chair_0001", views_per_set=24, seed=0)["spherical"]
    )
    assert not np.allclose(
        a["spherical"], view_set_viewpoints("chair", "chair_0002", views_per_set=24, seed=0)["spherical"]
    )
    assert not np.allclose(
        a["hemispherical"], view_set_viewpoints("chair", "chair_0001", views_per_set=24, seed=1)["hemispherical"]
    )
    big = view_set_viewpoints("chair", "chair_0001", views_per_set=20000)
    hemi, sphere = big["hemispherical"], big["spherical"]
    assert hemi[:, 1].min() >= 0 and hemi[:, 1].max() <= 90 and sphere[:, 1].min() >= -90
    assert np.all((hemi[:, 0] >= -180) & (hemi[:, 0] < 180))
    # Area-uniform: the cap above 30 degrees is half the hemisphere (1 - sin 30); angle-uniform would give 2/3.
    assert np.mean(hemi[:, 1] > 30) == pytest.approx(0.5, abs=0.02)
    # On the sphere, sin(pitch) is uniform in [-1, 1]: mean 0, variance 1/3.
    s = np.sin(np.radians(sphere[:, 1]))
    assert s.mean() == pytest.approx(0.0, abs=0.02) and s.var() == pytest.approx(1 / 3, abs=0.02)
    assert np.mean(sphere[:, 0] > 0) == pytest.approx(0.5, abs=0.02)


# ------------------------------------------------------------------------------------------ content


def test_build_writes_the_documented_layout(small):
    root, report = small
    assert report.finalized and len(report.built) == 6 and not report.failed and not report.skipped
    meta = load_metadata(root)
    assert meta["image_size"] == 32 and meta["views_per_set"] == 4 and meta["aligned_pitch"] == 30.0
    assert sorted(meta["objects"]) == [f"{c}/{c}_{i:04d}" for c in ("chair", "table") for i in range(3)]
    assert json.loads((root / "errors.json").read_text()) == {}
    for key, info in meta["objects"].items():
        category, oid = key.split("/")
        expected = view_set_viewpoints(category, oid, views_per_set=4, aligned_pitch=30.0, seed=0)
        for name in ("aligned", "hemispherical", "spherical"):
            np.testing.assert_allclose(info["views"][name], expected[name], atol=1e-6)
        d = object_dir(root, category, oid)
        assert json.loads((d / "object.json").read_text())["views"] == info["views"]
        assert sorted(p.name for p in (d / "spherical").iterdir()) == ["00.png", "01.png", "02.png", "03.png"]


def test_voxels_and_images_match_the_object(small):
    from PIL import Image

    from lightning_vtr.renderer import get_renderer

    root, _ = small
    mesh = make_object("chair", 1)
    np.testing.assert_array_equal(
        read_binvox(object_dir(root, "chair", "chair_0001") / "model.binvox"), voxelize(mesh, 32)
    )
    record = next(r for r in scan_dataset(root) if r.object_id == "chair_0001")
    paths, viewpoints = record.views["hemispherical"]
    expected = get_renderer(32).render(mesh, viewpoints)
    for path, want in zip(paths, expected):
        got = np.asarray(Image.open(path))
        assert got.shape == (32, 32, 4) and got.dtype == np.uint8
        assert np.abs(got.astype(int) - want.astype(int)).max() <= 1
    saved = trimesh.load(record.mesh_path, process=False)
    np.testing.assert_allclose(saved.bounds, mesh.bounds, atol=1e-5)


def test_split_is_7_1_2_per_category_and_shard_independent(tiny_dataset):
    # The session fixture: 3 categories x 10 objects.
    meta = load_metadata(tiny_dataset)
    splits = json.loads((Path(tiny_dataset) / "splits.json").read_text())
    for category, parts in splits.items():
        assert [len(parts[s]) for s in ("train", "val", "test")] == [7, 1, 2]
        for s, ids in parts.items():
            assert all(meta["objects"][f"{category}/{i}"]["split"] == s for i in ids)
    from lightning_vtr.data.splits import split_objects as _splits

    keys = [tuple(k.split("/")) for k in meta["objects"]]
    assert _splits(keys, (0.7, 0.1, 0.2), 0) == splits  # a pure function of the ids and the seed
    assert _splits(list(reversed(keys)), (0.7, 0.1, 0.2), 0) == splits
    assert _splits(keys, (0.7, 0.1, 0.2), 1) != splits


# ------------------------------------------------------------------------------------------ robustness


def test_resume_redoes_only_the_damaged_object(tmp_path):
    root = tmp_path / "ds"
    build_dataset(root, **SMALL)
    damaged = object_dir(root, "table", "table_0002")
    (damaged / "object.json").unlink()
    (damaged / "aligned" / "01.png").unlink()
    (root / "metadata.json").unlink()  # as if killed before the end
    untouched = object_dir(root, "chair", "chair_0000") / "aligned" / "00.png"
    os.utime(untouched, (1_000_000, 1_000_000))
    report = build_dataset(root, **SMALL)
    assert report.built == ["table/table_0002"]
    assert len(report.skipped) == 5 and report.finalized
    assert (damaged / "aligned" / "01.png").is_file() and (damaged / "object.json").is_file()
    assert untouched.stat().st_mtime == 1_000_000
    assert len(load_metadata(root)["objects"]) == 6


def test_rerun_with_other_options_is_refused(small):
    root, _ = small
    with pytest.raises(ValueError, match="image_size: 32 on disk vs 64 now"):
        build_dataset(root, **{**SMALL, "image_size": 64})


def test_shards_then_finalize_equal_a_single_build(tmp_path, small):
    root = tmp_path / "sharded"
    r0 = build_dataset(root, **SMALL, shard=(0, 2), finalize=False)
    assert not r0.finalized and len(r0.built) == 3 and not (root / "metadata.json").exists()
    with pytest.raises(RuntimeError, match="3 object"):
        finalize_dataset(root)
    r1 = build_dataset(root, **SMALL, shard=(1, 2), finalize=False)
    assert not set(r0.built) & set(r1.built)
    report = finalize_dataset(root)
    assert report.finalized
    single = load_metadata(small[0])
    sharded = load_metadata(root)
    assert sharded["objects"] == single["objects"]
    a = read_binvox(object_dir(root, "table", "table_0001") / "model.binvox")
    np.testing.assert_array_equal(a, read_binvox(object_dir(small[0], "table", "table_0001") / "model.binvox"))


def test_last_shard_writes_the_metadata(tmp_path):
    root = tmp_path / "ds"
    assert not build_dataset(root, **SMALL, shard=(1, 2)).finalized
    assert build_dataset(root, **SMALL, shard=(0, 2)).finalized


def _write_box(path: Path, extents=(0.3, 0.6, 0.9)) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    trimesh.creation.box(extents=extents).export(path)


def test_bad_mesh_is_reported_not_fatal(tmp_path):
    src = tmp_path / "meshes"
    _write_box(src / "crate" / "good.obj")
    _write_box(src / "crate" / "good2.ply")
    (src / "crate" / "broken.off").write_text("OFF\n3 1 0\n0 0 0\n1 0\n")  # truncated
    (src / "crate" / "notes.txt").write_text("not a mesh")  # ignored: not a mesh extension
    root = tmp_path / "ds"
    report = build_dataset(root, source=src, image_size=32, views_per_set=4, progress=False)
    assert sorted(report.built) == ["crate/good", "crate/good2"]
    assert list(report.failed) == ["crate/broken"] and "broken.off" in report.failed["crate/broken"]
    errors = json.loads((root / "errors.json").read_text())
    assert list(errors) == ["crate/broken"] and "broken.off" in errors["crate/broken"]
    meta = load_metadata(root)
    assert meta["failed"] == ["crate/broken"] and sorted(meta["objects"]) == ["crate/good", "crate/good2"]
    assert "crate/broken" in report.summary()
    # A re-run retries the failed object only (it fails again) and keeps the report.
    again = build_dataset(root, source=src, image_size=32, views_per_set=4, progress=False)
    assert list(again.failed) == ["crate/broken"] and sorted(again.skipped) == ["crate/good", "crate/good2"]


def test_shapenet_v1_source_is_converted_from_y_up(tmp_path):
    src = tmp_path / "ShapeNetCore.v1"
    # Tall along +Y (ShapeNet's up), thin along Z.
    _write_box(src / "03001627" / "abc123" / "model.obj", extents=(0.4, 1.0, 0.2))
    _write_box(src / "03001627" / "def456" / "model.obj", extents=(0.5, 1.0, 0.5))
    root = tmp_path / "ds"
    report = build_dataset(root, source=src, image_size=32, views_per_set=4, progress=False)
    assert sorted(report.built) == ["chair/abc123", "chair/def456"]  # synset named
    vox = read_binvox(object_dir(root, "chair", "abc123") / "model.binvox")
    extent = [int(np.ptp(np.nonzero(vox.any(axis=tuple(a for a in range(3) if a != ax)))[0])) + 1 for ax in range(3)]
    # Cells touched by the surface: 0.4 * 32 = 12.8 -> 14 cells, 0.2 * 32 = 6.4 -> 8 cells (partial cells count).
    assert extent == [14, 8, 32]
    assert load_metadata(root)["categories"] == ["chair"]


def test_invalid_arguments(tmp_path):
    with pytest.raises(ValueError, match="shard"):
        build_dataset(tmp_path, shard=(2, 2))
    with pytest.raises(ValueError, match="split"):
        build_dataset(tmp_path, split=(0.5, 0.5, 0.5))
    with pytest.raises(ValueError, match="aligned_pitch"):
        build_dataset(tmp_path, aligned_pitch=120)
    with pytest.raises(ValueError, match="spaceship"):
        build_dataset(tmp_path, categories=["spaceship"])
    with pytest.raises(ValueError, match="source"):
        build_dataset(tmp_path, source=tmp_path / "missing")
    with pytest.raises(TypeError, match=r"`image_size` must be an int, got float 64.0"):
        build_dataset(tmp_path, image_size=64.0)
    with pytest.raises(ValueError, match=r"`views_per_set` must be an int in \[1, 100\], got 101"):
        build_dataset(tmp_path, views_per_set=101)
    with pytest.raises(
        ValueError, match=r"`source_layout` must be one of 'auto', 'shapenet_v1', 'shapenet_v2', 'generic'"
    ):
        build_dataset(tmp_path, source_layout="flat")
    with pytest.raises(ValueError, match=r"`up_axis` must be one of None, 'y', 'z', got 'x'"):
        build_dataset(tmp_path, up_axis="x")
    with pytest.raises(TypeError, match=r"`shard` must be a pair \(i, n\), got 3"):
        build_dataset(tmp_path, shard=3)
    assert not any(tmp_path.iterdir())  # arguments are checked before anything is written


def test_ensure_embedded_dataset_builds_once(tmp_path, monkeypatch):
    monkeypatch.setenv("LIGHTNING_VTR_DATA", str(tmp_path))
    opts = dict(categories=["lamp"], objects_per_category=2, image_size=16, views_per_set=2, progress=False, workers=1)
    root = ensure_embedded_dataset(**opts)
    assert root.parent == tmp_path and root.name.startswith("embedded-")
    stamp = (root / "metadata.json").stat().st_mtime_ns
    assert ensure_embedded_dataset(**opts) == root and (root / "metadata.json").stat().st_mtime_ns == stamp
    assert ensure_embedded_dataset(**{**opts, "image_size": 24}) != root  # other options, other directory


@pytest.mark.slow
def test_two_workers_build_the_same_dataset(tmp_path, small):
    root = tmp_path / "parallel"
    report = build_dataset(root, **SMALL, workers=2)
    assert report.finalized and len(report.built) == 6
    assert load_metadata(root)["objects"] == load_metadata(small[0])["objects"]


# ------------------------------------------------------------------------------------------ Pix3D protocol

PIX3D = dict(
    protocol="pix3d", categories=["chair"], objects_per_category=2, views_per_object=4, image_size=16, progress=False
)


def test_pix3d_viewpoints_are_seeded_uniform_yaw_and_moderate_pitch():
    from lightning_vtr.data.builder import PIX3D_PITCH_RANGE, pix3d_viewpoints

    assert PIX3D_PITCH_RANGE == (0.0, 40.0)
    a = pix3d_viewpoints("chair", "chair_0000", views_per_object=60, seed=0)
    assert a.shape == (60, 2) and a.dtype == np.float64
    np.testing.assert_array_equal(a, pix3d_viewpoints("chair", "chair_0000", views_per_object=60, seed=0))
    assert not np.allclose(a, pix3d_viewpoints("chair", "chair_0001", views_per_object=60, seed=0))
    assert not np.allclose(a, pix3d_viewpoints("chair", "chair_0000", views_per_object=60, seed=1))
    big = pix3d_viewpoints("chair", "chair_0000", views_per_object=20000)
    yaw, pitch = big[:, 0], big[:, 1]
    assert yaw.min() >= -180 and yaw.max() < 180 and pitch.min() >= 0 and pitch.max() <= 40
    # Uniform in both angles: yaw quadrants equally full, pitch mean 20 and variance 40^2 / 12.
    counts = np.histogram(yaw, bins=4, range=(-180, 180))[0] / len(yaw)
    np.testing.assert_allclose(counts, 0.25, atol=0.02)
    assert pitch.mean() == pytest.approx(20.0, abs=0.5) and pitch.var() == pytest.approx(1600 / 12, rel=0.05)
    low = pix3d_viewpoints("chair", "chair_0000", views_per_object=500, pitch_range=(-10.0, 5.0))
    assert low[:, 1].min() >= -10 and low[:, 1].max() <= 5 and low[:, 1].min() < -8 and low[:, 1].max() > 3
    # Another stream than the VTR view sets of the same object.
    vtr = view_set_viewpoints("chair", "chair_0000", views_per_set=60)
    assert not any(np.allclose(a[:, 0], vtr[name][:, 0]) for name in vtr)


def test_pix3d_build_writes_n_views_per_object_readable_by_the_reader(tmp_path):
    from PIL import Image

    from lightning_vtr.data.builder import pix3d_viewpoints
    from lightning_vtr.data.dataset import VTRDataset

    root = tmp_path / "pix3d"
    report = build_dataset(root, **PIX3D)
    assert report.finalized and sorted(report.built) == ["chair/chair_0000", "chair/chair_0001"] and not report.failed
    pngs = sorted(p.relative_to(root).as_posix() for p in root.rglob("*.png"))
    assert pngs == [f"objects/chair/chair_000{o}/pix3d/0{i}.png" for o in range(2) for i in range(4)]
    for o in range(2):  # only the pix3d set: no aligned / hemispherical / spherical folders
        d = object_dir(root, "chair", f"chair_000{o}")
        assert sorted(p.name for p in d.iterdir()) == ["mesh.ply", "model.binvox", "object.json", "pix3d"]
    meta = load_metadata(root)
    assert meta["protocol"] == "pix3d" and meta["view_sets"] == ["pix3d"]
    assert meta["views_per_set"] == 4 and meta["views_per_object"] == 4 and meta["pitch_range"] == [0.0, 40.0]
    assert meta["sampling"] == {"pix3d": "yaw uniform in [-180, 180), pitch uniform in [0, 40]"}
    for key, info in meta["objects"].items():
        category, oid = key.split("/")
        assert list(info["views"]) == ["pix3d"]
        recorded = np.asarray(info["views"]["pix3d"])
        assert recorded.shape == (4, 2)
        assert np.all((recorded[:, 0] >= -180) & (recorded[:, 0] < 180))
        assert np.all((recorded[:, 1] >= 0) & (recorded[:, 1] <= 40))
        np.testing.assert_allclose(recorded, pix3d_viewpoints(category, oid, views_per_object=4), atol=1e-6)
    records = scan_dataset(root, check_files=True)  # the existing reader
    assert [len(r.views["pix3d"][0]) for r in records] == [4, 4] and all(r.mesh_path for r in records)
    item = VTRDataset(records, "pix3d", num_views=2)[0]
    assert tuple(item["images"].shape) == (2, 3, 224, 224)
    alpha = np.asarray(Image.open(records[0].views["pix3d"][0][0]))[..., 3]
    assert alpha.shape == (16, 16) and 0 < (alpha > 0).mean() < 1  # an object on a transparent background
    # Deterministic: a second build (in two shards, finalized separately) writes the same bytes.
    again = tmp_path / "again"
    build_dataset(again, **PIX3D, shard=(0, 2), finalize=False)
    build_dataset(again, **PIX3D, shard=(1, 2), finalize=False)
    assert finalize_dataset(again).finalized
    assert load_metadata(again)["objects"] == meta["objects"]
    assert load_metadata(again)["view_sets"] == ["pix3d"]
    for png in pngs:
        assert (again / png).read_bytes() == (root / png).read_bytes()
    # A re-run skips everything; a VTR build into the same directory is refused.
    assert len(build_dataset(root, **PIX3D).skipped) == 2
    vtr = dict(categories=["chair"], objects_per_category=2, image_size=16, views_per_set=4, progress=False)
    with pytest.raises(ValueError, match="pitch_range: .0.0, 40.0. on disk vs None now, protocol: 'pix3d' on disk"):
        build_dataset(root, **vtr)


def test_pix3d_protocol_arguments_are_checked(tmp_path):
    with pytest.raises(ValueError, match=r"`protocol` must be one of 'vtr', 'pix3d', got 'pix4d'"):
        build_dataset(tmp_path, protocol="pix4d")
    with pytest.raises(
        ValueError, match=r"`views_per_object` applies to protocol='pix3d' only .* got views_per_object=60"
    ):
        build_dataset(tmp_path, views_per_object=60)
    with pytest.raises(ValueError, match=r"`pitch_range` applies to protocol='pix3d' only"):
        build_dataset(tmp_path, pitch_range=(0, 30))
    with pytest.raises(ValueError, match=r"`views_per_set` applies to protocol='vtr' only.* got views_per_set=8"):
        build_dataset(tmp_path, protocol="pix3d", views_per_set=8)
    with pytest.raises(ValueError, match=r"`views_per_object` must be an int in \[1, 100\], got 101"):
        build_dataset(tmp_path, protocol="pix3d", views_per_object=101)
    with pytest.raises(ValueError, match=r"`pitch_range` must be \(low, high\) with low <= high, got \(40.0, 0.0\)"):
        build_dataset(tmp_path, protocol="pix3d", pitch_range=(40, 0))
    with pytest.raises(ValueError, match=r"`pitch_range\[1\]` must be"):
        build_dataset(tmp_path, protocol="pix3d", pitch_range=(0, 100))
    with pytest.raises(TypeError, match=r"`pitch_range` must be a pair of numbers \(low, high\) in degrees, got 30"):
        build_dataset(tmp_path, protocol="pix3d", pitch_range=30)
    assert not any(tmp_path.iterdir())


def test_a_pix3d_build_trains_through_the_datamodule_with_train_view_set(tmp_path):
    from lightning_vtr.data import VTRDataModule
    from lightning_vtr.data.dataset import VTRDataset

    root = tmp_path / "pix3d"
    build_dataset(root, **{**PIX3D, "objects_per_category": 10})
    dm = VTRDataModule(root, train_view_set="pix3d", num_views=2, image_size=16, batch_size=2)
    dm.setup("fit")
    train = dm.split_records("train")
    assert train and dm.split_records("val")
    served = dm.train_dataset()
    expected = VTRDataset(train, "pix3d", num_views=2, transform=dm.train_transform, train=True, seed=dm.seed)
    expected.set_epoch(0)
    assert len(served) == len(train)
    for i in range(len(train)):
        assert served[i]["object_id"] == train[i].object_id
        assert torch.equal(served[i]["images"], expected[i]["images"])
    assert next(iter(dm.train_dataloader()))["images"].shape == (2, 2, 3, 16, 16)
    val = dm.split_records("val")
    assert next(iter(dm.val_dataloader()))["images"].shape == (min(2, len(val)), 2, 3, 16, 16)
    with pytest.raises(KeyError, match="has no view set 'aligned'"):
        VTRDataModule(root, num_views=2, image_size=16).train_dataloader()
