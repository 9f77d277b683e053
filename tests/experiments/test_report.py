"""run_report: tables equal the runs' results, files, resume, multi-seed spread; ReportConfig and its runs."""

from __future__ import annotations

import csv
import json

import lightning as L
import pytest

import lightning_vtr.experiments.training as experiment
from lightning_vtr.experiments.report import (
    STRATEGIES,
    STRATEGY_TITLES,
    ReportConfig,
    _plan,
    _table,
    default_experiment,
    run_report,
)
from lightning_vtr.experiments.training import ExperimentConfig
from lightning_vtr.protocol import VIEW_SETS
from lightning_vtr.selection import SELECTORS


def _parse_tables(markdown: str) -> dict[str, tuple[list[str], dict[str, list[str]]]]:
    """``{section title: (header cells, {row title: cells})}`` of every pipe table under a ``##`` title."""
    tables, title = {}, None
    for line in markdown.splitlines():
        if line.startswith("## "):
            title = line[3:]
        elif line.startswith("|") and not line.startswith("|---"):
            cells = [c.strip() for c in line.strip("|").split("|")]
            if title not in tables:
                tables[title] = (cells, {})
            else:
                tables[title][1][cells[0]] = cells[1:]
    return tables


def _pct(value: float) -> str:
    return f"{100 * value:.2f}"


@pytest.fixture
def counters(monkeypatch):
    """Counts Trainer.fit / Trainer.test calls and records run_strategy's arguments and configurations."""
    counts = {"fit": 0, "test": 0, "runs": [], "configs": []}
    fit, test, run_strategy = L.Trainer.fit, L.Trainer.test, experiment.run_strategy

    def counting_fit(self, *args, **kwargs):
        counts["fit"] += 1
        return fit(self, *args, **kwargs)

    def counting_test(self, *args, **kwargs):
        counts["test"] += 1
        return test(self, *args, **kwargs)

    def recording_run_strategy(name, config, pretrained, **kwargs):
        counts["runs"].append((name, kwargs["run_name"], kwargs["selector_kwargs"], kwargs["callback_kwargs"]))
        counts["configs"].append(config)
        return run_strategy(name, config, pretrained, **kwargs)

    monkeypatch.setattr(L.Trainer, "fit", counting_fit)
    monkeypatch.setattr(L.Trainer, "test", counting_test)
    monkeypatch.setattr(experiment, "run_strategy", recording_run_strategy)
    return counts


