from __future__ import annotations

import hashlib
import os
import socket

import numpy as np
import pytest
import torch
import torch.distributed as dist
import torch.multiprocessing as mp

from lightning_vtr.data.datamodule import VTRDataModule
from lightning_vtr.data.dataset import GeneratedSample, ImageTransform


def _dm(root, **kw):
    kw.setdefault("image_size", 32)
    kw.setdefault("batch_size", 4)
    dm = VTRDataModule(str(root), **kw)
    dm.setup("fit")
    return dm


def _sample(dm, index=0, fill=0):
    rec = dm.split_records("train")[index]
    images = np.zeros((3, 16, 16, 4), np.uint8)
    images[..., 0] = fill
    images[..., 3] = 255
    return GeneratedSample(
        rec.category, rec.object_id, images, np.array([[10.0, 20.0], [-30.0, 45.0], [170.0, -80.0]]), 0
    )


def test_splits_follow_7_1_2_per_category(tiny_dataset):
    dm = _dm(tiny_dataset)
    for cat in dm.categories:
        counts = [sum(r.category == cat for r in dm.split_records(s)) for s in ("train", "val", "test")]
        assert counts == [7, 1, 2]
    keys = [(r.category, r.object_id) for r in dm.records]
    assert keys == sorted(keys)  # fixed order shared by every process


def test_batches_have_the_protocol_shapes_and_normalisation(tiny_dataset):
    dm = _dm(tiny_dataset, num_views=3, image_size=32, batch_size=5)
    batch = next(iter(dm.train_dataloader()))
    assert batch["images"].shape == (5, 3, 3, 32, 32)
    assert batch["voxels"].shape == (5, 32, 32, 32)
    assert set(torch.unique(batch["voxels"]).tolist()) <= {0.0, 1.0}
    assert batch["viewpoints"].shape == (5, 3, 2)
    # Aligned training views all share the builder's fixed elevation.
    assert torch.allclose(batch["viewpoints"][..., 1], torch.full((5, 3), 30.0))
    # White background after ImageNet normalisation: (1 - mean) / std in the corners.
    expected = (1.0 - torch.tensor([0.485, 0.456, 0.406])) / torch.tensor([0.229, 0.224, 0.225])
    assert torch.allclose(batch["images"][0, 0, :, 0, 0], expected, atol=1e-4)


def test_evaluation_views_are_deterministic_and_seed_dependent(tiny_dataset):
    a = next(iter(_dm(tiny_dataset).val_dataloader()))
    b = next(iter(_dm(tiny_dataset).val_dataloader()))
    c = next(iter(_dm(tiny_dataset, seed=5).val_dataloader()))
    assert torch.equal(a["images"], b["images"]) and torch.equal(a["viewpoints"], b["viewpoints"])
    assert not torch.equal(a["viewpoints"], c["viewpoints"])


def test_training_views_depend_on_epoch_only(tiny_dataset):
    dm = _dm(tiny_dataset)
    ds = dm.train_dataset()
    ds.epoch = 3
    first = [ds.view_indices(i).tolist() for i in range(len(ds))]
    assert first == [ds.view_indices(i).tolist() for i in range(len(ds))]
    ds.epoch = 4
    assert first != [ds.view_indices(i).tolist() for i in range(len(ds))]


def test_test_dataloaders_are_the_three_view_sets(tiny_dataset):
    dm = _dm(tiny_dataset, batch_size=64)
    loaders = dm.test_dataloader()
    assert len(loaders) == 3
    batches = [next(iter(dl)) for dl in loaders]
    assert [b["view_set"][0] for b in batches] == ["aligned", "hemispherical", "spherical"]
    assert all(len(b["object_id"]) == 6 for b in batches)  # 2 test objects x 3 categories
    pitch = [b["viewpoints"][..., 1] for b in batches]
    assert torch.all(pitch[0] == 30.0)
    assert pitch[1].min() >= 0.0 and pitch[1].max() <= 90.0
    assert pitch[2].min() < 0.0  # only the spherical set looks from below


