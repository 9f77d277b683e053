"""ErrorGuidedViewAugmentation's contract: the datamodule check, the cap, the threshold, the collectives, the one
private Lightning attribute it writes, the checkpoint state key and the selection records."""

from __future__ import annotations

import inspect
import json
from pathlib import Path
from types import SimpleNamespace

import lightning as L
import pytest
import torch
from helpers import TinyUserModel, make_callback, make_datamodule, make_trainer
from lightning.pytorch.utilities.exceptions import MisconfigurationException

import lightning_vtr.augmentation.distributed as distributed_module
import lightning_vtr.augmentation.runner as runner_module
import lightning_vtr.callback as callback_module
from lightning_vtr.augmentation.distributed import all_gather_objects, sharded_map
from lightning_vtr.augmentation.runner import object_selection
from lightning_vtr.callback import RECORD_VERSION, _reload_train_dataloader
from lightning_vtr.data.datamodule import VTRDataModule
from lightning_vtr.protocol import DEFAULT_THRESHOLD
from lightning_vtr.selection import ErrorGuidedSelector, RandomSelector

_NEW_KEY = "ErrorGuidedViewAugmentation{'selector': 'ErrorGuidedSelector'}"


# ---------------------------------------------------------------------------------------- the datamodule protocol
def test_setup_names_the_missing_datamodule_member(tiny_dataset, tmp_path):
    class NoRecord(VTRDataModule):
        record = None  # everything else a VTRDataModule has

    dm = NoRecord(str(tiny_dataset), image_size=32, batch_size=8, generated_dir=str(tmp_path / "gen"))
    with pytest.raises(MisconfigurationException) as info:
        make_trainer(tmp_path, 1, [make_callback()]).fit(TinyUserModel(), datamodule=dm)
    message = str(info.value)
    assert (
        "NoRecord does not satisfy lightning_vtr.AugmentableDataModule: missing record(category, object_id)." in message
    )
    assert "eval_item" not in message and "add_samples" not in message
    assert "lightning_vtr.protocol.AugmentableDataModule" in message


# ---------------------------------------------------------------------------------------- the threshold
def test_the_callback_binarises_at_the_selectors_threshold():
    record = SimpleNamespace(category="chair", object_id="a")
    predicted, target, views = torch.full((4, 4, 4), 0.35), torch.ones(4, 4, 4), torch.zeros(3, 2)
    at_03 = object_selection(
        record,
        0,
        views,
        predicted,
        target,
        make_callback(selector=ErrorGuidedSelector(threshold=0.3)).selector.threshold,
    )
    at_default = object_selection(record, 0, views, predicted, target, make_callback().selector.threshold)
    assert at_03.error == 0.0  # 0.35 >= 0.3: every voxel right
    assert at_default.error == 1.0  # 0.35 < 0.4: every voxel wrong
    # selectors that do not binarise measure at the package default
    assert RandomSelector().threshold == ErrorGuidedSelector().threshold == DEFAULT_THRESHOLD == 0.4


# ---------------------------------------------------------------------------------------- collectives
def test_collectives_go_through_the_trainers_strategy():
    calls = []

    class Strategy:
        def broadcast(self, obj, src=0):
            calls.append((obj, src))
            return obj if obj is not None else f"rank {src}"

    trainer = SimpleNamespace(world_size=3, global_rank=1, strategy=Strategy())
    assert all_gather_objects(trainer, "mine") == ["rank 0", "mine", "rank 2"]
    assert calls == [(None, 0), ("mine", 1), (None, 2)]
    for module in (callback_module, distributed_module, runner_module):
        assert "torch.distributed" not in inspect.getsource(module)


def test_sharded_map_gives_every_rank_the_results_in_item_order():
    # rank 1 of 3 works on items 1 and 4; the other ranks' parts come through the strategy
    parts = {0: [0, 30], 2: [20]}

    class Strategy:
        def broadcast(self, obj, src=0):
            return obj if src == 1 else parts[src]

    trainer = SimpleNamespace(world_size=3, global_rank=1, strategy=Strategy())
    assert sharded_map(trainer, [0, 1, 2, 3, 4], lambda mine: [10 * i for i in mine]) == [0, 10, 20, 30, 40]


