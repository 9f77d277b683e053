"""lightning_vtr.experiments.training: the registries, the fine-tuning learning-rate schedule, the result cache."""

from __future__ import annotations

import json
import math

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


@pytest.mark.parametrize("schedule, expected", [("cosine", 1), ("constant", 0)])
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
    payload = {"strategy": "none", "config": experiment._comparable(config), "results": {"aligned": {"iou@0.4": 0.5}}}
    (tmp_path / "none").mkdir()
    (tmp_path / "none" / "results.json").write_text(json.dumps(payload))
    missing = tmp_path / "never-read.ckpt"
    # Same experiment (another device count only): the cache is the answer, nothing is loaded.
    assert run_strategy("none", ExperimentConfig(out=str(tmp_path), finetune_epochs=3, devices=2), missing) == payload
    with pytest.raises(ValueError, match=r"results.json was written with another configuration .*'finetune_lr'"):
        run_strategy("none", ExperimentConfig(out=str(tmp_path), finetune_epochs=3, finetune_lr="constant"), missing)


def test_models_registry_builds_each_model_class_with_its_preset():
    from lightning_vtr.models.lrgt import LRGT
    from lightning_vtr.models.pix2vox import Pix2VoxPlusPlus

    assert experiment.MODELS == {"pix2vox": Pix2VoxPlusPlus, "lrgt": LRGT}
    for name, cls in experiment.MODELS.items():
        model = experiment.make_model(ExperimentConfig(model=name, preset="tiny"))
        assert type(model) is cls
    with pytest.raises(ValueError, match="`model` must be one of 'pix2vox', 'lrgt', got 'unet'"):
        experiment.make_model(ExperimentConfig(model="unet"))
    with pytest.warns(DeprecationWarning, match="MODEL_CLASSES"):
        assert experiment.MODEL_CLASSES == ("pix2vox", "lrgt")


def test_make_strategy_builds_every_registered_selector():
    from lightning_vtr.callback import ErrorGuidedViewAugmentation
    from lightning_vtr.selection import SELECTORS

    config = ExperimentConfig(fraction=0.2, seed=3)
    assert experiment.STRATEGIES == ("none", *SELECTORS)
    assert experiment.make_strategy("none", config) is None
    for name, cls in SELECTORS.items():
        callback = experiment.make_strategy(name, config)
        assert isinstance(callback, ErrorGuidedViewAugmentation) and type(callback.selector) is cls, name
        assert (callback.fraction, callback.seed) == (0.2, 3)
    with pytest.raises(ValueError, match="`name` must be one of 'none', 'nature', .*, got 'ours'"):
        experiment.make_strategy("ours", config)


def test_make_strategy_passes_selector_and_callback_arguments():
    from lightning_vtr.selection import ErrorGuidedSelector, VIATSelector

    config = ExperimentConfig(fraction=0.2, seed=3)
    callback = experiment.make_strategy(
        "error_guided", config, selector_kwargs={"k": 15}, callback_kwargs={"use_pool": False, "fraction": 0.5}
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
    with pytest.warns(DeprecationWarning, match="`n_views` was renamed `num_views`"):
        assert experiment.make_datamodule(config, model, n_views=2).num_views == 2


def test_config_reads_a_device_count_from_a_command_line():
    assert ExperimentConfig(devices="2").devices == 2
    assert ExperimentConfig(devices="auto").devices == "auto"
    assert ExperimentConfig(devices="0,1").devices == "0,1"


def test_cosine_fine_tuning_rejects_a_non_integer_epoch_count():
    with pytest.raises(TypeError, match="`epochs` must be an int, got float 2.5"):
        CosineFineTuning(2.5)
