"""Paper-style robustness table and conversion of trainer.test output."""

from __future__ import annotations

import pytest

from lightning_vtr.experiments.tables import format_robustness_table, results_from_test_output

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