# ---------------------------------------------------------------------------------------- the private attribute
def test_lightning_still_has_the_reload_attribute_the_callback_writes(tmp_path):
    # `_reload_train_dataloader` relies on FitLoop rebuilding the train loader when
    # `current_epoch - _last_train_dl_reload_epoch >= reload_dataloaders_every_n_epochs`, and on `setup_data`
    # recording the epoch of each rebuild there. If this fails, Lightning changed it: update the helper.
    from lightning.pytorch.loops.fit_loop import _FitLoop

    trainer = make_trainer(tmp_path, 1, [])
    loop = trainer.fit_loop
    assert isinstance(loop, _FitLoop) and hasattr(loop, "_last_train_dl_reload_epoch")
    assert "self._last_train_dl_reload_epoch = trainer.current_epoch" in inspect.getsource(_FitLoop.setup_data)
    loop._last_train_dl_reload_epoch = trainer.current_epoch  # as setup_data leaves it
    assert not loop._should_reload_train_dl
    _reload_train_dataloader(trainer)
    assert loop._should_reload_train_dl


# ---------------------------------------------------------------------------------------- checkpoints and records
def _fit(root, run_dir, epochs, seed, ckpt=None, samples_of=None):
    # `samples_of`: the run whose generated samples a resume reads (its datamodule state lists them)
    dm = make_datamodule(root, samples_of or run_dir)
    callback = make_callback(selector="paper", fraction=0.15, seed=seed, max_samples=2)
    checkpoint = L.pytorch.callbacks.ModelCheckpoint(dirpath=run_dir / "ckpt", save_last=True)
    make_trainer(run_dir, epochs, [callback, checkpoint]).fit(TinyUserModel(), datamodule=dm, ckpt_path=ckpt)
    return dm, callback


@pytest.fixture(scope="module")
def one_epoch(tiny_dataset, tmp_path_factory):
    """A 1-epoch fit (the paper's rule, seed 0, one selection before epoch 0, ``max_samples=2``) and its last
    checkpoint."""
    run_dir = tmp_path_factory.mktemp("contract_run")
    dm, callback = _fit(tiny_dataset, run_dir, 1, seed=0)
    return run_dir, dm, callback


def _pool(callback):
    return {c: callback.pool.view_sets(c) for c in callback.pool.categories()}


def _same_state(a, b):
    assert (a.last_epoch, a.history) == (b.last_epoch, b.history)
    pool_a, pool_b = _pool(a), _pool(b)
    assert pool_a.keys() == pool_b.keys()
    for category in pool_a:
        assert pool_a[category][0] == pool_b[category][0] and torch.equal(pool_a[category][1], pool_b[category][1])


def test_max_samples_is_the_one_cap(one_epoch):
    _, dm, callback = one_epoch
    # round(0.15 * 21) = 3 samples generated before epoch 0, the oldest dropped by max_samples=2
    assert [e["id"] for e in dm.generated_samples] == [1, 2]
    assert callback.history[0]["samples"] == 3 and not hasattr(dm, "max_generated")


def test_the_state_key_does_not_name_the_seed(one_epoch):
    run_dir, _, callback = one_epoch
    assert callback.state_key == _NEW_KEY == make_callback(seed=7).state_key
    states = torch.load(run_dir / "ckpt" / "last.ckpt", map_location="cpu", weights_only=False)["callbacks"]
    assert _NEW_KEY in states and states[_NEW_KEY]["seed"] == 0


