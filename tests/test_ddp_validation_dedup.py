"""``Trainer.validate`` on two processes counts every validation object once: its means equal one process's.

``VTRDataModule.val_dataloader`` keeps Lightning's default ``DistributedSampler`` under DDP (every process runs
as many batches), which pads a validation set whose size does not divide among the processes with repeats of its
first items. The fixture's validation split has 9 objects, so two processes see 10, object 0 twice (alone in
rank 1's last batch of 2). The model leaves the repeats out of ``val/loss`` and the metrics (the mechanism of
``tests/test_ddp_test_dedup.py`` for test loaders that pad). The tests check that counting the repeat would move
the means, that two processes log one process's means and count 9 objects, and that a padding sampler whose
repeat shares a batch with an owned object is cut at the right item.
"""

from __future__ import annotations

import lightning as L
import pytest
import torch
from helpers import build_odd_dataset, odd_model, one_thread
from torch.utils.data import DataLoader, DistributedSampler

from lightning_vtr.data.datamodule import VTRDataModule
from lightning_vtr.metrics import voxel_fscore, voxel_iou

FSCORE_POINTS = 512
N_VAL = 9

# One thread here as in each DDP process (Lightning gives each of the 2 CPU processes one core), so that the
# convolutions reduce in the same order everywhere.
_one_thread = pytest.fixture(autouse=True)(one_thread)


class _CountObjects(L.Callback):
    """Logs ``items/iou`` / ``items/fscore``: the objects the validation metrics hold, summed over processes.

    Callbacks' ``on_validation_epoch_end`` runs before the model's, which computes and resets the metrics.
    """

    def on_validation_epoch_end(self, trainer, pl_module):
        for name, metric in pl_module.val_metrics.items():
            pl_module.log(f"items/{name}", float(metric.count), reduce_fx="sum", sync_dist=True)


@pytest.fixture(scope="module")
def odd_dataset(tmp_path_factory):
    """3 categories x 5 objects, 3 of each in the validation split: 9 validation objects."""
    return build_odd_dataset(tmp_path_factory.mktemp("odd_val_vtr"), split=(0.2, 0.6, 0.2))


@pytest.fixture(scope="module")
def model():
    return odd_model(FSCORE_POINTS)


def _datamodule(root, **kw) -> VTRDataModule:
    return VTRDataModule(str(root), num_views=2, image_size=64, batch_size=2, **kw)


@pytest.fixture(scope="module")
def direct(odd_dataset, model):
    """(IoU@0.4, F-score) of each validation object, in dataset order, computed directly."""
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    dm = _datamodule(odd_dataset)
    dm.setup("validate")
    dataset = dm.val_dataloader().dataset
    items = [dataset[i] for i in range(len(dataset))]
    model.eval()
    with torch.no_grad():
        probs = model.predict_voxels(torch.stack([item["images"] for item in items]))
    voxels = torch.stack([item["voxels"] for item in items])
    iou = voxel_iou(probs, voxels, (0.4,))[:, 0].double()
    fscore = torch.cat(
        [voxel_fscore(probs[i : i + 1], voxels[i : i + 1], num_points=FSCORE_POINTS) for i in range(len(items))]
    ).double()
    torch.set_num_threads(previous)
    return iou, fscore


def _validate(model, tmp_path, devices: int, **data) -> dict[str, float]:
    trainer = L.Trainer(
        accelerator="cpu",
        devices=devices,
        strategy="ddp_spawn" if devices > 1 else "auto",
        default_root_dir=str(tmp_path),
        logger=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        callbacks=[_CountObjects()],
    )
    results = trainer.validate(model, **data, verbose=False)
    return {key: value for per_loader in results for key, value in per_loader.items()}


def _padded_order(length: int, replicas: int = 2) -> list[int]:
    """The items ``replicas`` processes validate with Lightning's default sampler, all shards together."""
    return [
        i
        for rank in range(replicas)
        for i in DistributedSampler(range(length), num_replicas=replicas, rank=rank, shuffle=False)
    ]


@pytest.mark.slow
def test_two_processes_count_each_validation_object_once(odd_dataset, model, direct, tmp_path):
    iou, fscore = direct
    # 1. The fixture really pads: two processes would validate object 0 twice, which moves the means.
    assert len(iou) == N_VAL and sorted(_padded_order(N_VAL)) == [0, *range(N_VAL)]
    order = _padded_order(N_VAL)
    correct = {"val/iou@0.4": iou.mean().item(), "val/fscore": fscore.mean().item()}
    padded = {"val/iou@0.4": iou[order].mean().item(), "val/fscore": fscore[order].mean().item()}
    assert max(abs(padded[k] - correct[k]) for k in correct) > 1e-3

    # 2. One process logs the direct means over the 9 objects.
    single = _validate(model, tmp_path / "one", 1, datamodule=_datamodule(odd_dataset))
    for key, value in correct.items():
        assert single[key] == pytest.approx(value, abs=1e-6), key
    assert single["items/iou"] == single["items/fscore"] == N_VAL

    # 3. Two processes (padded shards of 5 and 5, rank 1's last batch only the repeat of object 0) log exactly
    #    the one-process metrics and count 9 objects, not 10.
    ddp = _validate(model, tmp_path / "two", 2, datamodule=_datamodule(odd_dataset))
    assert ddp.keys() == single.keys()
    assert ddp["items/iou"] == ddp["items/fscore"] == N_VAL
    for key in ("val/iou@0.4", "val/iou@0.2", "val/iou@0.5", "val/fscore"):
        assert ddp[key] == pytest.approx(single[key], abs=1e-6), key

    # 4. The spawned processes did not add into the launching process's metric states (shared memory).
    again = _validate(model, tmp_path / "again", 1, datamodule=_datamodule(odd_dataset))
    assert again == pytest.approx(single, abs=1e-6)


@pytest.mark.parametrize("rank", [0, 1])
def test_validation_drops_the_repeats_a_padding_sampler_adds(odd_dataset, model, direct, tmp_path, rank):
    # What one DDP process meets: rank 1's shard is objects 1, 3, 5, 7 and a repeat of object 0; in batches of 3
    # the repeat shares the last batch with object 7.
    iou, fscore = direct
    dataset = _datamodule(odd_dataset)
    dataset.setup("validate")
    dataset = dataset.val_dataloader().dataset
    loader = DataLoader(
        dataset, batch_size=3, sampler=DistributedSampler(dataset, num_replicas=2, rank=rank, shuffle=False)
    )
    shard = list(loader.sampler)
    owned = list(range(rank, N_VAL, 2))
    assert shard == owned + ([0] if rank == 1 else [])
    logged = _validate(model, tmp_path, 1, dataloaders=loader)
    assert logged["items/iou"] == len(owned)
    assert logged["val/iou@0.4"] == pytest.approx(iou[owned].mean().item(), abs=1e-6)
    assert logged["val/fscore"] == pytest.approx(fscore[owned].mean().item(), abs=1e-6)
    if rank == 1:  # counting the repeat would have moved the means
        assert abs(iou[shard].mean().item() - iou[owned].mean().item()) > 1e-3
