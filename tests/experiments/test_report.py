"""run_report: tables equal the runs' results, files, resume, confidence intervals, paired differences, view
distributions, the time split; ReportConfig and its runs."""

from __future__ import annotations

import csv
import json
import math

import lightning as L
import pytest

import lightning_vtr.experiments.training as experiment
from lightning_vtr.experiments.report import (
    ABLATIONS,
    MAIN_STRATEGIES,
    STRATEGIES,
    STRATEGY_TITLES,
    ReportConfig,
    default_experiment,
    run_report,
)
from lightning_vtr.experiments.report_plan import plan_runs as _plan
from lightning_vtr.experiments.report_tables import robustness_table as _table
from lightning_vtr.experiments.training import VARIANTS, ExperimentConfig
from lightning_vtr.protocol import VIEW_SETS


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
        test_repeats=2,
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
    # Two selections (before epoch 0 and after it) of 15 % of the 21 training objects each.
    assert searched["generated_samples"] == 2 * round(0.15 * 21)

    # One checkpoint callback per run: no duplicate "-v1" files beside each epoch's checkpoint.
    for run in ("pretrain", "none", "error_guided"):
        names = sorted(p.name for p in (seed_dir / run / "checkpoints").iterdir())
        assert len(names) == 2 and names[1] == "last.ckpt" and names[0].startswith("epoch="), (run, names)

    # Files.
    for name in ("report.md", "results.csv", "differences.csv", "report.png", "timing.json"):
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
    header, rows = tables["Table 1: robustness to view transformations (%, test set; 1 seed: no interval)"]
    assert header == ["Method"] + [
        f"{s} {m}" for s in ("Aligned", "Hemispherical", "Spherical") for m in ("mIoU", "best mIoU", "F-score")
    ]
    assert list(rows) == ["None-VTR", "Error-guided (default rule)"]
    for title, run in (("None-VTR", "none"), ("Error-guided (default rule)", "error_guided")):
        res = runs[run]["results"]
        # best mIoU: the largest of the set's mean IoUs at 0.2 ... 0.5 (VTR's test script)
        best = {s: max(res[s][f"iou@{t}"] for t in ("0.2", "0.3", "0.4", "0.5")) for s in VIEW_SETS}
        assert rows[title] == [
            _pct(value) for s in VIEW_SETS for value in (res[s]["iou@0.4"], best[s], res[s]["fscore"])
        ]
    header, rows = tables["Ablation: bin interval K (mIoU, %)"]
    assert header == ["Method", "Aligned mIoU", "Hemispherical mIoU", "Spherical mIoU"]
    assert rows == {
        "K = 15": [_pct(runs["error_guided_k15"]["results"][s]["iou@0.4"]) for s in VIEW_SETS],
        "K = 30": [_pct(runs["error_guided"]["results"][s]["iou@0.4"]) for s in VIEW_SETS],
    }
    _, rows = tables["Ablation: single-view input (%)"]
    single = runs["single_view_error_guided"]["results"]
    assert rows["Default rule (1 view)"] == [
        _pct(value)
        for s in VIEW_SETS
        for value in (
            single[s]["iou@0.4"],
            max(v for k, v in single[s].items() if k.startswith("iou@")),
            single[s]["fscore"],
        )
    ]
    assert "Ablation: viewpoint pool (%)" not in tables

    # One seed: the paired difference to None-VTR without an interval; no Random row, so no table against it.
    _, rows = tables["Paired difference to None-VTR (mIoU points)"]
    diffs = [runs["error_guided"]["results"][s]["iou@0.4"] - runs["none"]["results"][s]["iou@0.4"] for s in VIEW_SETS]
    # one seed: the difference alone, no interval and no sign count (the note says "1 seed: no interval")
    assert rows == {"Error-guided (default rule)": [f"{100 * d:+.2f}" for d in diffs]}
    assert "Paired difference to Random (paper: angle-uniform) (mIoU points)" not in tables
    # The views the callback generated: a start selection and one after epoch 0, 3 objects each.
    _, rows = tables["Where the training views went"]
    assert list(rows) == ["Error-guided (default rule)"] and rows["Error-guided (default rule)"][0] == "6"
    assert sum(float(v) for v in rows["Error-guided (default rule)"][1:7]) == pytest.approx(100, abs=0.2)
    # Where the time went: measured stages of every fit and test, in results.json, timing.json and the report.
    for name in ("none", "error_guided"):
        timing = runs[name]["timing"]
        assert timing["fit"] > 0 and timing["test"] > 0 and timing["test_steps"] > 0
        assert (timing["augmentation"] > 0) == (name == "error_guided")
    split = json.loads((out / "timing.json").read_text())["split"]
    assert split["fine_tuning"]["augmentation"] == pytest.approx(
        runs["error_guided_k15"]["timing"]["augmentation"] + runs["error_guided"]["timing"]["augmentation"]
    )
    assert (
        split["pretraining"]["total"]
        == json.loads((seed_dir / "pretrain" / "timing.json").read_text())["seconds"]["fit"]
    )
    time_rows = _parse_tables(markdown)["Where the time goes"][1]
    assert time_rows["Pretraining"][0] == f"{split['pretraining']['total']:.1f}"
    assert time_rows["none"][0] == f"{runs['none']['train_seconds']:.1f}"

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
        ious = [v for k, v in payload["results"][row["view_set"]].items() if k.startswith("iou@")]
        assert len(ious) == 4 and float(row["iou_best"]) == max(ious)
        assert float(row["train_seconds"]) == pytest.approx(payload["train_seconds"], abs=1e-3)

    # A re-run (a killed report restarted) trains and tests nothing again and writes the same tables.
    mtimes = {p: p.stat().st_mtime_ns for p in seed_dir.rglob("results.json")}
    counters["fit"] = counters["test"] = 0
    again = run_report(config)
    assert counters["fit"] == 0 and counters["test"] == 0
    assert {p: p.stat().st_mtime_ns for p in seed_dir.rglob("results.json")} == mtimes
    assert _parse_tables(again["markdown"]) == tables
    assert len(json.loads((out / "timing.json").read_text())["invocations"]) == 2


