"""``--verify`` also checks ``splits.json``, each object's ``object.json`` and its ``mesh.ply``; a killed write's
``.tmp`` file is removed at the next start."""

from __future__ import annotations

import json
import os
import shutil
import time

import pytest

from lightning_vtr.cli import main
from lightning_vtr.data.verify import verify_dataset
from lightning_vtr.utils.io import atomic_write, remove_stale_temporaries


@pytest.fixture
def dataset(tiny_dataset, tmp_path):
    root = tmp_path / "vtr"
    shutil.copytree(tiny_dataset, root)
    return root


def _first_object(root):
    meta = json.loads((root / "metadata.json").read_text())
    key = sorted(meta["objects"])[0]
    category, object_id = key.split("/")
    return key, root / "objects" / category / object_id if (root / "objects").is_dir() else None


def _object_dir(root, key):
    from lightning_vtr.data.format import object_dir

    return object_dir(root, *key.split("/"))


def test_a_clean_dataset_passes_with_the_new_checks(dataset):
    report = verify_dataset(dataset, workers=1, progress=False)
    assert report.ok, report.problems


def test_verify_names_a_truncated_mesh_a_missing_or_wrong_object_json_and_splits(dataset, capsys):
    key, _ = _first_object(dataset)
    other_key = sorted(json.loads((dataset / "metadata.json").read_text())["objects"])[1]
    mesh = _object_dir(dataset, key) / "mesh.ply"
    assert mesh.is_file()
    mesh.write_bytes(mesh.read_bytes()[: mesh.stat().st_size // 2])
    (_object_dir(dataset, other_key) / "object.json").unlink()
    splits = json.loads((dataset / "splits.json").read_text())
    category, object_id = key.split("/")
    for split, ids in splits[category].items():
        if object_id in ids:
            ids.remove(object_id)
            moved_from = split
    splits[category]["train" if moved_from != "train" else "test"].append(object_id)
    (dataset / "splits.json").write_text(json.dumps(splits))

    report = verify_dataset(dataset, workers=1, progress=False)
    found = {(p.path.name, p.kind) for p in report.problems}
    assert found == {("mesh.ply", "unreadable"), ("object.json", "missing"), ("splits.json", "inconsistent")}
    [problem] = [p for p in report.problems if p.kind == "inconsistent"]
    assert str(problem).endswith(
        f"splits.json disagrees with metadata.json on {key!r} (expected {moved_from}, got "
        f"{'train' if moved_from != 'train' else 'test'})"
    )
    assert main(["dataset-info", str(dataset), "--verify", "--no-progress"]) == 1
    out = capsys.readouterr().out
    assert "PROBLEM [unreadable]" in out and "mesh.ply: cannot read the mesh" in out


def test_verify_names_an_object_json_of_another_object_and_a_missing_splits_json(dataset):
    key, _ = _first_object(dataset)
    path = _object_dir(dataset, key) / "object.json"
    info = json.loads(path.read_text())
    info["object_id"] = "someone_else"
    path.write_text(json.dumps(info))
    (dataset / "splits.json").unlink()
    report = verify_dataset(dataset, workers=1, progress=False)
    assert sorted((p.path.name, p.kind, p.message) for p in report.problems) == [
        ("object.json", "inconsistent", "object.json names another object"),
        ("splits.json", "missing", "the dataset's splits.json does not exist"),
    ]


def test_stale_temporaries_of_a_killed_write_are_removed_and_live_ones_kept(tmp_path):
    folder = tmp_path / "gen" / "0000001_chair_a"
    folder.mkdir(parents=True)
    stale, live = folder / ".00.png.abc123.tmp", folder / ".01.png.def456.tmp"
    stale.write_bytes(b"half a png")
    live.write_bytes(b"being written")
    old = time.time() - 3600
    os.utime(stale, (old, old))
    atomic_write(folder / "00.png", b"whole")
    assert remove_stale_temporaries(tmp_path / "gen") == [stale]
    assert not stale.exists() and live.exists() and (folder / "00.png").read_bytes() == b"whole"


def test_build_dataset_and_the_synthesis_cache_remove_stale_temporaries_at_start(tmp_path):
    from lightning_vtr.data.builder import build_dataset
    from lightning_vtr.synthesis.cache import SynthesisCache

    cache = tmp_path / "cache" / "abc"
    cache.mkdir(parents=True)
    (cache / ".x.png.1.tmp").write_bytes(b"")
    old = time.time() - 3600
    os.utime(cache / ".x.png.1.tmp", (old, old))
    SynthesisCache(tmp_path / "cache")
    assert not (cache / ".x.png.1.tmp").exists()

    root = tmp_path / "vtr"
    root.mkdir()
    (root / "build_config.json").write_text("{}")  # an earlier build's folder: not refused as other files
    (root / ".metadata.json.2.tmp").write_bytes(b"{")
    os.utime(root / ".metadata.json.2.tmp", (old, old))
    with pytest.raises(ValueError, match="was built with other options"):
        build_dataset(
            root, categories=["chair"], objects_per_category=1, image_size=16, views_per_set=1, progress=False
        )
    assert not (root / ".metadata.json.2.tmp").exists()
