"""Every selector states its effective settings: ``settings()``, ``repr``, constant defaults, the named rules."""

from __future__ import annotations

import inspect
import json
import math

import pytest
import torch

from lightning_vtr.selection import (
    SCORES,
    ErrorGuidedSelector,
    MVTNSelector,
    NatureSelector,
    RandomSelector,
    ReleasedScore,
    VIATSelector,
    VisibleScore,
)

# one selector per class with settings other than the defaults
NON_DEFAULT = [
    RandomSelector(num_views=2, mode="angle", yaw_range=(-90, 90), pitch_range=(0, 45)),
    NatureSelector(num_views=4, pitch={"lamp": 20.0}, pitch_jitter=5.0, yaw_range=(-10, 10)),
    VIATSelector(num_components=2, population=4, lr=0.2, iterations=1, entropy_weight=0.0, model_batch_size=8),
    MVTNSelector(base_yaw=[0.0, 90.0], base_pitch=10.0, max_yaw_offset=45.0, steps=1, lr=0.1, seed=3),
    ErrorGuidedSelector(
        score=ReleasedScore(eps=0.1), k=60, num_views=2, threshold=0.3, min_separation=None, spread=0.1, relative=True
    ),
    ErrorGuidedSelector(score=VisibleScore(mode="soft"), temperature=1.0, fallback="angle"),
]


def _rebuild(selector):
    """The selector built again from its settings alone."""
    settings = dict(selector.settings())
    if isinstance(selector, ErrorGuidedSelector):
        score = SCORES[settings.pop("score")]
        options = {name: settings.pop(name) for name in selector.score_options.settings()}
        settings["score"] = score(**options)
    return type(selector)(**settings)


@pytest.mark.parametrize("selector", NON_DEFAULT, ids=lambda s: type(s).__name__)
def test_settings_are_complete_json_and_rebuild_the_same_selector(selector):
    settings = selector.settings()
    assert json.loads(json.dumps(settings)) == settings  # plain JSON values, no tuples or tensors
    assert type(selector).__name__ not in json.dumps(settings)
    rebuilt = _rebuild(selector)
    assert rebuilt.settings() == settings
    assert repr(rebuilt) == repr(selector)


@pytest.mark.parametrize("selector", NON_DEFAULT, ids=lambda s: type(s).__name__)
def test_repr_prints_every_effective_setting(selector):
    text = repr(selector)
    assert text.startswith(f"{type(selector).__name__}(") and text.endswith(")")
    for name, value in selector.settings().items():
        if name == "score":
            assert f"score={type(selector.score_options).__name__}(" in text
        else:
            assert f"{name}={value!r}" in text, name


def test_mvtn_evenly_spaced_preset_spreads_the_base_yaws():
    selector = MVTNSelector.evenly_spaced(4, steps=2)
    assert selector.settings()["base_yaw"] == [0.0, 90.0, 180.0, 270.0]
    assert selector.settings()["max_yaw_offset"] == 45.0
    assert selector.num_views == 4 and selector.steps == 2
    # the 3-view preset is the constructor's defaults
    assert MVTNSelector.evenly_spaced(3).settings() == MVTNSelector().settings()


def _shown(default):
    """How an Args entry states a default: ``"area"``, ``3``, ``None``, ``(-180.0, 180.0)``."""
    return f"``{json.dumps(default) if isinstance(default, str) else 'None' if default is None else default}``"


@pytest.mark.parametrize(
    "cls",
    [RandomSelector, NatureSelector, VIATSelector, MVTNSelector, ErrorGuidedSelector, *SCORES.values()],
    ids=lambda c: c.__name__,
)
def test_every_default_is_a_constant_the_docstring_states(cls):
    args = (inspect.getdoc(cls) or "").split("Args:\n")[1].split("\n\n")[0]
    entries = {}
    for line in args.splitlines():
        if not line.startswith("        "):
            name, _, text = line.strip().partition(":")
            entries[name] = text
        else:
            entries[name] += " " + line.strip()
    for name, parameter in inspect.signature(cls).parameters.items():
        assert name in entries, f"{cls.__name__} does not document `{name}`"
        assert f"{_shown(parameter.default)} (default" in entries[name], (cls.__name__, name, entries[name])


def test_the_spread_is_a_fraction_of_the_bin_interval():
    # the default spread is a constant; the draws' sigma in degrees is the paper's K / 6 at every K
    assert ErrorGuidedSelector(k=60).spread == ErrorGuidedSelector(k=15).spread == 1 / 6
    assert (ErrorGuidedSelector(k=60).sigma, ErrorGuidedSelector(k=15).sigma, ErrorGuidedSelector().sigma) == (
        10.0,
        2.5,
        5.0,
    )


def test_no_arguments_is_the_measured_default_rule_and_paper_is_one_call_away():
    default = ErrorGuidedSelector()
    assert default.settings() == ErrorGuidedSelector.default().settings()
    assert (default.score, default.min_separation, default.temperature) == ("visible", 30.0, 10.0)
    assert ErrorGuidedSelector(k=15).settings() == {**default.settings(), "k": 15}
    paper = ErrorGuidedSelector.paper()
    assert (paper.score, paper.min_separation, paper.temperature) == ("paper", None, None)
    assert ErrorGuidedSelector.paper(k=15).settings() == {**paper.settings(), "k": 15}
    assert {**paper.settings(), "score": "visible"} != default.settings()


def test_both_rules_select_as_their_spelled_out_settings():
    # the named rules are exactly the arguments they name, for the same inputs and generator seed
    g = torch.Generator().manual_seed(0)
    predicted = torch.rand(3, 10, 10, 10, generator=g)
    target = (torch.rand(3, 10, 10, 10, generator=g) > 0.6).float()
    cats = ["a", "a", "b"]
    pairs = [
        (ErrorGuidedSelector.default(), ErrorGuidedSelector(score="visible", min_separation=30.0, temperature=10.0)),
        (ErrorGuidedSelector.paper(), ErrorGuidedSelector(score="paper", min_separation=None, temperature=None)),
    ]
    for named, spelled in pairs:
        one = named.select(predicted, target, cats, generator=torch.Generator().manual_seed(1))
        two = spelled.select(predicted, target, cats, generator=torch.Generator().manual_seed(1))
        assert torch.equal(one, two)
    # and the paper's rule keeps the hard top 3: its bins are the three best-scoring ones
    paper = ErrorGuidedSelector.paper()
    paper.select(predicted, target, cats, generator=torch.Generator().manual_seed(1))
    scores = paper.last_scores
    chosen = scores.gather(1, paper.last_bins)
    assert torch.equal(chosen.sort(1, descending=True).values, scores.topk(3, dim=1).values)


def _mean_abs_sin_pitch(selector, n=20000):
    volumes = torch.zeros(n, 2, 2, 2)
    views = selector.select(volumes, volumes, ["c"] * n, generator=torch.Generator().manual_seed(0))
    return float(torch.sin(torch.deg2rad(views[..., 1].double())).abs().mean())


def test_random_is_area_uniform_by_default_and_angle_uniform_one_argument_away():
    # uniform on the sphere: |sin(pitch)| is uniform on [0, 1], mean 1/2; uniform pitch: mean 2/pi = 0.637.
    # 60000 draws: standard error about 0.0012 for both
    assert RandomSelector().mode == "area"
    assert abs(_mean_abs_sin_pitch(RandomSelector()) - 0.5) < 0.006
    assert abs(_mean_abs_sin_pitch(RandomSelector(mode="angle")) - 2 / math.pi) < 0.006
