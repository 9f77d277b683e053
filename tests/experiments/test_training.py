"""lightning_vtr.experiments.training: the registries, the fine-tuning learning-rate schedule, the result cache."""

from __future__ import annotations

import json
import math
import time

import lightning as L
import pytest
import torch

import lightning_vtr.experiments.training as experiment
from lightning_vtr.experiments.training import CosineFineTuning, ExperimentConfig, run_strategy


class _LinearModel(L.LightningModule):
    """Two parameter groups with different rates and a MultiStepLR that would halve them at epoch 1."""

    def __init__(self) -> None:
        super().__init__()
        self.a = torch.nn.Linear(2, 1)
        self.b = torch.nn.Linear(2, 1)
        self.seen: list[tuple[int, float, float]] = []

    def training_step(self, batch, batch_idx):
        group_a, group_b = self.trainer.optimizers[0].param_groups
        self.seen.append((self.current_epoch, group_a["lr"], group_b["lr"]))
        return (self.a(batch[0]) + self.b(batch[0])).pow(2).mean()

    def train_dataloader(self):
        return torch.utils.data.DataLoader(torch.utils.data.TensorDataset(torch.ones(4, 2)), batch_size=2)

    def configure_optimizers(self):
        groups = [{"params": self.a.parameters(), "lr": 0.1}, {"params": self.b.parameters(), "lr": 0.01}]
        optimizer = torch.optim.Adam(groups)
        return [optimizer], [torch.optim.lr_scheduler.MultiStepLR(optimizer, milestones=[1], gamma=0.5)]


def _trainer(tmp_path, epochs: int) -> L.Trainer:
    return L.Trainer(
        max_epochs=epochs,
        callbacks=[CosineFineTuning(4)],
        default_root_dir=str(tmp_path),
        logger=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        accelerator="cpu",
    )


def _expected(epoch: int) -> float:
    return 0.5 * (1 + math.cos(math.pi * epoch / 4))


def test_cosine_fine_tuning_anneals_every_group_from_its_own_rate(tmp_path):
    model = _LinearModel()
    _trainer(tmp_path, 4).fit(model)
    by_epoch = {epoch: (a, b) for epoch, a, b in model.seen}
    assert sorted(by_epoch) == [0, 1, 2, 3]
    for epoch, (a, b) in by_epoch.items():
        # The model's MultiStepLR milestone at epoch 1 is overridden: the curve is the cosine alone.
        assert a == pytest.approx(0.1 * _expected(epoch)) and b == pytest.approx(0.01 * _expected(epoch))
    assert by_epoch[2][0] == pytest.approx(0.05)


def test_cosine_fine_tuning_resumes_on_the_same_curve(tmp_path):
    first = _LinearModel()
    trainer = _trainer(tmp_path, 2)
    trainer.fit(first)
    trainer.save_checkpoint(tmp_path / "mid.ckpt")
    resumed = _LinearModel()
    _trainer(tmp_path, 4).fit(resumed, ckpt_path=str(tmp_path / "mid.ckpt"))
    assert {e for e, _, _ in resumed.seen} == {2, 3}
    for epoch, a, b in resumed.seen:
        assert a == pytest.approx(0.1 * _expected(epoch)) and b == pytest.approx(0.01 * _expected(epoch))


def test_cosine_fine_tuning_rejects_zero_epochs():
    with pytest.raises(ValueError, match="epochs"):
        CosineFineTuning(0)


@pytest.mark.parametrize(("schedule", "expected"), [("cosine", 1), ("constant", 0)])
def test_run_strategy_uses_the_configured_schedule(tmp_path, monkeypatch, schedule, expected):
    seen = {}

    class Stop(Exception):
        pass

    def fake_fit(self, *args, **kwargs):
        seen["callbacks"] = [c for c in self.callbacks if isinstance(c, CosineFineTuning)]
        raise Stop

    model = experiment.make_model(ExperimentConfig(preset="tiny"))
    torch.save({"state_dict": model.state_dict()}, tmp_path / "pre.ckpt")
    monkeypatch.setattr(L.Trainer, "fit", fake_fit)
    monkeypatch.setattr(experiment, "make_datamodule", lambda config, model: None)
    config = ExperimentConfig(out=str(tmp_path / "runs"), finetune_epochs=7, finetune_lr=schedule, accelerator="cpu")
    with pytest.raises(Stop):
        run_strategy("none", config, tmp_path / "pre.ckpt")
    assert len(seen["callbacks"]) == expected
    if expected:
        assert seen["callbacks"][0].epochs == 7


def test_config_rejects_an_unknown_schedule():
    with pytest.raises(ValueError, match="finetune_lr.*'step'"):
        ExperimentConfig(finetune_lr="step")


