"""The named view strategies of the harness, read from a YAML file of rows (``strategies.yaml``).

Each row names a selector of :data:`lightning_vtr.selection.SELECTORS`, a selector class of your own by import path,
or none; the arguments of the selector and of :class:`~lightning_vtr.callback.ErrorGuidedViewAugmentation`, a title
and a description. :data:`VARIANTS` holds the rows of the file shipped with the package (:data:`STRATEGIES_FILE`), in
the report's row order; :func:`load_variants` reads and validates any such file and :func:`report_variants` merges a
file of yours with the shipped rows. Example rows::

    visible_fresh:
      title: Visible, 20 % fresh
      description: visible score, 20 % of the objects given views per selection, the latest selection kept
      selector: error_guided
      selector_kwargs: {score: visible, min_separation: 30.0, temperature: null}
      callback_kwargs: {fraction: 0.2}
      max_samples_fraction: 0.2   # generated samples kept: 20 % of the training objects' count
    mine:
      title: My selector
      description: my own rule
      selector:                   # jsonargparse's form: any ViewSelector subclass, the working folder importable
        class_path: my_selectors.FarthestViews
        init_args: {k: 30}
      callback_kwargs: {fraction: 0.2}
    mine_prerendered:
      title: Default rule, prerendered views
      description: the default rule served from views rendered into the dataset (no OpenGL while training)
      selector: error_guided
      synthesizer: {class_path: lightning_vtr.synthesis.PrerenderedSynthesizer}

A row's ``selector`` is a registry name (its arguments in ``selector_kwargs``) or ``{class_path, init_args}``
(``selector_kwargs`` then adds to ``init_args``). An argument may itself be ``{class_path, init_args}``, an object
built before the selector (e.g. a :class:`~lightning_vtr.selection.scores.ViewScore` of your own for
:class:`~lightning_vtr.selection.ErrorGuidedSelector`'s ``score``)::

    mine_scored:
      title: My score
      description: the default rule's bins, chosen by my own view score
      selector: error_guided
      selector_kwargs:
        score: {class_path: my_scores.EdgeScore, init_args: {weight: 2.0}}
"""

from __future__ import annotations

import inspect
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import TYPE_CHECKING, Any

from lightning_vtr.errors import DataError

__all__ = [
    "STRATEGIES",
    "STRATEGIES_FILE",
    "VARIANTS",
    "StrategyFileError",
    "StrategyVariant",
    "build_arguments",
    "load_variants",
    "report_variants",
    "selector_class",
]

STRATEGIES_FILE = Path(__file__).with_name("strategies.yaml")
"""The YAML file of named strategies shipped with the package."""
ROW_KEYS = (
    "title",
    "description",
    "selector",
    "selector_kwargs",
    "callback_kwargs",
    "max_samples_fraction",
    "synthesizer",
)
"""The keys a row of a strategies file may hold."""
_RESERVED_CALLBACK_KEYS = {
    "selector": "the row's `selector` builds it",
    "synthesizer": "a row names its own with the row key `synthesizer`",
    "max_samples": "a count depends on the dataset's size; use `max_samples_fraction`",
}
"""Callback arguments a row may not set: the report supplies them, or they depend on a dataset's size."""


#: The most views a row's selector may ask for per generated sample (``num_views``): each view is rendered or
#: synthesized, so a larger number is a typo that would otherwise surface only after the pretraining.
MAX_ROW_VIEWS = 64


class StrategyFileError(DataError):
    """A strategies file is not valid YAML or a row is not a valid strategy (names the file and the row)."""


