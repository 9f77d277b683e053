"""Imports go one way: the plugin layer never imports the experiments or the command line, ``data`` never imports
``models``, only the command line imports the command line, and no module of the package imports the research
folder beside it (``research/``).

Every ``import`` and ``from ... import`` of every module is read with :mod:`ast`, at module level and inside
functions, classes and ``if TYPE_CHECKING:`` blocks alike; relative imports are resolved against the module.
"""

from __future__ import annotations

import ast
from collections.abc import Iterator
from pathlib import Path

import lightning_vtr

PACKAGE = "lightning_vtr"
PACKAGE_DIR = Path(lightning_vtr.__file__).parent
#: The reusable layer: modules and packages a Lightning user imports without the experiments or the CLI.
PLUGIN_LAYER = (
    "callback",
    "augmentation",
    "protocol",
    "geometry",
    "renderer",
    "errors",
    "selection",
    "synthesis",
    "data",
    "models",
    "metrics",
    "evaluation",
    "visualize",
    "export",
    "utils",
)
#: (importing part, imported part, why): ``importer`` / ``imported`` are first components under the package.
RULES = (
    *((part, "experiments", "the plugin layer must not import the experiments") for part in PLUGIN_LAYER),
    *((part, "cli", "the plugin layer must not import the command line") for part in PLUGIN_LAYER),
    ("data", "models", "data must not import models"),
)


#: The research folder beside the package (``research/`` at the repository root): it imports the package, never the
#: other way round.
RESEARCH = "research"


def module_name(path: Path, root: Path = PACKAGE_DIR) -> str:
    """``lightning_vtr.a.b`` for ``root/a/b.py`` (``lightning_vtr.a`` for ``root/a/__init__.py``)."""
    parts = [PACKAGE, *path.relative_to(root).with_suffix("").parts]
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imported_modules(source: str, module: str, is_package: bool = False) -> Iterator[tuple[int, str]]:
    """``(line, absolute module name)`` of every import in ``source``, at any depth; ``from X import y`` gives
    ``X`` (``X.y`` when ``X`` is the package itself), relative forms resolved against ``module``."""
    package = module if is_package else module.rpartition(".")[0]
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield node.lineno, alias.name
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base_parts = package.split(".")
                base_parts = base_parts[: len(base_parts) - (node.level - 1)]
                base = ".".join(base_parts + ([node.module] if node.module else []))
            else:
                base = node.module or ""
            if base == PACKAGE:  # from lightning_vtr import cli: the names are the package's parts
                yield from ((node.lineno, f"{base}.{alias.name}") for alias in node.names if alias.name != "*")
            else:
                yield node.lineno, base


def _part(module: str) -> str | None:
    """The first component under the package (``data`` for ``lightning_vtr.data.format``), else ``None``."""
    head, _, rest = module.partition(".")
    return rest.split(".")[0] if head == PACKAGE and rest else None


def violations(source: str, module: str, is_package: bool = False) -> list[str]:
    """The forbidden imports of one module's source, one line each (``module:line imports X: why``)."""
    importer = _part(module)
    found = []
    for line, imported in imported_modules(source, module, is_package):
        target = _part(imported)
        if target is None or target == importer:
            continue
        reasons = [why for part, forbidden, why in RULES if part == importer and forbidden == target]
        if target == "cli" and importer != "cli" and not reasons:
            reasons = ["only the command line imports the command line"]
        found += [f"{module}:{line} imports {imported}: {why}" for why in reasons]
    for line, imported in imported_modules(source, module, is_package):
        if imported.partition(".")[0] == RESEARCH:
            found.append(f"{module}:{line} imports {imported}: the package must not import the research folder")
    return sorted(set(found))


def package_violations(root: Path = PACKAGE_DIR) -> list[str]:
    """The forbidden imports of every module under ``root``."""
    found = []
    for path in sorted(root.rglob("*.py")):
        found += violations(path.read_text(encoding="utf-8"), module_name(path, root), path.name == "__init__.py")
    return found


def test_the_package_has_no_forbidden_import():
    assert package_violations() == []


def test_every_module_is_read():
    names = {module_name(p) for p in PACKAGE_DIR.rglob("*.py")}
    assert {"lightning_vtr.data.format", "lightning_vtr.cli.predict", "lightning_vtr.models"} <= names
    assert {"lightning_vtr.evaluation.predict", "lightning_vtr.models.registry"} <= names


def test_a_function_level_import_of_models_in_data_is_reported():
    source = "def load():\n    from lightning_vtr.models.registry import load_model\n    return load_model\n"
    assert violations(source, "lightning_vtr.data.folder_test_set") == [
        "lightning_vtr.data.folder_test_set:2 imports lightning_vtr.models.registry: data must not import models"
    ]


def test_relative_and_type_checking_imports_are_resolved_and_reported():
    source = (
        "from typing import TYPE_CHECKING\n"
        "if TYPE_CHECKING:\n"
        "    from ..experiments import training\n"
        "from .. import cli\n"
        "from . import geometry_helpers\n"
    )
    found = violations(source, "lightning_vtr.evaluation.dataset")
    assert "lightning_vtr.evaluation.dataset:3 imports lightning_vtr.experiments: " in "\n".join(found) + ": "
    assert any(v.startswith("lightning_vtr.evaluation.dataset:4 imports lightning_vtr.cli:") for v in found)
    assert not any("geometry_helpers" in v for v in found)  # lightning_vtr.evaluation.geometry_helpers: allowed


def test_the_plugin_layer_importing_experiments_or_cli_is_reported():
    for part in PLUGIN_LAYER:
        module = f"lightning_vtr.{part}"
        assert violations("import lightning_vtr.experiments.training\n", module) == [
            f"{module}:1 imports lightning_vtr.experiments.training: the plugin layer must not import the experiments"
        ]
        assert violations("from lightning_vtr.cli.predict import run\n", module, is_package=True) != []


def test_an_import_of_the_research_folder_is_reported_at_any_depth():
    source = "def study():\n    from research.scores import MapScore\n    import research\n    return MapScore\n"
    assert violations(source, "lightning_vtr.selection.scores") == [
        "lightning_vtr.selection.scores:2 imports research.scores: the package must not import the research folder",
        "lightning_vtr.selection.scores:3 imports research: the package must not import the research folder",
    ]
    assert violations("import researchers\n", "lightning_vtr.selection.scores") == []


def test_only_the_cli_imports_the_cli():
    assert violations("import lightning_vtr.cli\n", "lightning_vtr.cli.report") == []
    assert violations("from lightning_vtr import cli\n", "lightning_vtr.experiments.report") == [
        "lightning_vtr.experiments.report:1 imports lightning_vtr.cli: only the command line imports the command line"
    ]
    assert violations("from lightning_vtr.models import load_model\n", "lightning_vtr.experiments.training") == []


def test_a_forbidden_import_written_into_a_package_copy_is_found(tmp_path):
    (tmp_path / "data").mkdir()
    (tmp_path / "data" / "__init__.py").write_text("")
    (tmp_path / "data" / "reader.py").write_text("def f():\n    from ..models import MODELS\n    return MODELS\n")
    assert package_violations(tmp_path) == [
        "lightning_vtr.data.reader:2 imports lightning_vtr.models: data must not import models"
    ]
