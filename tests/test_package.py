"""The top-level package: lazily exported names, visible to dir(), without importing Lightning up front."""

from __future__ import annotations

import subprocess
import sys

import pytest

import lightning_vtr


def test_lazy_names_resolve_to_their_modules_objects():
    from lightning_vtr.callback import ErrorGuidedViewAugmentation
    from lightning_vtr.data.datamodule import VTRDataModule
    from lightning_vtr.protocol import ReconstructionModel, check_reconstruction_model
    from lightning_vtr.selection.registry import SELECTORS

    assert lightning_vtr.ErrorGuidedViewAugmentation is ErrorGuidedViewAugmentation
    assert lightning_vtr.VTRDataModule is VTRDataModule
    assert lightning_vtr.ReconstructionModel is ReconstructionModel
    assert lightning_vtr.check_reconstruction_model is check_reconstruction_model
    assert lightning_vtr.SELECTORS is SELECTORS


def test_dir_lists_every_exported_name():
    assert set(lightning_vtr.__all__) <= set(dir(lightning_vtr))
    assert {"ErrorGuidedViewAugmentation", "SELECTORS", "VTRDataModule", "__version__"} <= set(lightning_vtr.__all__)


def test_unknown_name_raises_attribute_error():
    with pytest.raises(AttributeError, match="has no attribute 'Nope'"):
        lightning_vtr.Nope  # noqa: B018


def test_import_stays_light():
    # dataset build workers import the package and must not pay for Lightning
    code = "import lightning_vtr, sys; dir(lightning_vtr); print('lightning' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"