@dataclass(frozen=True)
class StrategyVariant:
    """A named view strategy: a selector (registered or your own) and its settings.

    Attributes:
        selector: the selector's registry name (:data:`lightning_vtr.selection.SELECTORS`) or the import path
            ``module.Class`` of a :class:`~lightning_vtr.selection.ViewSelector` subclass; ``None`` for no
            augmentation (no callback).
        selector_kwargs: arguments of the selector class.
        callback_kwargs: arguments of :class:`~lightning_vtr.callback.ErrorGuidedViewAugmentation`.
        title: the row title in the report's tables.
        description: one line saying what the strategy does.
        max_samples_fraction: cap on the generated samples kept in the datamodule, as a share of the training
            objects (the callback's ``max_samples`` is :meth:`max_samples` of the dataset's count); ``None``: no cap.
        synthesizer: ``{class_path, init_args}`` of the callback's :class:`~lightning_vtr.synthesis.base.Synthesizer`
            (e.g. ``lightning_vtr.synthesis.PrerenderedSynthesizer``), used instead of the one the report supplies;
            ``None``: the report's (mesh rendering by default).

    Raises:
        ValueError: ``selector`` is neither a registered selector nor an importable ``ViewSelector`` class, or
            ``max_samples_fraction`` is not in (0, 1].

    Example::

        StrategyVariant("random", {"mode": "area"}, title="Random (area-uniform)")
    """

    selector: str | None
    selector_kwargs: Mapping[str, Any] = field(default_factory=dict)
    callback_kwargs: Mapping[str, Any] = field(default_factory=dict)
    title: str = ""
    description: str = ""
    max_samples_fraction: float | None = None
    synthesizer: Mapping[str, Any] | None = None

    def __post_init__(self) -> None:
        if self.selector is not None:
            selector_class(self.selector)
        share = self.max_samples_fraction
        if share is not None and (isinstance(share, bool) or not isinstance(share, (int, float)) or not 0 < share <= 1):
            raise ValueError(f"`max_samples_fraction` must be a number in (0, 1], got {share!r}")
        # read-only copies: a registry entry cannot be changed through a caller's dict
        object.__setattr__(self, "selector_kwargs", MappingProxyType(dict(self.selector_kwargs)))
        object.__setattr__(self, "callback_kwargs", MappingProxyType(dict(self.callback_kwargs)))
        if self.synthesizer is not None:
            if not _is_class_spec(self.synthesizer):
                raise ValueError(f"`synthesizer` must be {{class_path, init_args}}, got {self.synthesizer!r}")
            object.__setattr__(self, "synthesizer", MappingProxyType(dict(self.synthesizer)))

    def make_synthesizer(self) -> Any:
        """The row's own synthesizer, built from :attr:`synthesizer`.

        Returns:
            A new :class:`~lightning_vtr.synthesis.base.Synthesizer`, or ``None`` when the row names none.

        Example::

            StrategyVariant("error_guided", synthesizer={"class_path": "lightning_vtr.synthesis.PrerenderedSynthesizer"}
                            ).make_synthesizer()  # PrerenderedSynthesizer(root=None)
        """
        if self.synthesizer is None:
            return None
        return build_arguments({"synthesizer": dict(self.synthesizer)})["synthesizer"]

    def max_samples(self, train_objects: int) -> int | None:
        """The callback's ``max_samples`` on a dataset of ``train_objects`` training objects.

        Args:
            train_objects: the dataset's number of training objects.

        Returns:
            ``round(max_samples_fraction * train_objects)``, at least 1; ``None`` when the row sets no cap.

        Example::

            StrategyVariant("random", max_samples_fraction=0.2).max_samples(170)  # 34
        """
        if self.max_samples_fraction is None:
            return None
        return max(1, round(self.max_samples_fraction * train_objects))


#: The pool keys of a row's ``callback_kwargs`` (the callback itself takes one ``pool`` object):
#: ``use_pool`` (default: the selector's ``uses_pool``), ``pool_capacity`` (``None``), ``pool_refresh`` (``False``)
#: and ``pool_prefer_others`` (``True``).
POOL_KEYS = ("use_pool", "pool_capacity", "pool_refresh", "pool_prefer_others")