def test_run_strategy_refuses_a_cached_result_of_another_configuration(tmp_path):
    config = ExperimentConfig(out=str(tmp_path), finetune_epochs=3)
    payload = {
        "strategy": "none",
        "config": experiment._comparable(config),
        "train_seconds": 1.0,
        "results": {"aligned": {"iou@0.4": 0.5}},
    }
    (tmp_path / "none").mkdir()
    (tmp_path / "none" / "results.json").write_text(json.dumps(payload))
    missing = tmp_path / "never-read.ckpt"
    # Same experiment (another device count only): the cache is the answer, nothing is loaded.
    assert run_strategy("none", ExperimentConfig(out=str(tmp_path), finetune_epochs=3, devices=2), missing) == payload
    with pytest.raises(ValueError, match=r"results.json was written with another configuration .*'finetune_lr'"):
        run_strategy("none", ExperimentConfig(out=str(tmp_path), finetune_epochs=3, finetune_lr="constant"), missing)
    # A cache written before a field existed measured that field's default: still the answer, not otherwise.
    older = {**payload, "config": {k: v for k, v in payload["config"].items() if k != "recipe"}}
    (tmp_path / "none" / "results.json").write_text(json.dumps(older))
    assert run_strategy("none", ExperimentConfig(out=str(tmp_path), finetune_epochs=3), missing) == older
    with pytest.raises(ValueError, match=r"another configuration .*'recipe'"):
        run_strategy("none", ExperimentConfig(out=str(tmp_path), finetune_epochs=3, recipe="pix2vox"), missing)


def test_models_registry_builds_each_model_class_with_its_preset():
    from lightning_vtr.models.lrgt import LRGT
    from lightning_vtr.models.pix2vox import Pix2VoxPlusPlus

    assert {"pix2vox": Pix2VoxPlusPlus, "lrgt": LRGT} == experiment.MODELS
    for name, cls in experiment.MODELS.items():
        model = experiment.make_model(ExperimentConfig(model=name, preset="tiny"))
        assert type(model) is cls
    with pytest.raises(ValueError, match="`model` must be pix2vox, lrgt or a class path module.Class, got 'unet'"):
        experiment.make_model(ExperimentConfig(model="unet"))
    assert not hasattr(experiment, "MODEL_CLASSES")  # removed: the names are the keys of MODELS


def test_fine_tuning_model_takes_no_weight_files_and_bce_refined_unless_asked(monkeypatch):
    from lightning_vtr.models.pix2vox import Pix2VoxPlusPlus

    built = []

    class Recording(Pix2VoxPlusPlus):
        def __init__(self, preset, **kwargs):
            built.append(kwargs)
            super().__init__(preset=preset, **{k: v for k, v in kwargs.items() if k != "backbone_weights"})

    monkeypatch.setitem(experiment.MODELS, "pix2vox", Recording)
    config = ExperimentConfig(preset="tiny", model_kwargs={"backbone_weights": "/weights/resnet50.pth", "lr": 0.01})
    experiment.make_model(config)
    assert built[-1] == {"backbone_weights": "/weights/resnet50.pth", "lr": 0.01}  # pretraining reads the file
    model = experiment.make_model(config, fine_tuning=True)
    # the pretrained checkpoint holds the backbone; VTR fine-tunes with BCE(refined)
    assert built[-1] == {"lr": 0.01, "two_stage_loss": False} and model.hparams.two_stage_loss is False
    asked = ExperimentConfig(preset="tiny", model_kwargs={"two_stage_loss": True})
    assert experiment.make_model(asked, fine_tuning=True).hparams.two_stage_loss is True


def test_recipe_reference_takes_the_models_published_recipe():
    from lightning_vtr.data import IMAGE_RECIPES
    from lightning_vtr.models.pix2vox import Pix2VoxPlusPlus

    model = Pix2VoxPlusPlus(preset="tiny")
    assert Pix2VoxPlusPlus.image_recipe == "pix2vox"
    dm = experiment.make_datamodule(ExperimentConfig(recipe="reference"), model)
    assert dm.recipe == IMAGE_RECIPES["pix2vox"]
    assert experiment.make_datamodule(ExperimentConfig(), model).recipe == IMAGE_RECIPES["plain"]
    with pytest.raises(ValueError, match="`recipe` must be one of 'reference', 'plain'"):
        ExperimentConfig(recipe="imagenet")


