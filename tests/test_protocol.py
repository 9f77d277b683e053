"""lightning_vtr.protocol: the view sets, the model protocol and its check, and that the module stays light."""

from __future__ import annotations

import subprocess
import sys

import pytest

from lightning_vtr.protocol import (
    DEFAULT_THRESHOLD,
    VIEW_SETS,
    AugmentableDataModule,
    ReconstructionModel,
    check_augmentable_datamodule,
    check_reconstruction_model,
)


class _Duck:
    """Satisfies the protocol without inheriting anything."""

    image_size = 64
    num_views = 3
    voxel_resolution = 32

    def predict_voxels(self, images):
        return images


def test_view_sets_are_the_papers_three_in_table_order():
    assert VIEW_SETS == ("aligned", "hemispherical", "spherical")
    assert isinstance(VIEW_SETS, tuple)  # immutable: one shared object everywhere


def test_view_sets_have_one_home():
    import lightning_vtr.data
    import lightning_vtr.data.builder
    import lightning_vtr.data.datamodule
    import lightning_vtr.data.format
    import lightning_vtr.models
    import lightning_vtr.models.base

    assert lightning_vtr.data.VIEW_SETS is lightning_vtr.models.VIEW_SETS is VIEW_SETS
    for module in (
        lightning_vtr.data.format,
        lightning_vtr.data.datamodule,
        lightning_vtr.data.builder,
        lightning_vtr.models.base,
    ):
        assert module.VIEW_SETS is VIEW_SETS, module.__name__


def test_a_duck_typed_model_satisfies_the_protocol():
    model = _Duck()
    assert isinstance(model, ReconstructionModel)
    check_reconstruction_model(model)


def test_check_names_what_is_missing():
    class NoViews:
        image_size = 64
        voxel_resolution = 32

    with pytest.raises(TypeError, match=r"NoViews does not satisfy .*missing num_views, predict_voxels"):
        check_reconstruction_model(NoViews())
    assert not isinstance(NoViews(), ReconstructionModel)


def test_importing_the_protocol_imports_neither_torch_nor_lightning():
    code = (
        "import sys; from lightning_vtr.protocol import VIEW_SETS, DEFAULT_THRESHOLD, AugmentableDataModule; "
        "print(sorted(m for m in ('torch', 'lightning') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


class _DuckDataModule:
    """Has every member of AugmentableDataModule without inheriting anything."""

    transform = staticmethod(lambda images: images)
    generated_samples: list = []  # noqa: RUF012 (a stand-in datamodule's attribute)

    def split_records(self, split):
        return []

    def record(self, category, object_id):
        return None

    def eval_item(self, record, view_set="aligned", seed=0):
        return {}

    def object_views(self, record, view_set="aligned", indices=None):
        return None, None

    def add_samples(self, samples, *, max_total=None):
        return []


def test_a_duck_typed_datamodule_satisfies_the_protocol():
    dm = _DuckDataModule()
    assert isinstance(dm, AugmentableDataModule)
    check_augmentable_datamodule(dm)


def test_datamodule_check_names_the_missing_method():
    class NoEvalItem(_DuckDataModule):
        eval_item = None

    with pytest.raises(TypeError) as info:
        check_augmentable_datamodule(NoEvalItem())
    assert str(info.value) == (
        "NoEvalItem does not satisfy lightning_vtr.AugmentableDataModule: missing eval_item(record, view_set, seed). "
        "Use lightning_vtr.data.VTRDataModule or add these members (see lightning_vtr.protocol.AugmentableDataModule)."
    )


def test_datamodule_check_names_everything_missing_at_once():
    class OldAddSamples(_DuckDataModule):
        transform = None

        def add_samples(self, samples):
            return []

    with pytest.raises(
        TypeError,
        match=r"missing add_samples\(samples, \*, max_total\) \(its add_samples takes no "
        r"max_total\), transform\. ",
    ):
        check_augmentable_datamodule(OldAddSamples())


def test_vtr_datamodule_satisfies_the_datamodule_protocol(tiny_dataset):
    from lightning_vtr.data import VTRDataModule

    check_augmentable_datamodule(VTRDataModule(str(tiny_dataset), image_size=32))


def test_the_threshold_is_one_constant():
    import lightning_vtr.metrics

    assert DEFAULT_THRESHOLD == 0.4 and lightning_vtr.metrics.DEFAULT_THRESHOLD is DEFAULT_THRESHOLD
