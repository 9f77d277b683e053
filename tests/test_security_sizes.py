"""Sizes are checked before decoding: a small file whose header claims a huge picture, a huge voxel grid or a huge
JSON file is refused with one line naming the file, the size and the limit, before any memory is spent on it
(:mod:`lightning_vtr.utils.limits`)."""

from __future__ import annotations

import json
import struct
import zlib
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from lightning_vtr.cli import main
from lightning_vtr.data.binvox import read_binvox, write_binvox
from lightning_vtr.data.dataset import VTRDataset, load_voxels
from lightning_vtr.data.format import scan_dataset
from lightning_vtr.data.verify import verify_dataset
from lightning_vtr.errors import DataError, UsageError
from lightning_vtr.utils.limits import MAX_JSON_BYTES_VARIABLE, MAX_VOXEL_SIDE, max_json_bytes, open_image


def png_claiming(path: Path, width: int, height: int) -> None:
    """A tiny PNG (a few hundred bytes) whose header (IHDR) states ``width x height`` pixels."""
    Image.new("L", (4, 4)).save(path)
    data = bytearray(path.read_bytes())
    start = data.index(b"IHDR")
    data[start + 4 : start + 12] = struct.pack(">II", width, height)
    data[start + 17 : start + 21] = struct.pack(">I", zlib.crc32(bytes(data[start : start + 17])))
    path.write_bytes(bytes(data))


def make_dataset(root: Path, image_size: int = 96) -> Path:
    """A dataset of one test object ``chair/c0``: 3 aligned views of ``image_size`` px and a 32^3 grid."""
    views = [[0.0, 30.0], [120.0, 30.0], [-120.0, 30.0]]
    directory = root / "objects" / "chair" / "c0"
    (directory / "aligned").mkdir(parents=True)
    for i in range(3):
        Image.new("RGBA", (image_size, image_size)).save(directory / "aligned" / f"{i:02d}.png")
    write_binvox(directory / "model.binvox", np.zeros((32, 32, 32), bool))
    obj = {"category": "chair", "object_id": "c0", "views": {"aligned": views}}
    (directory / "object.json").write_text(json.dumps(obj))
    meta = {"format": "lightning_vtr.shapenet_vtr", "version": 1, "resolution": 32, "image_size": image_size,
            "views_per_set": 3, "view_sets": ["aligned"], "objects": {"chair/c0": {"split": "test", "views": {"aligned": views}}}}  # fmt: skip
    (root / "metadata.json").write_text(json.dumps(meta))
    (root / "splits.json").write_text(json.dumps({"chair": {"train": [], "val": [], "test": ["c0"]}}))
    return root


def tiny_checkpoint(folder: Path) -> Path:
    """A tiny Pix2Vox++ checkpoint as ``Trainer.fit`` saves one."""
    import lightning as L
    import torch

    from lightning_vtr.models.pix2vox import Pix2VoxPlusPlus

    model = Pix2VoxPlusPlus(preset="tiny")
    ckpt = {
        "state_dict": model.state_dict(),
        "hyper_parameters": dict(model.hparams),
        "pytorch-lightning_version": L.__version__,
    }
    model.on_save_checkpoint(ckpt)
    torch.save(ckpt, folder / "tiny.ckpt")
    return folder / "tiny.ckpt"


# ------------------------------------------------------------------------------------------------ pictures
def test_a_dataset_picture_far_larger_than_the_dataset_is_refused_before_decoding(tmp_path):
    root = make_dataset(tmp_path / "data")
    bomb = root / "objects" / "chair" / "c0" / "aligned" / "01.png"
    png_claiming(bomb, 12000, 12000)
    assert bomb.stat().st_size < 1000
    dataset = VTRDataset(scan_dataset(root), "aligned", num_views=3)
    message = f"{bomb}: a picture of at most 768x768 pixels was expected, found 12000x12000; not decoded"
    with pytest.raises(DataError, match=f"^{_escape(message)}$"):
        dataset[0]
    report = verify_dataset(root, workers=1, progress=False)  # listed as a wrong size, not decoded either
    assert [(p.path, p.kind, p.actual) for p in report.problems] == [(bomb, "image_size", "12000x12000")]


