"""``Trainer.test`` on two processes counts every test object once: its means equal one process's.

Lightning's default ``DistributedSampler`` pads a test set whose size does not divide among the processes
with repeats of its first items. The fixture's test split has 9 objects per view set, so two processes
would see 10, object 0 twice. The tests check that this padding would change the means, that two processes
with ``VTRDataModule`` (unpadded shards) log one process's means, and that the model drops the repeats of a
padding sampler (what it meets with loaders of another datamodule).
"""

from __future__ import annotations

import lightning as L
import pytest
import torch
from helpers import build_odd_dataset, odd_model, one_thread
from torch.utils.data import DataLoader, DistributedSampler

from lightning_vtr.data.datamodule import VTRDataModule, _UnpaddedShardSampler
from lightning_vtr.metrics import voxel_fscore, voxel_iou
from lightning_vtr.protocol import VIEW_SETS

FSCORE_POINTS = 512

# One thread here as in each DDP process (Lightning gives each of the 2 CPU processes one core), so that the
# convolutions reduce in the same order everywhere.
_one_thread = pytest.fixture(autouse=True)(one_thread)


@pytest.fixture(scope="module")
def odd_dataset(tmp_path_factory):
    """3 categories x 5 objects, 3 of each in the test split: 9 test objects per view set."""
    return build_odd_dataset(tmp_path_factory.mktemp("odd_vtr"), split=(0.2, 0.2, 0.6))


@pytest.fixture(scope="module")
def model():
    return odd_model(FSCORE_POINTS)


@pytest.fixture(scope="module")
def direct(odd_dataset, model):
    """View set -> (categories, IoU@0.4, F-score) of each test item, in dataset order, computed directly."""
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    dm = _datamodule(odd_dataset)
    dm.setup("test")
    yield _per_object_scores(model, dm)
    torch.set_num_threads(previous)


def _datamodule(root, **kw) -> VTRDataModule:
    return VTRDataModule(str(root), num_views=2, image_size=64, batch_size=2, **kw)


def _test(model, tmp_path, devices: int, **data) -> dict[str, float]:
    trainer = L.Trainer(
        accelerator="cpu",
        devices=devices,
        strategy="ddp_spawn" if devices > 1 else "auto",
        default_root_dir=str(tmp_path),
        logger=False,
        enable_progress_bar=False,
        enable_model_summary=False,
    )
    results = trainer.test(model, **data, verbose=False)
    return {key: value for per_loader in results for key, value in per_loader.items()}


def _per_object_scores(model, dm: VTRDataModule) -> dict[str, tuple[list[str], torch.Tensor, torch.Tensor]]:
    model.eval()
    out = {}
    with torch.no_grad():
        for name, loader in zip(dm.test_view_sets, dm.test_dataloader()):
            items = [loader.dataset[i] for i in range(len(loader.dataset))]
            probs = model.predict_voxels(torch.stack([item["images"] for item in items]))
            voxels = torch.stack([item["voxels"] for item in items])
            iou = voxel_iou(probs, voxels, (0.4,))[:, 0]
            fscore = torch.cat(
                [voxel_fscore(probs[i : i + 1], voxels[i : i + 1], num_points=FSCORE_POINTS) for i in range(len(items))]
            )
            out[name] = ([item["category"] for item in items], iou.double(), fscore.double())
    return out


def _padded_order(length: int) -> list[int]:
    """The items two processes test with Lightning's default sampler, both shards together."""
    return [i for rank in range(2) for i in DistributedSampler(range(length), num_replicas=2, rank=rank, shuffle=False)]


def _padding_effect(direct) -> tuple[dict[str, float], dict[str, float]]:
    """(correct, padded): the means over the 9 test objects, and over the 10 items two padded shards hold."""
    order = _padded_order(9)
    padded, correct = {}, {}
    for name, (categories, iou, fscore) in direct.items():
        correct[f"test/{name}/iou@0.4"] = iou.mean().item()
        padded[f"test/{name}/iou@0.4"] = iou[order].mean().item()
        correct[f"test/{name}/fscore"] = fscore.mean().item()
        padded[f"test/{name}/fscore"] = fscore[order].mean().item()
        first = categories[0]
        members = [i for i, c in enumerate(categories) if c == first]
        correct[f"test/{name}/{first}/iou@0.4"] = iou[members].mean().item()
        padded[f"test/{name}/{first}/iou@0.4"] = iou[[i for i in order if i in members]].mean().item()
    return correct, padded