def test_report_tables_equal_the_runs_results_and_a_rerun_skips_every_run(tiny_dataset, tmp_path, counters):
    experiment_config = default_experiment(
        data=str(tiny_dataset),
        out=str(tmp_path / "report"),
        pretrain_epochs=1,
        finetune_epochs=2,  # epoch 0 ends with one search, so the callback really runs
        fraction=0.15,
        batch_size=4,
        accelerator="cpu",
        trainer_kwargs={
            "limit_train_batches": 1,
            "limit_val_batches": 1,
            "limit_test_batches": 1,
            "enable_progress_bar": False,
        },
    )
    config = ReportConfig(
        experiment_config,
        seeds=[0],
        strategies=["none", "error_guided"],
        ablations=["k", "single_view"],
        k_values=[15, 30],
        callback_kwargs={"progress_bar": False},
    )
    result = run_report(config)
    out = tmp_path / "report"
    seed_dir = out / "seed_0"

    # 1 pretraining + none + error_guided (K = 30) + K = 15: four fits; three fine-tunes, two single-view tests.
    assert counters["fit"] == 4
    assert counters["test"] == 3 + 2
    assert [r[:3] for r in counters["runs"]] == [
        ("none", "none", {}),
        ("error_guided", "error_guided", {}),
        ("error_guided", "error_guided_k15", {"k": 15}),
    ]
    assert all(r[3] == {"progress_bar": False} for r in counters["runs"])
    # Every run gets the report's experiment, with the seed's own `out`.
    expected = ExperimentConfig(**{**vars(experiment_config), "seed": 0, "out": str(tmp_path / "report" / "seed_0")})
    assert all(c == expected for c in counters["configs"])
    searched = json.loads((seed_dir / "error_guided_k15" / "results.json").read_text())
    assert searched["generated_samples"] == round(0.15 * 21)

    # One checkpoint callback per run: no duplicate "-v1" files beside each epoch's checkpoint.
    for run in ("pretrain", "none", "error_guided"):
        names = sorted(p.name for p in (seed_dir / run / "checkpoints").iterdir())
        assert len(names) == 2 and names[1] == "last.ckpt" and names[0].startswith("epoch="), (run, names)

    # Files.
    for name in ("report.md", "results.csv", "report.png", "timing.json"):
        assert (out / name).is_file(), name
    assert (out / "report.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    runs = {
        name: json.loads((seed_dir / name / "results.json").read_text())
        for name in ("none", "error_guided", "error_guided_k15", "single_view_none", "single_view_error_guided")
    }
    assert runs["single_view_none"]["num_views"] == 1 and runs["single_view_none"]["source_run"] == "none"

    # Markdown: Table 1 layout, values = results.json in percent.
    markdown = (out / "report.md").read_text()
    assert markdown == result["markdown"]
    assert "Command: `lightning-vtr report" in markdown and "Total wall time:" in markdown
    tables = _parse_tables(markdown)
    header, rows = tables["Table 1: robustness to view transformations (%, test set)"]
    assert header == ["Method"] + [
        f"{s} {m}" for s in ("Aligned", "Hemispherical", "Spherical") for m in ("mIoU", "F-score")
    ]
    assert list(rows) == ["None-VTR", "Ours"]
    for title, run in (("None-VTR", "none"), ("Ours", "error_guided")):
        res = runs[run]["results"]
        assert rows[title] == [_pct(res[s][m]) for s in VIEW_SETS for m in ("iou@0.4", "fscore")]
    header, rows = tables["Ablation: bin interval K (mIoU, %)"]
    assert header == ["Method", "Aligned mIoU", "Hemispherical mIoU", "Spherical mIoU"]
    assert rows == {
        "K = 15": [_pct(runs["error_guided_k15"]["results"][s]["iou@0.4"]) for s in VIEW_SETS],
        "K = 30": [_pct(runs["error_guided"]["results"][s]["iou@0.4"]) for s in VIEW_SETS],
    }
    _, rows = tables["Ablation: single-view input (%)"]
    assert rows["Ours (1 view)"] == [
        _pct(runs["single_view_error_guided"]["results"][s][m]) for s in VIEW_SETS for m in ("iou@0.4", "fscore")
    ]
    assert "Ablation: viewpoint pool (%)" not in tables

    # CSV: one row per run x view set, the same values unrounded.
    with (out / "results.csv").open() as f:
        rows_csv = list(csv.DictReader(f))
    assert len(rows_csv) == 5 * 3
    for row in rows_csv:
        payload = runs[row["run"]]
        assert row["strategy"] == ("none" if row["run"].endswith("none") else "error_guided")
        assert row["seed"] == "0"
        assert float(row["iou@0.4"]) == payload["results"][row["view_set"]]["iou@0.4"]
        assert float(row["fscore"]) == payload["results"][row["view_set"]]["fscore"]
        assert float(row["train_seconds"]) == pytest.approx(payload["train_seconds"], abs=1e-3)

    # A re-run (a killed report restarted) trains and tests nothing again and writes the same tables.
    mtimes = {p: p.stat().st_mtime_ns for p in seed_dir.rglob("results.json")}
    counters["fit"] = counters["test"] = 0
    again = run_report(config)
    assert counters["fit"] == 0 and counters["test"] == 0
    assert {p: p.stat().st_mtime_ns for p in seed_dir.rglob("results.json")} == mtimes
    assert _parse_tables(again["markdown"]) == tables
    assert len(json.loads((out / "timing.json").read_text())["invocations"]) == 2


