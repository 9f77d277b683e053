"""lightning_vtr.experiments.strategies: the YAML file of named strategies and its validation."""

from __future__ import annotations

import pytest
import yaml

from lightning_vtr.experiments.strategies import (
    STRATEGIES_FILE,
    VARIANTS,
    StrategyFileError,
    StrategyVariant,
    load_variants,
)


def test_the_shipped_file_is_the_registry_and_no_row_depends_on_a_dataset_size():
    assert STRATEGIES_FILE.name == "strategies.yaml" and STRATEGIES_FILE.is_file()
    assert load_variants() == VARIANTS
    rows = yaml.safe_load(STRATEGIES_FILE.read_text())
    assert list(rows) == list(VARIANTS)
    # the paper's Table 1 rows, area-uniform Random, the package's default rule and that rule on prerendered views
    assert list(VARIANTS) == [
        "none", "nature", "random", "random_area", "viat", "mvtn", "paper", "error_guided", "prerendered"
    ]  # fmt: skip
    for name, variant in VARIANTS.items():
        assert variant.title and variant.description, name
        assert "max_samples" not in variant.callback_kwargs, name  # a count would fit one dataset only
        assert variant.max_samples_fraction is None, name


def test_the_shipped_rows_are_distinct_rules_and_their_titles_say_which():
    from lightning_vtr.experiments.training import resolved_strategy

    resolved = [resolved_strategy(name) for name in VARIANTS]
    assert all(resolved.count(r) == 1 for r in resolved)  # no two rows train one rule
    titles = {name: v.title for name, v in VARIANTS.items()}
    assert titles["random"] == "Random (paper: angle-uniform)" and titles["random_area"] == "Random (area-uniform)"
    assert titles["paper"] == "Error-guided (paper's rule)"
    assert titles["error_guided"] == "Error-guided (default rule)"
    assert not any("Ours" in title for title in titles.values())


def _write(tmp_path, text: str):
    path = tmp_path / "rows.yaml"
    path.write_text(text)
    return path


ROW = "  title: T\n  description: d\n"


@pytest.mark.parametrize(
    ("text", "match"),
    [
        (f"mine:\n{ROW}  selector: ours\n", r"row 'mine': unknown selector 'ours'"),
        (f"mine:\n{ROW}  selector: random\n  colour: red\n", r"row 'mine': unknown key\(s\) 'colour'"),
        (f"mine:\n{ROW}  selector: random\n  selector_kwargs: {{modes: area}}\n", r"selector_kwargs: unknown key"),
        (f"mine:\n{ROW}  selector: random\n  callback_kwargs: {{fractions: 0.1}}\n", r"callback_kwargs: unknown key"),
        (f"mine:\n{ROW}  selector: random\n  callback_kwargs: {{max_samples: 34}}\n", "max_samples_fraction"),
        (f"mine:\n{ROW}  selector: random\n  max_samples_fraction: 2\n", r"row 'mine': `max_samples_fraction`"),
        ("mine:\n  title: T\n  selector: random\n", r"row 'mine': missing key\(s\) 'description'"),
        (f"mine:\n{ROW}  selector: null\n  selector_kwargs: {{k: 15}}\n", "needs a selector"),
        (f"mine:\n{ROW}  selector: random\nmine:\n{ROW}  selector: nature\n", r"repeated key\(s\) 'mine'"),
        (f"a:\n{ROW}  selector: random\nb:\n{ROW}  selector: nature\n", r"repeated title\(s\) 'T'"),
        ("- a\n- b\n", "expected a mapping"),
        ("mine: [\n", "not valid YAML"),
    ],
)
def test_invalid_files_are_refused_naming_the_file_and_the_row(tmp_path, text, match):
    path = _write(tmp_path, text)
    with pytest.raises(StrategyFileError, match=match) as error:
        load_variants(path)
    assert str(path) in str(error.value)


def test_a_valid_file_gives_its_rows_in_order(tmp_path):
    path = _write(
        tmp_path,
        "plain:\n  title: Plain\n  description: nothing\n  selector: null\n"
        "area:\n  title: Area\n  description: d\n  selector: random\n  selector_kwargs: {mode: area}\n"
        "  callback_kwargs: {fraction: 0.3}\n  max_samples_fraction: 0.5\n",
    )
    variants = load_variants(path)
    assert list(variants) == ["plain", "area"]
    assert variants["area"] == StrategyVariant(
        "random", {"mode": "area"}, {"fraction": 0.3}, title="Area", description="d", max_samples_fraction=0.5
    )
    assert variants["area"].max_samples(21) == 10 and variants["plain"].max_samples(21) is None


