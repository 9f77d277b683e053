"""A dataset (untrusted data: a tar archive from someone else) is read only through regular files inside it: an
image or voxel file that is a symlink leading out of the dataset is refused, and so is a FIFO (a tar archive keeps
them), which would otherwise block ``predict --data`` and ``dataset-info --verify`` forever. Each refusal is one
line naming the file (:func:`lightning_vtr.utils.limits.check_regular_file`); ``verify_dataset`` lists them.
"""

from __future__ import annotations

import json
import os
import re
import time
from pathlib import Path

import numpy as np
import pytest
from helpers import one_thread, save_tiny_checkpoint
from PIL import Image

from lightning_vtr.cli import main
from lightning_vtr.data.binvox import read_binvox, write_binvox
from lightning_vtr.data.dataset import VTRDataset, load_rgba, load_voxels
from lightning_vtr.data.format import scan_dataset
from lightning_vtr.data.verify import verify_dataset
from lightning_vtr.errors import DataError
from lightning_vtr.utils.limits import check_regular_file, open_image, read_json

pytestmark = pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="FIFOs and symlinks of a POSIX system")
_one_thread = pytest.fixture(autouse=True)(one_thread)

_FIFO = "a regular file was expected, found a FIFO (named pipe)"
_SIZE = 64


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    """A tiny Pix2Vox++ checkpoint (64 px inputs)."""
    return save_tiny_checkpoint(tmp_path_factory.mktemp("ckpt") / "tiny.ckpt", image_size=_SIZE)


@pytest.fixture(scope="module")
def pristine(tmp_path_factory):
    """A dataset of one test object ``airplane/airplane_0000``: 3 aligned 64 px views and a 32^3 grid."""
    root = tmp_path_factory.mktemp("pristine") / "data"
    views = [[0.0, 30.0], [120.0, 30.0], [-120.0, 30.0]]
    directory = root / "objects" / "airplane" / "airplane_0000"
    (directory / "aligned").mkdir(parents=True)
    for i in range(3):
        Image.new("RGBA", (_SIZE, _SIZE), (200, 20 * i, 0, 255)).save(directory / "aligned" / f"{i:02d}.png")
    write_binvox(directory / "model.binvox", np.zeros((32, 32, 32), bool))
    obj = {"category": "airplane", "object_id": "airplane_0000", "views": {"aligned": views}}
    (directory / "object.json").write_text(json.dumps(obj))
    meta = {"format": "lightning_vtr.shapenet_vtr", "version": 1, "resolution": 32, "image_size": _SIZE,
            "views_per_set": 3, "view_sets": ["aligned"],
            "objects": {"airplane/airplane_0000": {"split": "test", "views": {"aligned": views}}}}  # fmt: skip
    (root / "metadata.json").write_text(json.dumps(meta))
    (root / "splits.json").write_text(json.dumps({"airplane": {"train": [], "val": [], "test": ["airplane_0000"]}}))
    return root


@pytest.fixture
def data(pristine, tmp_path):
    """A fresh copy of :func:`pristine` to plant files in (links copied as links)."""
    import shutil

    return Path(shutil.copytree(pristine, tmp_path / "data", symlinks=True))


def _object(root: Path) -> Path:
    return root / "objects" / "airplane" / "airplane_0000"


def _predict(checkpoint: Path, root: Path, out: Path) -> list[str]:
    return ["predict", "--ckpt", str(checkpoint), "--data", str(root), "--view-sets", "aligned", "--limit", "1",
            "--out", str(out), "--no-progress"]  # fmt: skip


def _one_line(capsys) -> str:
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err, err
    return err


# ------------------------------------------------------------------------------------------ symlinks leading out
def test_predict_refuses_images_linked_out_of_the_dataset_and_reads_links_inside_it(checkpoint, data, tmp_path, capsys):
    aligned = _object(data) / "aligned"
    # a link that stays inside the dataset keeps working
    (aligned / "02.png").unlink()
    (aligned / "02.png").symlink_to("00.png")
    assert main(_predict(checkpoint, data, tmp_path / "inside")) == 0, capsys.readouterr().err
    assert (tmp_path / "inside" / "index.html").is_file()
    capsys.readouterr()

    outside = tmp_path / "outside.png"
    Image.new("RGBA", (_SIZE, _SIZE), (0, 0, 255, 255)).save(outside)
    for i in range(3):
        (aligned / f"{i:02d}.png").unlink()
        (aligned / f"{i:02d}.png").symlink_to(outside)
    out = tmp_path / "out"
    start = time.perf_counter()
    assert main(_predict(checkpoint, data, out)) == 1
    assert time.perf_counter() - start < 30
    err = _one_line(capsys)
    pattern = (
        f"lightning-vtr predict: error: {re.escape(str(aligned))}/0[0-2]\\.png is a symbolic link leading out of "
        f"the dataset \\(to {re.escape(str(outside))}\\); not read\n"
    )
    assert re.fullmatch(pattern, err), err
    assert not (out / "index.html").exists()


