"""VIAT and MVTN (learning, ``batched`` selectors) through ErrorGuidedViewAugmentation: the same
guarantees as the error-guided selector (samples = selector outputs, state in checkpoints, exact resume,
DDP = one process)."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import lightning as L
import numpy as np
import pytest
import torch
from helpers import (
    EmptyPredictionModel,
    TinyUserModel,
    generated_contents,
    generated_index,
    make_callback,
    make_datamodule,
    make_trainer,
)

from lightning_vtr.geometry import wrap_yaw
from lightning_vtr.selection import MVTNSelector, VIATSelector

SELECTORS = {
    "viat": lambda: VIATSelector(population=4, iterations=2),
    "mvtn": lambda: MVTNSelector(steps=2),
}


def _state_digest(state) -> str:
    """A hash of a nested state dict's content (tensor bytes, scalars), independent of object identity."""
    digest = hashlib.sha1()

    def visit(value) -> None:
        if isinstance(value, dict):
            for key in sorted(value, key=str):
                digest.update(repr(key).encode())
                visit(value[key])
        elif isinstance(value, (list, tuple)):
            digest.update(b"[")
            for item in value:
                visit(item)
            digest.update(b"]")
        elif isinstance(value, torch.Tensor):
            digest.update(str(value.dtype).encode() + value.detach().cpu().contiguous().numpy().tobytes())
        else:
            digest.update(repr(value).encode())

    visit(state)
    return digest.hexdigest()


def _record_order(path: Path) -> str:
    return "" if path.stem == "start" else path.stem  # the selection before epoch 0 first


def _records(tmp_path: Path) -> list[dict]:
    paths = [p for p in (tmp_path / "vtr_selection").glob("*.json") if p.stem != "settings"]  # the settings record
    return [json.loads(p.read_text()) for p in sorted(paths, key=_record_order)]


def test_viat_samples_are_its_view_sets_spaced_120_degrees_in_yaw(tiny_dataset, tmp_path):
    dm = make_datamodule(tiny_dataset, tmp_path)
    callback = make_callback(selector=SELECTORS["viat"](), fraction=0.15)
    make_trainer(tmp_path, 3, [callback]).fit(TinyUserModel(), datamodule=dm)
    assert callback.pool is None  # VIAT trains on what it selects, no pool
    records = _records(tmp_path)
    assert [r["epoch"] for r in records] == [-1, 0, 1]  # before epoch 0, after epochs 0 and 1
    samples = dm.generated_samples
    # round(0.15 * 21) = 3 objects per selection
    assert [s["epoch"] for s in samples] == [-1] * 3 + [0] * 3 + [1] * 3
    for record in records:
        assert record["view_sets"] == record["selected"]
        for views in np.array(record["selected"]):
            yaw0, pitch0 = views[0]
            expected_yaw = wrap_yaw(torch.tensor([yaw0, yaw0 + 120.0, yaw0 + 240.0], dtype=torch.float64)).numpy()
            np.testing.assert_allclose(views[:, 0], expected_yaw, atol=2e-3)  # the log rounds to 1e-3
            np.testing.assert_allclose(views[:, 1], pitch0, atol=1e-9)
            assert -90.0 <= pitch0 <= 90.0
    # The trained samples carry exactly those view sets, object by object, in order.
    logged = [(o, v) for r in records for o, v in zip(r["objects"], r["view_sets"])]
    for s, (obj, views) in zip(samples, logged):
        assert f"{s['category']}/{s['object_id']}" == obj
        np.testing.assert_allclose(s["viewpoints"], views, atol=1e-3)
    # Every category searched has a learned distribution, moved away from its deterministic start.
    searched = {o.split("/")[0] for r in records for o in r["objects"]}
    assert searched
    for category in searched:
        means = callback.selector.distribution(category)["means"]
        start_yaw = -180.0 + (torch.arange(3, dtype=torch.float64) + 0.5) * 120.0
        assert not torch.allclose(means[:, 0], start_yaw, atol=1e-6)


