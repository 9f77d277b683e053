"""A synthesizer that cannot serve the dataset is refused at setup, before any training."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import TinyUserModel, make_trainer, write_rendering_layout

from lightning_vtr.callback import ErrorGuidedViewAugmentation
from lightning_vtr.data.datamodule import VTRDataModule
from lightning_vtr.data.format import ObjectRecord
from lightning_vtr.synthesis import CachedSynthesizer, RenderSynthesizer, Synthesizer

MODELS = {"chairA": "train", "chairB": "train", "chairC": "train", "chairD": "val", "chairE": "test"}


@pytest.fixture
def rendering_layout(tmp_path):
    """3D-R2N2's layout (images + voxels, no meshes): 3 train, 1 val, 1 test chair of 4 32-px views."""
    image = np.zeros((32, 32, 4), dtype=np.uint8)
    image[8:24, 8:24] = (120, 60, 30, 255)
    voxels = np.zeros((32, 32, 32), dtype=bool)
    voxels[8:24, 8:24, 8:24] = True
    return write_rendering_layout(tmp_path, MODELS, image, voxels)


def _datamodule(layout, tmp_path) -> VTRDataModule:
    return VTRDataModule(
        shapenet_rendering=layout,
        image_size=32,
        batch_size=2,
        test_view_sets=["aligned"],
        generated_dir=str(tmp_path / "gen"),
    )


class CountingModel(TinyUserModel):
    """Counts its training steps: the refusal must come before the first."""

    def __init__(self) -> None:
        super().__init__()
        self.steps = 0

    def training_step(self, batch, batch_idx):
        self.steps += 1
        return super().training_step(batch, batch_idx)


class ImagesOnlySynthesizer(Synthesizer):
    """A Zero-1-to-3 stand-in: needs the source images only; returns its input's first view per target."""

    image_size = 32

    def __init__(self) -> None:
        self.calls = 0

    def synthesize(self, requests):
        self.calls += 1
        return [np.repeat(r.source_images[:1], len(r.target_viewpoints), axis=0) for r in requests]


# ------------------------------------------------------------------------------------------ the check itself


def test_render_synthesizer_refuses_records_without_meshes(rendering_layout, tmp_path):
    dm = _datamodule(rendering_layout, tmp_path)
    dm.setup("fit")
    train = dm.split_records("train")
    with pytest.raises(ValueError, match="RenderSynthesizer renders each object's mesh") as info:
        RenderSynthesizer().check_serves(train)
    message = str(info.value)
    assert message.startswith("RenderSynthesizer renders each object's mesh, but 3 of 3 training objects have none")
    first_dir = f"{rendering_layout['rendering_root']}/03001627/chairA/rendering"
    assert f"(first: chair/chairA (images in {first_dir}))" in message
    assert "Zero123Synthesizer" in message and "lightning-vtr build-dataset" in message
    # Through the cache wrapper too (it serves what it wraps).
    with pytest.raises(ValueError, match="RenderSynthesizer renders each object's mesh, but 3 of 3"):
        CachedSynthesizer(RenderSynthesizer(), tmp_path / "cache").check_serves(train)
    # Objects with a mesh pass; the count is of those without.
    meshed = [ObjectRecord(r.category, r.object_id, r.split, r.voxel_path, tmp_path / "m.ply", r.views) for r in train]
    RenderSynthesizer().check_serves(meshed)
    with pytest.raises(ValueError, match=r"but 1 of 3 training objects have none \(first: chair/chairB"):
        RenderSynthesizer().check_serves([meshed[0], train[1], meshed[2]])


def test_image_synthesizers_need_images_only(rendering_layout, tmp_path):
    dm = _datamodule(rendering_layout, tmp_path)
    dm.setup("fit")
    train = dm.split_records("train")
    ImagesOnlySynthesizer().check_serves(train, view_set="aligned")  # no mesh needed
    CachedSynthesizer(ImagesOnlySynthesizer(), tmp_path / "cache").check_serves(train, view_set="aligned")
    with pytest.raises(ValueError, match="ImagesOnlySynthesizer synthesizes from") as info:
        ImagesOnlySynthesizer().check_serves(train, view_set="spherical")
    assert str(info.value).startswith(
        "ImagesOnlySynthesizer synthesizes from an object's source images, but 3 of 3 training objects have no "
        "image in view set 'spherical' (first: chair/chairA"
    )
    no_images = ObjectRecord("chair", "bare", "train", train[0].voxel_path, None, {"aligned": ([], np.zeros((0, 2)))})
    with pytest.raises(ValueError, match=r"1 of 4 training objects have no image in any view set \(first: chair/bare"):
        ImagesOnlySynthesizer().check_serves([*train, no_images])


# ------------------------------------------------------------------------------------------ at setup


def test_fit_refuses_render_synthesis_at_setup_before_any_training_step(rendering_layout, tmp_path):
    model = CountingModel()
    callback = ErrorGuidedViewAugmentation(synthesizer=RenderSynthesizer(image_size=32), progress_bar=False)
    trainer = make_trainer(tmp_path, 2, [callback])
    with pytest.raises(ValueError, match="RenderSynthesizer renders each object's mesh, but 3 of 3") as info:
        trainer.fit(model, datamodule=_datamodule(rendering_layout, tmp_path))
    assert "Zero123Synthesizer" in str(info.value) and "lightning-vtr build-dataset" in str(info.value)
    assert model.steps == 0 and trainer.global_step == 0
    assert callback.last_epoch < 0  # nothing was selected or synthesized


def test_default_synthesizer_is_refused_too(rendering_layout, tmp_path):
    # The callback's default synthesizer renders meshes, which a dataset without meshes cannot serve.
    model = CountingModel()
    trainer = make_trainer(tmp_path, 2, [ErrorGuidedViewAugmentation(progress_bar=False)])
    with pytest.raises(ValueError, match="RenderSynthesizer renders each object's mesh"):
        trainer.fit(model, datamodule=_datamodule(rendering_layout, tmp_path))
    assert model.steps == 0


def test_an_images_only_synthesizer_passes_setup_and_trains(rendering_layout, tmp_path):
    model = CountingModel()
    synthesizer = ImagesOnlySynthesizer()
    callback = ErrorGuidedViewAugmentation(synthesizer=synthesizer, progress_bar=False, log_images=False)
    trainer = make_trainer(tmp_path, 2, [callback], num_sanity_val_steps=0)
    trainer.fit(model, datamodule=_datamodule(rendering_layout, tmp_path))
    assert model.steps == 4  # 2 epochs x 2 batches (3 objects, batch 2)
    assert synthesizer.calls >= 1  # epoch 0's end synthesized from the images