def callback_arguments(uses_pool: bool, callback_kwargs: dict[str, Any]) -> dict[str, Any]:
    """A row's ``callback_kwargs`` (with ``fraction``) as arguments of ``ErrorGuidedViewAugmentation``.

    Rows keep the paper's callback settings unless they say otherwise: ``search_fraction`` missing or ``None``
    searches as many objects as get views (``fraction``), and the :data:`POOL_KEYS` become one ``pool`` mapping
    (``None`` without a pool).

    Example:
        >>> callback_arguments(True, {"fraction": 0.1, "pool_refresh": True})
        {'fraction': 0.1, 'search_fraction': 0.1, 'pool': {'capacity': None, 'refresh': True, 'prefer_others': True}}
    """
    options = {k: v for k, v in callback_kwargs.items() if k not in POOL_KEYS}
    if options.get("search_fraction") is None:
        options["search_fraction"] = options["fraction"]
    use_pool = callback_kwargs.get("use_pool")
    if use_pool if use_pool is not None else uses_pool:
        options["pool"] = {
            "capacity": callback_kwargs.get("pool_capacity"),
            "refresh": bool(callback_kwargs.get("pool_refresh") or False),
            "prefer_others": bool(callback_kwargs.get("pool_prefer_others", True)),
        }
    else:
        options["pool"] = None
    return options


def selector_class(name: str, where: str = "selector") -> type:
    """The selector class a row names: a key of :data:`lightning_vtr.selection.SELECTORS` or an import path
    ``module.Class`` of a :class:`~lightning_vtr.selection.ViewSelector` subclass (the working folder importable).

    Args:
        name: the row's ``selector`` (a registry name) or its ``class_path``.
        where: what the error message names (e.g. ``"my.yaml, row 'mine'"``).

    Returns:
        The selector class.

    Raises:
        ValueError: neither (a :class:`~lightning_vtr.errors.UsageError` naming ``where`` and the problem).

    Example:
        >>> selector_class("random").__name__
        'RandomSelector'
    """
    from lightning_vtr.errors import UsageError
    from lightning_vtr.models.registry import import_class
    from lightning_vtr.selection import SELECTORS, ViewSelector

    if name in SELECTORS:
        return SELECTORS[name]
    if "." not in name:
        raise UsageError(
            f"{where}: unknown selector {name!r} (expected null, one of {', '.join(map(repr, SELECTORS))}, or "
            "{class_path: module.Class, init_args: {...}})"
        )
    cls = import_class(name, where)
    if not issubclass(cls, ViewSelector):
        raise UsageError(f"{where}: {name} is not a lightning_vtr.selection.ViewSelector subclass")
    return cls


def _is_class_spec(value: Any) -> bool:
    return isinstance(value, Mapping) and "class_path" in value and set(value) <= {"class_path", "init_args"}


def _check_nested(value: Any, where: str) -> None:
    """Check that every ``{class_path, init_args}`` inside a row's arguments names an importable class."""
    from lightning_vtr.models.registry import import_class

    if _is_class_spec(value):
        if not isinstance(value["class_path"], str):
            raise StrategyFileError(f"{where}: `class_path` must be a string module.Class, got {value['class_path']!r}")
        try:
            import_class(value["class_path"], where)
        except ValueError as error:
            raise StrategyFileError(str(error)) from None
        init_args = value.get("init_args") or {}
        if not isinstance(init_args, Mapping):
            raise StrategyFileError(f"{where}: `init_args` must be a mapping, got {type(init_args).__name__}")
        for key, item in init_args.items():
            _check_nested(item, f"{where}, {key}")
    elif isinstance(value, Mapping):
        for key, item in value.items():
            _check_nested(item, f"{where}, {key}")


