"""Confidence intervals, paired differences and view-distribution figures against hand-computed values."""

from __future__ import annotations

import math

import pytest
import torch

from lightning_vtr.experiments.statistics import (
    antipodal_share,
    mean_estimate,
    paired_difference,
    pitch_histogram,
    triplet_spread,
)


def test_mean_estimate_uses_student_t():
    e = mean_estimate([1.0, 2.0, 3.0])
    assert e.mean == 2.0 and e.n == 3 and e.agree == 3
    assert e.half_width == pytest.approx(4.302652729911275 * 1.0 / math.sqrt(3))  # t(0.975, 2) * s / sqrt(n)
    assert (e.low, e.high) == pytest.approx((2.0 - e.half_width, 2.0 + e.half_width))
    assert not e.excludes_zero  # [-0.48, 4.48]
    assert mean_estimate([1.0, 1.1, 0.9]).excludes_zero


def test_one_value_has_no_interval():
    e = mean_estimate([0.5])
    assert e.mean == 0.5 and math.isnan(e.half_width) and not e.excludes_zero


def test_paired_difference_uses_shared_seeds_and_counts_sign_agreement():
    e = paired_difference({0: 0.5, 1: 0.4, 2: 0.3}, {0: 0.4, 1: 0.45, 2: 0.1, 7: 1.0})
    assert e.n == 3
    assert e.mean == pytest.approx((0.1 - 0.05 + 0.2) / 3)
    assert e.agree == 2
    with pytest.raises(ValueError, match="must share a seed"):
        paired_difference({0: 1.0}, {1: 1.0})


def test_pitch_histogram_bands():
    vp = torch.tensor([[0.0, -90.0], [10.0, -60.0], [0.0, 0.0], [0.0, 45.0], [0.0, 90.0]])
    assert pitch_histogram(vp).tolist() == [0.2, 0.2, 0.0, 0.2, 0.2, 0.2]
    assert pitch_histogram(vp, edges=(-90, 0, 90)).tolist() == [0.4, 0.6]


def test_antipodal_share_and_spread():
    sets = torch.tensor(
        [
            [[0.0, 0.0], [180.0, 0.0], [90.0, 0.0]],  # an antipodal pair; distances 180, 90, 90
            [[0.0, 0.0], [10.0, 0.0], [20.0, 0.0]],  # distances 10, 20, 10
            [[0.0, 80.0], [0.0, -90.0], [90.0, 0.0]],  # 170 degrees apart: within the default 15
        ]
    )
    assert antipodal_share(sets) == pytest.approx(2 / 3)
    assert antipodal_share(sets, tolerance=5.0) == pytest.approx(1 / 3)
    spread_first_two = triplet_spread(sets[:2])
    assert spread_first_two == pytest.approx((120.0 + 40.0 / 3) / 2)