def test_mvtn_samples_are_its_network_views_of_the_error(tiny_dataset, tmp_path):
    dm = make_datamodule(tiny_dataset, tmp_path)
    # Two epochs, no selection before epoch 0: only epoch 0's end generates, so the selector's final network
    # is the one that chose its views.
    callback = make_callback(selector=SELECTORS["mvtn"](), fraction=0.15, select_at_start=False)
    make_trainer(tmp_path, 2, [callback]).fit(EmptyPredictionModel(), datamodule=dm)
    assert callback.pool is None
    samples = dm.generated_samples
    assert len(samples) == 3
    # With an empty prediction the error volume is the ground truth; the network's views of it, recomputed
    # independently of the callback, are the samples' viewpoints.
    voxels = torch.stack([dm.object_voxels(dm.record(s["category"], s["object_id"])) for s in samples]).float()
    with torch.no_grad():
        views = callback.selector.views(voxels[:, None])
    expected = torch.stack([wrap_yaw(views[..., 0]), views[..., 1].clamp(-90, 90)], -1).numpy()
    got = np.stack([s["viewpoints"] for s in samples])
    np.testing.assert_allclose(got, expected, atol=1e-3)
    # The documented structure: view i stays within +-60 degrees of yaw of its base yaw 0 / 120 / 240.
    base = np.array([0.0, 120.0, 240.0])
    offset = (got[..., 0] - base + 180.0) % 360.0 - 180.0
    assert np.all(np.abs(offset) <= 60.0 + 1e-6)
    assert np.all(np.abs(got[..., 1]) < 90.0)
    # Two Adam steps moved the network off its zero-initialised head: the views are not the base views.
    assert not np.allclose(got, np.broadcast_to(callback.selector.base_views().numpy(), got.shape), atol=1e-3)


class TrainSetSizeProbe(L.Callback):
    """Records the size of the train set each epoch actually iterates."""

    def __init__(self) -> None:
        self.sizes: list[tuple[int, int]] = []

    def on_train_epoch_start(self, trainer, pl_module):
        self.sizes.append((trainer.current_epoch, len(trainer.train_dataloader.dataset)))


def _fit(root, tmp_path, epochs, name, ckpt=None):
    L.seed_everything(0, verbose=False)
    dm = make_datamodule(root, tmp_path)
    checkpoint = L.pytorch.callbacks.ModelCheckpoint(dirpath=tmp_path / "ckpt", save_last=True)
    callback = make_callback(selector=SELECTORS[name](), fraction=0.15)
    probe = TrainSetSizeProbe()
    # EmptyPredictionModel: the selections depend on the selector's state and the data, not on how the model
    # trained, so any difference below is the selector's (or the callback's) doing. (The model's own batch
    # order after a resume is the datamodule's business: see VTRDataModule's seeded shuffling.)
    trainer = make_trainer(tmp_path, epochs, [callback, checkpoint, probe])
    trainer.fit(EmptyPredictionModel(), datamodule=dm, ckpt_path=ckpt)
    return dm, callback, probe.sizes


@pytest.fixture(scope="module")
def uninterrupted(tiny_dataset, tmp_path_factory):
    """Selector name -> ``(run dir, _fit(..., 3 epochs, name))``: each uninterrupted 3-epoch run fitted once, read by
    the resume test and, as its one-process reference, by the DDP test."""
    runs = {}

    def get(name):
        if name not in runs:
            root = tmp_path_factory.mktemp(f"uninterrupted_{name}")
            runs[name] = (root, _fit(tiny_dataset, root, 3, name))
        return runs[name]

    return get


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(SELECTORS))
def test_resume_restores_the_selector_and_generates_what_an_uninterrupted_run_does(
    tiny_dataset, tmp_path, uninterrupted, name
):
    # Interrupted after epoch 0 (its last, which searches nothing); resumed to epoch 2, which searches after epoch 1.
    full, full_cb, full_sizes = uninterrupted(name)[1]
    _, part_cb, part_sizes = _fit(tiny_dataset, tmp_path / "part", 1, name)
    ckpt = tmp_path / "part" / "ckpt" / "last.ckpt"
    # The selector's learned state is in the callback's checkpoint entry (saved after the search before epoch 0).
    saved = torch.load(ckpt, map_location="cpu", weights_only=False)["callbacks"][part_cb.state_key]["selector"]
    assert saved and _state_digest(saved) == _state_digest(part_cb.selector.state_dict())
    resumed, resumed_cb, resumed_sizes = _fit(tiny_dataset, tmp_path / "part", 3, name, ckpt=str(ckpt))
    assert [s["epoch"] for s in full.generated_samples] == [-1] * 3 + [0] * 3 + [1] * 3
    # Epoch 0's search (which the checkpoint predates) is caught up from the restored selector ...
    assert generated_contents(resumed) == generated_contents(full)
    assert _state_digest(resumed_cb.selector.state_dict()) == _state_digest(full_cb.selector.state_dict())
    # ... and a fresh selector differs, so the equalities above are not vacuous.
    assert _state_digest(SELECTORS[name]().state_dict()) != _state_digest(full_cb.selector.state_dict())
    # The first resumed epoch trains on the caught-up samples too: 21 objects + 3 per selection, the first
    # made before epoch 0.
    assert full_sizes == [(0, 24), (1, 27), (2, 30)]
    assert part_sizes + resumed_sizes == full_sizes


