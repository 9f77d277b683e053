"""The registry of view strategies: names -> selector classes, built with keyword arguments."""

from __future__ import annotations

import re

import pytest

import lightning_vtr
from lightning_vtr.selection import (
    SELECTORS,
    ErrorGuidedSelector,
    MVTNSelector,
    NatureSelector,
    RandomSelector,
    VIATSelector,
    ViewSelector,
    make_selector,
)
from lightning_vtr.selection.registry import SELECTOR_PRESETS


def test_names_map_to_the_selector_classes_in_table_order():
    assert {
        "nature": NatureSelector,
        "random": RandomSelector,
        "viat": VIATSelector,
        "mvtn": MVTNSelector,
        "error_guided": ErrorGuidedSelector,
    } == SELECTORS
    assert list(SELECTORS) == ["nature", "random", "viat", "mvtn", "error_guided"]
    assert all(issubclass(cls, ViewSelector) for cls in SELECTORS.values())


@pytest.mark.parametrize(
    ("name", "kwargs", "attributes"),
    [
        ("error_guided", {"k": 60, "num_views": 2}, {"k": 60, "num_views": 2, "sigma": 10.0}),
        ("random", {"num_views": 4, "mode": "area"}, {"num_views": 4, "mode": "area"}),
        ("nature", {"pitch": 20.0, "pitch_jitter": 5.0}, {"pitch": 20.0, "pitch_jitter": 5.0, "num_views": 3}),
        ("viat", {"population": 4, "iterations": 1}, {"population": 4, "iterations": 1}),
        ("mvtn", {"steps": 2, "base_pitch": 10.0}, {"steps": 2, "base_pitch": 10.0}),
    ],
)
def test_make_selector_builds_the_class_with_its_kwargs(name, kwargs, attributes):
    selector = make_selector(name, **kwargs)
    assert type(selector) is SELECTORS[name]
    assert {key: getattr(selector, key) for key in attributes} == attributes


def test_make_selector_without_kwargs_uses_the_defaults():
    assert repr(make_selector("random")) == repr(RandomSelector())


def test_paper_names_the_papers_exact_selector_and_takes_overrides():
    assert SELECTOR_PRESETS == {
        "paper": ("error_guided", {"score": "paper", "min_separation": None, "temperature": None})
    }
    paper = make_selector("paper")
    assert type(paper) is ErrorGuidedSelector
    assert (paper.score, paper.min_separation, paper.temperature, paper.k, paper.num_views) == (
        "paper",
        None,
        None,
        30,
        3,
    )
    assert paper.settings() == ErrorGuidedSelector.paper().settings()
    assert make_selector("paper", k=15).k == 15
    assert make_selector("paper", temperature=3.0).temperature == 3.0
    assert "paper" not in SELECTORS  # a preset, not a row of the paper's Table 1


def test_unknown_name_lists_the_registered_names():
    message = "`name` must be one of 'nature', 'random', 'viat', 'mvtn', 'error_guided', 'paper', got 'ours'"
    with pytest.raises(ValueError, match=f"^{re.escape(message)}$"):
        make_selector("ours")


def test_bad_kwargs_reach_the_selector():
    with pytest.raises(ValueError, match="^`num_views` must be an int >= 1, got 0$"):
        make_selector("random", num_views=0)
    with pytest.raises(TypeError, match="unexpected keyword argument 'k'"):
        make_selector("random", k=30)


def test_the_registry_is_exported_lazily_at_the_top_level():
    assert lightning_vtr.SELECTORS is SELECTORS
    assert "SELECTORS" in lightning_vtr.__all__ and "SELECTORS" in dir(lightning_vtr)