def build_arguments(arguments: Mapping[str, Any]) -> dict[str, Any]:
    """A row's selector arguments with every ``{class_path, init_args}`` value built into its object.

    Args:
        arguments: keyword arguments of a selector class; a value that is a mapping of ``class_path`` (an import
            path ``module.Class``, the working folder importable) and optional ``init_args`` becomes
            ``Class(**init_args)``, its own such values built first.

    Returns:
        A new dict; the other values as given.

    Raises:
        ValueError: a ``class_path`` that does not import (a :class:`~lightning_vtr.errors.UsageError`).

    Example:
        >>> build_arguments({"score": {"class_path": "lightning_vtr.selection.ReleasedScore",
        ...                            "init_args": {"eps": 0.1}}, "k": 30})
        {'score': ReleasedScore(mode='soft', mask='gt', reduction='mean', eps=0.1), 'k': 30}
    """
    from lightning_vtr.models.registry import import_class

    def build(value: Any) -> Any:
        if _is_class_spec(value):
            init_args = {key: build(item) for key, item in (value.get("init_args") or {}).items()}
            return import_class(value["class_path"], "class_path")(**init_args)
        return value

    return {key: build(value) for key, value in arguments.items()}


def _parameters(cls: type) -> set[str] | None:
    """Names of the keyword arguments ``cls`` takes; ``None`` when it takes any (``**kwargs``)."""
    parameters = inspect.signature(cls).parameters.values()
    if any(p.kind is inspect.Parameter.VAR_KEYWORD for p in parameters):
        return None
    return {p.name for p in parameters}


def _unknown(where: str, keys: Any, known: set[str] | None) -> None:
    unknown = sorted(k for k in keys if known is not None and k not in known)
    if unknown:
        assert known is not None, "a key is unknown only against a known set"
        raise StrategyFileError(f"{where}: unknown key(s) {', '.join(map(repr, unknown))} (expected {sorted(known)})")


