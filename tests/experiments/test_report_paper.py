"""The report's files for a paper: Table 1 in LaTeX and CSV equal to the runs' numbers, report.json round-trips
results.csv and records the command, version and settings, the per-category tables, the reference row's paired
differences and ``maps`` (one robustness map per strategy, pooled over seeds)."""

from __future__ import annotations

import csv
import json
import math
import shlex
import statistics
import sys
import textwrap

import pytest
from helpers import one_thread
from scipy import stats

import lightning_vtr
import lightning_vtr.experiments.training as experiment
from lightning_vtr.experiments.report import ReportConfig, default_experiment, run_report
from lightning_vtr.protocol import VIEW_SETS

_one_thread = pytest.fixture(autouse=True)(one_thread)

ROWS = ["none", "random", "error_guided"]
SEEDS = [0, 1, 2]
#: Per category, the per-object IoUs of a run's test (scaled per run, seed and view set below): two objects of
#: "chair", one of "lamp", so the view set's mean is the object-weighted mean of the categories' means.
OBJECTS = {"chair": [0.30, 0.50], "lamp": [0.70]}


def _scale(run: str, seed: int, view_set: str) -> float:
    return 1.0 - 0.1 * ROWS.index(run) - 0.03 * seed * seed - 0.05 * VIEW_SETS.index(view_set)


def _payload(run: str, seed: int) -> dict:
    results = {}
    for view_set in VIEW_SETS:
        scale = _scale(run, seed, view_set)
        every = [scale * v for values in OBJECTS.values() for v in values]
        results[view_set] = {"iou@0.4": sum(every) / len(every), "fscore": 0.5 * sum(every) / len(every)}
        for category, values in OBJECTS.items():
            mean = scale * sum(values) / len(values)
            results[f"{view_set}/{category}"] = {"iou@0.4": mean, "fscore": 0.5 * mean}
    return {"results": results, "train_seconds": 1.0 + seed, "eval_seconds": 0.5}


@pytest.fixture
def stubbed(tmp_path, monkeypatch):
    """A 3-seed report of none / random / error_guided with the error-guided row as reference, runs stubbed."""
    monkeypatch.setattr(experiment, "pretrain", lambda config: tmp_path / "pretrained.ckpt")
    monkeypatch.setattr(
        experiment, "run_strategy", lambda name, config, pretrained, run_name, **kw: _payload(run_name, config.seed)
    )
    config = ReportConfig(
        default_experiment(out=str(tmp_path / "r")), seeds=SEEDS, strategies=ROWS, reference="error_guided"
    )
    return config, run_report(config), tmp_path / "r"


def _estimate(values: list[float]) -> tuple[float, float]:
    mean = statistics.mean(values)
    return mean, stats.t.ppf(0.975, len(values) - 1) * statistics.stdev(values) / math.sqrt(len(values))


def _expected_cell(run: str, view_set: str, metric: str) -> tuple[float, float]:
    return _estimate([_payload(run, s)["results"][view_set][metric] for s in SEEDS])


def test_table1_latex_and_csv_hold_the_runs_means_and_intervals(stubbed):
    config, _, out = stubbed
    titles = config.titles()
    latex = (out / "table1.tex").read_text()
    assert r"\toprule" in latex and r"\midrule" in latex and r"\bottomrule" in latex
    assert r"\multicolumn{2}{c}{Aligned} & \multicolumn{2}{c}{Hemispherical} & \multicolumn{2}{c}{Spherical}" in latex
    body = latex.split("\\midrule\n")[1].split("\\bottomrule")[0].strip().splitlines()
    rows = {line.split(" & ")[0]: line.removesuffix(r" \\").split(" & ")[1:] for line in body}
    assert list(rows) == [titles[r] for r in ROWS]
    for run in ROWS:
        expected = []
        for view_set in VIEW_SETS:
            for metric in ("iou@0.4", "fscore"):
                mean, half = _expected_cell(run, view_set, metric)
                text = f"{100 * mean:.2f}"
                expected.append((rf"\textbf{{{text}}}" if run == "none" else text) + rf" $\pm$ {100 * half:.2f}")
        assert rows[titles[run]] == expected  # "none" scores highest here: its cells are the bold ones

    with (out / "table1.csv").open() as f:
        table = list(csv.DictReader(f))
    assert len(table) == len(ROWS) * 3 * 3  # rows x view sets x (mIoU, best mIoU, F-score)
    for row in table:
        metric = "iou@0.4" if row["metric"] == "iou_best" else row["metric"]  # only iou@0.4 logged: best = it
        mean, half = _expected_cell(row["run"], row["view_set"], metric)
        assert float(row["mean"]) == pytest.approx(mean) and float(row["half_width"]) == pytest.approx(half)
        assert float(row["ci_low"]) == pytest.approx(mean - half) and row["seeds"] == "3"
        assert row["method"] == titles[row["run"]]


