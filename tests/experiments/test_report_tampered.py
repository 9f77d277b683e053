"""A report resumed from a tampered output folder: every JSON file it reads back is checked against the schema
the report writes, and a bad one is refused with one line naming the file, the field, the types and the remedy."""

from __future__ import annotations

import json
import shutil

import pytest

import lightning_vtr.experiments.training as training
from lightning_vtr.cli import main
from lightning_vtr.errors import DataError, exit_status
from lightning_vtr.experiments.output_files import RUN_RESULTS, read_output_json
from lightning_vtr.experiments.report import ReportConfig, default_experiment
from lightning_vtr.experiments.report_plan import ReportRun
from lightning_vtr.experiments.report_run import single_view
from lightning_vtr.protocol import VIEW_SETS


def _argv(out) -> list[str]:
    return ["report", "--out", str(out), "--strategies", "none", "--seeds", "0", "--jobs", "1", "--no-progress"]


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    """A report folder whose pretraining and run ``none`` are cached (no fit happens), reported once."""
    out = tmp_path_factory.mktemp("template") / "R"
    seed_exp = ReportConfig(default_experiment(out=str(out)), seeds=[0], strategies=["none"]).seed_config(0)
    (out / "seed_0" / "pretrain").mkdir(parents=True)
    (out / "seed_0" / "pretrain" / "pretrained.ckpt").write_bytes(b"")  # never read: the run is cached
    (out / "seed_0" / "pretrain" / "timing.json").write_text(json.dumps({"seconds": {"fit": 2.0}, "resumed": False}))
    records = out / "seed_0" / "none" / "vtr_selection"
    records.mkdir(parents=True)
    (records / "start.json").write_text(json.dumps({"epoch": -1, "view_sets": [[[30.0, 10.0], [150.0, -5.0]]]}))
    (records / "settings.json").write_text(json.dumps({"version": 1, "callback": "x", "settings": {"k": 30}}))
    payload = {
        "strategy": "none",
        "config": training._comparable(seed_exp),
        "train_seconds": 1.0,
        "eval_seconds": 0.5,
        "timing": {"test": 0.5, "fit": 1.0},
        "generated_samples": 0,
        "results": {v: {"iou@0.4": 0.5, "fscore": float("nan")} for v in VIEW_SETS},
    }
    (out / "seed_0" / "none" / "results.json").write_text(json.dumps(payload))
    assert main(_argv(out)) == 0  # what the report writes reads back: the same command resumes from it
    assert json.loads((out / "timing.json").read_text())["invocations"]
    return out


@pytest.fixture
def report(finished, tmp_path, capsys):
    out = tmp_path / "R"
    shutil.copytree(finished, out)
    capsys.readouterr()
    return out


def _rerun(out, capsys) -> str:
    """The one line the report command prints after refusing ``out``; exit status 1."""
    capsys.readouterr()
    assert main(_argv(out)) == 1
    err = capsys.readouterr().err
    assert err.endswith("\n") and err.count("\n") == 1 and "Traceback" not in err, err
    return err.strip()


def _edit(path, change) -> None:
    content = json.loads(path.read_text())
    change(content)
    path.write_text(json.dumps(content))


def test_the_untouched_folder_reports_again(report, capsys):
    assert main(_argv(report)) == 0
    assert len(json.loads((report / "timing.json").read_text())["invocations"]) == 2


@pytest.mark.parametrize(
    ("change", "field", "expected", "found"),
    [
        (lambda p: p.update(train_seconds="12"), "'train_seconds'", "a number", "str"),
        (lambda p: p.update(train_seconds=True), "'train_seconds'", "a number", "bool"),
        (lambda p: p.update(results="x"), "'results'", "a dict", "str"),
        (
            lambda p: p["results"]["spherical"].update({"iou@0.4": "0.5"}),
            "'results'['spherical']['iou@0.4']",
            "a number",
            "str",
        ),
        (lambda p: p["results"].update(spherical=[0.5]), "'results'['spherical']", "a dict", "list"),
        (lambda p: p.pop("results"), "'results'", "a dict", "no such field"),
        (lambda p: p.update(config="x"), "'config'", "a dict", "str"),
        (lambda p: p.update(timing={"test": None}), "'timing'['test']", "a number", "null"),
        (lambda p: p.update(generated_samples=1.5), "'generated_samples'", "an int", "float"),
    ],
)
def test_a_tampered_results_json_is_refused_naming_the_file_and_field(report, capsys, change, field, expected, found):
    results = report / "seed_0" / "none" / "results.json"
    _edit(results, change)
    assert _rerun(report, capsys) == (
        f"lightning-vtr report: error: {results}: {field} must be {expected}, found {found}; "
        f"delete that run's folder ({report / 'seed_0' / 'none'}) to run it again"
    )