def test_several_seeds_print_mean_and_sample_std():
    payloads = {
        "none": {
            0: {"results": {"aligned": {"iou@0.4": 0.5, "fscore": 0.2}}},
            1: {"results": {"aligned": {"iou@0.4": 0.7, "fscore": 0.4}}},
        }
    }
    _, rows = _parse_tables("## t\n" + _table({"None-VTR": "none"}, payloads, ("iou@0.4", "fscore"), [0, 1]))["t"]
    # mean 60, sample std sqrt(((50-60)^2 + (70-60)^2) / 1) = 14.14; missing sets print "-".
    assert rows["None-VTR"] == ["60.00 ± 14.14", "30.00 ± 14.14", "-", "-", "-", "-"]
    _, rows = _parse_tables("## t\n" + _table({"None-VTR": "none"}, payloads, ("iou@0.4",), [1]))["t"]
    assert rows["None-VTR"] == ["70.00", "-", "-"]


def test_strategies_are_none_then_the_selector_registry_each_with_a_row_title():
    assert STRATEGIES == ("none", "nature", "random", "viat", "mvtn", "error_guided")
    assert STRATEGIES == ("none", *SELECTORS) and STRATEGIES is experiment.STRATEGIES
    assert list(STRATEGY_TITLES) == list(STRATEGIES)


def test_report_config_gives_each_seed_the_experiment_with_its_own_seed_and_directory():
    exp = default_experiment(data="/data/vtr", out="runs/x", preset="paper", fraction=0.1, model_kwargs={"lr": 1.0})
    config = ReportConfig(exp, seeds=[3, 7])
    for seed in (3, 7):
        seed_config = config.seed_config(seed)
        assert isinstance(seed_config, ExperimentConfig)
        assert vars(seed_config) == {**vars(exp), "seed": seed, "out": f"runs/x/seed_{seed}"}
    assert config.experiment is exp and exp.seed == 0 and exp.out == "runs/x"  # the given one is not changed
    # The report's defaults: its own budget and directory over ExperimentConfig's.
    default = ReportConfig().experiment
    assert (default.out, default.pretrain_epochs, default.finetune_epochs, default.batch_size) == (
        "runs/report",
        30,
        10,
        8,
    )
    assert ReportConfig().experiment is not ReportConfig().experiment


def test_plan_adds_the_runs_the_ablations_need():
    names = [r.name for r in _plan(ReportConfig(strategies=["viat"]))]
    assert names == [
        "none",
        "viat",
        "error_guided",
        "error_guided_k15",
        "error_guided_k60",
        "error_guided_k90",
        "error_guided_no_pool",
        "single_view_none",
        "single_view_error_guided",
    ]
    no_pool = next(r for r in _plan(ReportConfig()) if r.name == "error_guided_no_pool")
    assert no_pool.callback_kwargs == {"use_pool": False}
    assert [r.name for r in _plan(ReportConfig(strategies=["mvtn", "random"], ablations=[]))] == ["random", "mvtn"]
    kwargs = {
        r.name: r.selector_kwargs for r in _plan(ReportConfig(selector_kwargs={"error_guided": {"mode": "soft"}}))
    }
    assert kwargs["error_guided_k60"] == {"mode": "soft", "k": 60} and kwargs["error_guided"] == {"mode": "soft"}


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"strategies": ["ours"]}, "strategies"),
        ({"ablations": ["dropout"]}, "ablations"),
        ({"k_values": [15, 25]}, "k_values"),
        ({"seeds": []}, "seeds"),
        ({"seeds": [1, 1]}, "seeds"),
        ({"selector_kwargs": {"ours": {}}}, "selector_kwargs"),
        ({"experiment": ExperimentConfig(finetune_epochs=0)}, "finetune_epochs"),
        ({"experiment": ExperimentConfig(pretrain_epochs=0)}, "pretrain_epochs"),
    ],
)
def test_config_rejects_bad_values(kwargs, match):
    with pytest.raises(ValueError, match=match):
        ReportConfig(**kwargs)


def test_config_rejects_wrong_types():
    with pytest.raises(TypeError, match="`experiment` must be an ExperimentConfig"):
        ReportConfig({"model": "pix2vox"})
    with pytest.raises(TypeError, match="`seeds` must be an int"):
        ReportConfig(seeds=["0"])