def test_several_seeds_print_mean_and_95_percent_confidence_interval():
    payloads = {
        "none": {
            0: {"results": {"aligned": {"iou@0.4": 0.5, "fscore": 0.2}}},
            1: {"results": {"aligned": {"iou@0.4": 0.7, "fscore": 0.4}}},
            2: {"results": {"aligned": {"iou@0.4": 0.6, "fscore": 0.3}}},
        }
    }
    _, rows = _parse_tables("## t\n" + _table({"None-VTR": "none"}, payloads, ("iou@0.4", "fscore"), [0, 1]))["t"]
    # mean 60, sample std 14.142, half-width t(0.975, 1) * 14.142 / sqrt(2) = 12.706 * 10; missing sets print "-".
    assert rows["None-VTR"] == ["60.00 ± 127.06", "30.00 ± 127.06", "-", "-", "-", "-"]
    _, rows = _parse_tables("## t\n" + _table({"None-VTR": "none"}, payloads, ("iou@0.4",), [0, 1, 2]))["t"]
    # std 10 points, half-width t(0.975, 2) * 10 / sqrt(3) = 4.3027 * 5.7735 = 24.84.
    assert rows["None-VTR"] == ["60.00 ± 24.84", "-", "-"]
    _, rows = _parse_tables("## t\n" + _table({"None-VTR": "none"}, payloads, ("iou@0.4",), [1]))["t"]
    assert rows["None-VTR"] == ["70.00", "-", "-"]


def test_strategies_are_none_then_the_selector_registry_each_with_a_row_title():
    assert STRATEGIES == ("none", "nature", "random", "viat", "mvtn", "paper")
    assert STRATEGIES is experiment.STRATEGIES
    assert list(STRATEGY_TITLES) == list(VARIANTS)
    assert [STRATEGY_TITLES[s] for s in STRATEGIES] == [
        "None-VTR",
        "Nature",
        "Random (paper: angle-uniform)",
        "VIAT",
        "MVTN",
        "Error-guided (paper's rule)",
    ]
    # the default report: what a user chooses between, each rule once
    assert MAIN_STRATEGIES == ("none", "random", "random_area", "paper", "error_guided")
    assert [STRATEGY_TITLES[s] for s in MAIN_STRATEGIES] == [
        "None-VTR",
        "Random (paper: angle-uniform)",
        "Random (area-uniform)",
        "Error-guided (paper's rule)",
        "Error-guided (default rule)",
    ]


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
    # Three seeds, the main comparison, no ablation, every test object on 4 view sets.
    assert (default.test_repeats, ExperimentConfig().test_repeats) == (4, 1)
    assert (ReportConfig().seeds, ReportConfig().strategies, ReportConfig().ablations) == (
        [0, 1, 2],
        ["none", "random", "random_area", "paper", "error_guided"],
        [],
    )


