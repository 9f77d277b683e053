"""Datasets and transforms of lightning_vtr.data.dataset: input checks, the num_views alias, atomic writes, and the
augmentation key each dataset hands its transform."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from lightning_vtr.data.dataset import (
    GeneratedDataset,
    GeneratedSample,
    ImageTransform,
    VTRDataset,
    dump_index,
    load_rgba,
    write_generated_sample,
)
from lightning_vtr.data.format import scan_dataset
from lightning_vtr.data.transforms import IMAGE_RECIPES


def test_image_transform_composites_on_the_background_and_scales():
    rgba = np.zeros((2, 2, 4), np.uint8)
    rgba[0, 0] = (255, 0, 0, 255)  # opaque red
    rgba[0, 1] = (0, 0, 0, 0)  # transparent: the background
    out = ImageTransform(2, background=(0, 51, 255), normalize=None)(rgba)
    assert out.shape == (3, 2, 2)
    assert out[:, 0, 0].tolist() == [1.0, 0.0, 0.0]
    assert torch.allclose(out[:, 0, 1], torch.tensor([0.0, 0.2, 1.0]))


@pytest.mark.parametrize(
    ("kwargs", "error", "match"),
    [
        ({"image_size": 0}, ValueError, r"`image_size` must be an int >= 1, got 0"),
        ({"image_size": 32.0}, TypeError, r"`image_size` must be an int, got float 32.0"),
        (
            {"background": (1, 2)},
            ValueError,
            r"`background` must be three ints \(R, G, B\) in \[0, 255\], got \(1, 2\)",
        ),
        ({"background": (0, 0, 300)}, ValueError, r"`background\[2\]` must be an int in \[0, 255\], got 300"),
        ({"background": 255}, TypeError, r"`background` must be a sequence of three ints"),
        ({"normalize": "unit"}, ValueError, r"`normalize` must be one of 'imagenet', 'pm1', None, got 'unit'"),
    ],
)
def test_image_transform_rejects_bad_arguments(kwargs, error, match):
    with pytest.raises(error, match=match):
        ImageTransform(**kwargs)


def test_image_transform_accepts_numpy_background():
    assert ImageTransform(8, background=np.array([1, 2, 3])).background == (1, 2, 3)


def test_vtr_dataset_num_views(tiny_dataset):
    records = [r for r in scan_dataset(tiny_dataset) if r.split == "test"]
    ds = VTRDataset(records, "hemispherical", num_views=4, transform=ImageTransform(16))
    assert ds.num_views == 4 and len(ds) == len(records)
    assert ds[0]["images"].shape == (4, 3, 16, 16) and ds[0]["view_set"] == "hemispherical"
    with pytest.raises(TypeError, match="n_views"):  # the deprecated alias is gone
        VTRDataset(records, "hemispherical", n_views=4, transform=ImageTransform(16))
    assert not hasattr(ds, "n_views")
    with pytest.raises(ValueError, match=r"`num_views` must be at most the number of views of each object, got 9"):
        VTRDataset(records, "aligned", num_views=9)  # the tiny dataset has 8 views per set
    with pytest.raises(ValueError, match=r"`num_views` must be an int >= 1, got 0"):
        VTRDataset(records, "aligned", num_views=0)


def test_evaluation_repeats_serve_each_object_with_distinct_fixed_view_sets(tiny_dataset):
    records = [r for r in scan_dataset(tiny_dataset) if r.split == "test"]
    single = VTRDataset(records, "spherical", num_views=3, transform=ImageTransform(8))
    first = VTRDataset(records, "spherical", num_views=3, transform=ImageTransform(8), repeats=4)
    again = VTRDataset(records, "spherical", num_views=3, transform=ImageTransform(8), repeats=4)
    assert len(first) == 4 * len(records)
    ids = [first[i]["object_id"] for i in range(len(first))]
    assert ids == [r.object_id for r in records for _ in range(4)]  # T items in a row per object
    for obj in range(len(records)):
        choices = [first.view_indices(4 * obj + r).tolist() for r in range(4)]
        assert len({tuple(sorted(c)) for c in choices}) == 4  # distinct view sets of one object
        assert choices == [again.view_indices(4 * obj + r).tolist() for r in range(4)]  # the same in every build
        assert choices[0] == single.view_indices(obj).tolist()  # the first is the one-repeat choice
        item = first[4 * obj + 2]
        views = np.asarray(records[obj].views["spherical"][1])[choices[2]]
        assert torch.equal(item["viewpoints"], torch.as_tensor(views, dtype=torch.float32))
    other_seed = VTRDataset(records, "spherical", num_views=3, transform=ImageTransform(8), repeats=4, seed=1)
    assert [other_seed.view_indices(i).tolist() for i in range(4)] != [first.view_indices(i).tolist() for i in range(4)]
    # An object with fewer view sets than repeats repeats some: 8 of its 8 views make a single set.
    few = VTRDataset(records[:1], "spherical", num_views=8, transform=ImageTransform(8), repeats=3)
    assert [sorted(few.view_indices(i).tolist()) for i in range(3)] == [list(range(8))] * 3
    with pytest.raises(ValueError, match=r"`repeats` must be 1 in training"):
        VTRDataset(records, "aligned", train=True, repeats=2)
    with pytest.raises(ValueError, match=r"`repeats` must be an int >= 1, got 0"):
        VTRDataset(records, "aligned", repeats=0)


def test_generated_sample_and_index_are_written_atomically(tmp_path):
    images = np.zeros((2, 4, 4, 4), np.uint8)
    images[1, ..., 1] = 200
    images[..., 3] = 255
    sample = GeneratedSample("chair", "c0", images, np.array([[0.0, 10.0], [90.0, -5.0]]), epoch=3)
    entry = write_generated_sample(sample, tmp_path / "s0")
    assert entry == {
        "category": "chair",
        "object_id": "c0",
        "epoch": 3,
        "dir": "s0",
        "images": ["00.png", "01.png"],
        "viewpoints": [[0.0, 10.0], [90.0, -5.0]],
    }
    assert sorted(p.name for p in (tmp_path / "s0").iterdir()) == ["00.png", "01.png"]  # no temporaries left
    assert np.array_equal(load_rgba(tmp_path / "s0" / "01.png"), images[1])
    dump_index([entry], tmp_path / "index.json")
    dump_index([entry, entry], tmp_path / "index.json")  # replaces
    assert json.loads((tmp_path / "index.json").read_text()) == [entry, entry]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["index.json", "s0"]
    with pytest.raises(ValueError, match=r"`images` of generated sample chair/c0 must be \(T, H, W, 4\) uint8"):
        write_generated_sample(GeneratedSample("chair", "c0", images[..., :3], np.zeros((2, 2))), tmp_path / "s1")
    with pytest.raises(ValueError, match=r"`viewpoints` of generated sample chair/c0 must be \(2, 2\), got \(3, 2\)"):
        write_generated_sample(GeneratedSample("chair", "c0", images, np.zeros((3, 2))), tmp_path / "s1")


def test_training_items_are_augmented_by_seed_epoch_and_index(tiny_dataset):
    records = [r for r in scan_dataset(tiny_dataset) if r.split == "train"]
    transform = IMAGE_RECIPES["pix2vox"].train_transform(16)
    ds = VTRDataset(records, "aligned", transform=transform, train=True, seed=4)
    ds.set_epoch(2)
    item = ds[5]
    images = np.stack([load_rgba(records[5].views["aligned"][0][i]) for i in ds.view_indices(5)])
    assert torch.equal(item["images"], transform(images, key=(4, 2, 5)))
    again = VTRDataset(records, "aligned", transform=IMAGE_RECIPES["pix2vox"].train_transform(16), train=True, seed=4)
    again.set_epoch(2)
    assert torch.equal(again[5]["images"], item["images"])  # another instance, same key, same tensors
    ds.set_epoch(3)
    assert not torch.equal(ds[5]["images"], item["images"])
    assert ds.epoch == 3
    with pytest.raises(ValueError, match=r"`epoch` must be an int >= 0, got -1"):
        ds.set_epoch(-1)
    # Any other callable keeps its one-argument form.
    plain = VTRDataset(records, "aligned", transform=lambda x: torch.as_tensor(x.shape), train=True)
    assert plain[0]["images"].tolist() == [3, 64, 64, 4]


def test_generated_items_are_augmented_by_their_sample_id(tmp_path, tiny_dataset):
    records = {(r.category, r.object_id): r for r in scan_dataset(tiny_dataset)}
    (category, object_id), _ = next(iter(records.items()))
    entries = []
    for i in range(3):
        images = np.random.default_rng(i).integers(0, 256, (3, 16, 16, 4), dtype=np.uint8)
        sample = GeneratedSample(category, object_id, images, np.zeros((3, 2)))
        entries.append(write_generated_sample(sample, tmp_path / f"s{i}") | {"id": 10 + i})
    transform = IMAGE_RECIPES["pix2vox"].train_transform(8)
    full = GeneratedDataset(entries, tmp_path, records, transform, seed=1, epoch=5)
    trimmed = GeneratedDataset(entries[1:], tmp_path, records, transform, seed=1, epoch=5)
    assert torch.equal(full[2]["images"], trimmed[1]["images"])  # dropping older samples changes nothing
    images = np.stack([load_rgba(tmp_path / "s2" / n) for n in entries[2]["images"]])
    assert torch.equal(full[2]["images"], transform(images, key=(1, 5, 12, 1)))
    full.set_epoch(6)
    assert not torch.equal(full[2]["images"], trimmed[1]["images"])