def test_report_json_round_trips_results_csv_and_records_how_it_was_made(stubbed):
    config, result, out = stubbed
    record = json.loads((out / "report.json").read_text())
    with (out / "results.csv").open() as f:
        results = list(csv.DictReader(f))
    assert len(results) == len(ROWS) * len(SEEDS) * len(VIEW_SETS)
    for row in results:
        logged = record["runs"][row["run"]][row["seed"]]
        assert logged["results"][row["view_set"]]["iou@0.4"] == float(row["iou@0.4"])
        assert logged["results"][row["view_set"]]["fscore"] == float(row["fscore"])
        assert f"{logged['train_seconds']:.3f}" == row["train_seconds"]
    assert record["version"] == lightning_vtr.__version__
    assert record["argv"] == shlex.join(sys.argv)
    assert record["command"] == record["equivalent_command"]
    assert "--reference error_guided" in record["command"] and "--seeds 0 1 2" in record["command"]
    assert record["settings"]["seeds"] == SEEDS and record["settings"]["strategies"] == ROWS
    assert record["settings"]["experiment"]["finetune_epochs"] == config.experiment.finetune_epochs
    assert record["rows"] == {config.titles()[r]: r for r in ROWS}
    assert record["strategies"]["none"]["resolved"] is None and "selector" not in record["strategies"]["none"]
    callback = experiment.make_strategy("error_guided", config.seed_config(0), variants=config.variants)
    guided = record["strategies"]["error_guided"]
    assert guided["selector_settings"] == json.loads(json.dumps(callback.selector.settings()))
    assert guided["selector_repr"] == repr(callback.selector)
    assert guided["selector"] == f"{type(callback.selector).__module__}.{type(callback.selector).__qualname__}"
    # the JSON's Table 1 and differences are the CSVs'
    with (out / "table1.csv").open() as f:
        for row in csv.DictReader(f):
            cell = record["table1"][row["method"]][row["view_set"]][row["metric"]]
            assert cell["mean"] == float(row["mean"]) and cell["half_width"] == float(row["half_width"])
    with (out / "differences.csv").open() as f:
        differences = list(csv.DictReader(f))
    assert {row["baseline"] for row in differences} == {"none", "random", "error_guided"}
    titles = config.titles()
    for row in differences:
        cell = record["differences"][row["baseline"]][row["metric"]][titles[row["run"]]][row["view_set"]]
        assert cell["mean"] == float(row["mean"]) and cell["ci_low"] == float(row["ci_low"])
    assert set(record["files"]) >= {"markdown", "csv", "table1_latex", "categories_csv", "json"}
    assert result["paths"]["json"] == out / "report.json"


def test_the_reference_row_gets_its_own_paired_difference_table(stubbed):
    config, result, out = stubbed
    titles = config.titles()
    random_minus_guided = [
        _payload("random", s)["results"]["spherical"]["iou@0.4"]
        - _payload("error_guided", s)["results"]["spherical"]["iou@0.4"]
        for s in SEEDS
    ]
    mean, half = _estimate(random_minus_guided)
    estimate = result["differences"]["error_guided"][titles["random"]]["spherical"]
    assert estimate.mean == pytest.approx(mean) and estimate.half_width == pytest.approx(half)
    markdown = (out / "differences.md").read_text()
    assert f"## Paired difference to {titles['error_guided']}" in markdown
    assert f"## Paired difference to {titles['error_guided']} (mIoU points)" in result["markdown"]
    latex = (out / "differences.tex").read_text()
    assert latex.count(r"\begin{tabular}") == 3  # None-VTR, Random, the reference
    assert f"${100 * mean:+.2f}$ [${100 * (mean - half):+.2f}$, ${100 * (mean + half):+.2f}$]" in latex