def test_test_repeats_serve_every_test_object_t_times_and_only_in_test(tiny_dataset):
    dm = _dm(tiny_dataset, batch_size=64, test_repeats=3)
    batches = [next(iter(dl)) for dl in dm.test_dataloader()]
    for batch in batches:
        assert len(batch["object_id"]) == 3 * 6
        counts = {oid: batch["object_id"].count(oid) for oid in batch["object_id"]}
        assert set(counts.values()) == {3}
    # Every strategy of a seed is tested on the same items: a second datamodule serves the same views.
    again = [next(iter(dl)) for dl in _dm(tiny_dataset, batch_size=64, test_repeats=3).test_dataloader()]
    assert all(torch.equal(a["viewpoints"], b["viewpoints"]) for a, b in zip(batches, again))
    assert len(dm.val_dataloader().dataset) == 3 and len(dm.train_dataset()) == 21
    with pytest.raises(ValueError, match=r"`test_repeats` must be an int >= 1, got 0"):
        VTRDataModule(str(tiny_dataset), test_repeats=0)


def test_add_samples_persists_and_serves_from_next_loader(tiny_dataset, tmp_path):
    dm = _dm(tiny_dataset, generated_dir=str(tmp_path / "gen"))
    n_train = len(dm.train_dataset())
    entries = dm.add_samples([_sample(dm, 0, fill=200), _sample(dm, 1, fill=100)])
    assert len(entries) == 2
    assert (tmp_path / "gen" / entries[0]["dir"] / "02.png").is_file()
    ds = dm.train_dataset()
    assert len(ds) == n_train + 2
    item = ds[n_train]
    expected = ImageTransform(32)(_sample(dm, 0, fill=200).images)
    assert torch.allclose(item["images"], expected, atol=1e-5)
    assert item["viewpoints"].tolist() == [[10.0, 20.0], [-30.0, 45.0], [170.0, -80.0]]
    rec = dm.split_records("train")[0]
    assert torch.equal(item["voxels"], dm.object_voxels(rec))


def test_state_dict_restores_exactly_the_injected_samples(tiny_dataset, tmp_path):
    dm = _dm(tiny_dataset, generated_dir=str(tmp_path / "gen"))
    dm.add_samples([_sample(dm, 0, 10), _sample(dm, 2, 20)])
    state = dm.state_dict()
    dm.add_samples([_sample(dm, 3, 30)])  # written after the checkpoint: must not reappear
    restored = _dm(tiny_dataset)
    restored.load_state_dict(state)
    assert [e["object_id"] for e in restored.generated_samples] == [e["object_id"] for e in state["generated"]]
    assert len(restored.train_dataset()) == len(_dm(tiny_dataset).train_dataset()) + 2
    # Ids continue where the checkpoint stopped, so a resumed run rewrites the same directories.
    assert restored.add_samples([_sample(restored, 3, 30)])[0]["id"] == 2


def test_missing_generated_files_are_reported(tiny_dataset, tmp_path):
    dm = _dm(tiny_dataset, generated_dir=str(tmp_path / "gen"))
    dm.add_samples([_sample(dm)])
    state = dm.state_dict()
    state["generated_dir"] = str(tmp_path / "elsewhere")
    with pytest.raises(FileNotFoundError, match="generated samples missing"):
        _dm(tiny_dataset).load_state_dict(state)


def test_max_generated_keeps_the_newest(tiny_dataset, tmp_path):
    dm = _dm(tiny_dataset, generated_dir=str(tmp_path / "gen"), max_generated=2)
    dm.add_samples([_sample(dm, i) for i in range(3)])
    assert [e["id"] for e in dm.generated_samples] == [1, 2]