def _variant(path: Path, name: Any, row: Any) -> StrategyVariant:
    """One row of a strategies file as a :class:`StrategyVariant`; every error names the file and the row."""
    where = f"{path}, row {name!r}"
    if not isinstance(name, str) or not name.isidentifier():
        raise StrategyFileError(f"{where}: a row name must be a word of letters, digits and underscores")
    if not isinstance(row, dict):
        raise StrategyFileError(f"{where}: expected a mapping of {', '.join(ROW_KEYS)}, got {type(row).__name__}")
    _unknown(where, row, set(ROW_KEYS))
    missing = [k for k in ("title", "description", "selector") if k not in row]
    if missing:
        raise StrategyFileError(f"{where}: missing key(s) {', '.join(map(repr, missing))}")
    for key in ("title", "description"):
        if not isinstance(row[key], str) or not row[key].strip():
            raise StrategyFileError(f"{where}: `{key}` must be a non-empty string, got {row[key]!r}")
    from lightning_vtr.callback import ErrorGuidedViewAugmentation

    selector = row["selector"]
    init_args: dict[str, Any] = {}
    if isinstance(selector, dict):
        _unknown(f"{where}, selector", selector, {"class_path", "init_args"})
        if not isinstance(selector.get("class_path"), str):
            raise StrategyFileError(f"{where}: `selector` needs a `class_path` string (module.Class), got {selector!r}")
        init_args = selector.get("init_args") or {}
        if not isinstance(init_args, dict):
            raise StrategyFileError(f"{where}: `selector.init_args` must be a mapping, got {type(init_args).__name__}")
        selector = selector["class_path"]
    if selector is not None and not isinstance(selector, str):
        raise StrategyFileError(
            f"{where}: `selector` must be null, a name or {{class_path, init_args}}, got {selector!r}"
        )
    if selector is not None:
        try:
            cls = selector_class(selector, where)
        except ValueError as error:
            raise StrategyFileError(str(error)) from None
    for key in ("selector_kwargs", "callback_kwargs"):
        value = row.get(key, {})
        if not isinstance(value, dict):
            raise StrategyFileError(f"{where}: `{key}` must be a mapping, got {type(value).__name__}")
        if value and selector is None:
            raise StrategyFileError(f"{where}: `{key}` needs a selector (this row has none)")
    if selector is not None:
        selector_kwargs = {**init_args, **row.get("selector_kwargs", {})}
        label = "selector_kwargs" if not init_args else "selector init_args / selector_kwargs"
        _unknown(f"{where}, {label}", selector_kwargs, _parameters(cls))
        for key, value in selector_kwargs.items():
            _check_nested(value, f"{where}, {label}, {key}")
        views = selector_kwargs.get("num_views")
        if views is not None and (
            isinstance(views, bool) or not isinstance(views, int) or not 1 <= views <= MAX_ROW_VIEWS
        ):
            raise StrategyFileError(
                f"{where}, {label}: `num_views` must be an integer in [1, {MAX_ROW_VIEWS}], got {views!r}"
            )
        callback_kwargs = row.get("callback_kwargs", {})
        for key, reason in _RESERVED_CALLBACK_KEYS.items():
            if key in callback_kwargs:
                raise StrategyFileError(f"{where}, callback_kwargs: {key!r} is not allowed ({reason})")
        known = (_parameters(ErrorGuidedViewAugmentation) or set()) - {"pool"} | set(POOL_KEYS)
        _unknown(f"{where}, callback_kwargs", callback_kwargs, known)
    elif row.get("max_samples_fraction") is not None:
        raise StrategyFileError(f"{where}: `max_samples_fraction` needs a selector (this row has none)")
    synthesizer = row.get("synthesizer")
    if synthesizer is not None:
        from lightning_vtr.models.registry import import_class
        from lightning_vtr.synthesis.base import Synthesizer

        if selector is None:
            raise StrategyFileError(f"{where}: `synthesizer` needs a selector (this row has none)")
        if not _is_class_spec(synthesizer) or not isinstance(synthesizer["class_path"], str):
            raise StrategyFileError(
                f"{where}: `synthesizer` must be {{class_path: module.Class, init_args: {{...}}}}, got {synthesizer!r}"
            )
        _check_nested(synthesizer, f"{where}, synthesizer")
        cls = import_class(synthesizer["class_path"], f"{where}, synthesizer")
        if not (isinstance(cls, type) and issubclass(cls, Synthesizer)):
            raise StrategyFileError(
                f"{where}, synthesizer: {synthesizer['class_path']} is not a lightning_vtr.synthesis.Synthesizer subclass"
            )
    try:
        return StrategyVariant(
            selector,
            {**init_args, **row.get("selector_kwargs", {})},
            row.get("callback_kwargs", {}),
            title=row["title"].strip(),
            description=" ".join(row["description"].split()),
            max_samples_fraction=row.get("max_samples_fraction"),
            synthesizer=synthesizer,
        )
    except ValueError as error:
        raise StrategyFileError(f"{where}: {error}") from error


def load_variants(path: str | Path = STRATEGIES_FILE) -> dict[str, StrategyVariant]:
    """Read and validate a YAML file of named strategies.

    Args:
        path: the file: a mapping of row names to rows (see the module docstring); default
            :data:`STRATEGIES_FILE`.

    Returns:
        Name -> :class:`StrategyVariant`, in the file's order.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        StrategyFileError: the file is not YAML, is not a mapping of rows, repeats a row name or a title, or a row
            has an unknown key, an unknown selector, an argument its selector or the callback does not take, or a
            missing or invalid value; the message names the file and the row.

    Example::

        variants = load_variants("my_strategies.yaml")
        make_strategy("visible_fresh", config, variants=variants)  # a row of that file
    """
    import yaml

    path = Path(path)

    class _Loader(yaml.SafeLoader):
        """SafeLoader refusing a repeated row name (PyYAML would keep the last one silently)."""

    def mapping(loader: yaml.SafeLoader, node: yaml.MappingNode) -> dict:
        keys = [loader.construct_object(key) for key, _ in node.value]
        repeated = sorted({k for k in keys if isinstance(k, str) and keys.count(k) > 1})
        if repeated:
            raise StrategyFileError(f"{path}: repeated key(s) {', '.join(map(repr, repeated))} ({node.start_mark})")
        return loader.construct_mapping(node)

    _Loader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, mapping)
    try:
        rows = yaml.load(path.read_text(encoding="utf-8"), Loader=_Loader)
    except yaml.YAMLError as error:
        raise StrategyFileError(f"{path}: not valid YAML ({error})") from error
    if not isinstance(rows, dict) or not rows:
        raise StrategyFileError(f"{path}: expected a mapping of strategy names to rows, got {type(rows).__name__}")
    variants = {name: _variant(path, name, row) for name, row in rows.items()}
    titles = [v.title for v in variants.values()]
    repeated = sorted({t for t in titles if titles.count(t) > 1})
    if repeated:
        raise StrategyFileError(f"{path}: repeated title(s) {', '.join(map(repr, repeated))}")
    return variants