def test_plan_adds_the_runs_the_ablations_need():
    assert [r.name for r in _plan(ReportConfig())] == ["none", "random", "random_area", "paper", "error_guided"]
    names = [r.name for r in _plan(ReportConfig(strategies=["viat"], ablations=ABLATIONS))]
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
    no_pool = next(r for r in _plan(ReportConfig(ablations=["pool"])) if r.name == "error_guided_no_pool")
    assert no_pool.callback_kwargs == {"use_pool": False}
    assert [r.name for r in _plan(ReportConfig(strategies=["mvtn", "random"], ablations=[]))] == ["random", "mvtn"]
    plan = _plan(ReportConfig(ablations=["k"], selector_kwargs={"error_guided": {"spread": 0.25}}))
    kwargs = {r.name: r.selector_kwargs for r in plan}
    assert kwargs["error_guided_k60"] == {"spread": 0.25, "k": 60} and kwargs["error_guided"] == {"spread": 0.25}
    # Variants run in the registry's order, each under its own name.
    plan = _plan(ReportConfig(strategies=["error_guided", "paper", "random_area", "none"]))
    assert [(r.name, r.strategy) for r in plan] == [
        ("none", "none"),
        ("random_area", "random_area"),
        ("paper", "paper"),
        ("error_guided", "error_guided"),
    ]


