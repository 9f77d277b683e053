"""``verify_dataset``: every missing, unreadable or inconsistent file is named, with expected and actual values."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from lightning_vtr.data.binvox import write_binvox
from lightning_vtr.data.datamodule import VTRDataModule
from lightning_vtr.data.dataset import load_rgba
from lightning_vtr.data.format import DatasetFormatError, object_dir
from lightning_vtr.data.verify import PROBLEM_KINDS, DatasetProblem, VerifyReport, verify_dataset

VIEWS = 4
SIZE = 32


@pytest.fixture(scope="module")
def clean_dataset(tmp_path_factory) -> Path:
    """2 categories x 2 procedural objects, 32 px, 4 views per set, R = 32 (built once, copied per test)."""
    from lightning_vtr.data.builder import build_dataset

    root = tmp_path_factory.mktemp("verify_clean")
    build_dataset(
        root,
        categories=["chair", "table"],
        objects_per_category=2,
        image_size=SIZE,
        resolution=32,
        views_per_set=VIEWS,
        split=(0.5, 0.0, 0.5),
        progress=False,
    )
    return root


@pytest.fixture
def dataset(clean_dataset, tmp_path) -> Path:
    """A copy of the clean dataset to corrupt."""
    return Path(shutil.copytree(clean_dataset, tmp_path / "vtr"))


def _obj(root: Path, key: str = "chair/chair_0000") -> Path:
    return object_dir(root, *key.split("/"))


def _only(report: VerifyReport) -> DatasetProblem:
    assert len(report.problems) == 1, [str(p) for p in report.problems]
    return report.problems[0]


def _truncate(path: Path) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


def _edit_metadata(root: Path, edit) -> None:
    meta = json.loads((root / "metadata.json").read_text())
    edit(meta)
    (root / "metadata.json").write_text(json.dumps(meta))


def test_a_clean_dataset_has_no_problems_and_every_file_is_read(clean_dataset):
    report = verify_dataset(clean_dataset, progress=False)
    assert report.ok and report.problems == []
    assert report.objects == 4
    assert report.files == 4 * (1 + 3 * VIEWS)  # one voxel file and 3 view sets of 4 images per object
    assert report.seconds > 0 and report.objects_per_second == pytest.approx(4 / report.seconds)
    assert report.summary().startswith("verified 4 objects (52 files) in ")
    assert report.summary().endswith("objects/s): 0 problem(s)")


def test_a_truncated_png_is_reported_before_training_reads_it(dataset):
    png = _obj(dataset) / "aligned" / "02.png"
    _truncate(png)
    with pytest.raises(OSError, match="image file is truncated"):  # what the first epoch drawing it would meet
        load_rgba(png)
    problem = _only(verify_dataset(dataset, progress=False))
    assert (problem.path, problem.kind) == (png, "unreadable")
    assert str(problem) == f"{png}: cannot read the image: image file is truncated"


def test_an_image_of_the_wrong_size_names_width_and_height(dataset):
    png = _obj(dataset, "table/table_0001") / "spherical" / "03.png"
    Image.new("RGBA", (20, 24)).save(png)  # 20 wide, 24 high
    problem = _only(verify_dataset(dataset, progress=False))
    assert (problem.path, problem.kind, problem.expected, problem.actual) == (png, "image_size", "32x32", "20x24")
    assert str(problem).endswith("(expected 32x32, got 20x24)")


def test_a_deleted_view_is_named_with_the_view_count(dataset):
    png = _obj(dataset) / "hemispherical" / "01.png"
    png.unlink()
    problem = _only(verify_dataset(dataset, progress=False))
    assert (problem.path, problem.kind, problem.expected, problem.actual) == (png, "view_count", 4, 3)
    assert "view 01 of 4 listed in metadata.json is missing" in str(problem)


def test_an_image_metadata_does_not_list_is_a_wrong_view_count(dataset):
    extra = _obj(dataset) / "aligned" / "04.png"
    shutil.copy(extra.with_name("00.png"), extra)
    problem = _only(verify_dataset(dataset, progress=False))
    assert (problem.path, problem.kind, problem.expected, problem.actual) == (extra, "view_count", 4, 5)


def test_metadata_listing_too_few_viewpoints_is_a_wrong_view_count(dataset):
    _edit_metadata(dataset, lambda m: m["objects"]["table/table_0000"]["views"]["spherical"].pop())
    problems = verify_dataset(dataset, progress=False).problems
    set_dir = _obj(dataset, "table/table_0000") / "spherical"
    assert [(p.path, p.kind, p.expected, p.actual) for p in problems] == [
        (set_dir, "view_count", 4, 3),  # metadata.json lists 3 viewpoints, views_per_set is 4
        (set_dir / "03.png", "view_count", 3, 4),  # so the fourth image on disk is not listed
    ]


def test_a_voxel_file_of_the_wrong_resolution(dataset):
    binvox = _obj(dataset, "chair/chair_0001") / "model.binvox"
    write_binvox(binvox, np.ones((16, 16, 16), bool))
    problem = _only(verify_dataset(dataset, progress=False))
    assert (problem.path, problem.kind, problem.expected, problem.actual) == (
        binvox,
        "voxel_resolution",
        "32x32x32",
        "16x16x16",
    )


def test_a_truncated_voxel_file_is_unreadable(dataset):
    binvox = _obj(dataset) / "model.binvox"
    _truncate(binvox)
    problem = _only(verify_dataset(dataset, progress=False))
    assert (problem.path, problem.kind) == (binvox, "unreadable")
    assert problem.message.startswith(f"cannot read the voxel file: Bad binvox data in '{binvox}'")


def test_metadata_pointing_to_missing_files(dataset):
    ghost = "chair/chair_0099"
    _edit_metadata(dataset, lambda m: m["objects"].update({ghost: m["objects"]["chair/chair_0000"]}))
    (_obj(dataset, "table/table_0000") / "model.binvox").unlink()
    problems = verify_dataset(dataset, progress=False).problems
    assert [(p.path, p.kind) for p in problems] == [
        (_obj(dataset, "table/table_0000") / "model.binvox", "missing"),
        (_obj(dataset, ghost), "missing"),  # listed last in metadata.json
    ]
    assert f"metadata.json lists object '{ghost}' but its directory does not exist" in str(problems[1])


def test_a_malformed_metadata_entry_is_a_metadata_problem(dataset):
    _edit_metadata(dataset, lambda m: m["objects"]["table/table_0001"].update(split="dev"))
    problem = _only(verify_dataset(dataset, progress=False))
    assert (problem.path, problem.kind, problem.actual) == (dataset / "metadata.json", "metadata", "dev")


def test_an_unsafe_name_is_its_own_problem_with_its_rule_and_is_never_read(dataset):
    # The traversal: the key leads out of objects/ and out of the dataset; a copy of a real object waits there.
    key = "chair/../../../outside/evil"
    shutil.copytree(_obj(dataset, "chair/chair_0001"), dataset.parent / "outside" / "evil")
    _edit_metadata(dataset, lambda m: m["objects"].update({key: m["objects"].pop("chair/chair_0001")}))
    (dataset / "objects" / "chair" / "Chair_0000").mkdir()  # a folder that is not listed: no problem of names
    report = verify_dataset(dataset, progress=False)
    problem = _only(report)
    assert (problem.path, problem.kind) == (dataset / "metadata.json", "unsafe_name")
    assert str(problem) == (
        f"{dataset / 'metadata.json'}: object key {key!r}: must not be '.' or '..', which name the folder itself "
        "or its parent (its part '..')"
    )
    assert report.objects == 4 and report.files == 3 * (1 + 3 * VIEWS)  # the other objects' files, not its


def test_object_keys_that_differ_only_in_case_are_an_unsafe_name(dataset):
    _edit_metadata(dataset, lambda m: m["objects"].update({"Chair/chair_0009": m["objects"]["chair/chair_0000"]}))
    problem = verify_dataset(dataset, progress=False).problems[0]
    assert problem.kind == "unsafe_name"
    assert "'Chair/chair_0009': must not differ only in case" in str(problem)


def test_every_problem_is_listed_in_metadata_order_whatever_the_workers(dataset):
    _truncate(_obj(dataset, "chair/chair_0000") / "aligned" / "00.png")
    (_obj(dataset, "chair/chair_0001") / "spherical" / "02.png").unlink()
    Image.new("RGBA", (31, 31)).save(_obj(dataset, "table/table_0000") / "aligned" / "01.png")
    write_binvox(_obj(dataset, "table/table_0001") / "model.binvox", np.ones((8, 8, 8), bool))
    serial = verify_dataset(dataset, workers=1, progress=False)
    threaded = verify_dataset(dataset, workers=4, progress=False)
    assert serial.problems == threaded.problems
    order = list(json.loads((dataset / "metadata.json").read_text())["objects"])
    keys = ["/".join(p.path.relative_to(dataset / "objects").parts[:2]) for p in serial.problems]
    assert sorted(keys, key=order.index) == keys and len(set(keys)) == 4
    assert {p.kind for p in serial.problems} == {"unreadable", "view_count", "image_size", "voxel_resolution"}
    assert set(PROBLEM_KINDS) >= {p.kind for p in serial.problems}


def test_the_error_message_lists_the_first_problems_and_counts_the_rest(dataset):
    for png in sorted((_obj(dataset) / "aligned").glob("*.png")):
        _truncate(png)
    report = verify_dataset(dataset, progress=False)
    assert len(report.problems) == 4
    message = report.error_message(limit=2)
    lines = message.splitlines()
    assert lines[0] == f"Verifying the dataset at {dataset} found 4 problem(s):"
    assert lines[1:3] == [f"  {report.problems[0]}", f"  {report.problems[1]}"]
    assert lines[3].startswith("  ... and 2 more; `lightning-vtr dataset-info ") and len(lines) == 4


def test_a_dataset_without_metadata_raises(tmp_path):
    with pytest.raises(DatasetFormatError, match="metadata.json does not exist"):
        verify_dataset(tmp_path, progress=False)


def test_workers_must_be_positive(clean_dataset):
    with pytest.raises(ValueError, match="^`workers` must be"):
        verify_dataset(clean_dataset, workers=0, progress=False)


def test_the_datamodule_option_raises_at_setup_naming_the_file(dataset):
    png = _obj(dataset, "table/table_0001") / "aligned" / "03.png"
    _truncate(png)
    unverified = VTRDataModule(str(dataset), image_size=SIZE)
    unverified.setup("fit")  # the file is only met when a loader draws it
    assert len(unverified.records) == 4
    with pytest.raises(DatasetFormatError) as caught:
        VTRDataModule(str(dataset), image_size=SIZE, verify=True).setup("fit")
    assert str(caught.value) == (
        f"Verifying the dataset at {dataset} found 1 problem(s):\n  {png}: cannot read the image: image file is truncated"
    )


def test_the_datamodule_option_passes_a_clean_dataset(clean_dataset):
    dm = VTRDataModule(str(clean_dataset), image_size=SIZE, verify=True)
    dm.setup("fit")
    assert dm.hparams["verify"] is True
    assert [r.key for r in dm.records] == [
        "chair/chair_0000",
        "chair/chair_0001",
        "table/table_0000",
        "table/table_0001",
    ]


def test_the_datamodule_option_checks_its_arguments():
    with pytest.raises(TypeError, match="^`verify` must be a bool, got str 'yes'$"):
        VTRDataModule(verify="yes")
    with pytest.raises(ValueError, match="^`verify` must be False with `shapenet_rendering`"):
        VTRDataModule(
            shapenet_rendering={"rendering_root": "r", "voxel_root": "v", "split_file": "s.json"}, verify=True
        )


@pytest.mark.slow
def test_every_ddp_process_raises_what_rank_0_found(dataset, tmp_path):
    import lightning as L

    from lightning_vtr.models import Pix2VoxPlusPlus

    png = _obj(dataset, "chair/chair_0001") / "hemispherical" / "00.png"
    _truncate(png)
    trainer = L.Trainer(
        accelerator="cpu",
        devices=2,
        strategy="ddp_spawn",
        default_root_dir=str(tmp_path),
        logger=False,
        enable_progress_bar=False,
        enable_model_summary=False,
    )
    # Rank 1 reads nothing; had it not raised too, it would wait for rank 0 in the test loop until a timeout.
    with pytest.raises(
        Exception, match=f"(?s)found 1 problem.*{re.escape(str(png))}: cannot read the image: image file is truncated"
    ):
        trainer.test(Pix2VoxPlusPlus(preset="tiny"), datamodule=VTRDataModule(str(dataset), image_size=64, verify=True))