def test_the_loaders_refuse_a_voxel_file_and_an_image_leading_out_of_the_dataset(data, tmp_path):
    outside = tmp_path / "elsewhere"
    outside.mkdir()
    voxel = _object(data) / "model.binvox"
    write_binvox(outside / "model.binvox", np.ones((32, 32, 32), bool))
    voxel.unlink()
    voxel.symlink_to(outside / "model.binvox")
    (record,) = scan_dataset(data)
    assert record.root == data.resolve()
    message = f"{voxel} is a symbolic link leading out of the dataset (to {outside / 'model.binvox'}); not read"
    with pytest.raises(DataError, match=f"^{re.escape(message)}$"):
        load_voxels(record)
    assert read_binvox(voxel).all()  # without a dataset folder the file is read as before

    # an image linked out, through a relative link with '..', read by the dataset
    image = _object(data) / "aligned" / "01.png"
    Image.new("RGBA", (_SIZE, _SIZE)).save(outside / "01.png")
    image.unlink()
    image.symlink_to(os.path.relpath(outside / "01.png", image.parent))
    message = f"{image} is a symbolic link leading out of the dataset (to {outside / '01.png'}); not read"
    with pytest.raises(DataError, match=f"^{re.escape(message)}$"):
        VTRDataset([record], "aligned", num_views=3)[0]
    with pytest.raises(DataError, match=f"^{re.escape(message)}$"):
        load_rgba(image, root=data)  # a root given unresolved is resolved once
    assert load_rgba(_object(data) / "aligned" / "00.png", root=data).shape == (_SIZE, _SIZE, 4)


# ------------------------------------------------------------------------------------------ FIFOs
@pytest.mark.timeout(60)
def test_predict_refuses_a_fifo_voxel_file_without_hanging(checkpoint, data, tmp_path, capsys):
    voxel = _object(data) / "model.binvox"
    voxel.unlink()
    os.mkfifo(voxel)
    start = time.perf_counter()
    assert main(_predict(checkpoint, data, tmp_path / "out")) == 1
    assert time.perf_counter() - start < 30
    assert _one_line(capsys) == f"lightning-vtr predict: error: {voxel}: {_FIFO}\n"


@pytest.mark.timeout(60)
def test_predict_refuses_a_fifo_image_without_hanging(checkpoint, data, tmp_path, capsys):
    image = _object(data) / "aligned" / "01.png"
    image.unlink()
    os.mkfifo(image)
    assert main(_predict(checkpoint, data, tmp_path / "out")) == 1
    assert _one_line(capsys) == f"lightning-vtr predict: error: {image}: {_FIFO}\n"


@pytest.mark.timeout(60)
def test_verify_lists_a_link_leading_out_and_fifos_as_problems_without_hanging(data, tmp_path, capsys):
    obj = _object(data)
    outside = tmp_path / "outside.png"
    Image.new("RGBA", (_SIZE, _SIZE)).save(outside)
    for path in (obj / "aligned" / "00.png", obj / "aligned" / "02.png", obj / "model.binvox", obj / "object.json"):
        path.unlink()
    (obj / "aligned" / "00.png").symlink_to(outside)
    for path in (obj / "aligned" / "02.png", obj / "model.binvox", obj / "object.json"):
        os.mkfifo(path)
    report = verify_dataset(data, workers=1, progress=False)
    assert [(p.path, p.kind, p.message) for p in report.problems] == [
        (obj / "object.json", "unreadable", f"{_FIFO}; not read"),
        (obj / "model.binvox", "unreadable", f"{_FIFO}; not read"),  # not "does not exist"
        (obj / "aligned" / "00.png", "outside", f"a symlink leading out of the dataset, to {outside}; not read"),
        (obj / "aligned" / "02.png", "unreadable", f"{_FIFO}; not read"),
    ]
    assert main(["dataset-info", str(data), "--verify", "--no-progress", "--workers", "1"]) == 1
    listed = [line for line in capsys.readouterr().out.splitlines() if "PROBLEM" in line]
    assert listed[1] == f"  PROBLEM [unreadable] {obj / 'model.binvox'}: {_FIFO}; not read"
    assert len(listed) == 4


@pytest.mark.timeout(60)
def test_check_regular_file_names_the_kind_and_every_reader_calls_it(tmp_path):
    fifo = tmp_path / "pipe.json"
    os.mkfifo(fifo)
    for read in (read_json, open_image, read_binvox, load_rgba):
        with pytest.raises(DataError, match=f"^{re.escape(f'{fifo}: {_FIFO}')}$"):
            read(fifo)
    with pytest.raises(DataError, match=f"^{re.escape(f'{tmp_path}: a regular file was expected, found a folder')}$"):
        check_regular_file(tmp_path)
    if os.path.exists("/dev/null"):
        with pytest.raises(DataError, match="^/dev/null: a regular file was expected, found a character device$"):
            check_regular_file("/dev/null")
    with pytest.raises(FileNotFoundError):
        check_regular_file(tmp_path / "absent.json")
    (tmp_path / "ok.json").write_text("[1]")
    (tmp_path / "link.json").symlink_to("ok.json")
    assert read_json(tmp_path / "link.json", root=tmp_path) == [1]
