"""``lightning-vtr dataset-info``: the summary of a dataset directory."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import numpy as np
from PIL import Image

from lightning_vtr.cli import main
from lightning_vtr.cli.dataset_info import EXIT_PROBLEMS
from lightning_vtr.data.binvox import write_binvox
from lightning_vtr.data.format import dataset_summary


def test_prints_the_summary_of_the_directory(tiny_dataset, capsys):
    assert main(["dataset-info", str(tiny_dataset)]) == 0
    printed = capsys.readouterr().out
    assert printed == dataset_summary(tiny_dataset) + "\n"
    for category in ("chair", "table", "airplane"):
        row = next(line for line in printed.splitlines() if line.split()[:1] == [category])
        assert row.split()[1:] == ["7", "1", "2", "10"]  # train, val, test, total


def test_a_missing_dataset_is_one_line_and_status_2(tmp_path, capsys):
    assert main(["dataset-info", str(tmp_path / "none")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("lightning-vtr dataset-info: error: ") and err.count("\n") == 1


def test_verify_a_clean_dataset_prints_the_summary_and_exits_0(tiny_dataset, capsys):
    assert main(["dataset-info", str(tiny_dataset), "--verify", "--no-progress", "--workers", "2"]) == 0
    out = capsys.readouterr().out
    lines = out.splitlines()
    assert out.startswith(dataset_summary(tiny_dataset) + "\n")
    assert "PROBLEM" not in out
    # 30 objects, each with one voxel file and 3 view sets of 8 images
    assert re.fullmatch(
        r"verified 30 objects \(750 files\) in [\d.]+ s \([\d.]+ objects/s\): 0 problem\(s\)", lines[-1]
    )


def test_verify_lists_every_problem_and_exits_1(tiny_dataset, tmp_path, capsys):
    root = Path(shutil.copytree(tiny_dataset, tmp_path / "vtr"))
    truncated = root / "objects" / "chair" / "chair_0003" / "aligned" / "04.png"
    truncated.write_bytes(truncated.read_bytes()[:100])
    resized = root / "objects" / "table" / "table_0005" / "spherical" / "00.png"
    Image.new("RGBA", (48, 48)).save(resized)
    deleted = root / "objects" / "airplane" / "airplane_0001" / "hemispherical" / "07.png"
    deleted.unlink()
    voxels = root / "objects" / "chair" / "chair_0000" / "model.binvox"
    write_binvox(voxels, np.ones((24, 24, 24), bool))

    assert main(["dataset-info", str(root), "--verify", "--no-progress"]) == EXIT_PROBLEMS == 1
    out = capsys.readouterr().out
    problems = sorted(line for line in out.splitlines() if line.startswith("  PROBLEM "))
    assert problems == sorted(
        [
            f"  PROBLEM [unreadable] {truncated}: cannot read the image: image file is truncated",
            f"  PROBLEM [image_size] {resized}: image of the wrong size (W x H) (expected 64x64, got 48x48)",
            f"  PROBLEM [view_count] {deleted}: view 07 of 8 listed in metadata.json is missing; the view set has "
            "7 images (expected 8, got 7)",
            f"  PROBLEM [voxel_resolution] {voxels}: voxel grid of the wrong resolution (expected 32x32x32, got 24x24x24)",
        ]
    )
    assert re.fullmatch(r"verified 30 objects \(749 files\) in .*: 4 problem\(s\)", out.splitlines()[-1])


def test_verify_of_a_missing_dataset_is_one_line_and_status_2(tmp_path, capsys):
    assert main(["dataset-info", str(tmp_path / "none"), "--verify"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("lightning-vtr dataset-info: error: ") and err.count("\n") == 1