def test_every_table_row_and_csv_row_comes_from_its_own_run(tmp_path, monkeypatch):
    """Stubbed runs with distinct values per (run, seed, view set, metric): each cell must find its own."""
    import statistics

    import lightning_vtr.experiments.report as report

    names = [
        "none",
        "nature",
        "random",
        "viat",
        "mvtn",
        "error_guided",
        "error_guided_k15",
        "error_guided_k60",
        "error_guided_k90",
        "error_guided_no_pool",
        "single_view_none",
        "single_view_error_guided",
    ]

    def value(run: str, seed: int, view_set: str, metric: str) -> float:
        return (
            names.index(run) * 7 + VIEW_SETS.index(view_set) * 3 + (metric == "fscore") * 50 + seed * seed * 5
        ) / 200

    def payload(run: str, seed: int) -> dict:
        res = {v: {m: value(run, seed, v, m) for m in ("iou@0.4", "fscore")} for v in VIEW_SETS}
        return {"results": res, "train_seconds": 10.0 * names.index(run) + seed}

    monkeypatch.setattr(experiment, "pretrain", lambda config: tmp_path / "pretrained.ckpt")
    monkeypatch.setattr(
        experiment, "run_strategy", lambda name, config, pretrained, run_name, **kw: payload(run_name, config.seed)
    )
    monkeypatch.setattr(report, "_single_view", lambda run, exp, source: payload(run.name, exp.seed))
    result = run_report(ReportConfig(default_experiment(out=str(tmp_path / "r")), seeds=[0, 2]))

    def cell(run: str, view_set: str, metric: str) -> str:
        a, b = (100 * value(run, s, view_set, metric) for s in (0, 2))
        return f"{statistics.fmean([a, b]):.2f} ± {statistics.stdev([a, b]):.2f}"

    both = [(v, m) for v in VIEW_SETS for m in ("iou@0.4", "fscore")]
    tables = _parse_tables(result["markdown"])
    _, rows = tables["Table 1: robustness to view transformations (%, test set)"]
    titles = {
        "None-VTR": "none",
        "Nature": "nature",
        "Random": "random",
        "VIAT": "viat",
        "MVTN": "mvtn",
        "Ours": "error_guided",
    }
    assert list(rows) == list(titles)
    assert rows == {t: [cell(r, v, m) for v, m in both] for t, r in titles.items()}
    _, rows = tables["Ablation: bin interval K (mIoU, %)"]
    k_runs = {
        "K = 15": "error_guided_k15",
        "K = 30": "error_guided",
        "K = 60": "error_guided_k60",
        "K = 90": "error_guided_k90",
    }
    assert rows == {t: [cell(r, v, "iou@0.4") for v in VIEW_SETS] for t, r in k_runs.items()}
    _, rows = tables["Ablation: viewpoint pool (%)"]
    pool_runs = {"Ours (with pool)": "error_guided", "Ours (without pool)": "error_guided_no_pool"}
    assert rows == {t: [cell(r, v, m) for v, m in both] for t, r in pool_runs.items()}
    _, rows = tables["Ablation: single-view input (%)"]
    single_runs = {"None-VTR (1 view)": "single_view_none", "Ours (1 view)": "single_view_error_guided"}
    assert rows == {t: [cell(r, v, m) for v, m in both] for t, r in single_runs.items()}

    with (tmp_path / "r" / "results.csv").open() as f:
        rows_csv = list(csv.DictReader(f))
    assert len(rows_csv) == len(names) * 2 * 3
    assert sorted({r["run"] for r in rows_csv}) == sorted(names)
    for row in rows_csv:
        seed = int(row["seed"])
        assert float(row["iou@0.4"]) == value(row["run"], seed, row["view_set"], "iou@0.4")
        assert float(row["fscore"]) == value(row["run"], seed, row["view_set"], "fscore")
        assert float(row["train_seconds"]) == 10.0 * names.index(row["run"]) + seed
        assert row["strategy"] == (
            row["run"]
            if row["run"] in titles.values()
            else "none"
            if row["run"] == "single_view_none"
            else "error_guided"
        )
