from __future__ import annotations

import dataclasses
import hashlib
import os
import socket
from types import SimpleNamespace

import numpy as np
import pytest
import torch
import torch.distributed as dist
import torch.multiprocessing as mp

from lightning_vtr.data.datamodule import VTRDataModule
from lightning_vtr.data.dataset import GeneratedSample, ImageTransform
from lightning_vtr.data.transforms import IMAGE_RECIPES, ImageRecipe


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


def test_test_split_val_serves_the_validation_objects_with_repeats(tiny_dataset):
    dm = _dm(tiny_dataset, batch_size=64, test_repeats=2, test_split="val")
    val_ids = {r.object_id for r in dm.split_records("val")}
    test_ids = {r.object_id for r in dm.split_records("test")}
    assert len(val_ids) == 3 and not val_ids & test_ids
    for batch in (next(iter(dl)) for dl in dm.test_dataloader()):
        assert len(batch["object_id"]) == 2 * 3 and set(batch["object_id"]) == val_ids
    assert len(dm.val_dataloader().dataset) == 3  # the validation loader itself keeps one item per object
    with pytest.raises(ValueError, match=r"^`test_split` must be one of 'test', 'val', got 'train'$"):
        VTRDataModule(str(tiny_dataset), test_split="train")


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
    import shutil

    dm = _dm(tiny_dataset, generated_dir=str(tmp_path / "gen"))
    dm.add_samples([_sample(dm, 0), _sample(dm, 1)])
    state = dm.state_dict()
    dirs = [e["dir"] for e in dm.generated_samples]
    # entries name the folder they were written to: the state's `generated_dir` is not where they are read from
    _dm(tiny_dataset).load_state_dict({**state, "generated_dir": str(tmp_path / "elsewhere")})
    # the run's folder moved: restoring fails naming both samples' folders ...
    shutil.move(tmp_path / "gen", tmp_path / "moved")
    with pytest.raises(FileNotFoundError, match="lists 2 generated samples whose folders are missing: ") as info:
        _dm(tiny_dataset).load_state_dict(state)
    assert all(str(tmp_path / "gen" / d) in str(info.value) for d in dirs)
    # ... and `generated_dir` at the new place restores them from there
    restored = _dm(tiny_dataset, generated_dir=str(tmp_path / "moved"))
    restored.load_state_dict(state)
    assert [e["root"] for e in restored.generated_samples] == [str(tmp_path / "moved")] * 2
    # one sample's folder deleted: restoring fails and names that folder only
    shutil.rmtree(tmp_path / "moved" / dirs[1])
    with pytest.raises(FileNotFoundError) as info:
        _dm(tiny_dataset, generated_dir=str(tmp_path / "moved")).load_state_dict(state)
    expected = f"lists 1 generated samples whose folders are missing: {tmp_path / 'moved' / dirs[1]}. Pass"
    assert expected in str(info.value)


def test_max_total_keeps_the_newest(tiny_dataset, tmp_path):
    dm = _dm(tiny_dataset, generated_dir=str(tmp_path / "gen"))
    dm.add_samples([_sample(dm, i) for i in range(3)], max_total=2)
    assert [e["id"] for e in dm.generated_samples] == [1, 2]
    dm.add_samples([_sample(dm, 3)])  # no cap: nothing dropped
    assert [e["id"] for e in dm.generated_samples] == [1, 2, 3]
    dm.add_samples([], max_total=1)
    assert [e["id"] for e in dm.generated_samples] == [3]


def test_the_datamodule_no_longer_caps_generated_samples(tiny_dataset):
    # One owner of the cap: the callback's `max_samples` (passed as `add_samples(max_total=...)`).
    with pytest.raises(ValueError, match=r"`max_generated` must be None .*ErrorGuidedViewAugmentation\(max_samples"):
        VTRDataModule(str(tiny_dataset), max_generated=2)
    dm = _dm(tiny_dataset, max_generated=None)  # what old hyperparameter files hold
    assert not hasattr(dm, "max_generated") and "max_generated" not in dm.hparams


