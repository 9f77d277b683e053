"""Paper-style robustness table and conversion of trainer.test output."""

from __future__ import annotations

import math

import pytest

from lightning_vtr.evaluation.tables import (
    VIEW_SET_TITLES,
    format_cell,
    format_robustness_table,
    results_from_test_output,
)
from lightning_vtr.protocol import VIEW_SETS

RESULTS = {
    "Pix2Vox++": {
        "aligned": {"iou@0.4": 0.6463, "fscore": 0.4202},
        "hemispherical": {"iou@0.4": 0.4702, "fscore": 0.2649},
        "spherical": {"iou@0.4": 0.3671, "fscore": 0.1844},
    },
    "Ours": {"aligned": {"iou@0.4": 0.65524}, "spherical": {"iou@0.4": 0.4612, "fscore": 0.2701}},
}


def test_markdown_table():
    expected = (
        "| Method | Aligned mIoU | Aligned F-score | Hemispherical mIoU | Hemispherical F-score "
        "| Spherical mIoU | Spherical F-score |\n"
        "|---|---|---|---|---|---|---|\n"
        "| Pix2Vox++ | 64.63 | 42.02 | 47.02 | 26.49 | 36.71 | 18.44 |\n"
        "| Ours | 65.52 | - | - | - | 46.12 | 27.01 |"
    )
    assert format_robustness_table(RESULTS) == expected


def test_text_table():
    expected = (
        "Method     Aligned mIoU  Spherical mIoU\n"
        "---------  ------------  --------------\n"
        "Pix2Vox++          64.6            36.7\n"
        "Ours               65.5            46.1"
    )
    table = format_robustness_table(
        RESULTS, metric_names=("iou@0.4",), view_sets=("aligned", "spherical"), fmt="text", digits=1
    )
    assert table == expected
    with pytest.raises(ValueError, match="`fmt`.*'html'"):
        format_robustness_table(RESULTS, fmt="html")


def test_results_from_test_output_merges_dataloaders():
    outputs = [
        {"test/aligned/iou@0.4": 0.5, "test/aligned/fscore": 0.25, "test/aligned/chair/iou@0.4": 0.75, "val/loss": 1.0},
        {"test/spherical/iou@0.4": 0.125},
    ]
    assert results_from_test_output(outputs, method="m") == {
        "m": {
            "aligned": {"iou@0.4": 0.5, "fscore": 0.25},
            "aligned/chair": {"iou@0.4": 0.75},
            "spherical": {"iou@0.4": 0.125},
        }
    }


def test_cells_format_mean_and_std_from_numbers():
    assert format_cell(0.6463) == "64.63"
    assert format_cell(0.6, 0.14142) == "60.00 ± 14.14"
    assert format_cell(0.6, 0.0) == "60.00 ± 0.00"
    assert format_cell(0.6, math.nan) == format_cell(0.6, None) == "60.00"
    assert format_cell(None, 0.1) == format_cell(math.nan, 0.1) == "-"
    assert format_cell(0.12345, 0.01, digits=1) == "12.3 ± 1.0"


def test_table_with_spreads_prints_mean_plus_minus_std_where_both_exist():
    means = {"Ours": {"aligned": {"iou@0.4": 0.6, "fscore": 0.3}, "spherical": {"iou@0.4": 0.4}}}
    std = {"Ours": {"aligned": {"iou@0.4": 0.1414, "fscore": math.nan}}}
    table = format_robustness_table(means, std=std, metric_names=("iou@0.4", "fscore"))
    assert table.splitlines()[2] == "| Ours | 60.00 ± 14.14 | 30.00 | - | - | 40.00 | - |"
    # Without spreads, the same table as before they existed.
    assert format_robustness_table(means) == format_robustness_table(means, std=None)
    assert "±" not in format_robustness_table(means)
    text = format_robustness_table(means, std=std, metric_names=("iou@0.4",), view_sets=("aligned",), fmt="text")
    assert text.splitlines() == ["Method   Aligned mIoU", "------  -------------", "Ours    60.00 ± 14.14"]


def test_column_titles_follow_the_protocol_view_sets():
    assert list(VIEW_SET_TITLES) == list(VIEW_SETS)
    header = format_robustness_table({"m": {}}, metric_names=("iou@0.4",)).splitlines()[0]
    assert header == "| Method | Aligned mIoU | Hemispherical mIoU | Spherical mIoU |"
