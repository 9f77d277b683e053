"""examples/*.py run end to end on the tiny dataset.

The harness examples print the results their runs wrote; the quickstart trains with the callback and tests.
"""

from __future__ import annotations

import csv
import importlib.util
import json
from pathlib import Path

import pytest

from lightning_vtr.experiments.strategies import DEFAULT_STRATEGY

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def _assert_no_lightning_test_table(printed: str) -> None:
    """Lightning's ``trainer.test`` table (a row per category, view set and threshold) is not printed."""
    assert "Test metric" not in printed and "DataLoader 0" not in printed
    assert not [line for line in printed.splitlines() if "test/aligned" in line or "iou@0.3" in line]


def _load(name: str):
    spec = importlib.util.spec_from_file_location(name, EXAMPLES / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.slow
@pytest.mark.parametrize(("name", "title"), [("pix2vox_vtr", "Pix2Vox++"), ("lrgt_vtr", "LRGT")])
def test_example_prints_the_table_of_its_runs(tiny_dataset, tmp_path, capsys, name, title):
    out = tmp_path / name
    argv = [
        "--data",
        str(tiny_dataset),
        "--pretrain-epochs",
        "1",
        "--finetune-epochs",
        "2",
        "--batch-size",
        "8",
        "--fraction",
        "0.15",
        "--accelerator",
        "cpu",
        "--out",
        str(out),
    ]
    runs = _load(name).main(argv)
    printed = capsys.readouterr().out

    assert list(runs) == [f"{title} (no VTR)", f"Ours ({title})"]
    # "Ours" is the callback's default rule
    for run_dir, row in (("none", f"{title} (no VTR)"), (DEFAULT_STRATEGY, f"Ours ({title})")):
        saved = json.loads((out / run_dir / "results.json").read_text())
        assert saved["results"] == runs[row]["results"]
        assert saved["config"]["finetune_lr"] == "cosine"
        line = next(line for line in printed.splitlines() if line.startswith(f"| {row} |"))
        assert f"{100 * saved['results']['spherical']['iou@0.4']:.2f}" in line
    # Two selections (before epoch 0 and after it) of 15 % of the 21 training objects; the baseline generates nothing.
    assert runs[f"Ours ({title})"]["generated_samples"] == 2 * round(0.15 * 21)
    assert runs[f"{title} (no VTR)"]["generated_samples"] == 0
    _assert_no_lightning_test_table(printed)


@pytest.mark.slow
def test_quickstart_trains_with_the_callback_and_tests_every_view_set(tiny_dataset, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)  # the Trainer writes lightning_logs/ into the working directory
    outputs = _load("quickstart").main(str(tiny_dataset))
    printed = capsys.readouterr().out

    # Two selections (before epoch 0 and after it) of 5 % of the 21 training objects (at least one object each).
    assert "generated samples: 2" in printed.splitlines()
    metrics = {k: v for output in outputs for k, v in output.items()}
    for view_set in ("aligned", "hemispherical", "spherical"):
        for metric in ("iou@0.4", "fscore"):
            assert 0.0 <= metrics[f"test/{view_set}/{metric}"] <= 1.0

    # It ends with one compact table, a line per view set, then the line naming the per-category CSV.
    lines = printed.splitlines()
    header = lines.index(next(line for line in lines if line.startswith("test views")))
    assert lines[header].split() == ["test", "views", "mIoU@0.4", "%", "F-score", "%"]
    assert len(lines) == header + 5
    for line, view_set in zip(lines[header + 1 : header + 4], ("aligned", "hemispherical", "spherical")):
        iou, fscore = (100 * metrics[f"test/{view_set}/{m}"] for m in ("iou@0.4", "fscore"))
        assert line.split() == [view_set.capitalize(), f"{iou:.2f}", f"{fscore:.2f}"]
    _assert_no_lightning_test_table(printed)
    assert lines[-1].startswith("per-category figures, every threshold: ")
    csv_path = Path(lines[-1].split(": ", 1)[1].split(" (and the logger")[0])
    assert csv_path.name == "test_metrics.csv" and csv_path.is_file()
    rows = list(csv.DictReader(csv_path.open()))
    # every value trainer.test returned, per category too, once
    assert len(rows) == len([k for k in metrics if k.startswith("test/")])
    for row in rows:
        key = "/".join(part for part in ("test", row["view_set"], row["category"], row["metric"]) if part)
        assert float(row["value"]) == pytest.approx(metrics[key])
    assert any(row["category"] and row["metric"] == "iou@0.3" for row in rows)
