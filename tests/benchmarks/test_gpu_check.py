"""benchmarks/gpu_check.py in its CPU smoke mode (``--tiny``): every row runs and gives sensible numbers."""

from __future__ import annotations

import importlib.util
import math
import sys
from pathlib import Path

import pytest
import torch
from helpers import one_thread

_one_thread = pytest.fixture(autouse=True)(one_thread)

SCRIPT = Path(__file__).resolve().parents[2] / "benchmarks" / "gpu_check.py"
CHECKS = [
    "fit: Pix2Vox++ tiny + callback",
    "selection: paper",
    "selection: released",
    "selection: visible",
    "zero123",
    "train: Pix2Vox++",
    "train: LRGT",
]


@pytest.fixture(scope="module")
def gpu_check():
    """The script as a module (benchmarks/ is no package); the modules and path entries it adds are removed after."""
    path = list(sys.path)
    spec = importlib.util.spec_from_file_location("gpu_check", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    sys.modules["gpu_check"] = module
    spec.loader.exec_module(module)
    yield module
    sys.path[:] = path
    for name in [n for n in sys.modules if n == "gpu_check" or n.startswith("_gpu_check_")]:
        del sys.modules[name]


def test_tiny_cpu_run_fills_every_row(gpu_check, tmp_path, capsys):
    out = tmp_path / "table.md"
    table = gpu_check.main(["--tiny", "--device", "cpu", "--out", str(out)])
    printed = capsys.readouterr().out

    assert [row.check for row in table] == CHECKS
    assert [row.error for row in table] == [None] * len(CHECKS)
    for row in table:
        assert row.results, row.check
        for name, value in row.results.items():
            assert math.isfinite(value) and value > 0, (row.check, name, value)
    rows = {row.check: row.results for row in table}

    fit = rows["fit: Pix2Vox++ tiny + callback"]
    # 2 categories x 5 objects split 3/1/1; two selections (before epoch 0, after epoch 0) of round(0.34 * 6) = 2
    assert fit["train objects"] == 6
    assert fit["generated samples"] == 2 * round(gpu_check.FIT_FRACTION * 6) == 4
    assert 0 < fit["final loss"] < 5
    assert "loss dtype float32" in table[0].setup
    for score in gpu_check.SCORES:
        selection = rows[f"selection: {score}"]
        assert selection["best objects/s"] >= selection["objects/s"]
    assert set(rows["zero123"]) == {"s/image batch 1", "s/image batch 8", "peak RSS GiB"}
    for check in ("train: Pix2Vox++", "train: LRGT"):
        assert 0 < rows[check]["loss"] < 5
        assert "bf16-mixed, batch 1" in next(row.setup for row in table if row.check == check)

    # one Markdown table, one line per row, no error; --out holds the same text
    lines = printed.strip().splitlines()
    assert lines[0].startswith("gpu_check --tiny on CPU")
    assert lines[2:4] == ["| check | setup | results |", "| --- | --- | --- |"]
    assert [line.split(" | ")[0].removeprefix("| ") for line in lines[4:]] == CHECKS
    assert "ERROR" not in printed
    assert out.read_text() == printed


def test_a_failing_row_shows_its_error_and_the_others_run(gpu_check, capsys):
    def boom():
        raise RuntimeError("CUDA out of memory\nmore detail")

    device = torch.device("cpu")
    failed = gpu_check.run_row("selection: paper", boom, device)
    ok = gpu_check.run_row("x", lambda: gpu_check.Row("x", "setup", {"n": 3, "rate": 12.3456}), device)
    assert "RuntimeError: CUDA out of memory" in capsys.readouterr().err  # the traceback, on stderr
    assert failed.error == "RuntimeError: CUDA out of memory" and not failed.results
    text = gpu_check.markdown([failed, ok], "caption")
    assert text.splitlines()[4:] == [
        "| selection: paper |  | ERROR: RuntimeError: CUDA out of memory |",
        "| x | setup | n 3; rate 12.35 |",
    ]
