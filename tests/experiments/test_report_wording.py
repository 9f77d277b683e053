"""What the report's tables say about their intervals: bold only where an interval separates a row, "above" /
"below" / "level" from each paired difference's interval, and one seed said plainly (no interval, no count)."""

from __future__ import annotations

import csv
import math

import pytest

from lightning_vtr.experiments.report_files import write_differences_csv
from lightning_vtr.experiments.report_paper import estimate_record, table1_estimates, table1_latex
from lightning_vtr.experiments.report_tables import (
    difference_note,
    difference_table,
    paired_differences,
    plural,
    separated_best,
    verdict,
)
from lightning_vtr.experiments.statistics import Estimate
from lightning_vtr.protocol import VIEW_SETS

ROWS = {"None-VTR": "none", "Level": "level", "Ours": "ours"}


def _payloads(iou: dict[str, list[float]]) -> dict[str, dict[int, dict]]:
    """Run ``r`` of seed ``s`` scores ``iou[r][s]`` on every view set (F-score: half of it)."""
    return {
        run: {
            seed: {"results": {v: {"iou@0.4": value, "fscore": value / 2} for v in VIEW_SETS}}
            for seed, value in enumerate(values)
        }
        for run, values in iou.items()
    }


def _bold_rows(latex: str) -> set[str]:
    body = latex.split("\\midrule\n")[1].split("\\bottomrule")[0].strip().splitlines()
    return {line.split(" & ")[0] for line in body if r"\textbf" in line}


def test_a_row_an_interval_separates_is_bold_and_level_rows_are_not():
    # Ours beats both others by 2 to 4 points on every seed; Level is within noise of None-VTR
    separated = _payloads({"none": [0.50, 0.40, 0.45], "level": [0.51, 0.39, 0.46], "ours": [0.53, 0.43, 0.49]})
    bold = separated_best(ROWS, separated, [0, 1, 2], ["iou@0.4", "fscore"])
    assert set(bold.values()) == {"Ours"} and len(bold) == 2 * len(VIEW_SETS)
    latex = table1_latex(table1_estimates(ROWS, separated, [0, 1, 2]), bold=bold)
    assert _bold_rows(latex) == {"Ours"}
    assert latex.count(r"\textbf") == 2 * len(VIEW_SETS)  # one cell per column

    # the best mean is only 1 point ahead of Level on average, +4 / -2 / +1: its interval holds zero -> no bold
    level = _payloads({"none": [0.50, 0.40, 0.45], "level": [0.49, 0.45, 0.47], "ours": [0.53, 0.43, 0.48]})
    bold = separated_best(ROWS, level, [0, 1, 2], ["iou@0.4", "fscore"])
    assert set(bold.values()) == {None}
    assert r"\textbf" not in table1_latex(table1_estimates(ROWS, level, [0, 1, 2]), bold=bold)
    # one seed has no interval: nothing is separated, however far ahead
    one = _payloads({"none": [0.40], "level": [0.41], "ours": [0.60]})
    assert set(separated_best(ROWS, one, [0], ["iou@0.4"]).values()) == {None}


def test_each_difference_says_where_its_interval_lies():
    assert [verdict(Estimate(0.02, 0.01, 3, 3)), verdict(Estimate(-0.02, 0.01, 3, 3))] == ["above", "below"]
    assert verdict(Estimate(0.02, 0.03, 3, 2)) == "level" and verdict(Estimate(0.0, 0.0, 3, 0)) == "level"
    assert verdict(Estimate(0.02, math.nan, 1, 1)) is None
    payloads = _payloads({"none": [0.50, 0.40, 0.45], "level": [0.51, 0.39, 0.46], "ours": [0.53, 0.43, 0.49]})
    table = difference_table(paired_differences(ROWS, "none", payloads, "iou@0.4", [0, 1, 2]), 3)
    lines = {line.split(" | ")[0].strip("| "): line.split(" | ")[1] for line in table.splitlines()[2:]}
    # Level - none: +1, -1, +1 points; Ours - none: +3, +3, +4 points
    assert lines["Level"].endswith(" level, 2/3") and lines["Level"].startswith("+0.33 [")
    assert lines["Ours"].startswith("+3.33 [+1.90, +4.77] above, 3/3")
    note = difference_note("None-VTR", 3)
    assert '"above"' in note and '"below"' in note and '"level"' in note


def test_one_seed_prints_no_interval_and_no_sign_count(tmp_path):
    payloads = _payloads({"none": [0.40], "level": [0.40], "ours": [0.45]})
    differences = paired_differences(ROWS, "none", payloads, "iou@0.4", [0])
    table = difference_table(differences, 1)
    assert table.splitlines()[2:] == ["| Level | +0.00 | +0.00 | +0.00 |", "| Ours | +5.00 | +5.00 | +5.00 |"]
    note = difference_note("None-VTR", 1)
    assert "1 seed: no interval" in note and "CI" not in note and "agree" not in note
    # a single shared seed inside a report of several says so in its cell
    assert (
        difference_table(differences, 3).splitlines()[3]
        == "| Ours | " + " | ".join(["+5.00 (1 seed: no interval)"] * 3) + " |"
    )
    assert estimate_record(differences["Ours"]["aligned"]) == {
        "mean": pytest.approx(0.05),
        "half_width": None,
        "ci_low": None,
        "ci_high": None,
        "seeds": 1,
        "agree": None,
    }
    path = tmp_path / "differences.csv"
    write_differences_csv(path, ROWS, payloads, [0])
    with path.open() as f:
        row = next(r for r in csv.DictReader(f) if (r["run"], r["metric"]) == ("ours", "iou@0.4"))
    assert float(row["mean"]) == pytest.approx(0.05)
    assert (row["ci_low"], row["ci_high"], row["seeds"], row["agree"]) == ("", "", "1", "")


def test_counts_are_pluralised():
    assert [plural(1, "epoch"), plural(2, "epoch"), plural(1, "fixed view set"), plural(0, "seed")] == [
        "1 epoch",
        "2 epochs",
        "1 fixed view set",
        "0 seeds",
    ]
