"""Bad input to a public entry point raises an error that names the problem: a dataset of another format
version, another model's checkpoint, a NaN viewpoint, an empty image folder for ``lightning-vtr predict``."""

from __future__ import annotations

import json
import re

import lightning as L
import numpy as np
import pytest
import torch
import trimesh
from helpers import one_thread

from lightning_vtr.cli import main
from lightning_vtr.data.datamodule import VTRDataModule
from lightning_vtr.data.format import FORMAT_NAME, DatasetFormatError
from lightning_vtr.geometry import camera_pose
from lightning_vtr.models import LRGT, Pix2VoxPlusPlus
from lightning_vtr.renderer import Renderer
from lightning_vtr.synthesis.base import SynthesisRequest
from lightning_vtr.synthesis.render import RenderSynthesizer

_one_thread = pytest.fixture(autouse=True)(one_thread)


# ------------------------------------------------------------------------------------ dataset format version
@pytest.mark.parametrize(
    ("version", "advice"),
    [
        (2, "a newer lightning_vtr wrote it: upgrade lightning_vtr to read it"),
        (0, "rebuild it with `lightning-vtr build-dataset`"),
        ("1", "rebuild it with `lightning-vtr build-dataset`"),
    ],
)
def test_a_dataset_of_another_format_version_names_the_file_and_both_versions(tmp_path, version, advice):
    meta = {"format": FORMAT_NAME, "version": version, "objects": {}, "view_sets": [], "resolution": 32}
    (tmp_path / "metadata.json").write_text(json.dumps(meta | {"image_size": 64}))
    message = f"{tmp_path / 'metadata.json'}: unsupported format version: expected 1, found {version!r}; {advice}"
    with pytest.raises(DatasetFormatError, match=f"^{re.escape(message)}$"):
        VTRDataModule(str(tmp_path), image_size=64).setup("fit")


# ------------------------------------------------------------------------------------ another model's checkpoint
def _save_checkpoint(model: L.LightningModule, path) -> str:
    """What Lightning writes for a model: its weights and hyperparameters (plus the model's own hook)."""
    checkpoint = {
        "state_dict": model.state_dict(),
        "hyper_parameters": dict(model.hparams),
        "pytorch-lightning_version": L.__version__,
    }
    model.on_save_checkpoint(checkpoint)
    torch.save(checkpoint, path)
    return str(path)


@pytest.mark.parametrize(
    ("saved_cls", "loading_cls", "where"),
    [
        (LRGT, Pix2VoxPlusPlus, "lightning_vtr.models.lrgt.LRGT"),
        (Pix2VoxPlusPlus, LRGT, "lightning_vtr.models.pix2vox.Pix2VoxPlusPlus"),
    ],
)
def test_another_models_checkpoint_names_both_classes_and_the_path(tmp_path, saved_cls, loading_cls, where):
    path = _save_checkpoint(saved_cls(preset="tiny"), tmp_path / "model.ckpt")
    saved, loading = saved_cls.__name__, loading_cls.__name__
    message = (
        f"'{path}' is a checkpoint of {saved} ({where}), not of {loading}: {loading}.load_from_checkpoint cannot "
        f"load it. Use {saved}.load_from_checkpoint(...) (`lightning-vtr predict --model {where}`)."
    )
    with pytest.raises(ValueError, match=f"^{re.escape(message)}$"):
        loading_cls.load_from_checkpoint(path)
    assert type(saved_cls.load_from_checkpoint(path)) is saved_cls  # the right class still loads it


# ------------------------------------------------------------------------------------ NaN viewpoints
_NAN_ROW_2 = [[0.0, 30.0], [90.0, 30.0], [float("nan"), 30.0], [180.0, float("nan")]]
_NAN_MESSAGE = (
    "`viewpoints` must hold finite (yaw, pitch) angles in degrees, got [nan, 30.0] at row 2 "
    "(2 of 4 rows hold NaN or infinite values)"
)


def test_a_nan_viewpoint_names_the_argument_and_row_in_geometry():
    with pytest.raises(ValueError, match=f"^{re.escape(_NAN_MESSAGE)}$"):
        camera_pose(torch.tensor(_NAN_ROW_2))
    batched = torch.zeros(2, 3, 2)
    batched[1, 2, 1] = float("inf")
    message = (
        "`viewpoints` must hold finite (yaw, pitch) angles in degrees, got [0.0, inf] at row (1, 2) "
        "(1 of 6 rows hold NaN or infinite values)"
    )
    with pytest.raises(ValueError, match=f"^{re.escape(message)}$"):
        camera_pose(batched)


def test_a_nan_viewpoint_names_the_argument_and_row_in_the_renderer_and_synthesizer(tmp_path):
    mesh = trimesh.creation.box(extents=(0.5, 0.5, 0.5))
    with pytest.raises(ValueError, match=f"^{re.escape(_NAN_MESSAGE)}$"):
        Renderer(image_size=16).render(mesh, np.array(_NAN_ROW_2))
    mesh.export(tmp_path / "mesh.ply")
    request = SynthesisRequest(
        object_id="box",
        category="cube",
        source_images=np.zeros((0, 0, 0, 4), np.uint8),
        source_viewpoints=torch.zeros(0, 2),
        target_viewpoints=torch.tensor(_NAN_ROW_2),
        mesh_path=tmp_path / "mesh.ply",
    )
    with pytest.raises(ValueError, match=f"^{re.escape(_NAN_MESSAGE)}$"):
        RenderSynthesizer(image_size=16).synthesize([request])