def test_resume_with_another_seed_restores_the_state_and_warns(tiny_dataset, one_epoch, tmp_path):
    run_dir, dm, callback = one_epoch
    assert callback.last_epoch == -1 and len(callback.pool) == 3
    with pytest.warns(UserWarning, match=r"with seed=5, but the checkpoint used seed=0"):
        resumed_dm, resumed = _fit(
            tiny_dataset, tmp_path, 1, seed=5, ckpt=str(run_dir / "ckpt" / "last.ckpt"), samples_of=run_dir
        )
    _same_state(resumed, callback)
    assert resumed_dm.generated_samples == dm.generated_samples


def test_resume_with_another_rule_warns_naming_both_and_starts_fresh(tiny_dataset, one_epoch, tmp_path):
    run_dir, _, callback = one_epoch
    ckpt = str(run_dir / "ckpt" / "last.ckpt")
    dm = make_datamodule(tiny_dataset, run_dir)
    other = make_callback(fraction=0.15, seed=0, max_samples=2)  # the default rule, same selector class: same key
    assert other.state_key == callback.state_key
    with pytest.warns(UserWarning, match="belongs to another rule") as caught:
        make_trainer(tmp_path, 2, [other]).fit(TinyUserModel(), datamodule=dm, ckpt_path=ckpt)
    message = next(str(w.message) for w in caught if "belongs to another rule" in str(w.message))
    # one line per effective difference (the paper's rule against the default one), nothing else
    assert [line for line in message.splitlines() if line.startswith("  ")] == [
        "  ErrorGuidedSelector.score: 'paper' in the checkpoint, 'visible' now",
        "  ErrorGuidedSelector.reduction: 'sum' in the checkpoint, not set now",  # mask='none', eps=0.0: no lines
        "  ErrorGuidedSelector.min_separation: None in the checkpoint, 30.0 now",
        "  ErrorGuidedSelector.temperature: None in the checkpoint, 10.0 now",
        "  search_fraction: 0.15 in the checkpoint, 0.35 now",
        "  pool.refresh: False in the checkpoint, True now",
    ]
    assert message.splitlines()[-2].startswith("Starting this callback's state fresh (empty pool, no history)")
    # nothing of the paper rule's state was loaded: the pool and history hold only the caught-up round of epoch 0
    assert [h["epoch"] for h in other.history] == [0] and callback.history[0]["epoch"] == -1
    assert len(other.pool) == round(0.35 * 21)


def test_a_checkpoint_of_0_3_resumes_and_a_newer_state_is_refused(tiny_dataset, one_epoch, tmp_path):
    run_dir, _, callback = one_epoch
    checkpoint = torch.load(run_dir / "ckpt" / "last.ckpt", map_location="cpu", weights_only=False)
    state = checkpoint["callbacks"][_NEW_KEY]
    assert state["version"] == 2 and state["rule"] == callback.rule()
    # 0.3 wrote version 1 under the same key, without the rule
    old = {k: v for k, v in state.items() if k != "rule"} | {"version": 1}
    checkpoint["callbacks"][_NEW_KEY] = old
    path = tmp_path / "v03.ckpt"
    torch.save(checkpoint, path)
    _, resumed = _fit(tiny_dataset, tmp_path, 1, seed=0, ckpt=str(path), samples_of=run_dir)
    _same_state(resumed, callback)
    with pytest.raises(ValueError, match=r"state has version 3; this lightning_vtr reads versions <= 2"):
        make_callback(selector="paper").load_state_dict(state | {"version": 3})


def test_selection_records_have_the_documented_fields(one_epoch):
    run_dir, _dm, _ = one_epoch
    record = json.loads((Path(run_dir) / "vtr_selection" / "start.json").read_text())
    assert RECORD_VERSION == 1
    assert record["version"] == RECORD_VERSION
    assert list(record) == ["version", "epoch", "objects", "selected", "view_sets", "mean_error", "searched"]
    assert record["epoch"] == -1 and record["searched"] == 3 and len(record["objects"]) == 3
    assert all(len(v) == 3 and len(v[0]) == 2 for v in record["selected"] + record["view_sets"])
    docs = (Path(__file__).parents[1] / "docs" / "records.md").read_text()
    assert all(f"`{field}`" in docs for field in record)