def test_make_strategy_builds_every_registered_selector():
    from lightning_vtr.callback import ErrorGuidedViewAugmentation
    from lightning_vtr.selection import SELECTORS

    config = ExperimentConfig(fraction=0.2, seed=3)
    assert experiment.STRATEGIES == ("none", "nature", "random", "viat", "mvtn", "paper")
    assert experiment.make_strategy("none", config) is None
    for name, cls in SELECTORS.items():
        callback = experiment.make_strategy(name, config)
        assert isinstance(callback, ErrorGuidedViewAugmentation) and type(callback.selector) is cls, name
        assert (callback.fraction, callback.seed) == (0.2, 3)
    with pytest.raises(
        ValueError,
        match="`name` must be one of 'none', 'nature', 'random', 'random_area', .*'paper', 'error_guided', "
        "'prerendered', got 'ours'",
    ):
        experiment.make_strategy("ours", config)


def test_make_strategy_passes_selector_and_callback_arguments():
    from lightning_vtr.selection import ErrorGuidedSelector, VIATSelector

    config = ExperimentConfig(fraction=0.2, seed=3)
    callback = experiment.make_strategy(
        "paper", config, selector_kwargs={"k": 15}, callback_kwargs={"use_pool": False, "fraction": 0.5}
    )
    assert isinstance(callback.selector, ErrorGuidedSelector)
    assert callback.selector.k == 15 and callback.selector.sigma == 2.5  # K / 6 degrees
    assert callback.pool is None  # the pool ablation
    assert callback.fraction == 0.5 and callback.seed == 3  # callback_kwargs override the config
    viat = experiment.make_strategy("viat", config, selector_kwargs={"population": 4, "iterations": 2})
    assert isinstance(viat.selector, VIATSelector) and (viat.selector.population, viat.selector.iterations) == (4, 2)
    assert viat.fraction == 0.2


def test_make_datamodule_takes_the_model_view_count_or_num_views(tmp_path):
    model = experiment.make_model(ExperimentConfig())
    config = ExperimentConfig(batch_size=4, seed=5)
    dm = experiment.make_datamodule(config, model)
    assert (dm.num_views, dm.batch_size, dm.seed) == (model.num_views, 4, 5)
    assert experiment.make_datamodule(config, model, num_views=1).num_views == 1
    with pytest.raises(TypeError, match="n_views"):  # the old name is gone
        experiment.make_datamodule(config, model, n_views=2)


def test_config_reads_a_device_count_from_a_command_line():
    assert ExperimentConfig(devices="2").devices == 2
    assert ExperimentConfig(devices="auto").devices == "auto"
    assert ExperimentConfig(devices="0,1").devices == "0,1"


def test_cosine_fine_tuning_rejects_a_non_integer_epoch_count():
    with pytest.raises(TypeError, match="`epochs` must be an int, got float 2.5"):
        CosineFineTuning(2.5)


def _callback_settings(callback) -> dict:
    """What a strategy callback does, as comparable values."""
    pool = callback.pool
    return {
        "selector": repr(callback.selector),
        "fraction": callback.fraction,
        "search_fraction": callback.search_fraction,
        "generate_for": callback.generate_for,
        "pool": None if pool is None else (pool.capacity, pool.prefer_others),
        "pool_refresh": None if pool is None else pool.refresh,
        "select_at_start": callback.select_at_start,
    }


def test_variants_registry_holds_the_table_1_strategies_and_the_named_variants():
    assert list(experiment.VARIANTS)[:2] == ["none", "nature"]
    assert set(experiment.STRATEGIES) <= set(experiment.VARIANTS)
    assert set(experiment.VARIANTS) - set(experiment.STRATEGIES) == {"random_area", "error_guided", "prerendered"}
    assert experiment.VARIANTS["prerendered"].synthesizer is not None  # the row names its own synthesizer
    titles = [v.title for v in experiment.VARIANTS.values()]
    assert all(titles) and len(set(titles)) == len(titles)
    assert experiment.VARIANTS["none"].selector is None
    # A registry entry cannot be changed through its kwargs.
    with pytest.raises(TypeError):
        experiment.VARIANTS["paper"].selector_kwargs["min_separation"] = 0.0
    with pytest.raises(ValueError, match="selector: unknown selector 'ours'"):
        experiment.StrategyVariant("ours")


