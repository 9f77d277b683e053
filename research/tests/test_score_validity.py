"""Score validity statistics on hand-built cases whose answers are known."""

from __future__ import annotations

import math

import numpy as np
import pytest

from research.score_validity import (
    category_mean_loss,
    chance_hit_rate,
    format_validity_table,
    mean_with_interval,
    spearman_per_object,
    top_hit_rate,
    validity_rows,
    worst_bins,
)

BINS = 72  # K = 30


@pytest.fixture
def loss():
    """50 objects x 72 bins of distinct losses."""
    return np.random.default_rng(0).uniform(size=(50, BINS))


def test_a_score_equal_to_the_truth_is_perfect(loss):
    rho = spearman_per_object(loss, loss)
    np.testing.assert_allclose(rho, 1.0)
    hits, chance = top_hit_rate(loss, loss)
    np.testing.assert_array_equal(hits, 1.0)  # 8 worst bins (ceil 7.2), all 3 picks inside
    np.testing.assert_allclose(chance, 8 / 72)
    summary = mean_with_interval(rho)
    assert summary.mean == pytest.approx(1.0) and summary.n == 50


def test_a_monotone_transform_of_the_truth_is_as_good(loss):
    np.testing.assert_allclose(spearman_per_object(np.exp(3 * loss), loss), 1.0)


def test_a_reversed_score_is_perfectly_wrong(loss):
    np.testing.assert_allclose(spearman_per_object(-loss, loss), -1.0)
    hits, _ = top_hit_rate(-loss, loss)
    np.testing.assert_array_equal(hits, 0.0)


def test_shuffled_scores_hit_at_the_chance_rate():
    rng = np.random.default_rng(1)
    objects = 4000
    loss = rng.uniform(size=(objects, BINS))
    scores = rng.uniform(size=(objects, BINS))  # unrelated to the loss: a shuffled score
    hits, chance = top_hit_rate(scores, loss)
    p = 8 / 72
    np.testing.assert_allclose(chance, p)
    # 3 picks per object: at most the binomial spread of 3 * objects independent draws (without replacement
    # within an object the spread is a little smaller)
    sd = math.sqrt(p * (1 - p) / (3 * objects))
    assert abs(hits.mean() - p) < 4 * sd
    rho = mean_with_interval(spearman_per_object(scores, loss))
    assert rho.low < 0 < rho.high or abs(rho.mean) < 0.01


def test_ties_get_average_ranks():
    # scores ranks (1.5, 1.5, 3, 4) against (1, 2, 3, 4): 4.5 / sqrt(4.5 * 5)
    rho = spearman_per_object(np.array([[1.0, 1.0, 2.0, 3.0]]), np.array([[1.0, 2.0, 3.0, 4.0]]))
    assert rho[0] == pytest.approx(4.5 / math.sqrt(4.5 * 5.0))
    # a constant row has no ranking
    assert np.isnan(spearman_per_object(np.ones((1, 4)), np.array([[1.0, 2.0, 3.0, 4.0]]))[0])


def test_ties_at_the_cut_are_broken_in_expectation():
    loss = np.array([[0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9]])  # worst 10 %: bin 9
    # a constant score picks 3 of the 10 bins at random: exactly the chance rate 1/10
    hits, chance = top_hit_rate(np.zeros((1, 10)), loss)
    assert hits[0] == pytest.approx(0.1) and chance[0] == pytest.approx(0.1)
    # bins 8 and 9 surely picked, the third among the 8 tied at 0: 1 hit of 3 (bin 9), none expected in the tie
    scores = np.array([[0, 0, 0, 0, 0, 0, 0, 0, 2.0, 3.0]])
    assert top_hit_rate(scores, loss)[0][0] == pytest.approx(1 / 3)
    # truth ties: every bin tied with the worst counts as worst
    np.testing.assert_array_equal(worst_bins(np.array([[0.1, 0.9, 0.9, 0.2]]), 0.25)[0], [False, True, True, False])


def test_category_truth_uses_the_category_mean_map():
    # two objects of one category: object 0 is worst at bin 0, object 1 at bin 1 (much worse): the category's
    # worst bin is 1
    loss = np.zeros((2, 10))
    loss[0, 0], loss[1, 1] = 0.5, 0.9
    np.testing.assert_allclose(category_mean_loss(loss, ["c", "c"])[0, :2], [0.25, 0.45])
    scores = np.zeros((2, 10))
    scores[:, 0] = 1.0  # both objects' scores point at bin 0
    own, _ = top_hit_rate(scores, loss, n=1)
    np.testing.assert_array_equal(own, [1.0, 0.0])
    category, chance = top_hit_rate(scores, loss, n=1, categories=["c", "c"])
    np.testing.assert_array_equal(category, [0.0, 0.0])
    np.testing.assert_allclose(chance, 0.1)


def test_chance_rate_is_the_share_of_worst_bins():
    truth = np.zeros((2, 72), bool)
    truth[0, :8] = True
    truth[1, :3] = True
    np.testing.assert_allclose(chance_hit_rate(truth), [8 / 72, 3 / 72])
    # by enumeration: 3 distinct random bins of 72, mean fraction of hits
    from itertools import combinations

    small = np.zeros(6, bool)
    small[:2] = True
    exact = np.mean([small[list(c)].mean() for c in combinations(range(6), 3)])
    assert chance_hit_rate(small[None])[0] == pytest.approx(exact)


def test_validity_table_rows_and_markdown(loss):
    categories = ["a"] * 25 + ["b"] * 25
    rows = validity_rows({"truth": loss, "reversed": -loss}, loss, categories)
    assert [r["score"] for r in rows] == ["truth", "reversed"]
    assert rows[0]["spearman"].mean == pytest.approx(1.0)
    assert rows[1]["hit_rate"].mean == 0.0
    assert rows[0]["chance"] == pytest.approx(8 / 72)
    table = format_validity_table(rows)
    assert table.splitlines()[0].startswith("| score | Spearman")
    assert "| truth | 1.000 [1.000, 1.000] | 1.000 [1.000, 1.000] | 0.111 |" in table


def test_mismatched_shapes_are_refused():
    with pytest.raises(ValueError, match=r"\(objects, bins\)"):
        spearman_per_object(np.zeros((2, 3)), np.zeros((2, 4)))