def _assert_states_close(a, b, path="state") -> None:
    """Nested states equal, tensors up to accumulated float32 round-off (reductions differ with the thread count,
    and three rounds of selector training compound it)."""
    if isinstance(a, dict):
        assert sorted(a, key=str) == sorted(b, key=str), path
        for key in a:
            _assert_states_close(a[key], b[key], f"{path}.{key}")
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b)):
            _assert_states_close(x, y, f"{path}[{i}]")
    elif isinstance(a, torch.Tensor):
        torch.testing.assert_close(a, b, rtol=0.0, atol=2e-3, msg=lambda m: f"{path}: {m}")
    else:
        assert a == b, path


class SelectorStateProbe(L.Callback):
    """At the end of training, rank 0 saves its selector's state and every rank's state digest."""

    def __init__(self, out: str) -> None:
        self.out = out

    def on_train_end(self, trainer, pl_module):
        from lightning_vtr.callback import ErrorGuidedViewAugmentation

        (vtr,) = [c for c in trainer.callbacks if isinstance(c, ErrorGuidedViewAugmentation)]
        state = vtr.selector.state_dict()
        gathered = [None] * trainer.world_size
        torch.distributed.all_gather_object(gathered, _state_digest(state))
        if trainer.is_global_zero:
            torch.save({"digests": gathered, "state": state}, self.out)


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(SELECTORS))
def test_two_process_ddp_generates_and_learns_what_one_process_does(tiny_dataset, tmp_path, uninterrupted, name):
    # One process: the uninterrupted 3-epoch run of the resume test (the same callback arguments and model; its
    # checkpoint and probe callbacks change nothing the selection sees).
    single, (_, callback, _) = uninterrupted(name)

    ddp = tmp_path / "ddp"
    probe = SelectorStateProbe(str(tmp_path / "ddp_state.pt"))
    trainer = make_trainer(
        ddp,
        3,
        [make_callback(selector=SELECTORS[name](), fraction=0.15), probe],
        devices=2,
        strategy="ddp_spawn",
        num_sanity_val_steps=2,
    )
    trainer.fit(EmptyPredictionModel(), datamodule=make_datamodule(tiny_dataset, ddp))

    ddp_index, single_index = generated_index(ddp / "gen"), generated_index(single / "gen")
    assert len(single_index) == 9
    assert [e[:3] for e in ddp_index] == [e[:3] for e in single_index]  # same epochs and objects, same order
    # Viewpoints chosen by the selector rank 0 learned: equal up to the float round-off of its state (below),
    # so the rendered views may differ in a few edge pixels; where the viewpoints agree exactly, so do the bytes.
    np.testing.assert_allclose([e[3] for e in ddp_index], [e[3] for e in single_index], atol=0.05)
    for d, s in zip(ddp_index, single_index):
        if d[3] == s[3]:
            assert d[4] == s[4]
    saved = torch.load(tmp_path / "ddp_state.pt", weights_only=False)
    # Both ranks hold exactly the selector rank 0 learned (it is broadcast) ...
    assert saved["digests"] == [_state_digest(saved["state"])] * 2
    # ... and it is the one a single process learns (bit-exactness is not expected: each DDP process
    # runs with fewer threads, which changes the order of float reductions).
    _assert_states_close(saved["state"], callback.selector.state_dict())
    assert _state_digest(SELECTORS[name]().state_dict()) != _state_digest(saved["state"])