#: ``resolved_strategy("paper")`` before the callback's default became the tempered rule, written out: the
#: report's `paper` row must keep training exactly this.
PAPER_RESOLVED = {
    "selector": "error_guided",
    "selector_kwargs": {
        "k": 30,
        "num_views": 3,
        "score": "paper",
        "threshold": 0.4,
        "min_separation": None,
        "temperature": None,
        "spread": 1 / 6,
        "fallback": "area",
        "relative": False,
    },
    "callback_kwargs": {
        "fraction": 0.05,
        "search_fraction": 0.05,
        "generate_for": "random",
        "min_objects": 1,
        "use_pool": True,
        "pool_capacity": None,
        "pool_refresh": False,
        "pool_prefer_others": True,
        "select_at_start": True,
        "max_samples": None,
        "batch_size": 16,
        "source_view_set": "aligned",
        "seed": 0,
        "log_images": True,
        "progress_bar": True,
    },
}


def _settings(callback) -> dict:
    selector, pool = callback.selector, callback.pool
    return {
        "selector": (type(selector).__name__, selector.score, selector.min_separation, selector.temperature),
        "search": (callback.fraction, callback.search_fraction, callback.generate_for, callback.min_objects),
        "pool": (pool.capacity, pool.prefer_others, pool.refresh),
        "select_at_start": callback.select_at_start,
        "seed": callback.seed,
    }


def test_the_paper_row_resolves_to_what_it_did_before_the_default_changed():
    from lightning_vtr.experiments.training import resolved_strategy

    assert resolved_strategy("paper") == PAPER_RESOLVED


def test_the_paper_row_builds_the_papers_callback_and_error_guided_the_default():
    from lightning_vtr.callback import ErrorGuidedViewAugmentation
    from lightning_vtr.experiments.config import ExperimentConfig
    from lightning_vtr.experiments.training import make_strategy

    config = ExperimentConfig(fraction=0.05, seed=2)
    paper = _settings(ErrorGuidedViewAugmentation.paper(fraction=0.05, seed=2))
    assert paper["selector"] == ("ErrorGuidedSelector", "paper", None, None)
    assert paper["search"] == (0.05, 0.05, "random", 1) and paper["pool"] == (None, True, False)
    assert _settings(make_strategy("paper", config)) == paper
    default = _settings(ErrorGuidedViewAugmentation(fraction=0.05, seed=2))
    assert default["selector"] == ("ErrorGuidedSelector", "visible", 30.0, 10.0)
    assert default["search"] == (0.05, 0.35, "random", 1) and default["pool"] == (None, True, True)
    assert _settings(make_strategy("error_guided", config)) == default


def test_a_selector_argument_given_as_class_path_is_built_and_a_bad_one_refused(tmp_path):
    from lightning_vtr.experiments.config import ExperimentConfig
    from lightning_vtr.experiments.training import make_strategy, resolved_strategy
    from lightning_vtr.selection import ReleasedScore

    score = "{class_path: lightning_vtr.selection.ReleasedScore, init_args: {eps: 0.1}}"
    path = _write(tmp_path, f"soft:\n{ROW}  selector: error_guided\n  selector_kwargs: {{score: {score}}}\n")
    variants = load_variants(path)
    callback = make_strategy("soft", ExperimentConfig(), variants=variants)
    assert callback.selector.score_options == ReleasedScore(eps=0.1)
    assert (callback.selector.min_separation, callback.selector.temperature) == (30.0, 10.0)
    # the resolved form keeps the mapping, so it compares and reads back from results.json
    assert resolved_strategy("soft", variants=variants)["selector_kwargs"]["score"]["init_args"] == {"eps": 0.1}
    bad = _write(
        tmp_path, f"soft:\n{ROW}  selector: error_guided\n  selector_kwargs: {{score: {{class_path: no.Such}}}}\n"
    )
    with pytest.raises(
        StrategyFileError, match=r"row 'soft', selector_kwargs, score must be an importable class path .*'no.Such'"
    ) as error:
        load_variants(bad)
    assert str(bad) in str(error.value)
