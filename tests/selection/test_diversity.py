"""Bin choice: solid angles, non-maximum suppression and tempered sampling on hand-built scores."""

from __future__ import annotations

import math

import pytest
import torch

from lightning_vtr.geometry import angular_distance, candidate_viewpoints
from lightning_vtr.selection.diversity import bin_solid_angles, choose_bins, suppression_matrix
from lightning_vtr.selection.projection import top_bins

CENTRES = candidate_viewpoints(30).to(torch.float64)


def _bin(yaw: float, pitch: float) -> int:
    return int(((CENTRES - torch.tensor([yaw, pitch], dtype=torch.float64)).abs().sum(1)).argmin())


def test_solid_angles_cover_the_sphere_and_shrink_towards_the_poles():
    area = bin_solid_angles(30)
    assert area.shape == (72,)
    assert area.sum().item() == pytest.approx(4 * math.pi)
    # pitch band [0, 30]: radians(30) * sin(30 deg) = pi/12
    assert area[_bin(15, 15)].item() == pytest.approx(math.pi / 12)
    assert area[_bin(15, 75)].item() == pytest.approx(math.radians(30) * (1 - math.sin(math.radians(60))))


def test_suppression_forbids_the_antipode_and_neighbours_within_the_angle():
    strict = suppression_matrix(30, 0.0)
    i, anti = _bin(-165, 15), _bin(15, -15)
    assert strict[i, i] and strict[i, anti]
    assert strict[i].sum() == 2  # itself and its antipode only
    wide = suppression_matrix(30, 30.0)
    assert wide[i, _bin(-135, 15)] and wide[i, _bin(-165, 45)]  # neighbours 30 degrees away
    assert wide[i, _bin(45, -15)]  # 30 degrees from the antipode
    assert not wide[i, _bin(-75, 15)]  # 90 degrees away
    assert torch.equal(wide, wide.t())


def test_hard_rule_without_options_equals_top_bins():
    scores = torch.rand(6, 72, generator=torch.Generator().manual_seed(3))
    scores[0, :10] = 1.0  # exact ties go in the same random order
    a = choose_bins(scores, 3, generator=torch.Generator().manual_seed(7))
    b = top_bins(scores, 3, generator=torch.Generator().manual_seed(7))
    assert torch.equal(a, b)


def test_nms_skips_the_antipode_of_the_best_view():
    # The error a paper-literal score sees from a view and from its antipode is the same silhouette.
    scores = torch.zeros(1, 72)
    best, anti, other = _bin(-165, 15), _bin(15, -15), _bin(105, 45)
    scores[0, best], scores[0, anti], scores[0, other] = 10.0, 9.0, 1.0
    assert choose_bins(scores, 2).tolist() == [[best, anti]]
    assert choose_bins(scores, 2, min_separation=0.0).tolist() == [[best, other]]


def test_nms_keeps_chosen_bins_apart():
    scores = torch.rand(20, 72, generator=torch.Generator().manual_seed(0))
    picks = choose_bins(scores, 3, min_separation=45.0, generator=torch.Generator().manual_seed(0))
    d = angular_distance(CENTRES[picks][:, :, None], CENTRES[picks][:, None, :])
    off = ~torch.eye(3, dtype=torch.bool)
    assert (d[:, off] > 45.0).all() and (d[:, off] < 135.0).all()


def test_nms_falls_back_when_too_few_bins_survive():
    scores = torch.arange(72, dtype=torch.float32)[None]
    picks = choose_bins(scores, 3, min_separation=180.0)  # the first pick forbids everything
    assert picks[0, 0].item() == 71 and len(set(picks[0].tolist())) == 3
    assert picks[0, 1:].tolist() == [70, 69]  # then the best remaining bins


def test_low_temperature_recovers_the_hard_top_n():
    scores = torch.rand(50, 72, generator=torch.Generator().manual_seed(1)) + 0.1
    hot = choose_bins(scores, 3, temperature=1e-4, generator=torch.Generator().manual_seed(2))
    hard = choose_bins(scores, 3, generator=torch.Generator().manual_seed(2))
    assert torch.equal(hot, hard)


def test_high_temperature_draws_bins_in_proportion_to_area():
    scores = torch.rand(1, 72, generator=torch.Generator().manual_seed(1)).expand(40000, -1).contiguous()
    picks = choose_bins(scores, 1, temperature=1e6, generator=torch.Generator().manual_seed(4))
    freq = torch.bincount(picks[:, 0], minlength=72).double() / picks.shape[0]
    expected = bin_solid_angles(30) / (4 * math.pi)
    assert (freq - expected).abs().max().item() < 0.004  # ~4 binomial standard errors of the largest bin
    polar, equatorial = freq[_bin(15, 75)].item(), freq[_bin(15, 15)].item()
    assert polar < 0.4 * equatorial  # area-uniform, not angle-uniform


def test_temperature_one_samples_in_proportion_to_score_times_area():
    scores = torch.zeros(1, 72)
    a, b = _bin(15, 15), _bin(-15, 15)  # same area
    scores[0, a], scores[0, b] = 3.0, 1.0
    picks = choose_bins(
        scores.expand(20000, -1).contiguous(), 1, temperature=1.0, generator=torch.Generator().manual_seed(5)
    )
    share = (picks[:, 0] == a).double().mean().item()
    assert share == pytest.approx(0.75, abs=0.015)
    assert set(picks[:, 0].tolist()) == {a, b}  # unscored bins never drawn while scored ones remain


def test_bad_arguments_name_themselves():
    with pytest.raises(ValueError, match=r"`scores` must have shape \(B, 72\)"):
        choose_bins(torch.zeros(1, 10))
    with pytest.raises(ValueError, match="`n` must be an int in"):
        choose_bins(torch.zeros(1, 72), 0)
    with pytest.raises(ValueError, match="`temperature` must be a number >= 0"):
        choose_bins(torch.zeros(1, 72), temperature=-1.0)
    with pytest.raises(TypeError, match="`min_separation` must be a number"):
        suppression_matrix(30, "wide")