def test_a_decompression_bomb_is_one_line_from_predict_images(tmp_path, capsys):
    views = tmp_path / "views"
    views.mkdir()
    png_claiming(views / "a.png", 30000, 30000)
    out = tmp_path / "out"
    argv = ["predict", "--ckpt", str(tiny_checkpoint(tmp_path)), "--images", str(views), "--out", str(out)]
    assert main(argv) == 1
    err = capsys.readouterr().err
    limit = 2 * Image.MAX_IMAGE_PIXELS
    assert err == (
        f"lightning-vtr predict: error: `--images`: {views / 'a.png'}: a picture of at most 8192x8192 pixels was "
        f"expected, found 900000000 pixels (more than PIL's decompression-bomb limit of {limit} pixels); not decoded\n"
    )
    assert not out.exists()


def test_open_image_refuses_a_side_over_the_limit_and_opens_one_within(tmp_path):
    png_claiming(tmp_path / "wide.png", 5000, 10)
    with pytest.raises(DataError, match="at most 4096x4096 pixels was expected, found 5000x10; not decoded$"):
        open_image(tmp_path / "wide.png", 4096)
    Image.new("RGB", (40, 30)).save(tmp_path / "ok.png")
    with open_image(tmp_path / "ok.png", 40) as image:
        assert image.size == (40, 30)


# ------------------------------------------------------------------------------------------------ binvox
def _binvox_header(path: Path, side: int) -> None:
    """A binvox file whose header asks for ``side``^3 voxels, followed by a few run-length bytes."""
    path.write_bytes(
        f"#binvox 1\ndim {side} {side} {side}\ntranslate 0 0 0\nscale 1\ndata\n".encode() + b"\x00\xff" * 8
    )


def test_a_binvox_header_asking_for_gigabytes_is_refused_before_allocating(tmp_path, monkeypatch):
    path = tmp_path / "model.binvox"
    _binvox_header(path, 2048)

    def no_allocation(*args, **kwargs):
        raise AssertionError("the grid was allocated")

    monkeypatch.setattr(np, "repeat", no_allocation)
    limit = MAX_VOXEL_SIDE
    with pytest.raises(
        DataError,
        match=f"^{_escape(f'{path}: a voxel grid of at most {limit}x{limit}x{limit} was expected, found 2048x2048x2048')}$",
    ):
        read_binvox(path)
    with pytest.raises(
        DataError, match=f"^{_escape(f'{path}: a 32x32x32 voxel grid was expected, found 2048x2048x2048')}$"
    ):
        read_binvox(path, resolution=32)


def test_a_dataset_voxel_file_of_another_resolution_is_refused(tmp_path):
    root = make_dataset(tmp_path / "data")
    voxel = root / "objects" / "chair" / "c0" / "model.binvox"
    write_binvox(voxel, np.zeros((64, 64, 64), bool))
    (record,) = scan_dataset(root)
    assert record.resolution == 32 and record.image_size == 96
    with pytest.raises(DataError, match=f"^{_escape(f'{voxel}: a 32x32x32 voxel grid was expected, found 64x64x64')}$"):
        load_voxels(record)


# ------------------------------------------------------------------------------------------------ JSON
def test_a_json_file_over_the_limit_is_one_line_and_the_limit_is_configurable(tmp_path, monkeypatch, capsys):
    root = make_dataset(tmp_path / "data")
    size = (root / "metadata.json").stat().st_size
    monkeypatch.setenv(MAX_JSON_BYTES_VARIABLE, str(size - 1))
    assert main(["dataset-info", str(root)]) == 1
    assert capsys.readouterr().err == (
        f"lightning-vtr dataset-info: error: {root / 'metadata.json'}: a JSON file of at most {size - 1} bytes was "
        f"expected, found {size} bytes (set ${MAX_JSON_BYTES_VARIABLE} to read larger files)\n"
    )
    monkeypatch.setenv(MAX_JSON_BYTES_VARIABLE, str(size))
    assert main(["dataset-info", str(root)]) == 0
    monkeypatch.setenv(MAX_JSON_BYTES_VARIABLE, "lots")
    with pytest.raises(
        UsageError, match=f"^\\${MAX_JSON_BYTES_VARIABLE} must be a positive number of bytes, got 'lots'$"
    ):
        max_json_bytes()
    monkeypatch.delenv(MAX_JSON_BYTES_VARIABLE)
    assert max_json_bytes() == 64 * 2**20


def _escape(text: str) -> str:
    import re

    return re.escape(text)