def report_variants(path: str | Path | None = None, *, replace: bool = False) -> dict[str, StrategyVariant]:
    """The report's named strategies: the shipped rows (:data:`VARIANTS`) and those of a file of yours.

    Args:
        path: a strategies file (:func:`load_variants`); ``None``: the shipped rows alone.
        replace: use the file's rows alone; ``False``: the shipped rows, then the file's (a row of the file with a
            shipped row's name takes its place).

    Returns:
        Name -> :class:`StrategyVariant`, in row order.

    Raises:
        FileNotFoundError: no file at ``path``.
        StrategyFileError: as :func:`load_variants`, or a row of the file repeats a shipped row's title.

    Example::

        variants = report_variants("my_strategies.yaml")  # shipped rows + mine
    """
    if path is None:
        return dict(_shipped())
    file = Path(path).expanduser()
    if not file.is_file():
        found = "a folder" if file.is_dir() else "no such file"
        raise FileNotFoundError(
            f"`--strategies-file` must be a YAML file of strategy rows, got {str(path)!r} ({found})"
        )
    mine = load_variants(file)
    if replace:
        return mine
    merged = {**_shipped(), **mine}
    titles = [v.title for v in merged.values()]
    repeated = sorted({t for t in titles if titles.count(t) > 1})
    if repeated:
        raise StrategyFileError(
            f"{file}: title(s) {', '.join(map(repr, repeated))} repeat a shipped row's; choose another title, or "
            "use the shipped row's name to replace it"
        )
    return merged


DEFAULT_STRATEGY = "error_guided"
"""The row that equals ``ErrorGuidedViewAugmentation()`` with no arguments: the package's default rule."""
STRATEGIES: tuple[str, ...] = ("none", "nature", "random", "viat", "mvtn", "paper")
"""The paper's Table 1 strategies, in its row order: ``"none"`` (no augmentation), Nature, Random as the paper
draws it (angle-uniform), VIAT, MVTN and the paper's rule (``ErrorGuidedViewAugmentation.paper()``); each is a
name in :data:`VARIANTS`."""
_LAZY: dict[str, Any] = {}


def _shipped() -> dict[str, StrategyVariant]:
    """The rows of :data:`STRATEGIES_FILE`, read once."""
    if "VARIANTS" not in _LAZY:
        _LAZY["VARIANTS"] = load_variants()
    return _LAZY["VARIANTS"]


def __getattr__(name: str) -> Any:
    # VARIANTS imports the selectors (torch): read on first use, so `lightning-vtr report --help` stays light.
    if name == "VARIANTS":
        return _shipped()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


if TYPE_CHECKING:
    VARIANTS: dict[str, StrategyVariant]
    """Strategy name -> :class:`StrategyVariant`, in the report's row order: the rows of :data:`STRATEGIES_FILE`:
    the paper's Table 1 strategies (:data:`STRATEGIES`), ``"random_area"`` (area-uniform Random) and
    ``"error_guided"`` (:data:`DEFAULT_STRATEGY`, the package's default rule)."""
