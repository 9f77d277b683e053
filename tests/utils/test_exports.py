"""Lazy re-exports: the helper itself, and every package ``__init__`` of lightning_vtr using it consistently."""

from __future__ import annotations

import ast
import importlib
import subprocess
import sys
from pathlib import Path

import pytest

import lightning_vtr
from lightning_vtr.utils.exports import lazy_exports

PACKAGE_DIR = Path(lightning_vtr.__file__).parent
#: Package ``__init__`` modules that re-export names (the others hold a docstring only).
REEXPORTING = sorted(
    path
    for path in PACKAGE_DIR.rglob("__init__.py")
    if any(isinstance(node, ast.ImportFrom) for node in ast.parse(path.read_text(encoding="utf-8")).body)
)


def _package_name(path: Path) -> str:
    return ".".join(["lightning_vtr", *path.parent.relative_to(PACKAGE_DIR).parts])


def _type_checking_block(tree: ast.Module) -> ast.If:
    return next(n for n in tree.body if isinstance(n, ast.If) and getattr(n.test, "id", None) == "TYPE_CHECKING")


def _lazy_mapping(tree: ast.Module) -> dict[str, list[str]]:
    """The literal mapping given to ``lazy_exports`` in the ``else:`` branch of ``if TYPE_CHECKING:``."""
    for node in _type_checking_block(tree).orelse:
        call = node.value if isinstance(node, ast.Assign) else None
        if isinstance(call, ast.Call) and getattr(call.func, "id", None) == "lazy_exports":
            return ast.literal_eval(call.args[1])
    raise AssertionError("no `else: __getattr__, __dir__ = lazy_exports(__name__, {...})` after `if TYPE_CHECKING:`")


def _type_checking_imports(tree: ast.Module) -> dict[str, list[str]]:
    block = _type_checking_block(tree)
    return {node.module: [a.name for a in node.names] for node in block.body if isinstance(node, ast.ImportFrom)}


def _write_package(root: Path, name: str) -> None:
    (root / name).mkdir()
    (root / name / "__init__.py").write_text(
        "from typing import TYPE_CHECKING\n"
        "from lightning_vtr.utils.exports import lazy_exports\n"
        "if TYPE_CHECKING:\n"
        f"    from {name}.heavy import VALUE\n"
        "else:\n"
        f"    __getattr__, __dir__ = lazy_exports(__name__, {{'{name}.heavy': ['VALUE']}})\n"
        "__all__ = ['VALUE']\n"
    )
    (root / name / "heavy.py").write_text("VALUE = 42\n")


def test_a_name_is_imported_on_first_use_and_kept(tmp_path, monkeypatch):
    _write_package(tmp_path, "lazy_pkg_a")
    monkeypatch.syspath_prepend(str(tmp_path))
    package = importlib.import_module("lazy_pkg_a")
    try:
        assert "lazy_pkg_a.heavy" not in sys.modules
        assert "VALUE" in dir(package) and "VALUE" not in vars(package)
        assert package.VALUE == 42
        assert "lazy_pkg_a.heavy" in sys.modules
        assert vars(package)["VALUE"] == 42  # stored: the next lookup does not go through __getattr__
        with pytest.raises(AttributeError, match="module 'lazy_pkg_a' has no attribute 'OTHER'"):
            package.OTHER  # noqa: B018
    finally:
        for name in ("lazy_pkg_a", "lazy_pkg_a.heavy"):
            sys.modules.pop(name, None)


def test_a_name_listed_under_two_modules_is_refused():
    with pytest.raises(ValueError, match=r"each name once, got 'x' under 'pkg.a' and 'pkg.b'"):
        lazy_exports("pkg", {"pkg.a": ["x"], "pkg.b": ["y", "x"]})


def test_every_reexporting_package_is_found():
    names = {_package_name(path) for path in REEXPORTING}
    assert {"lightning_vtr", "lightning_vtr.data", "lightning_vtr.selection", "lightning_vtr.cli"} <= names


@pytest.mark.parametrize("path", REEXPORTING, ids=_package_name)
def test_the_package_reexports_lazily_and_its_three_lists_agree(path):
    tree = ast.parse(path.read_text(encoding="utf-8"))
    eager = [
        f"line {node.lineno}: from {node.module} import ..."
        for node in tree.body
        if isinstance(node, ast.ImportFrom)
        and (node.module or "").startswith("lightning_vtr")
        and node.module != "lightning_vtr.utils.exports"
    ]
    assert eager == [], "a package re-exports through lazy_exports only, never by a module-level import"
    mapping = _lazy_mapping(tree)
    assert _type_checking_imports(tree) == mapping, "the TYPE_CHECKING imports must match the lazy_exports mapping"
    package = importlib.import_module(_package_name(path))
    lazy_names = {name for names in mapping.values() for name in names}
    assert set(package.__all__) - lazy_names <= {"__version__"}
    assert lazy_names <= set(package.__all__)
    submodules = {p.stem for p in path.parent.iterdir() if p.suffix == ".py" or (p / "__init__.py").exists()}
    assert lazy_names & submodules == set(), "an exported name must not shadow a submodule"
    for module, names in mapping.items():
        defining = importlib.import_module(module)
        for name in names:
            assert getattr(package, name) is getattr(defining, name), f"{package.__name__}.{name}"


def test_one_module_of_a_package_imports_without_its_siblings_dependencies():
    code = (
        "import sys\n"
        "import lightning_vtr.synthesis.pose, lightning_vtr.selection.bins, lightning_vtr.metrics.functional\n"
        "import lightning_vtr.cli, lightning_vtr.models, lightning_vtr.evaluation\n"
        "print(sorted(m for m in ('lightning', 'matplotlib', 'transformers', 'torchmetrics') if m in sys.modules))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"
