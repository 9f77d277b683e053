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
    assert load_variants() == VARIANTS and len(VARIANTS) == 27
    rows = yaml.safe_load(STRATEGIES_FILE.read_text())
    assert list(rows) == list(VARIANTS)
    for name, variant in VARIANTS.items():
        assert variant.title and variant.description, name
        assert "max_samples" not in variant.callback_kwargs, name  # a count would fit one dataset only
    fresh = [name for name, v in VARIANTS.items() if v.max_samples_fraction is not None]
    assert fresh == ["random_fresh", "random_area_fresh", "visible_tau3_search_fresh", "visible_tau10_search_fresh"]
    assert all(VARIANTS[name].max_samples_fraction == 0.2 for name in fresh)


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