def test_a_pretraining_timing_that_is_no_dict_is_refused(report, capsys):
    timing = report / "seed_0" / "pretrain" / "timing.json"
    timing.write_text("[1]")
    assert _rerun(report, capsys) == (
        f"lightning-vtr report: error: {timing}: its content must be a dict, found list; delete that file "
        f"({timing}); the report then shows the pretraining's times as unknown"
    )
    timing.write_text(json.dumps({"seconds": {"fit": "2"}}))
    assert f"{timing}: 'seconds'['fit'] must be a number, found str;" in _rerun(report, capsys)


def test_the_reports_own_timing_is_checked(report, capsys):
    timing = report / "timing.json"
    _edit(timing, lambda t: t.update(invocations=[1.0, "2"]))
    assert _rerun(report, capsys) == (
        f"lightning-vtr report: error: {timing}: 'invocations'[1] must be a number, found str; delete that file "
        f"({timing}) to start its record of wall times afresh"
    )
    _edit(timing, lambda t: t.pop("invocations"))
    assert f"{timing}: 'invocations' must be a list, found no such field;" in _rerun(report, capsys)


@pytest.mark.parametrize("name", ["seed_0/none/results.json", "seed_0/pretrain/timing.json", "timing.json"])
def test_truncated_json_is_refused_naming_the_file(report, capsys, name):
    path = report / name
    path.write_text(path.read_text()[:-3])
    line = _rerun(report, capsys)
    assert line.startswith(f"lightning-vtr report: error: {path}: not valid JSON (")
    assert "line " in line and "column " in line and "; delete that " in line


def test_empty_and_non_utf8_json_are_refused_naming_the_file(report, capsys):
    results = report / "seed_0" / "none" / "results.json"
    results.write_text("")
    assert _rerun(report, capsys).startswith(
        f"lightning-vtr report: error: {results}: not valid JSON (Expecting value: line 1 column 1); delete that"
    )
    results.write_bytes(b'{"a": "\xff\xfe\xfa"}')
    assert f"{results}: not valid JSON (" in _rerun(report, capsys)


def test_deeply_nested_json_is_refused_naming_the_file(report, capsys):
    results = report / "seed_0" / "none" / "results.json"
    results.write_text("[" * 100_000 + "]" * 100_000)
    assert _rerun(report, capsys) == (
        f"lightning-vtr report: error: {results}: not valid JSON (nested deeper than Python's recursion limit); "
        f"delete that run's folder ({report / 'seed_0' / 'none'}) to run it again"
    )


def test_a_tampered_selection_record_is_refused(report, capsys):
    record = report / "seed_0" / "none" / "vtr_selection" / "start.json"
    _edit(record, lambda r: r.update(view_sets=[[[30.0, 10.0, 1.0]]]))
    assert f"{record}: 'view_sets'[0][0] must be a list of 2 items, found 3 items;" in _rerun(report, capsys)
    record.write_text(json.dumps({"epoch": -1, "view_sets": [[["30", 10.0]]]}))
    assert f"{record}: 'view_sets'[0][0][0] must be a number, found str;" in _rerun(report, capsys)
    (record.parent / "settings.json").write_text("[]")
    record.unlink()
    assert f"{record.parent / 'settings.json'}: its content must be a dict, found list;" in _rerun(report, capsys)


def test_a_tampered_validation_cache_is_refused(tmp_path):
    run_dir = tmp_path / "none"
    run_dir.mkdir()
    cache = run_dir / "validation.json"
    cache.write_text(json.dumps({"repeats": 2, "results": {"spherical": 0.5}}))
    with pytest.raises(DataError) as caught:
        training.validate_run(default_experiment(out=str(tmp_path)), run_dir, 2)
    assert str(caught.value) == (
        f"{cache}: 'results'['spherical'] must be a dict, found float; delete that file ({cache}) to validate the "
        "run again"
    )
    assert exit_status(caught.value) == 1
    cache.write_text(json.dumps({"repeats": "2", "results": {}}))
    with pytest.raises(DataError, match="'repeats' must be an int, found str"):
        training.validate_run(default_experiment(out=str(tmp_path)), run_dir, 2)


def test_a_tampered_single_view_result_is_refused(tmp_path):
    run = ReportRun("single_view_none", "none", single_view_of="none")
    result = tmp_path / "single_view_none" / "results.json"
    result.parent.mkdir()
    result.write_text(json.dumps({"train_seconds": 1.0, "num_views": "1", "results": {}}))
    with pytest.raises(DataError) as caught:
        single_view(run, default_experiment(out=str(tmp_path)), {"train_seconds": 1.0})
    assert str(caught.value) == (
        f"{result}: 'num_views' must be an int, found str; delete that run's folder ({result.parent}) to run it again"
    )


def test_a_configuration_nested_too_deeply_is_refused(tmp_path):
    nested: list = []
    for _ in range(40):
        nested = [nested]
    path = tmp_path / "results.json"
    path.write_text(json.dumps({"train_seconds": 1.0, "results": {}, "config": {"model_kwargs": nested}}))
    with pytest.raises(DataError, match=r"'config'\['model_kwargs'\] must be JSON nested at most 32 levels deep"):
        read_output_json(path, RUN_RESULTS, "delete it")
    assert read_output_json(tmp_path / "missing.json", RUN_RESULTS, "delete it") is None