def test_per_category_tables_agree_with_the_per_object_results(stubbed):
    config, _, out = stubbed
    titles = config.titles()
    with (out / "categories.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == len(OBJECTS) * len(ROWS) * len(SEEDS) * len(VIEW_SETS)
    by_key = {(r["run"], int(r["seed"]), r["view_set"], r["category"]): float(r["iou@0.4"]) for r in rows}
    with (out / "results.csv").open() as f:
        overall = {(r["run"], int(r["seed"]), r["view_set"]): float(r["iou@0.4"]) for r in csv.DictReader(f)}
    for (run, seed, view_set), value in overall.items():
        scale = _scale(run, seed, view_set)
        for category, objects in OBJECTS.items():  # each category's value is the mean of its objects' IoUs
            assert by_key[run, seed, view_set, category] == pytest.approx(scale * sum(objects) / len(objects))
        # weighted by its object count, the categories' values give the view set's mean over every object
        weighted = sum(len(o) * by_key[run, seed, view_set, c] for c, o in OBJECTS.items())
        assert weighted / sum(map(len, OBJECTS.values())) == pytest.approx(value)

    markdown = (out / "categories.md").read_text()
    section = markdown.split("## Hemispherical\n")[1].split("## ")[0]
    table = [line for line in section.splitlines() if line.startswith("| ") and "---" not in line]
    assert table[0] == "| " + " | ".join(["Category", *(titles[r] for r in ROWS)]) + " |"
    lamp = next(line for line in table if line.startswith("| lamp "))
    cells = [c.strip() for c in lamp.strip("|").split("|")][1:]
    for run, cell in zip(ROWS, cells):
        mean, half = _estimate([by_key[run, s, "hemispherical", "lamp"] for s in SEEDS])
        assert cell == f"{100 * mean:.2f} ± {100 * half:.2f}"


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"reference": "paper"}, "reference"),
        ({"map_k": 50}, "map_k"),
        ({"map_objects": 0}, "map_objects"),
    ],
)
def test_config_rejects_bad_reference_and_map_settings(kwargs, match):
    with pytest.raises(ValueError, match=match):
        ReportConfig(strategies=["none", "random"], **kwargs)


MODEL_SOURCE = textwrap.dedent(
    """
    import lightning as L
    import torch
    import torch.nn.functional as F
    from torch import nn


    class GridNet(L.LightningModule):
        def __init__(self, image_size: int = 64, num_views: int = 3, voxel_resolution: int = 32):
            super().__init__()
            self.image_size, self.num_views, self.voxel_resolution = image_size, num_views, voxel_resolution
            self.colour = nn.Linear(3, 4)
            self.grid = nn.Parameter(torch.zeros(4, voxel_resolution, voxel_resolution, voxel_resolution))

        def predict_voxels(self, images):
            weights = torch.softmax(self.colour(images.mean(dim=(1, 3, 4))), dim=-1)
            return torch.sigmoid(torch.einsum("bk,kxyz->bxyz", weights, self.grid))

        def training_step(self, batch, batch_idx):
            return F.binary_cross_entropy(self.predict_voxels(batch["images"]), batch["voxels"])

        def configure_optimizers(self):
            return torch.optim.Adam(self.parameters(), lr=0.05)
    """
)


@pytest.mark.slow
def test_maps_write_one_robustness_map_per_strategy_pooled_over_seeds(tiny_dataset, tmp_path, monkeypatch):
    from lightning_vtr.evaluation.robustness import RobustnessMap

    (tmp_path / "gridnet.py").write_text(MODEL_SOURCE)
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delitem(sys.modules, "gridnet", raising=False)
    exp = default_experiment(
        model="gridnet.GridNet",
        data=str(tiny_dataset),
        out=str(tmp_path / "r"),
        pretrain_epochs=1,
        finetune_epochs=1,
        batch_size=4,
        test_repeats=1,
        accelerator="cpu",
        trainer_kwargs={"limit_train_batches": 1, "limit_val_batches": 1, "enable_progress_bar": False},
    )
    config = ReportConfig(
        exp, seeds=[0, 1], strategies=["none", "random"], maps=True, map_k=90, map_objects=2,
        callback_kwargs={"progress_bar": False, "fraction": 0.2},
    )  # fmt: skip
    result = run_report(config)
    out, titles = tmp_path / "r", config.titles()
    record = json.loads((out / "report.json").read_text())
    for run in ("none", "random"):
        written = record["maps"][titles[run]]
        assert (out / written["picture"]).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        pooled = RobustnessMap.from_csv(out / written["folder"])
        seeds = [RobustnessMap.from_csv(out / f"seed_{s}" / run / "robustness_map") for s in (0, 1)]
        assert pooled.iou.shape == (4, 8)  # two objects per seed, K = 90: 8 bins
        assert pooled.iou.tolist() == seeds[0].iou.tolist() + seeds[1].iou.tolist()
        assert pooled.mean() == pytest.approx((seeds[0].mean() + seeds[1].mean()) / 2)
        assert record["maps"][titles[run]]["overall"] == pytest.approx(pooled.overall())
        assert result["maps"][titles[run]]["objects"] == 4
    assert (out / "maps" / "index.html").is_file()
    # one map per strategy, and the difference of Random's to None-VTR's
    assert len(list((out / "maps").glob("*.png"))) == 3
    # a real test's per-category values average to the view set's (the tiny dataset: 2 test objects per category)
    payload = result["runs"]["random"][0]["results"]
    for view_set in VIEW_SETS:
        categories = [v["iou@0.4"] for k, v in payload.items() if k.startswith(f"{view_set}/")]
        assert len(categories) == 3 and sum(categories) / 3 == pytest.approx(payload[view_set]["iou@0.4"])