# ------------------------------------------------------------------------------------ lightning-vtr predict
def test_predict_refuses_an_empty_image_folder_before_loading_the_model(tmp_path, capsys, monkeypatch):
    import lightning_vtr.models.registry as registry  # predict imports load_model from it when it runs

    def load_model(*args, **kwargs):
        raise AssertionError("the model was loaded before the image folders were checked")

    monkeypatch.setattr(registry, "load_model", load_model)
    good, empty, out = tmp_path / "chair", tmp_path / "empty", tmp_path / "out"
    good.mkdir()
    empty.mkdir()
    (good / "view.png").write_bytes(b"")  # never opened: the check only lists the folders
    (empty / "notes.txt").write_text("not a picture")
    (tmp_path / "model.ckpt").write_bytes(b"")
    argv = ["predict", "--ckpt", str(tmp_path / "model.ckpt"), "--images", str(good), str(empty), "--out", str(out)]

    assert main(argv) == 2
    message = (
        f"lightning-vtr predict: error: no pictures in the image folder '{empty}': expected files ending in "
        ".png, .jpg, .jpeg, .webp, .bmp (case-insensitive, masks <stem>_mask.<ext> aside); it holds none\n"
    )
    assert capsys.readouterr().err == message
    assert not out.exists()  # nothing was written for the first folder either


# ------------------------------------------------------------------------------------ untrusted names and files
def _one_object_dataset(root, category="chair", object_id="c0", split="test"):
    """A dataset of one object with 3 aligned 16-px views and a 32^3 grid (``dataset-info`` and ``--verify``)."""
    from PIL import Image

    from lightning_vtr.data.binvox import write_binvox

    views = [[0.0, 30.0], [120.0, 30.0], [-120.0, 30.0]]
    directory = root / "objects" / category / object_id
    (directory / "aligned").mkdir(parents=True)
    for i in range(3):
        Image.new("RGBA", (16, 16)).save(directory / "aligned" / f"{i:02d}.png")
    write_binvox(directory / "model.binvox", np.zeros((32, 32, 32), bool))
    obj = {"category": category, "object_id": object_id, "views": {"aligned": views}}
    (directory / "object.json").write_text(json.dumps(obj))
    key = f"{category}/{object_id}"
    meta = {"format": FORMAT_NAME, "version": 1, "resolution": 32, "image_size": 16, "views_per_set": 3,
            "view_sets": ["aligned"], "objects": {key: {"split": split, "views": {"aligned": views}}}}  # fmt: skip
    (root / "metadata.json").write_text(json.dumps(meta))
    (root / "splits.json").write_text(json.dumps({category: {"train": [], "val": [], "test": [object_id]}}))
    return root


def test_dataset_info_escapes_a_category_holding_an_ansi_escape_sequence(tmp_path, capsys):
    root = _one_object_dataset(tmp_path / "data", category="evil\x1b[2J\x1b[31m")
    assert main(["dataset-info", str(root)]) == 0
    out = capsys.readouterr().out
    assert "\x1b" not in out
    assert "  evil\\x1b[2J\\x1b[31m       0      0      1      1" in out.splitlines()


def test_verify_lists_a_splits_category_holding_a_list_and_an_image_linking_out(tmp_path):
    from lightning_vtr.data.verify import verify_dataset

    root = _one_object_dataset(tmp_path / "data")
    (root / "splits.json").write_text(json.dumps({"chair": ["c0"]}))
    secret = tmp_path / "secret.png"
    image = root / "objects" / "chair" / "c0" / "aligned" / "01.png"
    secret.write_bytes(image.read_bytes())
    image.unlink()
    image.symlink_to(secret)
    problems = [(p.path, p.kind, p.message) for p in verify_dataset(root, workers=1, progress=False).problems]
    assert problems == [
        (
            root / "splits.json",
            "unreadable",
            "splits.json must map categories to {split: [object ids]}; category 'chair' holds a list",
        ),
        (image, "outside", f"a symlink leading out of the dataset, to {secret}; not read"),
    ]


def test_dataset_info_verify_lists_a_bad_split_instead_of_stopping(tmp_path, capsys):
    root = _one_object_dataset(tmp_path / "data", split="evil")
    assert main(["dataset-info", str(root), "--verify", "--workers", "1", "--no-progress"]) == 1
    out = capsys.readouterr().out
    assert "  1 object entry(ies) not a JSON object or without a valid split (not counted)" in out
    assert "PROBLEM [metadata] " in out and "object 'chair/c0' has an unknown split" in out


def test_csv_cells_a_spreadsheet_would_run_are_written_as_text_and_read_back(tmp_path):
    import csv

    from lightning_vtr.evaluation.robustness import RobustnessMap, read_bins_csv
    from lightning_vtr.utils.io import csv_cell, uncsv_cell

    ids = ['=HYPERLINK("http://x","y")', "+1+cmd", "@SUM(A1)", "\tx", "'=already", "plain"]
    rmap = RobustnessMap.from_iou(np.full((6, 18), -0.5), k=60, object_ids=ids, categories=["=c"] * 6)
    rmap.to_csv(tmp_path, per_category=True)
    with open(tmp_path / "objects.csv", newline="") as f:
        rows = list(csv.reader(f))[1:]
    assert [row[1] for row in rows] == ["'" + i for i in ids[:5]] + ["plain"]
    assert {row[0] for row in rows} == {"'=c"} and rows[0][2] == "-0.5"  # a negative number stays a number
    again = RobustnessMap.from_csv(tmp_path)
    assert again.object_ids == ids and again.categories == ["=c"] * 6
    assert {row["category"] for row in read_bins_csv(tmp_path / "bins.csv")} == {"all", "=c"}
    assert [csv_cell(v) for v in ("-1e-3", "-inf", "-x", 3)] == ["-1e-3", "-inf", "'-x", 3]
    assert [uncsv_cell(csv_cell(v)) for v in ids] == ids
