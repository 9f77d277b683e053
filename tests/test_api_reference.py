"""The API reference covers the public API, in reference style, and its examples run.

The pages under ``docs/api`` render modules with mkdocstrings (``::: module``), which shows a module's public
names that carry a docstring and hides the rest. So: every public package has a page; every name of a rendered
module's ``__all__`` has a docstring (else the page silently omits it); every public function and class there
documents each of its arguments, what it returns and an example; and the ``>>>`` examples pass as doctests.
Docstrings are read with griffe, the loader mkdocstrings itself uses, without importing the modules' code for it.
"""

from __future__ import annotations

import doctest
import importlib
import inspect
import re
from functools import cache
from pathlib import Path

import griffe
import pytest

import lightning_vtr

ROOT = Path(__file__).resolve().parents[1]
API_DIR = ROOT / "docs" / "api"
PACKAGE_DIR = Path(lightning_vtr.__file__).parent
#: Top-level modules without their own API page: the command line (its page is generated from the parsers) and
#: the package's internal helpers.
NO_PAGE = {"cli", "utils"}
_VARIADIC = {"variadic positional", "variadic keyword"}


def rendered_modules() -> list[str]:
    """Every module a ``::: module`` line of an API page renders, in page order."""
    found: list[str] = []
    for page in sorted(API_DIR.glob("*.md")):
        found += re.findall(r"^::: (\S+)", page.read_text(encoding="utf-8"), flags=re.M)
    return found


@cache
def package() -> griffe.Module:
    return griffe.load("lightning_vtr", search_paths=[str(ROOT)], docstring_parser="google")


def public_objects() -> list[tuple[str, griffe.Object]]:
    """``(module, object)`` for each distinct function and class of a rendered module's ``__all__``."""
    seen: dict[str, tuple[str, griffe.Object]] = {}
    for module in rendered_modules():
        names = importlib.import_module(module).__all__
        node = package()[module.removeprefix("lightning_vtr.")]
        for name in names:
            obj = node[name]
            target = obj.final_target if obj.is_alias else obj
            if target.kind.value in ("function", "class"):
                seen.setdefault(target.path, (module, target))
    return list(seen.values())


def _parameters(obj: griffe.Object) -> list[str]:
    function = obj.members.get("__init__") if obj.kind.value == "class" else obj
    if function is None or function.is_alias or function.kind.value != "function":
        return []
    return [p.name for p in function.parameters if p.name not in ("self", "cls") and p.kind.value not in _VARIADIC]


def reference_gaps(obj: griffe.Object) -> list[str]:
    """What the docstring of a public function or class lacks: documented arguments, returns, an example."""
    docstring = obj.docstring
    if docstring is None:
        return ["a docstring"]
    sections = docstring.parse("google")
    documented: set[str] = set()
    kinds = set()
    for section in sections:
        kinds.add(section.kind.value)
        if section.kind.value in ("parameters", "attributes", "other parameters"):
            documented |= {item.name for item in section.value}
    gaps = []
    is_exception = obj.kind.value == "class" and any("Error" in str(base) for base in obj.bases)
    undocumented = [name for name in _parameters(obj) if name not in documented]
    if undocumented and not is_exception:
        gaps.append(f"arguments {undocumented}")
    returns_value = obj.kind.value == "function" and obj.returns is not None and str(obj.returns) != "None"
    if returns_value and not kinds & {"returns", "yields"}:
        gaps.append("a Returns section")
    if not is_exception and "examples" not in kinds and not re.search(r"^\s*Example", docstring.value, re.M):
        gaps.append("an example")
    return gaps


def test_every_public_package_has_an_api_page():
    modules = {p.stem for p in PACKAGE_DIR.iterdir() if (p.suffix == ".py" or p.is_dir()) and p.stem[0] != "_"}
    modules -= NO_PAGE | {"py"}
    pages = {p.stem for p in API_DIR.glob("*.md")} - {"index"}
    assert modules - pages == set(), "public modules without a page under docs/api"
    assert {m.removeprefix("lightning_vtr.").split(".")[0] for m in rendered_modules()} == modules


def test_every_exported_name_is_shown_by_its_page():
    hidden = []
    for module in rendered_modules():
        node = package()[module.removeprefix("lightning_vtr.")]
        hidden += [f"{module}.{name}" for name in importlib.import_module(module).__all__ if not node[name].docstring]
    assert hidden == [], "exported names without a docstring: mkdocstrings leaves them out of the reference"


def test_public_functions_and_classes_are_documented_in_reference_style():
    objects = public_objects()
    assert len(objects) > 150  # the reference covers the whole public API, not a corner of it
    gaps = {obj.path: reference_gaps(obj) for _, obj in objects}
    assert {path: gap for path, gap in gaps.items() if gap} == {}


def test_reference_gaps_are_found():
    """The audit itself: a docstring without arguments, returns or example is caught."""
    module = griffe.temporary_visited_module(
        'def f(x: int, y: int = 1) -> int:\n    """Add."""\n    return x + y\n'
        'def g(x: int) -> int:\n    """Add.\n\n    Args:\n        x: a number.\n\n    Returns:\n        x.\n\n'
        '    Example:\n        >>> g(1)\n        1\n    """\n    return x\n',
        docstring_parser="google",
    )
    with module as mod:
        assert reference_gaps(mod["f"]) == ["arguments ['x', 'y']", "a Returns section", "an example"]
        assert reference_gaps(mod["g"]) == []


@pytest.mark.parametrize("module", sorted(set(rendered_modules())))
def test_the_reference_examples_pass_as_doctests(module):
    imported = importlib.import_module(module)
    finder = doctest.DocTestFinder(exclude_empty=True)
    runner = doctest.DocTestRunner(optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    tests = []
    for name in imported.__all__:
        obj = getattr(imported, name)
        if inspect.isfunction(obj) or inspect.isclass(obj):
            tests += finder.find(obj, name, globs=dict(vars(inspect.getmodule(obj))))
    for test in tests:
        runner.run(test)
    assert runner.summarize(verbose=False).failed == 0