@pytest.mark.parametrize(
    ("kwargs", "match"),
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
    import lightning_vtr.experiments.report_run as report_run
    from lightning_vtr.experiments.statistics import mean_estimate

    names = [
        "none",
        "nature",
        "random",
        "viat",
        "mvtn",
        "paper",
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

    def best(run: str, seed: int, view_set: str) -> float:
        # iou@0.3 beats iou@0.4 on every other run: the best-threshold mIoU must take it there
        return value(run, seed, view_set, "iou@0.4") + (0.01 if names.index(run) % 2 else 0.0)

    def payload(run: str, seed: int) -> dict:
        res = {v: {m: value(run, seed, v, m) for m in ("iou@0.4", "fscore")} for v in VIEW_SETS}
        for v in VIEW_SETS:
            res[v]["iou@0.3"] = value(run, seed, v, "iou@0.4") + (0.01 if names.index(run) % 2 else -0.01)
        return {"results": res, "train_seconds": 10.0 * names.index(run) + seed}

    monkeypatch.setattr(experiment, "pretrain", lambda config: tmp_path / "pretrained.ckpt")
    monkeypatch.setattr(
        experiment, "run_strategy", lambda name, config, pretrained, run_name, **kw: payload(run_name, config.seed)
    )
    monkeypatch.setattr(report_run, "single_view", lambda run, exp, source: payload(run.name, exp.seed))
    config = ReportConfig(
        default_experiment(out=str(tmp_path / "r")),
        seeds=[0, 2],
        strategies=[*STRATEGIES, "error_guided"],
        ablations=ABLATIONS,
        selector_kwargs=_OWN_PAPER_RUN,
    )
    result = run_report(config)

    def cell(run: str, view_set: str, metric: str) -> str:
        get = best if metric == "iou_best" else lambda r, s, v: value(r, s, v, metric)
        estimate = mean_estimate([100 * get(run, s, view_set) for s in (0, 2)])
        return f"{estimate.mean:.2f} ± {estimate.half_width:.2f}"

    both = [(v, m) for v in VIEW_SETS for m in ("iou@0.4", "iou_best", "fscore")]
    tables = _parse_tables(result["markdown"])
    _, rows = tables["Table 1: robustness to view transformations (%, test set; mean ± 95 % CI over seeds (Student t))"]
    titles = {
        "None-VTR": "none",
        "Nature": "nature",
        "Random (paper: angle-uniform)": "random",
        "VIAT": "viat",
        "MVTN": "mvtn",
        "Error-guided (paper's rule)": "paper",
        "Error-guided (default rule)": "error_guided",
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
    pool_runs = {"Default rule (with pool)": "error_guided", "Default rule (without pool)": "error_guided_no_pool"}
    assert rows == {t: [cell(r, v, m) for v, m in both] for t, r in pool_runs.items()}
    _, rows = tables["Ablation: single-view input (%)"]
    single_runs = {"None-VTR (1 view)": "single_view_none", "Default rule (1 view)": "single_view_error_guided"}
    assert rows == {t: [cell(r, v, m) for v, m in both] for t, r in single_runs.items()}
    # Per-seed differences are constant here (the seed term cancels): no spread, every seed agrees.
    _, rows = tables["Paired difference to Random (paper: angle-uniform) (mIoU points)"]
    gap = (names.index("paper") - names.index("random")) * 7 / 2
    assert rows["Error-guided (paper's rule)"] == [f"+{gap:.2f} [+{gap:.2f}, +{gap:.2f}] above, 2/2"] * 3

    with (tmp_path / "r" / "results.csv").open() as f:
        rows_csv = list(csv.DictReader(f))
    assert len(rows_csv) == len(names) * 2 * 3
    assert sorted({r["run"] for r in rows_csv}) == sorted(names)
    for row in rows_csv:
        seed = int(row["seed"])
        assert float(row["iou@0.4"]) == value(row["run"], seed, row["view_set"], "iou@0.4")
        assert float(row["fscore"]) == value(row["run"], seed, row["view_set"], "fscore")
        assert float(row["iou_best"]) == best(row["run"], seed, row["view_set"])
        assert float(row["train_seconds"]) == 10.0 * names.index(row["run"]) + seed
        assert row["strategy"] == (
            row["run"]
            if row["run"] in titles.values()
            else "none"
            if row["run"] == "single_view_none"
            else "error_guided"
        )


#: A paper rule unlike the callback's default, so that the report fits it as a run of its own.
_OWN_PAPER_RUN = {"paper": {"spread": 0.25}}


def _stub_runs(monkeypatch, tmp_path, iou: dict[str, dict[int, float]], views=None, timing=None):
    """Stub pretraining and fine-tuning: run ``r`` of seed ``s`` scores ``iou[r][s]`` on every view set (F-score
    half of it); ``views[r][s]`` are written as its selection record, ``timing[r][s]`` as its measured stages."""
    import lightning_vtr.experiments.report_run as report_run

    def pretrain(config):
        directory = tmp_path / "r" / f"seed_{config.seed}" / "pretrain"
        directory.mkdir(parents=True, exist_ok=True)
        seconds = (timing or {}).get("pretrain", {}).get(config.seed)
        if seconds is not None:
            (directory / "timing.json").write_text(json.dumps({"seconds": seconds}))
        return directory / "pretrained.ckpt"

    def run_strategy(name, config, pretrained, run_name, **kwargs):
        run_dir = tmp_path / "r" / f"seed_{config.seed}" / run_name
        if views and views.get(run_name, {}).get(config.seed) is not None:
            (run_dir / "vtr_selection").mkdir(parents=True, exist_ok=True)
            record = {"epoch": -1, "view_sets": views[run_name][config.seed]}
            (run_dir / "vtr_selection" / "start.json").write_text(json.dumps(record))
        value = iou[run_name][config.seed]
        payload = {"results": {v: {"iou@0.4": value, "fscore": value / 2} for v in VIEW_SETS}, "train_seconds": 1.0}
        if timing and run_name in timing:
            payload["timing"] = timing[run_name][config.seed]
            payload["train_seconds"] = timing[run_name][config.seed]["fit"]
            payload["eval_seconds"] = timing[run_name][config.seed]["test"]
        return payload

    monkeypatch.setattr(experiment, "pretrain", pretrain)
    monkeypatch.setattr(experiment, "run_strategy", run_strategy)
    monkeypatch.setattr(report_run, "single_view", lambda run, exp, source: None)


def test_paired_differences_against_none_and_random_with_intervals_and_sign_agreement(tmp_path, monkeypatch):
    from scipy import stats

    seeds = [0, 1, 2]
    none = {0: 0.40, 1: 0.50, 2: 0.45}
    # Against none: +1, +2, +3 points for Random; +3, -1, +1 for Ours; exactly 0 for the paper rule.
    iou = {
        "none": none,
        "random": {s: none[s] + d for s, d in zip(seeds, (0.01, 0.02, 0.03))},
        "error_guided": {s: none[s] + d for s, d in zip(seeds, (0.03, -0.01, 0.01))},
        "paper": dict(none),
    }
    _stub_runs(monkeypatch, tmp_path, iou)
    strategies = ["none", "random", "paper", "error_guided"]
    config = ReportConfig(default_experiment(out=str(tmp_path / "r")), seeds=seeds, strategies=strategies)
    result = run_report(config)
    tables = _parse_tables(result["markdown"])
    t = stats.t.ppf(0.975, 2)

    def expected(diffs: list[float]) -> str:
        mean = sum(diffs) / 3
        half = t * (sum((d - mean) ** 2 for d in diffs) / 2) ** 0.5 / 3**0.5
        agree = sum(d * mean > 0 for d in diffs)
        word = "above" if mean - half > 0 else "below" if mean + half < 0 else "level"
        return f"{mean:+.2f} [{mean - half:+.2f}, {mean + half:+.2f}] {word}, {agree}/3"

    header, rows = tables["Paired difference to None-VTR (mIoU points)"]
    assert header == ["Method", "Aligned", "Hemispherical", "Spherical"]
    assert rows == {
        "Random (paper: angle-uniform)": [expected([1, 2, 3])] * 3,  # +2.00 [-0.48, +4.48] level, 3/3
        "Error-guided (default rule)": [expected([3, -1, 1])] * 3,  # +1.00 [-3.97, +5.97] level, 2/3
        "Error-guided (paper's rule)": ["+0.00 [+0.00, +0.00] level, 0/3"] * 3,
    }
    assert rows["Random (paper: angle-uniform)"][0] == "+2.00 [-0.48, +4.48] level, 3/3"
    _, rows = tables["Paired difference to Random (paper: angle-uniform) (mIoU points)"]
    assert rows == {
        "None-VTR": [expected([-1, -2, -3])] * 3,
        "Error-guided (default rule)": [expected([2, -3, -2])] * 3,
        "Error-guided (paper's rule)": [expected([-1, -2, -3])] * 3,
    }
    estimate = result["differences"]["random"]["Error-guided (default rule)"]["spherical"]
    assert (estimate.n, estimate.agree) == (3, 2) and estimate.mean == pytest.approx(-0.01)
    assert not estimate.excludes_zero

    with (tmp_path / "r" / "differences.csv").open() as f:
        rows_csv = list(csv.DictReader(f))
    assert len(rows_csv) == 2 * 3 * 3 * 3  # baselines x other rows x view sets x metrics (mIoU, best mIoU, F)
    # only iou@0.4 is logged here, so the best-threshold mIoU is it
    best = next(r for r in rows_csv if (r["baseline"], r["run"], r["metric"]) == ("none", "random", "iou_best"))
    assert float(best["mean"]) == pytest.approx(0.02)
    row = next(
        r
        for r in rows_csv
        if (r["baseline"], r["run"], r["view_set"], r["metric"]) == ("none", "random", "hemispherical", "iou@0.4")
    )
    assert float(row["mean"]) == pytest.approx(0.02) and float(row["ci_low"]) == pytest.approx(0.02 - t * 0.01 / 3**0.5)
    assert (row["seeds"], row["agree"]) == ("3", "3")
    fscore = next(r for r in rows_csv if (r["baseline"], r["run"], r["metric"]) == ("none", "random", "fscore"))
    assert float(fscore["mean"]) == pytest.approx(0.01)


def test_view_distribution_table_pools_every_seeds_generated_views(tmp_path, monkeypatch):
    seeds = [0, 1]
    iou = {name: {s: 0.5 for s in seeds} for name in MAIN_STRATEGIES}
    # Seed 0: an antipodal pair at the equator plus a view at pitch 45 (spread (180 + 90 + 90) / 3 = 120);
    # seed 1: three views below -60 on one meridian (spread (10 + 5 + 5) / 3).
    views = {
        "random": {0: [[[0, 0], [180, 0], [90, 45]]], 1: [[[0, -80], [0, -70], [0, -75]]]},
        "paper": {0: [[[0, 0], [180, 0], [90, 45]]]},
    }
    _stub_runs(monkeypatch, tmp_path, iou, views=views)
    config = ReportConfig(default_experiment(out=str(tmp_path / "r")), seeds=seeds, selector_kwargs=_OWN_PAPER_RUN)
    result = run_report(config)
    header, rows = _parse_tables(result["markdown"])["Where the training views went"]
    assert header == [
        "Method",
        "View sets",
        "Pitch [-90, -60)",
        "Pitch [-60, -30)",
        "Pitch [-30, 0)",
        "Pitch [0, 30)",
        "Pitch [30, 60)",
        "Pitch [60, 90]",
        "Antipodal pairs",
        "Mean spread (°)",
    ]
    # "none" and "error_guided" generated nothing: no row.
    assert rows == {
        "Random (paper: angle-uniform)": ["2", "50.0", "0.0", "0.0", "33.3", "16.7", "0.0", "50.0", "63.3"],
        "Error-guided (paper's rule)": ["1", "0.0", "0.0", "0.0", "66.7", "33.3", "0.0", "100.0", "120.0"],
    }
    assert result["views"]["Random (paper: angle-uniform)"]["triplet_spread"] == pytest.approx((120 + 20 / 3) / 2)
    assert (tmp_path / "r" / "report.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


#: A strategies file whose row repeats the shipped paper's rule under another title.
_REPEATED_RULE = (
    "paper_again:\n  title: Paper's rule again\n  description: the shipped paper row, repeated\n"
    "  selector: error_guided\n  selector_kwargs: {score: paper, min_separation: null, temperature: null}\n"
    "  callback_kwargs: {search_fraction: null, pool_refresh: false}\n"
)
_WITH_REPEAT = ["none", "random", "paper", "paper_again"]


def _repeat_file(tmp_path) -> str:
    path = tmp_path / "repeat.yaml"
    path.write_text(_REPEATED_RULE)
    return str(path)


def test_strategies_resolving_to_the_same_arguments_are_fitted_once_and_shown_in_both_rows(tmp_path, monkeypatch):
    """A row of a strategies file that repeats a shipped rule is one run per seed, shown in both rows."""
    seeds = [0, 1]
    iou = {name: {s: 0.40 + 0.01 * i + 0.001 * s for s in seeds} for i, name in enumerate(_WITH_REPEAT)}
    timing = {
        name: {s: {"fit": 100.0, "train_steps": 80.0, "test": 10.0} for s in seeds}
        for name in ("none", "random", "paper")
    }
    calls = []
    _stub_runs(monkeypatch, tmp_path, iou, timing=timing)
    stub = experiment.run_strategy
    monkeypatch.setattr(experiment, "run_strategy", lambda *a, **kw: calls.append(kw["run_name"]) or stub(*a, **kw))
    rows_file = _repeat_file(tmp_path)
    config = ReportConfig(
        default_experiment(out=str(tmp_path / "r")), seeds=seeds, strategies=_WITH_REPEAT, strategies_file=rows_file
    )
    result = run_report(config)

    assert calls == ["none", "random", "paper"] * 2  # no "paper_again" fit
    assert result["runs"]["paper_again"] == result["runs"]["paper"]
    _, rows = _parse_tables(result["markdown"])["Paired difference to Random (paper: angle-uniform) (mIoU points)"]
    assert rows["Paper's rule again"] == rows["Error-guided (paper's rule)"] == ["+1.00 [+1.00, +1.00] above, 2/2"] * 3
    assert (
        "fitted once because their selector and callback arguments are identical: "
        "Paper's rule again = Error-guided (paper's rule)"
    ) in result["markdown"]
    split = result["time_split"]
    assert split["fine_tuning"]["total"] == 3 * 2 * 100.0  # three fits per seed, not four
    assert split["testing"]["total"] == 3 * 2 * 10.0
    assert all(math.isnan(v) for v in split["per_run"]["paper_again"].values())
    # other arguments make it a run of its own again
    calls.clear()
    own = {"paper_again": {"spread": 0.25}}
    run_report(
        ReportConfig(
            default_experiment(out=str(tmp_path / "r2")),
            seeds=[0],
            strategies=_WITH_REPEAT,
            strategies_file=rows_file,
            selector_kwargs=own,
        )
    )
    assert calls == _WITH_REPEAT


def test_resolved_strategy_fills_in_every_default():
    resolved = experiment.resolved_strategy("paper")
    assert resolved != experiment.resolved_strategy("error_guided")
    assert resolved["selector_kwargs"]["k"] == 30 and resolved["callback_kwargs"]["use_pool"] is True
    assert resolved["callback_kwargs"]["search_fraction"] == resolved["callback_kwargs"]["fraction"] == 0.05
    assert experiment.resolved_strategy("error_guided", {"k": 15}) != resolved
    assert experiment.resolved_strategy("error_guided", callback_kwargs={"use_pool": False}) != resolved
    assert experiment.resolved_strategy("random")["callback_kwargs"]["use_pool"] is False
    assert experiment.resolved_strategy("none") is None


def test_time_split_sums_the_measured_stages(tmp_path, monkeypatch):
    seeds = [0, 1]
    iou = {name: {s: 0.5 for s in seeds} for name in ("none", "random")}

    def stages(fit: float, augmentation: float, test: float) -> dict:
        return {
            "fit": fit,
            "train_steps": fit - augmentation - 3.0,
            "train_data": 1.0,
            "validation": 1.5,
            "augmentation": augmentation,
            "fit_other": 0.5,
            "test": test,
            "test_steps": test - 2.0,
            "test_data": 2.0,
        }

    timing = {
        "pretrain": {s: stages(100.0, 0.0, 0.0) for s in seeds},
        "none": {s: stages(40.0, 0.0, 10.0) for s in seeds},
        "random": {s: stages(50.0 + s, 6.0, 12.0) for s in seeds},
    }
    _stub_runs(monkeypatch, tmp_path, iou, timing=timing)
    result = run_report(
        ReportConfig(default_experiment(out=str(tmp_path / "r")), seeds=seeds, strategies=["none", "random"])
    )
    split = result["time_split"]
    assert split["pretraining"]["total"] == 200.0 and split["pretraining"]["train_steps"] == 2 * 97.0
    assert split["fine_tuning"]["total"] == 2 * 40.0 + 50.0 + 51.0
    assert split["fine_tuning"]["augmentation"] == 12.0 and split["fine_tuning"]["validation"] == 6.0
    assert split["testing"] == {"total": 2 * 10.0 + 2 * 12.0, "test_steps": 2 * 8.0 + 2 * 10.0, "test_data": 8.0}
    assert split["measured"] == 200.0 + 181.0 + 44.0
    assert split["per_run"]["random"]["fine_tuning"] == 50.5 and split["per_run"]["random"]["augmentation"] == 6.0
    assert json.loads((tmp_path / "r" / "timing.json").read_text())["split"] == split
    _, rows = _parse_tables(result["markdown"])["Where the time goes"]
    assert rows["Pretraining"] == ["200.0", f"{100 * 200 / 425:.1f}"]
    assert rows["Fine-tuning"] == ["181.0", f"{100 * 181 / 425:.1f}"]
    assert rows["&nbsp;&nbsp;selection + synthesis"] == ["12.0", f"{100 * 12 / 425:.1f}"]
    assert rows["Testing"] == ["44.0", f"{100 * 44 / 425:.1f}"]
    assert rows["random"] == ["50.5", "41.5", "1.0", "1.5", "6.0", "0.5", "12.0"]


def test_validation_tables_pair_the_validation_results_and_merged_runs_are_validated_once(tmp_path, monkeypatch):
    seeds = [0, 1, 2]
    test_iou = {"none": {0: 0.4, 1: 0.5, 2: 0.45}, "random": {0: 0.5, 1: 0.6, 2: 0.55}}
    test_iou["paper"] = test_iou["paper_again"] = {0: 0.45, 1: 0.55, 2: 0.5}
    _stub_runs(monkeypatch, tmp_path, test_iou)
    # On the validation objects: Random +1, +2, +3 points over none; Ours -1, 0, +1 over none.
    val_iou = {"none": {0: 0.30, 1: 0.40, 2: 0.35}}
    val_iou["random"] = {s: val_iou["none"][s] + d for s, d in zip(seeds, (0.01, 0.02, 0.03))}
    val_iou["paper"] = {s: val_iou["none"][s] + d for s, d in zip(seeds, (-0.01, 0.0, 0.01))}
    validated = []

    def validate_run(config, run_dir, repeats):
        validated.append((run_dir.name, config.seed, repeats))
        return {v: {"iou@0.4": val_iou[run_dir.name][config.seed]} for v in VIEW_SETS}

    monkeypatch.setattr(experiment, "validate_run", validate_run)
    rows_file = _repeat_file(tmp_path)
    chosen = {"strategies": _WITH_REPEAT, "strategies_file": rows_file}
    config = ReportConfig(default_experiment(out=str(tmp_path / "r")), seeds=seeds, validation_repeats=12, **chosen)
    result = run_report(config)
    # paper and paper_again are one run: validated once per seed
    assert sorted(validated) == sorted((r, s, 12) for r in ("none", "random", "paper") for s in seeds)
    tables = _parse_tables(result["markdown"])
    _, rows = tables["Validation split: paired difference to None-VTR (mIoU points)"]
    assert rows["Random (paper: angle-uniform)"] == ["+2.00 [-0.48, +4.48] level, 3/3"] * 3
    assert rows["Paper's rule again"] == rows["Error-guided (paper's rule)"] == ["+0.00 [-2.48, +2.48] level, 0/3"] * 3
    _, rows = tables["Validation split: paired difference to Random (paper: angle-uniform) (mIoU points)"]
    assert rows["Error-guided (paper's rule)"] == ["-2.00 [-2.00, -2.00] below, 3/3"] * 3
    # the test-split tables keep the test results (Ours +5 points over none on every seed there)
    _, rows = tables["Paired difference to None-VTR (mIoU points)"]
    assert rows["Error-guided (paper's rule)"] == ["+5.00 [+5.00, +5.00] above, 3/3"] * 3
    assert "--validation-repeats 12" in result["markdown"]
    assert result["validation_differences"]["random"]["Error-guided (paper's rule)"]["spherical"].mean == pytest.approx(
        -0.02
    )

    validated.clear()
    plain = run_report(ReportConfig(default_experiment(out=str(tmp_path / "r")), seeds=seeds, **chosen))
    assert validated == [] and "Validation split" not in plain["markdown"]
    with pytest.raises(ValueError, match=r"`validation_repeats` must be an int >= 1, got 0"):
        ReportConfig(default_experiment(out=str(tmp_path / "r")), validation_repeats=0)


def test_a_parallel_report_equals_the_one_process_report_at_the_same_thread_count(tiny_dataset, tmp_path, capfd):
    import torch

    def config(out: str, jobs: int) -> ReportConfig:
        experiment_config = default_experiment(
            data=str(tiny_dataset),
            out=str(tmp_path / out),
            pretrain_epochs=1,
            finetune_epochs=2,
            fraction=0.15,
            batch_size=4,
            test_repeats=1,
            accelerator="cpu",
            trainer_kwargs={"limit_train_batches": 1, "limit_val_batches": 1, "limit_test_batches": 2},
        )
        return ReportConfig(
            experiment_config,
            seeds=[0, 1],
            strategies=["none", "error_guided"],
            callback_kwargs={"progress_bar": False},
            validation_repeats=1,
            jobs=jobs,
        )

    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # the children of jobs=2 get max(1, 1 // 2) = 1 thread too
    try:
        sequential = run_report(config("one", 1))
        capfd.readouterr()
        parallel = run_report(config("two", 2))
    finally:
        torch.set_num_threads(threads)
    captured = capfd.readouterr()  # the children's file descriptors too
    assert "GPU available" not in captured.out + captured.err  # Lightning's log lines went to the fits' logs
    lines = captured.out.splitlines()
    # 2 pretrainings + 2 x 2 fits, one line each.
    assert lines[0].startswith("report: 6 fits on 2 processes, 1 torch thread(s) each")
    done = [line for line in lines if " done in " in line]
    assert len(done) == 6 and done[-1].startswith("report: [6/6] seed ")
    assert sum("pretraining" in line for line in done) == 2
    for seed in (0, 1):
        logs = tmp_path / "two" / f"seed_{seed}" / "logs"
        assert sorted(p.name for p in logs.iterdir()) == ["error_guided.log", "none.log", "pretrain.log"]
        log = (logs / "error_guided.log").read_text()
        assert "epoch 1/2" in log and "GPU available" in log  # the fit's own output went to its log
    for run in ("none", "error_guided"):
        for seed in (0, 1):
            one, two = sequential["runs"][run][seed], parallel["runs"][run][seed]
            assert two["results"] == one["results"], (run, seed)
            assert two["generated_samples"] == one["generated_samples"], (run, seed)
    assert (tmp_path / "two" / "seed_1" / "error_guided" / "validation.json").read_text() == (
        tmp_path / "one" / "seed_1" / "error_guided" / "validation.json"
    ).read_text()
    assert (
        parallel["markdown"].split("## Table 1")[1].split("## Where the time")[0]
        == sequential["markdown"].split("## Table 1")[1].split("## Where the time")[0]
    )


def test_parallel_report_names_the_failed_fit_and_keeps_the_finished_ones(tiny_dataset, tmp_path):
    experiment_config = default_experiment(
        data=str(tiny_dataset),
        out=str(tmp_path / "r"),
        pretrain_epochs=1,
        finetune_epochs=1,
        batch_size=4,
        accelerator="cpu",
        trainer_kwargs={"limit_train_batches": 1, "limit_val_batches": 1, "limit_test_batches": 1},
    )
    # VIAT with a population of 0 passes the report's checks and fails inside the child, when it is built.
    config = ReportConfig(
        experiment_config, seeds=[0], strategies=["none", "viat"], selector_kwargs={"viat": {"population": 0}}, jobs=2
    )
    with pytest.raises(RuntimeError, match=r"seed 0, viat failed .*population.*logs/viat.log"):
        run_report(config)
    assert (tmp_path / "r" / "seed_0" / "pretrain" / "pretrained.ckpt").is_file()
    assert "population" in (tmp_path / "r" / "seed_0" / "logs" / "viat.log").read_text()


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"jobs": 0}, "`jobs` must be an int >= 1, got 0"),
        ({"jobs": 2, "experiment": default_experiment(devices=2)}, "jobs=2 with experiment.devices=2"),
        ({"jobs": 2, "synthesizer": lambda views: views}, "cannot be pickled"),
    ],
)
def test_config_rejects_jobs_it_cannot_run(kwargs, match):
    with pytest.raises(ValueError, match=match):
        ReportConfig(**kwargs)