def test_bad_arguments_are_named(tiny_dataset):
    with pytest.raises(ValueError, match=r"`num_views` must be an int >= 1, got 0"):
        VTRDataModule(str(tiny_dataset), num_views=0)
    with pytest.raises(TypeError, match=r"`batch_size` must be an int, got float 4.0"):
        VTRDataModule(str(tiny_dataset), batch_size=4.0)
    with pytest.raises(ValueError, match=r"`max_total` must be an int >= 0, got -1"):
        _dm(tiny_dataset).add_samples([], max_total=-1)
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
    s = _sample(dm)
    s.images = s.images.astype(np.float32)
    with pytest.raises(ValueError, match="uint8"):
        dm.add_samples([s])


def test_num_views_sets_the_views_per_item(tiny_dataset):
    dm = _dm(tiny_dataset, num_views=2, batch_size=3)
    assert dm.num_views == 2
    assert dm.hparams["num_views"] == 2 and "n_views" not in dm.hparams
    assert next(iter(dm.val_dataloader()))["images"].shape == (3, 2, 3, 32, 32)
    with pytest.raises(TypeError, match="n_views"):  # the deprecated alias is gone
        _dm(tiny_dataset, n_views=2)
    assert not hasattr(dm, "n_views")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _ddp_worker(rank, world, port, root, gen_dir, out, recipe="plain"):
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port))
    dist.init_process_group("gloo", rank=rank, world_size=world)
    dm = VTRDataModule(root, image_size=32, generated_dir=gen_dir, recipe=recipe)
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
    # With Pix2Vox++'s recipe: views, random augmentation and generated samples must all agree across ranks.
    out = tmp_path / "ddp.pt"
    args = (2, _free_port(), str(tiny_dataset), str(tmp_path / "gen"), str(out), "pix2vox")
    mp.spawn(_ddp_worker, args=args, nprocs=2)
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


# ---------------------------------------------------------------------------------------------- image recipes
def test_default_recipe_is_the_plain_transform(tiny_dataset):
    dm = _dm(tiny_dataset)
    assert dm.recipe == IMAGE_RECIPES["plain"] and dm.train_transform is dm.transform
    assert not dm.transform.is_random and dm.hparams["recipe"] == "plain"
    custom = _dm(tiny_dataset, background=(0, 0, 0), normalize="pm1")
    assert custom.recipe == ImageRecipe(background=(0, 0, 0), normalize="pm1")
    corner = next(iter(custom.val_dataloader()))["images"][0, 0, :, 0, 0]
    assert corner.tolist() == [-1.0, -1.0, -1.0]  # black background, x * 2 - 1


def test_plain_recipe_with_a_background_range_draws_only_in_training(tiny_dataset):
    dm = _dm(tiny_dataset, normalize=None, background=(240, 240, 240), background_range=(225, 255))
    assert dm.train_transform.is_random and not dm.transform.is_random
    val = next(iter(dm.val_dataloader()))["images"]
    assert torch.allclose(val[..., 0, 0], torch.full_like(val[..., 0, 0], 240 / 255))
    train = next(iter(dm.train_dataloader()))["images"][..., 0, 0] * 255  # (B, T, 3) corner colours
    assert torch.all((train > 224.99) & (train < 255.01))
    assert torch.allclose(train, train[:, :1].expand_as(train))  # one colour per sample, all its views
    assert len({tuple(c.round().tolist()) for c in train[:, 0]}) > 1  # but not one for all samples


@pytest.mark.parametrize("recipe", ["pix2vox", "lrgt"])
def test_reference_recipes_test_on_background_240_in_plus_minus_one(tiny_dataset, recipe):
    dm = _dm(tiny_dataset, recipe=recipe, batch_size=64)
    assert dm.recipe is IMAGE_RECIPES[recipe] and dm.train_transform.is_random
    for batch in [next(iter(dm.val_dataloader()))] + [next(iter(dl)) for dl in dm.test_dataloader()]:
        corners = batch["images"][..., 0, 0]
        assert torch.allclose(corners, torch.full_like(corners, 240 / 255 * 2 - 1), atol=1e-6)
    train = next(iter(dm.train_dataloader()))["images"]
    assert train.shape == (21, 3, 3, 32, 32)
    if recipe == "lrgt":  # no jitter: [0, 1] images, so [-1, 1]; Pix2Vox++'s unclamped jitter leaves it
        assert train.min() >= -1.0 and train.max() <= 1.0


