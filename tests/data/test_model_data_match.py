"""What the datamodule serves and what the model declares: the image size comes from the dataset unless given,
and a model whose ``image_size`` / ``num_views`` / ``voxel_resolution`` disagree fails at setup."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import TinyUserModel, make_trainer, write_rendering_layout

from lightning_vtr.data.datamodule import VTRDataModule
from lightning_vtr.data.format import load_metadata


class CountingModel(TinyUserModel):
    """:class:`TinyUserModel` that counts its training steps."""

    def __init__(self) -> None:
        super().__init__()
        self.steps = 0

    def training_step(self, batch, batch_idx):
        self.steps += 1
        return super().training_step(batch, batch_idx)


def test_image_size_comes_from_the_dataset_unless_given(tiny_dataset):
    meta = load_metadata(tiny_dataset)
    dm = VTRDataModule(str(tiny_dataset), batch_size=2)
    assert dm.image_size == meta["image_size"] == 64 and dm.voxel_resolution == meta["resolution"] == 32
    assert dm.transform.image_size == dm.train_transform.image_size == 64
    assert next(iter(dm.train_dataloader()))["images"].shape == (2, 3, 3, 64, 64)
    assert dm.hparams["image_size"] is None  # a reloaded datamodule reads the dataset again
    resized = VTRDataModule(str(tiny_dataset), image_size=40, batch_size=2)
    assert resized.image_size == 40 and resized.voxel_resolution == 32
    assert next(iter(resized.val_dataloader()))["images"].shape == (2, 3, 3, 40, 40)


def test_shapenet_rendering_image_size_is_its_images_side(tmp_path):
    image = np.zeros((12, 12, 4), dtype=np.uint8)
    image[:, :6] = 255
    layout = write_rendering_layout(tmp_path, {"a": "train", "b": "val"}, image, np.ones((32, 32, 32), dtype=bool))
    dm = VTRDataModule(shapenet_rendering=layout, num_views=2, batch_size=1, test_view_sets=["aligned"])
    assert (dm.image_size, dm.voxel_resolution) == (12, 32)
    assert next(iter(dm.train_dataloader()))["images"].shape == (1, 2, 3, 12, 12)


def test_an_empty_background_folder_still_fails_at_construction_without_a_size(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match="has no images"):
        VTRDataModule(str(tmp_path), background=f"folder:{tmp_path / 'empty'}")


class Res16(CountingModel):
    voxel_resolution = 16


@pytest.mark.parametrize(
    ("model_cls", "dm_kw", "message"),
    [
        (CountingModel, {}, r"^CountingModel\.image_size is 32 but VTRDataModule\.image_size is 64: "),
        (
            CountingModel,
            {"image_size": 32, "num_views": 2},
            r"^CountingModel\.num_views is 3 but VTRDataModule\.num_views is 2: ",
        ),
        (Res16, {"image_size": 32}, r"^Res16\.voxel_resolution is 16 but VTRDataModule\.voxel_resolution is 32: "),
    ],
    ids=["image_size", "num_views", "voxel_resolution"],
)
def test_a_mismatched_model_fails_at_setup_naming_both_values(tiny_dataset, tmp_path, model_cls, dm_kw, message):
    model = model_cls()
    dm = VTRDataModule(str(tiny_dataset), batch_size=4, **dm_kw)
    trainer = make_trainer(tmp_path, 1, [])
    with pytest.raises(ValueError, match=message) as caught:
        trainer.fit(model, datamodule=dm)
    assert "\n" not in str(caught.value) and model.steps == 0  # one line, before any training step


def test_two_mismatches_are_named_in_one_line_and_a_matching_model_trains(tiny_dataset, tmp_path):
    model = Res16()
    dm = VTRDataModule(str(tiny_dataset), batch_size=4, num_views=2)
    with pytest.raises(ValueError, match="^Res16.image_size") as caught:
        make_trainer(tmp_path, 1, []).fit(model, datamodule=dm)
    assert [part.split(":")[0] for part in str(caught.value).split("; ")] == [
        "Res16.image_size is 32 but VTRDataModule.image_size is 64",
        "Res16.num_views is 3 but VTRDataModule.num_views is 2",
        "Res16.voxel_resolution is 16 but VTRDataModule.voxel_resolution is 32",
    ]
    matching = CountingModel()
    trainer = make_trainer(tmp_path, 1, [])
    trainer.fit(matching, datamodule=VTRDataModule(str(tiny_dataset), batch_size=4, image_size=32))
    assert matching.steps == 2 and trainer.global_step == 2


def test_evaluation_serves_another_number_of_views(tiny_dataset, tmp_path):
    # num_views is what the model trains with; validation with 2 views of a 3-view model runs
    dm = VTRDataModule(str(tiny_dataset), batch_size=4, image_size=32, num_views=2)
    (metrics,) = make_trainer(tmp_path, 1, []).validate(TinyUserModel(), datamodule=dm, verbose=False)
    assert 0.0 < metrics["val_loss"] < 10.0
