"""The lazy ``lightning_vtr.data`` package: visible names, one object per name, no Lightning in build workers."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

import lightning_vtr.data
from lightning_vtr.protocol import VIEW_SETS


def test_dir_lists_every_export():
    names = dir(lightning_vtr.data)
    assert set(lightning_vtr.data.__all__) <= set(names)
    assert {"VTRDataModule", "VIEW_SETS", "build_dataset", "scan_dataset", "ImageTransform"} <= set(names)


def test_every_export_resolves_to_its_module_object():
    from lightning_vtr.data import builder, datamodule, dataset, format, shapenet_rendering

    assert lightning_vtr.data.VIEW_SETS is VIEW_SETS
    assert lightning_vtr.data.VTRDataModule is datamodule.VTRDataModule
    assert lightning_vtr.data.build_dataset is builder.build_dataset
    assert lightning_vtr.data.ImageTransform is dataset.ImageTransform
    assert lightning_vtr.data.scan_dataset is format.scan_dataset
    assert lightning_vtr.data.ShapeNetRenderingSource is shapenet_rendering.ShapeNetRenderingSource
    for name in lightning_vtr.data.__all__:
        assert getattr(lightning_vtr.data, name) is not None
    with pytest.raises(AttributeError, match="has no attribute 'nope'"):
        lightning_vtr.data.nope  # noqa: B018


def test_type_checking_imports_cover_the_exports():
    """Type checkers and IDEs read the ``if TYPE_CHECKING:`` block: it must import every lazy name."""
    tree = ast.parse(Path(lightning_vtr.data.__file__).read_text())
    block = next(n for n in tree.body if isinstance(n, ast.If) and getattr(n.test, "id", None) == "TYPE_CHECKING")
    imported = {alias.asname or alias.name for node in block.body for alias in node.names}
    assert imported == set(lightning_vtr.data.__all__)


def test_build_worker_modules_do_not_import_lightning():
    code = (
        "import sys\n"
        "import lightning_vtr.data\n"
        "from lightning_vtr.data import VIEW_SETS, build_dataset, scan_dataset\n"
        "import lightning_vtr.data.binvox, lightning_vtr.data.mesh, lightning_vtr.data.procedural\n"
        "import lightning_vtr.data.voxelize, lightning_vtr.data.dataset, lightning_vtr.data.shapenet_rendering\n"
        "print('lightning' in sys.modules)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"