def test_bad_arguments_are_named(tiny_dataset):
    with pytest.raises(ValueError, match=r"`num_views` must be an int >= 1, got 0"):
        VTRDataModule(str(tiny_dataset), num_views=0)
    with pytest.raises(TypeError, match=r"`batch_size` must be an int, got float 4.0"):
        VTRDataModule(str(tiny_dataset), batch_size=4.0)
    with pytest.raises(ValueError, match=r"`max_generated` must be an int >= 0, got -1"):
        VTRDataModule(str(tiny_dataset), max_generated=-1)
    with pytest.raises(ValueError, match="`shapenet_rendering` must be None when `root`"):
        VTRDataModule(str(tiny_dataset), shapenet_rendering={})
    with pytest.raises(
        ValueError, match=r"`shapenet_rendering` must have the keys.*missing \['split_file', 'voxel_root'\]"
    ):
        VTRDataModule(shapenet_rendering={"rendering_root": "r"})
    with pytest.raises(ValueError, match="categories"):
        _dm(tiny_dataset, categories=["spaceship"])
    dm = _dm(tiny_dataset)
    with pytest.raises(KeyError, match="unknown object"):
        dm.add_samples([GeneratedSample("chair", "nope", np.zeros((3, 8, 8, 4), np.uint8), np.zeros((3, 2)))])
    with pytest.raises(ValueError, match="uint8"):
        s = _sample(dm)
        s.images = s.images.astype(np.float32)
        dm.add_samples([s])


def test_n_views_is_a_deprecated_alias_of_num_views(tiny_dataset):
    with pytest.warns(DeprecationWarning, match="`n_views` was renamed `num_views`"):
        dm = _dm(tiny_dataset, n_views=2, batch_size=3)
    assert dm.num_views == 2
    # The checkpointed hyperparameters hold the new name only, with the resolved value.
    assert dm.hparams["num_views"] == 2 and "n_views" not in dm.hparams
    assert next(iter(dm.val_dataloader()))["images"].shape == (3, 2, 3, 32, 32)
    with pytest.warns(DeprecationWarning, match="`VTRDataModule.n_views` was renamed `num_views`"):
        assert dm.n_views == 2


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _ddp_worker(rank, world, port, root, gen_dir, out):
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port))
    dist.init_process_group("gloo", rank=rank, world_size=world)
    dm = VTRDataModule(root, image_size=32, generated_dir=gen_dir)
    dm.setup("fit")
    # Every rank adds the same (gathered) samples, as the callback does; all write the same files.
    dm.add_samples([_sample(dm, i, fill=10 * i) for i in range(3)])
    ds = dm.train_dataset()
    digest = hashlib.sha1()
    for i in range(len(ds)):
        item = ds[i]
        digest.update(item["object_id"].encode())
        digest.update(item["images"].numpy().tobytes())
    sampler = torch.utils.data.DistributedSampler(ds, num_replicas=world, rank=rank, shuffle=True, seed=0)
    result = {"len": len(ds), "digest": digest.hexdigest(), "indices": list(sampler)}
    gathered = [None] * world
    dist.all_gather_object(gathered, result)
    if rank == 0:
        torch.save(gathered, out)
    dist.destroy_process_group()


def test_two_process_ddp_sees_identical_datasets(tiny_dataset, tmp_path):
    out = tmp_path / "ddp.pt"
    mp.spawn(_ddp_worker, args=(2, _free_port(), str(tiny_dataset), str(tmp_path / "gen"), str(out)), nprocs=2)
    r0, r1 = torch.load(out)
    assert r0["len"] == r1["len"] == 21 + 3
    assert r0["digest"] == r1["digest"]
    assert sorted(r0["indices"] + r1["indices"]) == list(range(24))


def test_train_order_is_the_same_at_every_iteration_of_an_epoch(tiny_dataset):
    dm = _dm(tiny_dataset, batch_size=21)
    loader = dm.train_dataloader()
    first = next(iter(loader))["object_id"]
    assert next(iter(loader))["object_id"] == first  # Lightning may iterate a loader more than once
    assert sorted(first) == sorted(r.object_id for r in dm.split_records("train"))
    assert first != [r.object_id for r in dm.split_records("train")]  # but it is shuffled
