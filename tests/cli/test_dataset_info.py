"""``lightning-vtr dataset-info``: the summary of a dataset directory."""

from __future__ import annotations

from lightning_vtr.cli import main
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