def test_recipe_augmentation_depends_on_seed_epoch_and_index_only(tiny_dataset):
    def items(dm, epoch):
        dm.trainer = SimpleNamespace(current_epoch=epoch, reload_dataloaders_every_n_epochs=1)
        ds = dm.train_dataset()
        return torch.stack([ds[i]["images"] for i in range(len(ds))])

    first = items(_dm(tiny_dataset, recipe="pix2vox"), 3)
    # A resumed run's datamodule at the same epoch, and one that saw other epochs first, serve the same tensors.
    later = _dm(tiny_dataset, recipe="pix2vox")
    items(later, 0)
    assert torch.equal(items(later, 3), first)
    assert not torch.equal(items(later, 4), first)  # a new epoch, new augmentation
    assert not torch.equal(items(_dm(tiny_dataset, recipe="pix2vox", seed=1), 3), first)


def test_recipe_augmentation_does_not_depend_on_dataloader_workers(tiny_dataset):
    batches = []
    for workers in (0, 2):
        dm = _dm(tiny_dataset, recipe="pix2vox", num_workers=workers, batch_size=8)
        batches.append([b["images"] for b in dm.train_dataloader()])
    assert len(batches[0]) == len(batches[1]) == 3
    assert all(torch.equal(a, b) for a, b in zip(*batches))


def test_recipe_object_and_conflicting_arguments(tiny_dataset):
    mine = dataclasses.replace(IMAGE_RECIPES["pix2vox"], normalize="imagenet")
    dm = _dm(tiny_dataset, recipe=mine)
    assert dm.recipe is mine and dm.transform.normalize == "imagenet"
    with pytest.raises(ValueError, match=r"`normalize` must be left at its default 'imagenet' with `recipe='lrgt'`"):
        VTRDataModule(str(tiny_dataset), recipe="lrgt", normalize=None)
    with pytest.raises(ValueError, match=r"`background` must be left at its default"):
        VTRDataModule(str(tiny_dataset), recipe="pix2vox", background=(240, 240, 240))
    with pytest.raises(ValueError, match=r"`background_range` must be left at its default None"):
        VTRDataModule(str(tiny_dataset), recipe=mine, background_range=(0, 255))
    with pytest.raises(ValueError, match=r"`recipe` must be one of 'plain', 'pix2vox', 'lrgt', got 'pix2vox\+\+'"):
        VTRDataModule(str(tiny_dataset), recipe="pix2vox++")
    with pytest.raises(TypeError, match=r"`recipe` must be a recipe name, an ImageRecipe or a dict of its fields"):
        VTRDataModule(str(tiny_dataset), recipe=0.9)
    # A recipe object lands in the hyperparameters as a dict of its fields, which rebuilds the same recipe.
    assert dm.hparams["recipe"] == dataclasses.asdict(mine)
    assert VTRDataModule(str(tiny_dataset), recipe=dm.hparams["recipe"]).recipe == mine
    with pytest.raises(ValueError, match=r"`normalize` must be one of 'imagenet', 'pm1', None, got 'half'"):
        VTRDataModule(str(tiny_dataset), normalize="half")


def test_random_recipe_warns_without_a_reload_every_epoch(tiny_dataset):
    dm = _dm(tiny_dataset, recipe="lrgt")
    dm.trainer = SimpleNamespace(current_epoch=0, reload_dataloaders_every_n_epochs=0)
    with pytest.warns(UserWarning, match=r"reload_dataloaders_every_n_epochs=0"):
        dm.train_dataloader()
    plain = _dm(tiny_dataset)
    plain.trainer = dm.trainer
    plain.train_dataloader()  # the plain recipe draws nothing, so nothing to warn about