def test_variants_build_their_selector_and_callback_settings():
    from lightning_vtr.callback import ErrorGuidedViewAugmentation
    from lightning_vtr.selection import RandomSelector

    config = ExperimentConfig(fraction=0.1, seed=4)

    def build(name, **kwargs):
        return experiment.make_strategy(name, config, **kwargs)

    assert build("none") is None
    assert isinstance(build("random").selector, RandomSelector) and build("random").selector.mode == "angle"
    assert build("random_area").selector.mode == "area" and build("random_area").pool is None
    # "paper" is the paper's Table 1 row: the paper's whole rule; "error_guided" the callback's default
    paper_rule = ErrorGuidedViewAugmentation.paper(fraction=0.1, seed=4)
    assert _callback_settings(build("paper")) == _callback_settings(paper_rule)
    default = ErrorGuidedViewAugmentation(fraction=0.1, seed=4)
    assert _callback_settings(build("error_guided")) == _callback_settings(default)
    paper = build("paper")
    assert (paper.selector.score, paper.selector.min_separation, paper.selector.temperature) == ("paper", None, None)
    assert _callback_settings(paper) | {"selector": None} == {
        "selector": None,
        "fraction": 0.1,
        "search_fraction": 0.1,
        "generate_for": "random",
        "pool": (None, True),
        "pool_refresh": False,
        "select_at_start": True,
    }
    # The caller's kwargs go over the variant's.
    merged = build("error_guided", selector_kwargs={"k": 15}, callback_kwargs={"search_fraction": 0.5})
    assert (merged.selector.k, merged.selector.score, merged.selector.min_separation) == (15, "visible", 30.0)
    assert (merged.search_fraction, merged.pool.refresh) == (0.5, True)


class _Sleepy(L.Callback):
    """Stands in for an augmentation callback: 50 ms at the start of training and at every epoch end."""

    def on_train_start(self, trainer, pl_module):
        time.sleep(0.05)

    def on_train_epoch_end(self, trainer, pl_module):
        time.sleep(0.05)


def test_stage_timer_splits_a_fit_and_a_test(tmp_path):
    timer = experiment.StageTimer()
    assert timer.bracket(None) == []
    callbacks = [timer, *timer.bracket(_Sleepy())]
    trainer = L.Trainer(
        max_epochs=2,
        callbacks=callbacks,
        default_root_dir=str(tmp_path),
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        accelerator="cpu",
    )
    model = _LinearModel()
    trainer.fit(model)
    seconds = timer.seconds
    assert set(seconds) == set(experiment.StageTimer.STAGES)
    # One on_train_start and two epoch ends of 50 ms each, and nothing of them in the epochs' share.
    assert 0.15 <= seconds["augmentation"] < 0.15 + 0.1
    assert seconds["train_steps"] > 0 and seconds["train_data"] >= 0 and seconds["fit_other"] >= 0
    parts = ("train_steps", "train_data", "validation", "augmentation", "fit_other")
    assert math.fsum(seconds[k] for k in parts) == pytest.approx(seconds["fit"], rel=1e-6)
    assert seconds["test"] == seconds["test_steps"] == seconds["test_data"] == 0.0


def test_validate_run_tests_the_final_weights_on_the_validation_objects_and_caches(tiny_dataset, tmp_path, monkeypatch):
    config = ExperimentConfig(preset="tiny", data=str(tiny_dataset), out=str(tmp_path), batch_size=4, accelerator="cpu")
    run_dir = tmp_path / "visible"
    with pytest.raises(FileNotFoundError, match="last.ckpt does not exist"):
        experiment.validate_run(config, run_dir, 2)
    torch.manual_seed(0)
    model = experiment.make_model(config, fine_tuning=True)
    (run_dir / "checkpoints").mkdir(parents=True)
    torch.save({"state_dict": model.state_dict()}, run_dir / "checkpoints" / "last.ckpt")

    tested: list[tuple[str, list[int]]] = []
    test = L.Trainer.test

    def recording_test(self, model, datamodule=None, **kwargs):
        tested.append((datamodule.test_split, [len(dl.dataset) for dl in datamodule.test_dataloader()]))
        return test(self, model, datamodule=datamodule, **kwargs)

    monkeypatch.setattr(L.Trainer, "test", recording_test)
    results = experiment.validate_run(config, run_dir, 2)
    # the 3 validation objects (one per category) on 2 view sets each, for each of the three view sets
    assert tested == [("val", [6, 6, 6])]
    assert json.loads((run_dir / "validation.json").read_text()) == {"repeats": 2, "results": results}

    # The same numbers as testing these weights on a datamodule of the validation split by hand.
    dm = experiment.make_datamodule(config, model)
    dm.test_split, dm.test_repeats = "val", 2
    by_hand = experiment.evaluate(model.eval(), dm, config, tmp_path / "by_hand")
    assert set(results) == set(by_hand)
    for view_set in ("aligned", "hemispherical", "spherical"):
        assert results[view_set]["iou@0.4"] == pytest.approx(by_hand[view_set]["iou@0.4"], abs=1e-6)
    # ... and not the test split's
    dm.test_split = "test"
    on_test = experiment.evaluate(model, dm, config, tmp_path / "on_test")
    assert on_test["spherical"]["iou@0.4"] != pytest.approx(results["spherical"]["iou@0.4"], abs=1e-6)

    tested.clear()
    assert experiment.validate_run(config, run_dir, 2) == results and tested == []  # cached
    experiment.validate_run(config, run_dir, 1)  # another repeat count is recomputed
    assert tested == [("val", [3, 3, 3])]
