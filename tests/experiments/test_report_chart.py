"""The report's picture: the paired-difference panels show the paired differences, with their CIs."""

from __future__ import annotations

import pytest
from matplotlib.container import BarContainer

from lightning_vtr.experiments.report_files import write_chart
from lightning_vtr.protocol import VIEW_SETS

# three seeds; "ours" beats "none" by 2, 4, 6 points on every view set and "random" by 1, 1, 1
_IOU = {"none": [0.40, 0.30, 0.50], "random": [0.41, 0.33, 0.55], "ours": [0.42, 0.34, 0.56]}


def _payloads() -> dict[str, dict[int, dict]]:
    return {
        run: {seed: {"results": {v: {"iou@0.4": value} for v in VIEW_SETS}} for seed, value in enumerate(values)}
        for run, values in _IOU.items()
    }


def _bars(ax) -> list[float]:
    return [patch.get_height() for patch in ax.patches]


def test_the_difference_panels_hold_each_rows_paired_difference_per_view_set(tmp_path):
    rows = {"None-VTR": "none", "Random": "random", "Ours": "ours"}
    fig = write_chart(tmp_path / "report.png", rows, _payloads(), [0, 1, 2], {})
    assert (tmp_path / "report.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    by_title = {ax.get_title(): ax for ax in fig.axes}
    to_none = by_title["Paired difference to None-VTR (95 % CI over seeds)"]
    to_random = by_title["Paired difference to Random (95 % CI over seeds)"]
    # bars grouped by row (every row but the baseline), a bar per view set, in points
    assert _bars(to_none) == pytest.approx([3.0] * 3 + [4.0] * 3)  # Random - none: 1, 3, 5; Ours - none: 2, 4, 6
    assert _bars(to_random) == pytest.approx([-3.0] * 3 + [1.0] * 3)  # none - Random; Ours - Random: 1, 1, 1
    # Ours - none is 2, 4, 6 points: a CI over 3 seeds of 4 +- t(0.975, 2) * 2 / sqrt(3) = 4 +- 4.97
    bars = [c for c in to_none.containers if isinstance(c, BarContainer)]
    ours = bars[1].errorbar.lines[2][0].get_segments()  # Ours' error bars, one per view set
    assert [segment[1][1] - segment[0][1] for segment in ours] == pytest.approx([2 * 4.302653 * 2 / 3**0.5] * 3)
    assert [(segment[0][1] + segment[1][1]) / 2 for segment in ours] == pytest.approx([4.0] * 3)
    # the absolute panel keeps the means
    absolute = by_title["Reconstruction IoU per test view set (mean, 95 % CI over 3 seeds)"]
    assert _bars(absolute)[:3] == pytest.approx([40.0] * 3)
