"""The research strategy rows (research/strategies.yaml): they load beside the shipped rows, build their selectors
and callbacks (the research scores by class_path), and repeat no rule."""

from __future__ import annotations

from pathlib import Path

from lightning_vtr.experiments import training as experiment
from lightning_vtr.experiments.config import ExperimentConfig
from lightning_vtr.experiments.strategies import report_variants
from research.scores import InputScore, MapScore

FILE = Path(__file__).resolve().parents[1] / "strategies.yaml"
VARIANTS = report_variants(FILE)


def test_the_research_rows_follow_the_shipped_rows_and_repeat_no_rule():
    shipped = report_variants()
    assert list(VARIANTS)[: len(shipped)] == list(shipped)
    research = [name for name in VARIANTS if name not in shipped]
    assert len(research) == 20 and {"released", "visible_nms", "input_nms", "map", "map_tau1"} <= set(research)
    resolved = [experiment.resolved_strategy(name, variants=VARIANTS) for name in VARIANTS]
    repeated = [name for name, r in zip(VARIANTS, resolved) if resolved.count(r) > 1]
    assert repeated == []


def test_the_research_score_rows_build_the_research_scores():
    config = ExperimentConfig(fraction=0.1, seed=4)
    row = experiment.make_strategy("map_tau1", config, variants=VARIANTS)
    assert row.selector.score_options == MapScore(objects=2, momentum=0.3)
    assert (row.selector.temperature, row.selector.batched, row.search_fraction) == (1.0, True, 0.35)
    assert experiment.make_strategy("input_nms", config, variants=VARIANTS).selector.score_options == InputScore()


def test_research_variants_build_their_selector_and_callback_settings():
    config = ExperimentConfig(fraction=0.1, seed=4)

    def build(name, **kwargs):
        return experiment.make_strategy(name, config, variants=VARIANTS, **kwargs)

    released = build("released")
    options = released.selector.score_options
    assert (released.selector.score, options.mask, options.reduction) == ("released", "gt", "mean")
    assert (released.pool.refresh, released.pool.prefer_others, released.search_fraction) == (True, False, 0.35)
    assert build("visible").selector.score == "visible" and build("visible").selector.min_separation is None
    nms = build("visible_nms").selector
    assert (nms.score, nms.min_separation, nms.temperature) == ("visible", 30.0, None)
    tau = build("visible_tau").selector
    assert (tau.score, tau.min_separation, tau.temperature) == ("visible", 30.0, 1.0)
    search = build("visible_nms_search")
    assert (search.selector.score, search.selector.min_separation) == ("visible", 30.0)
    assert (search.search_fraction, search.pool.refresh, search.fraction) == (0.35, True, 0.1)
    # The caller's kwargs go over the variant's.
    merged = build("visible_nms_search", selector_kwargs={"k": 15}, callback_kwargs={"search_fraction": 0.5})
    assert (merged.selector.k, merged.selector.score, merged.selector.min_separation) == (15, "visible", 30.0)
    assert (merged.search_fraction, merged.pool.refresh) == (0.5, True)
    # The input-side rows query the model through a context and train each object on its own selection.
    for name, temperature in (("input_nms", None), ("input_tau", 1.0)):
        row = build(name)
        selector = row.selector
        assert (selector.score, selector.min_separation, selector.temperature) == ("input", 30.0, temperature)
        assert selector.needs_context and row.pool is None and row.fraction == 0.1
    # The fresh variants fix their own budget (20 %, latest selection only) over the config's 10 %.
    for name, mode in (("random_fresh", "angle"), ("random_area_fresh", "area")):
        fresh = build(name)
        assert (fresh.selector.mode, fresh.fraction, fresh.max_samples, fresh.pool) == (mode, 0.2, 34, None)
    for name, temperature in (("visible_tau3_search_fresh", 3.0), ("visible_tau10_search_fresh", 10.0)):
        fresh = build(name)
        assert (fresh.selector.score, fresh.selector.min_separation, fresh.selector.temperature) == (
            "visible",
            30.0,
            temperature,
        )
        assert (fresh.fraction, fresh.max_samples, fresh.search_fraction, fresh.pool.refresh) == (0.2, 34, 0.35, True)


def test_the_fresh_rows_cap_scales_with_the_dataset_and_is_34_on_the_embedded_one(tiny_dataset):
    from lightning_vtr.data.format import load_metadata

    # the embedded dataset: 10 categories x 17 training objects; 20 % of them is the former fixed cap of 34
    assert experiment.training_objects(ExperimentConfig()) == 170
    assert VARIANTS["random_fresh"].max_samples(170) == 34
    assert experiment.make_strategy("random_fresh", ExperimentConfig(), variants=VARIANTS).max_samples == 34
    # another dataset, another cap: 20 % of its own training objects
    tiny = ExperimentConfig(data=str(tiny_dataset))
    count = sum(info["split"] == "train" for info in load_metadata(tiny_dataset)["objects"].values())
    assert experiment.training_objects(tiny) == count == 21
    assert (
        experiment.make_strategy("visible_tau3_search_fresh", tiny, variants=VARIANTS).max_samples
        == round(0.2 * 21)
        == 4
    )
    # a given count or an explicit max_samples wins; rows without a cap have none
    assert experiment.make_strategy("random_fresh", tiny, train_objects=1000, variants=VARIANTS).max_samples == 200
    assert (
        experiment.make_strategy(
            "random_fresh", tiny, callback_kwargs={"max_samples": 7}, variants=VARIANTS
        ).max_samples
        == 7
    )
    assert experiment.make_strategy("random", tiny, variants=VARIANTS).max_samples is None
    assert (
        experiment.resolved_strategy("random_fresh", variants=VARIANTS)["callback_kwargs"]["max_samples_fraction"]
        == 0.2
    )
