"""Names read from data are plain path components, and every writer's path stays inside its root."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest
import torch

from lightning_vtr.utils.paths import (
    RULES,
    UnsafeNameError,
    UnsafePathError,
    check_name,
    check_no_case_collisions,
    check_object_key,
    check_relative_path,
    join_under,
)


def _files(root) -> set[str]:
    return {
        os.path.relpath(os.path.join(folder, name), root)
        for folder, _, names in os.walk(root, followlinks=True)
        for name in names
    }


# ---------------------------------------------------------------------------------------------- names
@pytest.mark.parametrize(
    ("name", "rule"),
    [
        ("", "empty"),
        (".", "dot"),
        ("..", "dot"),
        ("a/b", "separator"),
        ("a\\b", "separator"),
        ("C:evil", "absolute"),
        ("a\x00b", "control"),
        ("a\nb", "control"),
        ("\x7f", "control"),
        ("-rf", "dash"),
        (3, "type"),
    ],
)
def test_a_name_that_is_not_a_plain_component_is_refused_with_its_rule(name, rule):
    with pytest.raises(UnsafeNameError) as info:
        check_name(name, source="ds/metadata.json", entry="category")
    assert info.value.rule == rule
    message = str(info.value)
    assert message.startswith(f"ds/metadata.json: category {name!r}: {RULES[rule]}")
    assert "\n" not in message


@pytest.mark.parametrize("name", ["chair", "03001627", "chair_0001", "a.b", "a-b", "été", "a b", "..."])
def test_plain_names_pass_unchanged(name):
    assert check_name(name, source="f", entry="e") == name


@pytest.mark.parametrize(
    ("key", "rule", "detail"),
    [
        ("chair/../../../outside/evil", "dot", "its part '..'"),
        ("/abs/evil", "absolute", ""),
        ("c0", "key", "found 0"),
        ("a/b/c", "key", "found 2"),
        ("chair/", "empty", "its object id ''"),
        ("-x/c0", "dash", "its category '-x'"),
        ("chair/c\x00", "control", "its object id 'c\\x00', found '\\x00' at index 1"),
    ],
)
def test_an_object_key_names_the_part_and_rule(key, rule, detail):
    with pytest.raises(UnsafeNameError) as info:
        check_object_key(key, source="m.json", entry="object key")
    assert info.value.rule == rule
    assert str(info.value) == f"m.json: object key {key!r}: {RULES[rule]}" + (f" ({detail})" if detail else "")


def test_an_object_key_splits_into_category_and_id():
    assert check_object_key("chair/chair_0001", source="m", entry="k") == ("chair", "chair_0001")


def test_names_that_differ_only_in_case_are_refused_and_others_pass():
    check_no_case_collisions(["chair/a", "chair/b", "table/a"], source="m", entry="object key")
    with pytest.raises(UnsafeNameError, match="'chair/A'.*against 'chair/a'") as info:
        check_no_case_collisions(["chair/a", "chair/A"], source="m", entry="object key")
    assert info.value.rule == "case"
    with pytest.raises(UnsafeNameError, match="its category 'Chair' against 'chair/a'"):
        check_no_case_collisions(["chair/a", "Chair/b"], source="m", entry="object key")


def test_a_relative_path_of_plain_parts_passes_and_others_are_refused():
    assert check_relative_path("img/chair/0001.png", source="p", entry="img") == "img/chair/0001.png"
    for bad, rule in [("../x.png", "dot"), ("/etc/passwd", "absolute"), ("img//a.png", "empty"), ("C:/x", "absolute")]:
        with pytest.raises(UnsafeNameError) as info:
            check_relative_path(bad, source="p", entry="img")
        assert info.value.rule == rule


# ---------------------------------------------------------------------------------------------- join_under
def test_join_under_keeps_paths_inside_and_refuses_the_rest(tmp_path):
    assert join_under(tmp_path, "chair", "c0") == tmp_path / "chair" / "c0"
    assert join_under(tmp_path, "a/../b") == tmp_path / "a/../b"  # still inside
    for parts in [("..",), ("chair/../../x",), ("/etc",), ("a", "..", "..", "x")]:
        with pytest.raises(UnsafePathError, match=f"expected a path inside {tmp_path}"):
            join_under(tmp_path, *parts)


def test_join_under_follows_symlinks_inside_the_root_but_not_the_root_itself(tmp_path):
    outside = tmp_path / "outside"
    outside.mkdir()
    root = tmp_path / "root"
    root.mkdir()
    (root / "link").symlink_to(outside, target_is_directory=True)
    with pytest.raises(UnsafePathError, match="resolves to .*outside"):
        join_under(root, "link", "file.txt")
    alias = tmp_path / "alias"  # a root that is itself a symlink is the user's choice: allowed
    alias.symlink_to(root, target_is_directory=True)
    assert join_under(alias, "a.txt") == alias / "a.txt"


# ---------------------------------------------------------------------------------------------- writers
def test_export_prediction_and_the_prediction_writer_stay_in_their_folder(tmp_path):
    from lightning_vtr.export import VoxelPredictionWriter, export_prediction

    out = tmp_path / "out"
    voxels = torch.rand(8, 8, 8)
    with pytest.raises(UnsafePathError):
        export_prediction(out, voxels, name="../../evil")
    writer = VoxelPredictionWriter(out, sheets=False)
    batch = {"images": torch.zeros(1, 1, 3, 8, 8), "category": ["chair"], "object_id": ["../../../evil"]}
    with pytest.raises(UnsafePathError):
        writer.write_on_batch_end(None, None, voxels[None], [0], batch, 0)
    assert _files(tmp_path) == set()


def test_export_predictions_refuses_a_result_name_that_leaves_out(tmp_path):
    from lightning_vtr.evaluation.predict import export_predictions

    result = {"name": "../evil", "predicted": torch.rand(8, 8, 8), "target": None}
    with pytest.raises(UnsafePathError):
        list(export_predictions(tmp_path / "out", [result], sheets=False))
    assert _files(tmp_path) == set()


def test_a_generated_sample_and_its_index_stay_in_the_generated_folder(tmp_path):
    from lightning_vtr.data.dataset import GeneratedDataset, GeneratedSample, write_generated_sample

    sample = GeneratedSample("chair", "c0", np.zeros((1, 4, 4, 4), np.uint8), np.zeros((1, 2)))
    entry = write_generated_sample(sample, tmp_path / "gen" / "0000000_chair_c0")
    assert _files(tmp_path) == {"gen/0000000_chair_c0/00.png"}
    with pytest.raises(UnsafeNameError, match="generated sample dir '../x'"):
        GeneratedDataset([{**entry, "dir": "../x"}], tmp_path / "gen", {})


def test_the_synthesis_cache_refuses_an_id_that_names_its_parent(tmp_path):
    from lightning_vtr.synthesis.cache import SynthesisCache

    cache = SynthesisCache(tmp_path / "cache")
    assert cache.path("a/b", (0.0, 0.0), "cfg").parent.name == "a%2Fb"  # one component
    with pytest.raises(UnsafePathError):
        cache.path("..", (0.0, 0.0), "cfg")


def test_png_fallback_paths_stay_in_images(tmp_path):
    from lightning_vtr.utils.image_logging import png_path

    assert png_path(tmp_path, "../../x", 3) == tmp_path / "images" / "x" / "step_000003.png"


def test_robustness_pictures_of_a_label_with_dots_stay_in_out(tmp_path):
    from lightning_vtr.evaluation.robustness import RobustnessMap, bin_area_fractions
    from lightning_vtr.evaluation.robustness_plot import write_index_html
    from lightning_vtr.geometry import candidate_viewpoints

    centres = candidate_viewpoints(90).numpy()
    areas = bin_area_fractions(90)
    rmap = RobustnessMap(np.full((1, len(centres)), 0.5), centres, areas, ["c0"], ["chair"], k=90)
    write_index_html(tmp_path / "out", {"../../evil": rmap})
    assert {os.path.dirname(p) for p in _files(tmp_path)} == {"out"}


# ---------------------------------------------------------------------------------------------- readers
def test_read_object_json_refuses_an_unsafe_object_id(tmp_path):
    from lightning_vtr.data.format import read_object_json

    views = {"aligned": [[0.0, 30.0]]}
    (tmp_path / "object.json").write_text(json.dumps({"category": "chair", "object_id": "../x", "views": views}))
    with pytest.raises(UnsafeNameError, match=r"object.json: object_id '../x': must not contain '/'"):
        read_object_json(tmp_path)
