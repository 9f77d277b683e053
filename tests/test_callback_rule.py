"""The resume warning for another rule: only the effective differences, one per line."""

from __future__ import annotations

from lightning_vtr.augmentation.rule import rule_differences, rule_mismatch
from lightning_vtr.callback import ErrorGuidedViewAugmentation
from lightning_vtr.selection import RandomSelector


def test_settings_that_mean_the_same_are_no_difference():
    old = {"selector": "S", "selector_settings": {"mask": None, "mode": "binary"}, "pool": None}
    new = {"selector": "S", "selector_settings": {"mask": "none", "mode": "binary", "eps": 0.0, "relative": False}}
    # None and "none" are one value; beside a setting the checkpoint lacks, so are 0.0 and False; pool: absent = None
    assert rule_differences(old, new) == []
    assert rule_mismatch(old, new) is None
    new["selector_settings"]["reduction"] = "sum"  # a setting the checkpoint lacks, not an "off" value: a difference
    assert rule_differences(old, new) == ["S.reduction: not set in the checkpoint, 'sum' now"]


def test_the_default_rule_against_the_papers_lists_each_real_difference_on_its_own_line():
    default, paper = ErrorGuidedViewAugmentation.default(), ErrorGuidedViewAugmentation.paper()
    lines = rule_mismatch(default.rule(), paper.rule()).splitlines()
    assert lines[0] == "ErrorGuidedViewAugmentation: the checkpoint's state belongs to another rule, which differs in:"
    assert [line for line in lines if line.startswith("  ")] == [
        "  ErrorGuidedSelector.score: 'visible' in the checkpoint, 'paper' now",
        "  ErrorGuidedSelector.min_separation: 30.0 in the checkpoint, None now",
        "  ErrorGuidedSelector.temperature: 10.0 in the checkpoint, None now",
        "  ErrorGuidedSelector.reduction: not set in the checkpoint, 'sum' now",
        "  search_fraction: 0.35 in the checkpoint, 0.05 now",
        "  pool.refresh: True in the checkpoint, False now",
    ]
    assert lines[-2].startswith("Starting this callback's state fresh (empty pool, no history); the datamodule")
    assert len(lines) == 6 + 3 and max(map(len, lines)) <= 120


def test_another_selector_class_is_one_difference_not_each_of_its_settings():
    default = ErrorGuidedViewAugmentation.default()
    other = ErrorGuidedViewAugmentation(RandomSelector())
    differences = rule_differences(default.rule(), other.rule())
    assert len(differences) == 2
    assert differences[0].startswith("selector: ErrorGuidedSelector(score='visible', ")
    assert differences[0].endswith(
        " in the checkpoint, RandomSelector(num_views=3, mode='area', yaw_range=[-180.0, 180.0], "
        "pitch_range=[-90.0, 90.0]) now"
    )
    assert differences[1].startswith("pool: {'capacity': None, ") and differences[1].endswith(
        " in the checkpoint, None now"
    )