@pytest.mark.slow
def test_two_processes_count_each_test_object_once(odd_dataset, model, direct, tmp_path):
    # 1. The fixture really pads: two processes would test object 0 twice, which moves the means.
    assert len(direct["aligned"][0]) == 9 and sorted(_padded_order(9)) == [0, *range(9)]
    correct, padded = _padding_effect(direct)
    assert max(abs(padded[k] - correct[k]) for k in correct) > 1e-3

    # 2. One process logs the direct means.
    single = _test(model, tmp_path / "one", 1, datamodule=_datamodule(odd_dataset))
    for key, value in correct.items():
        assert single[key] == pytest.approx(value, abs=1e-6), key

    # 3. Two processes (unequal shards of 5 and 4 objects) log exactly the one-process metrics: every view
    #    set, threshold and category.
    ddp = _test(model, tmp_path / "two", 2, datamodule=_datamodule(odd_dataset, verify=True))  # rank 0 verifies
    expected_keys = {f"test/{s}/{c}/iou@0.4" for s in VIEW_SETS for c in ("airplane", "chair", "table")}
    assert expected_keys <= single.keys()
    assert ddp.keys() == single.keys()
    for key, value in single.items():
        assert ddp[key] == pytest.approx(value, abs=1e-6), key

    # 4. The spawned processes received the metric states in shared memory; they must not have added into
    #    the launching process's states, or testing the same model again here would count their objects too.
    again = _test(model, tmp_path / "again", 1, datamodule=_datamodule(odd_dataset))
    assert again == pytest.approx(single, abs=1e-6)


def test_datamodule_shards_the_test_set_without_padding(odd_dataset):
    dataset = _datamodule(odd_dataset)._dataset("test", "aligned", train=False)
    shards = [list(_UnpaddedShardSampler(dataset, num_replicas=2, rank=rank)) for rank in range(2)]
    assert shards == [[0, 2, 4, 6, 8], [1, 3, 5, 7]]
    assert [len(_UnpaddedShardSampler(dataset, num_replicas=2, rank=rank)) for rank in range(2)] == [5, 4]
    assert [len(_UnpaddedShardSampler(dataset, num_replicas=4, rank=rank)) for rank in range(4)] == [3, 2, 2, 2]


@pytest.mark.parametrize("rank", [0, 1])
def test_the_model_drops_the_repeats_a_padding_sampler_adds(odd_dataset, model, direct, tmp_path, rank):
    # What one DDP process meets with plain loaders: Lightning's padding sampler. Rank 1's shard is items
    # 1, 3, 5, 7 and a repeat of item 0; in batches of 3 the repeat shares the last batch with item 7.
    dm = _datamodule(odd_dataset)
    loaders = [
        DataLoader(dataset, batch_size=3, sampler=DistributedSampler(dataset, num_replicas=2, rank=rank, shuffle=False))
        for dataset in (loader.dataset for loader in dm.test_dataloader())
    ]
    shard = list(loaders[0].sampler)
    owned = list(range(rank, 9, 2))
    assert shard == owned + ([0] if rank == 1 else [])  # the last batch of rank 1 is [7, 0]: one item dropped
    logged = _test(model, tmp_path, 1, dataloaders=loaders)
    for name, (categories, iou, fscore) in direct.items():
        assert logged[f"test/{name}/iou@0.4"] == pytest.approx(iou[owned].mean().item(), abs=1e-6)
        assert logged[f"test/{name}/fscore"] == pytest.approx(fscore[owned].mean().item(), abs=1e-6)
        for category in set(categories):
            members = [i for i in owned if categories[i] == category]
            assert logged[f"test/{name}/{category}/iou@0.4"] == pytest.approx(iou[members].mean().item(), abs=1e-6)
    if rank == 1:  # counting the repeat would have moved the means
        assert abs(direct["aligned"][1][shard].mean().item() - direct["aligned"][1][owned].mean().item()) > 1e-3
