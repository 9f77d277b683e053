"""``build-dataset`` gives every category of at least 3 objects one validation and one test object, keeps the
rounded split wherever it already does, and warns naming the categories too small for it."""

from __future__ import annotations

import warnings
from pathlib import Path

import pytest
import trimesh

from lightning_vtr.data.builder import build_dataset
from lightning_vtr.data.format import load_metadata
from lightning_vtr.data.splits import MIN_OBJECTS_FOR_SPLITS, split_counts

TINY = dict(image_size=16, resolution=16, views_per_set=2, progress=False)
RATIOS = [(0.7, 0.1, 0.2), (0.8, 0.1, 0.1), (0.2, 0.2, 0.6), (0.45, 0.45, 0.1), (0.9, 0.05, 0.05)]


def _counts(root: Path) -> dict[str, list[int]]:
    out: dict[str, list[int]] = {}
    for key, info in load_metadata(root)["objects"].items():
        row = out.setdefault(key.split("/")[0], [0, 0, 0])
        row[("train", "val", "test").index(info["split"])] += 1
    return out


def test_four_objects_per_category_give_a_validation_and_a_test_object_each(tmp_path):
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # nothing to warn about
        build_dataset(tmp_path, categories=["chair", "table"], objects_per_category=4, **TINY)
    # the rounded 0.7 / 0.1 / 0.2 of 4 is 3 / 0 / 1: the validation object comes from training
    assert _counts(tmp_path) == {"chair": [2, 1, 1], "table": [2, 1, 1]}


@pytest.mark.parametrize("ratios", RATIOS)
def test_rounded_counts_are_kept_wherever_they_give_both(ratios):
    for n in range(1, 60):
        rounded = [round(ratios[0] * n), round(ratios[1] * n)]
        rounded.append(n - sum(rounded))
        counts = split_counts(n, ratios)
        assert sum(counts) == n and min(counts) >= 0
        if rounded[1] >= 1 and rounded[2] >= 1:
            assert counts == rounded, n  # the embedded dataset's 17 / 2 / 5 of 24 among them
        elif n >= MIN_OBJECTS_FOR_SPLITS:
            assert counts[1] >= 1 and counts[2] >= 1 and counts[0] >= 1, (n, counts)


def test_a_zero_ratio_stays_empty():
    assert split_counts(4, (1.0, 0.0, 0.0)) == [4, 0, 0]
    assert split_counts(4, (0.8, 0.2, 0.0)) == [3, 1, 0]


def test_too_few_objects_warn_naming_the_category(tmp_path):
    src = tmp_path / "meshes"
    for category, count in (("crate", 4), ("tub", 2)):
        for i in range(count):
            (src / category).mkdir(parents=True, exist_ok=True)
            trimesh.creation.box(extents=(0.3, 0.6, 0.9)).export(src / category / f"{category}{i}.obj")
    root = tmp_path / "ds"
    with pytest.warns(UserWarning, match=r"at least 3\): tub \(2 objects, no val\); build more") as seen:
        build_dataset(root, source=src, **TINY)
    assert not any("crate" in str(w.message) for w in seen)
    assert _counts(root) == {"crate": [2, 1, 1], "tub": [1, 0, 1]}
