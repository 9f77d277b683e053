"""The on-disk format helpers: atomic writes, metadata validation, scanning into ObjectRecords."""

from __future__ import annotations

import json

import numpy as np
import pytest

from lightning_vtr.data.format import (
    FORMAT_NAME,
    FORMAT_VERSION,
    DatasetFormatError,
    atomic_write_json,
    dataset_summary,
    load_metadata,
    object_dir,
    read_object,
    read_object_json,
    scan_dataset,
)
from lightning_vtr.utils.paths import UnsafeNameError

VIEWS = {"aligned": [[0, 30], [90, 30]], "hemispherical": [[10, 5], [-20, 80]], "spherical": [[170, -60], [-180, 0]]}


def _metadata(objects: dict) -> dict:
    return {
        "format": FORMAT_NAME,
        "version": FORMAT_VERSION,
        "resolution": 32,
        "image_size": 16,
        "views_per_set": 2,
        "view_sets": ["aligned", "hemispherical", "spherical"],
        "aligned_pitch": 30.0,
        "source": "procedural",
        "objects": objects,
    }


@pytest.fixture
def root(tmp_path):
    objects = {
        "chair/c0": {"split": "train", "views": VIEWS},
        "chair/c1": {"split": "test", "views": VIEWS},
        "table/t0": {"split": "val", "views": VIEWS},
    }
    atomic_write_json(tmp_path / "metadata.json", _metadata(objects))
    for key in objects:
        d = object_dir(tmp_path, *key.split("/"))
        d.mkdir(parents=True)
        (d / "model.binvox").write_bytes(b"")
        for name, vps in VIEWS.items():
            (d / name).mkdir()
            for i in range(len(vps)):
                (d / name / f"{i:02d}.png").write_bytes(b"")
    (object_dir(tmp_path, "chair", "c0") / "mesh.ply").write_bytes(b"")
    return tmp_path


def test_atomic_write_json_round_trip_leaves_no_temporary(tmp_path):
    atomic_write_json(tmp_path / "a" / "x.json", {"k": [1, 2.5]})
    atomic_write_json(tmp_path / "a" / "x.json", {"k": [3]})  # replaces
    assert json.loads((tmp_path / "a" / "x.json").read_text()) == {"k": [3]}
    assert [p.name for p in (tmp_path / "a").iterdir()] == ["x.json"]


def test_scan_dataset_records(root):
    records = scan_dataset(root, check_files=True)
    assert [(r.category, r.object_id, r.split) for r in records] == [
        ("chair", "c0", "train"),
        ("chair", "c1", "test"),
        ("table", "t0", "val"),
    ]
    r = records[0]
    assert r.key == "chair/c0" and r.voxel_up_axis == "z"
    assert r.voxel_path == root / "objects" / "chair" / "c0" / "model.binvox"
    assert r.mesh_path == root / "objects" / "chair" / "c0" / "mesh.ply"
    assert records[1].mesh_path is None  # no mesh.ply written for c1
    paths, vp = r.views["spherical"]
    assert paths == [root / "objects/chair/c0/spherical/00.png", root / "objects/chair/c0/spherical/01.png"]
    np.testing.assert_array_equal(vp, [[170, -60], [-180, 0]])
    assert read_object(root, "table", "t0").split == "val"
    with pytest.raises(DatasetFormatError, match="no object 'table/zz'"):
        read_object(root, "table", "zz")


def test_scan_dataset_check_files_names_missing_image(root):
    (root / "objects/table/t0/aligned/01.png").unlink()
    scan_dataset(root)  # without the check, nothing is stat-ed
    with pytest.raises(DatasetFormatError, match="t0/aligned/01.png"):
        scan_dataset(root, check_files=True)


def test_load_metadata_errors(tmp_path):
    with pytest.raises(DatasetFormatError, match="build-dataset"):
        load_metadata(tmp_path)
    (tmp_path / "objects").mkdir()
    with pytest.raises(DatasetFormatError, match="--finalize"):
        load_metadata(tmp_path)
    (tmp_path / "metadata.json").write_text("{not json")
    with pytest.raises(DatasetFormatError, match="not valid JSON"):
        load_metadata(tmp_path)
    atomic_write_json(tmp_path / "metadata.json", {**_metadata({}), "format": "something.else"})
    with pytest.raises(DatasetFormatError, match="something.else"):
        load_metadata(tmp_path)
    atomic_write_json(tmp_path / "metadata.json", {**_metadata({}), "version": FORMAT_VERSION + 1})
    with pytest.raises(DatasetFormatError, match="version"):
        load_metadata(tmp_path)
    atomic_write_json(tmp_path / "metadata.json", {k: v for k, v in _metadata({}).items() if k != "objects"})
    with pytest.raises(DatasetFormatError, match="objects"):
        load_metadata(tmp_path)


def test_malformed_entries_are_reported(tmp_path):
    atomic_write_json(tmp_path / "metadata.json", _metadata({"chair/c0": {"split": "training", "views": VIEWS}}))
    with pytest.raises(DatasetFormatError, match="split 'training'"):
        scan_dataset(tmp_path)
    bad_views = {**VIEWS, "spherical": [[1, 2, 3]]}
    atomic_write_json(tmp_path / "metadata.json", _metadata({"chair/c0": {"split": "train", "views": bad_views}}))
    with pytest.raises(DatasetFormatError, match="spherical"):
        scan_dataset(tmp_path)
    atomic_write_json(tmp_path / "metadata.json", _metadata({"c0": {"split": "train", "views": VIEWS}}))
    with pytest.raises(UnsafeNameError, match="<category>/<object_id>"):
        scan_dataset(tmp_path)


def test_read_object_json(tmp_path):
    atomic_write_json(tmp_path / "object.json", {"category": "chair", "object_id": "c0", "views": VIEWS})
    assert read_object_json(tmp_path)["object_id"] == "c0"
    atomic_write_json(tmp_path / "object.json", {"category": "chair", "views": VIEWS})
    with pytest.raises(DatasetFormatError, match="object_id"):
        read_object_json(tmp_path)
    with pytest.raises(DatasetFormatError, match="Cannot read"):
        read_object_json(tmp_path / "missing")


def test_dataset_summary_counts(root):
    text = dataset_summary(root)
    lines = {line.split()[0]: line.split()[1:] for line in text.splitlines()[3:]}
    assert lines["chair"] == ["1", "0", "1", "2"]
    assert lines["table"] == ["0", "1", "0", "1"]
    assert lines["all"] == ["1", "1", "1", "3"]
