"""Command-line flags from configuration dataclasses: one flag per field marked with
:func:`~lightning_vtr.experiments.config.flag`, named after the field (``pretrain_epochs`` is
``--pretrain-epochs``), defaulting to the value of the instance given.

Example::

    parser = argparse.ArgumentParser()
    add_config_arguments(parser, ExperimentConfig(out="runs/mine"), exclude=("seed",))
    config = config_from_arguments(parser.parse_args(), ExperimentConfig(out="runs/mine"), exclude=("seed",))
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import types
import typing
from collections.abc import Collection, Sequence
from typing import Any

from lightning_vtr.utils.argtypes import at_least, comma_separated

__all__ = ["add_config_arguments", "config_from_arguments", "flag_fields", "key_values", "option", "yaml_word"]


def option(name: str) -> str:
    """The flag of a field: ``"pretrain_epochs"`` -> ``"--pretrain-epochs"``."""
    return "--" + name.replace("_", "-")


def flag_fields(cls: type, exclude: Collection[str] = ()) -> list[dataclasses.Field]:
    """The fields of dataclass ``cls`` that are flags (their ``metadata`` has ``"flag"``), less ``exclude``."""
    return [f for f in dataclasses.fields(cls) if "flag" in f.metadata and f.name not in exclude]


def _scalar(hint: Any) -> Any:
    """The one non-``None`` type of ``X | None``; ``str`` for any other union (e.g. ``int | str``)."""
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        arguments = [a for a in typing.get_args(hint) if a is not type(None)]
        return arguments[0] if len(arguments) == 1 else str
    return hint


def _default_text(value: Any, spec: dict[str, Any]) -> str:
    """How the help names the default (``%`` escaped for argparse); ``%(default)s`` where argparse's own text
    reads well, so that ``ArgumentDefaultsHelpFormatter`` adds no second one."""
    if spec["default_text"] is not None:
        return spec["default_text"].replace("%", "%%")
    if isinstance(value, (list, tuple)):
        return (("," if spec["comma_separated"] else " ").join(map(str, value)) or "none").replace("%", "%%")
    return "%(default)s"


def _argument(f: dataclasses.Field, hint: Any, value: Any) -> dict[str, Any]:
    """The ``add_argument`` keywords of field ``f`` (annotation ``hint``) defaulting to ``value``."""
    spec = f.metadata["flag"]
    choices = spec["choices"]() if callable(spec["choices"]) else spec["choices"]
    help_text = spec["help"].replace("%", "%%")
    kwargs: dict[str, Any] = {"dest": f.name, "help": f"{help_text} (default {_default_text(value, spec)})"}
    hint = _scalar(hint)
    if typing.get_origin(hint) in (list, tuple, Sequence):
        if spec["comma_separated"]:
            kwargs["type"] = comma_separated(None if choices is None else tuple(choices))
        else:
            (element, *_) = typing.get_args(hint) or (str,)
            kwargs.update(nargs="+", type=element)
        kwargs["default"] = list(value)
        return kwargs
    if hint is bool:
        if value is not False:
            raise TypeError(f"field {f.name!r}: a bool flag must default to False (a switch), got {value!r}")
        return {"dest": f.name, "help": help_text, "action": "store_true", "default": False}
    if spec["minimum"] is not None:
        kwargs["type"] = at_least(spec["minimum"])
    elif hint in (int, float):
        kwargs["type"] = hint
    if choices is not None:
        kwargs["choices"] = tuple(choices)
    kwargs["default"] = value
    if hint is str and value is not None and not isinstance(value, str):
        kwargs["default"] = str(value)  # e.g. `devices`: an int default of an `int | str` field
    return kwargs


def add_config_arguments(
    parser: Any,
    defaults: Any,
    *,
    exclude: Collection[str] = (),
    groups: dict[str, Any] | None = None,
) -> list[argparse.Action]:
    """Add a flag to ``parser`` for every flag field of dataclass instance ``defaults``.

    Args:
        parser: an ``argparse.ArgumentParser`` (or argument group).
        defaults: a dataclass instance: its field values are the flags' defaults.
        exclude: names of fields that get no flag.
        groups: field name -> the group (e.g. a mutually exclusive one) its flag goes into, instead of ``parser``.

    Returns:
        The added actions, in field order.

    A bool field defaulting to ``False`` is a switch (``store_true``).

    Raises:
        TypeError: a bool flag field whose default is not ``False``.

    Example::

        add_config_arguments(parser, default_experiment(), exclude=("seed",))
    """
    hints = typing.get_type_hints(type(defaults))
    actions = []
    for f in flag_fields(type(defaults), exclude):
        target = (groups or {}).get(f.name, parser)
        actions.append(target.add_argument(option(f.name), **_argument(f, hints[f.name], getattr(defaults, f.name))))
    return actions


def config_from_arguments(args: argparse.Namespace, defaults: Any, *, exclude: Collection[str] = (), **changes: Any):
    """``defaults`` with every flag field set from parsed ``args`` (and ``changes`` over them).

    Args:
        args: what a parser of :func:`add_config_arguments` parsed.
        defaults: the dataclass instance the parser was built with.
        exclude: the fields :func:`add_config_arguments` excluded (kept from ``defaults``).
        changes: further field values.

    Returns:
        A new instance of ``defaults``'s class (its ``__post_init__`` checks run again).

    Example::

        experiment = config_from_arguments(args, default_experiment(), exclude=("seed",))
    """
    values = {f.name: getattr(args, f.name) for f in flag_fields(type(defaults), exclude)}
    return dataclasses.replace(defaults, **{**values, **changes})


def key_values(words: Sequence[str] | None, option: str) -> dict[str, Any]:
    """``KEY=VALUE`` words (a repeated flag) as a dict, each ``VALUE`` read as YAML: ``64`` an int, ``0.5`` a float,
    ``true`` a bool, ``[1, 2]`` a list, ``null`` None, anything else a string.

    Args:
        words: the flag's words, in command-line order (``None``: none given).
        option: the flag, quoted in the messages.

    Returns:
        ``{KEY: value}`` in the words' order.

    Raises:
        UsageError: a word without ``=`` or with a ``KEY`` that is not a Python identifier, a ``VALUE`` that is no
            YAML, or a ``KEY`` given twice.

    Example:
        >>> key_values(["image_size=64", "name=small", "widths=[8, 16]", "dropout=0.5"], "--model-arg")
        {'image_size': 64, 'name': 'small', 'widths': [8, 16], 'dropout': 0.5}
    """
    import yaml

    from lightning_vtr.errors import UsageError

    out: dict[str, Any] = {}
    for word in words or ():
        key, equals, text = word.partition("=")
        if not equals or not key.isidentifier():
            raise UsageError(f"`{option}` must be KEY=VALUE with KEY an argument name, got {word!r}")
        if key in out:
            raise UsageError(f"`{option}` gives {key!r} twice ({key}={out[key]!r} and {word!r}); give it once")
        try:
            out[key] = yaml.safe_load(text)
        except yaml.YAMLError as error:
            problem = str(error).splitlines()[0]
            raise UsageError(
                f"`{option}` {key}: VALUE must be YAML (64, 0.5, true, [1, 2], text), got {text!r} ({problem})"
            ) from None
    return out


def yaml_word(value: Any) -> str:
    """``value`` as a command-line ``VALUE`` that :func:`key_values` reads back equal.

    Example:
        >>> [yaml_word(v) for v in (64, 1e-05, "small", "64", True, None, [1, 2], {"a": 1})]
        ['64', '1.0e-05', 'small', '"64"', 'true', 'null', '[1, 2]', '{"a": 1}']
    """
    import yaml

    if isinstance(value, str):
        try:
            if yaml.safe_load(value) == value and "\n" not in value:
                return value
        except yaml.YAMLError:
            pass
    if isinstance(value, float) and math.isfinite(value):
        text = repr(value)
        return text if "." in text or "e" not in text else text.replace("e", ".0e", 1)
    if isinstance(value, float):
        return ".nan" if math.isnan(value) else ".inf" if value > 0 else "-.inf"
    return json.dumps(value, default=str)
