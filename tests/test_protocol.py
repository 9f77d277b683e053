"""lightning_vtr.protocol: the view sets, the model protocol and its check, and that the module stays light."""

from __future__ import annotations

import subprocess
import sys

import pytest

from lightning_vtr.protocol import VIEW_SETS, ReconstructionModel, check_reconstruction_model


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
        "import sys; from lightning_vtr.protocol import VIEW_SETS; "
        "print(sorted(m for m in ('torch', 'lightning') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"
