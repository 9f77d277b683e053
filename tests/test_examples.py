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

    assert list(runs) == [f"{title} (no VTR)", f"{title} + VTR (default rule)"]
    # the second row is the callback's default rule
    for run_dir, row in (("none", f"{title} (no VTR)"), (DEFAULT_STRATEGY, f"{title} + VTR (default rule)")):
        saved = json.loads((out / run_dir / "results.json").read_text())
        assert saved["results"] == runs[row]["results"]
        assert saved["config"]["finetune_lr"] == "cosine"
        line = next(line for line in printed.splitlines() if line.startswith(f"| {row} |"))
        assert f"{100 * saved['results']['spherical']['iou@0.4']:.2f}" in line
    # Two selections (before epoch 0 and after it) of 15 % of the 21 training objects; the baseline generates nothing.
    assert runs[f"{title} + VTR (default rule)"]["generated_samples"] == 2 * round(0.15 * 21)
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


@pytest.mark.slow
def test_benchmark_your_method_prints_the_paired_differences_of_report_json(
    tiny_dataset, tmp_path, monkeypatch, capsys
):
    import sys

    from lightning_vtr.experiments.report_tables import paired_differences

    spec = importlib.util.spec_from_file_location("benchmark_your_method", EXAMPLES / "benchmark_your_method.py")
    module = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, "benchmark_your_method", module)  # its classes are named by import path
    spec.loader.exec_module(module)
    out = tmp_path / "bench"
    argv = ["--data", str(tiny_dataset), "--out", str(out), "--seeds", "0", "1", "--pretrain-epochs", "1"]
    argv += ["--finetune-epochs", "1", "--train-batches", "1", "--batch-size", "4", "--map-objects", "1"]
    argv += ["--fraction", "0.2"]
    result = module.main(argv)
    printed = capsys.readouterr().out
    record = json.loads((out / "report.json").read_text())
    titles = {name: title for title, name in record["rows"].items()}
    assert list(record["rows"].values()) == ["none", "random_area", "error_guided", "mine"]
    assert record["strategies"]["mine"]["selector"] == "benchmark_your_method.ViewsFromBelow"
    assert record["settings"]["experiment"]["model"] == "benchmark_your_method.TinyVoxelNet"
    assert record["command"] == "python examples/benchmark_your_method.py " + " ".join(argv)

    # Table 1's rows are the four strategies, with results.csv's spherical mIoU
    table = [line for line in printed.splitlines() if line.startswith("| ") and "---" not in line]
    with (out / "results.csv").open() as f:
        results = list(csv.DictReader(f))
    for name in ("none", "random_area", "error_guided", "mine"):
        row = next(line for line in table if line.startswith(f"| {titles[name]} |"))
        values = [float(r["iou@0.4"]) for r in results if r["run"] == name and r["view_set"] == "spherical"]
        assert f"{100 * sum(values) / 2:.2f} ±" in row
    # the differences printed are report.json's (to None-VTR and the reference) and results.csv's (to Random)
    mine = titles["mine"]
    payloads = {run: {int(s): v for s, v in seeds.items()} for run, seeds in record["runs"].items()}
    for other in ("none", "random_area", "error_guided"):
        line = next(line for line in table if line.startswith(f"| {titles[other]} | ") and "[" in line)
        cells = [c.strip() for c in line.strip("|").split("|")][1:]
        for view_set, cell in zip(("aligned", "hemispherical", "spherical"), cells):
            if other == "random_area":
                estimate = paired_differences(record["rows"], other, payloads, "iou@0.4", [0, 1])[mine][view_set]
                mean, low, high = estimate.mean, estimate.low, estimate.high
            else:
                stored = record["differences"][other]["iou@0.4"][mine][view_set]
                mean, low, high = stored["mean"], stored["ci_low"], stored["ci_high"]
            assert cell.startswith(f"{100 * mean:+.2f} [{100 * low:+.2f}, {100 * high:+.2f}] ")
            assert result["mine"][titles[other]][view_set].mean == pytest.approx(mean)
    # one robustness map per strategy
    assert sorted(record["maps"]) == sorted(titles.values())
    for summary in record["maps"].values():
        assert (out / summary["picture"]).is_file() and summary["objects"] == 2  # one object per seed
