"""Reading back the JSON files an earlier run wrote into its output folder, checked against what it writes.

An output folder may come from someone else (``lightning-vtr report --out`` resumes from it), so every cached
file is data to check: :func:`read_output_json` parses it under the size limit of
:func:`~lightning_vtr.utils.limits.read_json` and checks the type of every field the report uses against a
schema (:class:`Fields`, :class:`DictOf`, :class:`ListOf` and the leaf kinds :data:`NUMBER`, :data:`INT`,
:data:`STRING`, :data:`ANYTHING`). A file that is not valid JSON or does not match is refused with one line naming
the file, the field, the type expected and the type found, and what to do
(:class:`~lightning_vtr.errors.DataError`, exit status 1 in ``lightning-vtr``).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from lightning_vtr.errors import DataError

__all__ = [
    "ANYTHING",
    "INT",
    "NUMBER",
    "PRETRAIN_TIMING",
    "REPORT_TIMING",
    "RUN_RESULTS",
    "SELECTION_RECORD",
    "STRING",
    "VALIDATION",
    "DictOf",
    "Fields",
    "ListOf",
    "read_output_json",
    "run_remedy",
]

NUMBER = "a number"
"""An int or a float (NaN and infinities included; JSON's ``true``/``false`` are not numbers)."""
INT = "an int"
"""An int (not a bool)."""
STRING = "a string"
"""A string."""
ANYTHING = "any JSON value"
"""Any value nested at most :data:`MAX_DEPTH` levels deep."""

MAX_DEPTH = 32
"""The deepest nesting accepted in a field of :data:`ANYTHING` (a configuration's values are a few levels deep)."""


@dataclass(frozen=True)
class DictOf:
    """A dict whose every value matches ``values``."""

    values: Any


@dataclass(frozen=True)
class ListOf:
    """A list whose every item matches ``items``; of exactly ``length`` items unless ``None``."""

    items: Any
    length: int | None = None


@dataclass(frozen=True)
class Fields:
    """A dict whose fields named in ``specs`` match their spec when present; those in ``required`` must be."""

    specs: dict[str, Any]
    required: tuple[str, ...] = field(default=())


_METRICS = DictOf(DictOf(NUMBER))
"""``{view_set: {metric: value}}``, per-category entries under ``"<view_set>/<category>"``."""

RUN_RESULTS = Fields(
    {
        "strategy": STRING,
        "source_run": STRING,
        "num_views": INT,
        "config": DictOf(ANYTHING),
        "train_seconds": NUMBER,
        "eval_seconds": NUMBER,
        "timing": DictOf(NUMBER),
        "generated_samples": INT,
        "results": _METRICS,
    },
    required=("train_seconds", "results"),
)
"""A run's ``results.json`` (:func:`~lightning_vtr.experiments.training.run_strategy` and the single-view runs)."""
VALIDATION = Fields({"repeats": INT, "results": _METRICS}, required=("repeats", "results"))
"""A run's ``validation.json`` (:func:`~lightning_vtr.experiments.training.validate_run`)."""
PRETRAIN_TIMING = Fields({"seconds": DictOf(NUMBER)})
"""A seed's ``pretrain/timing.json``: the pretraining's seconds per stage."""
REPORT_TIMING = Fields({"invocations": ListOf(NUMBER), "split": ANYTHING}, required=("invocations",))
"""The report's ``timing.json``: the wall time of every invocation and the last time split."""
SELECTION_RECORD = Fields({"view_sets": ListOf(ListOf(ListOf(NUMBER, length=2)))})
"""A run's ``vtr_selection/*.json`` record: the ``(n, 2)`` viewpoints (degrees) of every generated sample."""


def run_remedy(run_dir: Path) -> str:
    """What to do about a bad cached file of the run in ``run_dir``."""
    return f"delete that run's folder ({run_dir}) to run it again"


class _Mismatch(Exception):
    def __init__(self, where: list[str | int], expected: str, found: str) -> None:
        super().__init__(where, expected, found)
        self.where, self.expected, self.found = where, expected, found


def _kind(value: Any) -> str:
    return "null" if value is None else type(value).__name__


def _depth_exceeds(value: Any, limit: int) -> bool:
    """Whether ``value`` nests lists or dicts deeper than ``limit`` (iterative: no recursion on crafted data)."""
    stack = [(value, 0)]
    while stack:
        item, depth = stack.pop()
        if isinstance(item, (dict, list)):
            if depth >= limit:
                return True
            stack.extend((v, depth + 1) for v in (item.values() if isinstance(item, dict) else item))
    return False


def _check(value: Any, spec: Any, where: list[str | int]) -> None:
    if spec == ANYTHING:
        if _depth_exceeds(value, MAX_DEPTH):
            raise _Mismatch(where, f"JSON nested at most {MAX_DEPTH} levels deep", "deeper nesting")
    elif spec == NUMBER:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise _Mismatch(where, NUMBER, _kind(value))
    elif spec == INT:
        if isinstance(value, bool) or not isinstance(value, int):
            raise _Mismatch(where, INT, _kind(value))
    elif spec == STRING:
        if not isinstance(value, str):
            raise _Mismatch(where, STRING, _kind(value))
    elif isinstance(spec, ListOf):
        if not isinstance(value, list):
            raise _Mismatch(where, "a list", _kind(value))
        if spec.length is not None and len(value) != spec.length:
            raise _Mismatch(where, f"a list of {spec.length} items", f"{len(value)} items")
        for index, item in enumerate(value):
            _check(item, spec.items, [*where, index])
    elif isinstance(spec, (DictOf, Fields)):
        if not isinstance(value, dict):
            raise _Mismatch(where, "a dict", _kind(value))
        if isinstance(spec, DictOf):
            for key, item in value.items():
                _check(item, spec.values, [*where, key])
        else:
            for key in spec.required:
                if key not in value:
                    raise _Mismatch([*where, key], _expected(spec.specs[key]), "no such field")
            for key, item_spec in spec.specs.items():
                if key in value:
                    _check(value[key], item_spec, [*where, key])
    else:  # pragma: no cover - a schema of this module
        raise TypeError(f"unknown schema {spec!r}")


def _expected(spec: Any) -> str:
    if isinstance(spec, str):
        return spec
    return "a list" if isinstance(spec, ListOf) else "a dict"


def _field_name(where: list[str | int]) -> str:
    if not where:
        return "its content"
    head, *rest = where
    return repr(head) + "".join(f"[{key!r}]" for key in rest)


def read_output_json(path: Path, schema: Any, remedy: str) -> Any:
    """The parsed JSON file ``path`` of an output folder, checked against ``schema``; ``None`` when it is no file.

    Args:
        path: the file (e.g. ``<out>/seed_0/none/results.json``).
        schema: what it must hold: :data:`RUN_RESULTS`, :data:`VALIDATION`, :data:`PRETRAIN_TIMING`,
            :data:`REPORT_TIMING`, :data:`SELECTION_RECORD`, or a :class:`Fields` of your own.
        remedy: what the user should do about a bad file, the end of the message
            (e.g. :func:`run_remedy`).

    Returns:
        The file's content, or ``None`` when ``path`` is not a file.

    Raises:
        DataError: the file is larger than :func:`~lightning_vtr.utils.limits.max_json_bytes`, is not valid JSON,
            or a field does not match ``schema``; one line naming the file, the field, the type expected and found,
            and ``remedy``.

    Example::

        payload = read_output_json(run_dir / "results.json", RUN_RESULTS, run_remedy(run_dir))
    """
    from lightning_vtr.utils.limits import read_json

    path = Path(path)
    if not path.is_file():
        return None
    try:
        content = read_json(path)
    except json.JSONDecodeError as err:
        raise DataError(f"{path}: not valid JSON ({err.msg}: line {err.lineno} column {err.colno}); {remedy}") from None
    except UnicodeDecodeError as err:
        raise DataError(f"{path}: not valid JSON (not UTF-8 text: {err.reason}); {remedy}") from None
    except RecursionError:
        raise DataError(f"{path}: not valid JSON (nested deeper than Python's recursion limit); {remedy}") from None
    except DataError as err:  # the size limit, or nesting the reader refused
        raise DataError(f"{err}; {remedy}") from None
    try:
        _check(content, schema, [])
    except _Mismatch as err:
        raise DataError(
            f"{path}: {_field_name(err.where)} must be {err.expected}, found {err.found}; {remedy}"
        ) from None
    return content
