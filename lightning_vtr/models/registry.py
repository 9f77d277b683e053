"""The model registry and checkpoint loading: which class a name or a checkpoint stands for.

:data:`MODELS` maps the names the command line and the experiments use to the model classes.
:func:`check_checkpoint` tells a Lightning checkpoint from any other file before anything loads it, and
:func:`load_model` finds the class that loads a checkpoint and returns the model in eval mode::

    from lightning_vtr.models.registry import load_model

    model = load_model("runs/vtr/last.ckpt")  # the class the checkpoint names, else the first that loads it
    probabilities = model.predict_voxels(images)  # (B, V, 3, H, W) -> (B, R, R, R)

A checkpoint is data, never code: every file is read with ``torch.load(weights_only=True)`` (a file that needs
a full pickle is refused unless the caller passes ``trust_checkpoint=True``), and a class path recorded in a
checkpoint is imported only when it names a class of ``lightning_vtr``; any other class is the caller's to name
(``--model module.Class``). See the Security page of the documentation.
"""

from __future__ import annotations

import importlib
import pickle
import re
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch

from lightning_vtr.errors import DataError, UsageError
from lightning_vtr.models.lrgt import LRGT
from lightning_vtr.models.pix2vox import Pix2VoxPlusPlus

__all__ = [
    "CLASS_PATH_KEY",
    "MODELS",
    "MODEL_FORM",
    "PACKAGE",
    "TRUST_HINT",
    "check_checkpoint",
    "check_model",
    "check_model_class",
    "check_recorded_classes",
    "checkpoint_hyperparameters",
    "checkpoint_path",
    "class_path",
    "import_class",
    "is_package_class_path",
    "load_model",
    "model_class",
    "read_checkpoint",
]

MODELS: dict[str, type[Pix2VoxPlusPlus] | type[LRGT]] = {"pix2vox": Pix2VoxPlusPlus, "lrgt": LRGT}
"""Model name -> class: the names ``--model`` and the experiments accept (each class takes a ``preset``)."""

#: The keys every Lightning checkpoint holds.
_LIGHTNING_KEYS = ("state_dict", "pytorch-lightning_version")


#: The key of a checkpoint under which ``lightning-vtr fit`` records the model's class path
#: (:class:`~lightning_vtr.cli.lightning.RecordModelClass`), so that a checkpoint of a ``lightning_vtr`` model loads
#: without ``--model`` (the class of any other model is named with ``--model``).
CLASS_PATH_KEY = "lightning_vtr_model_class"
#: The package whose classes a checkpoint may name by itself; any other class is named by the user (``--model``).
PACKAGE = "lightning_vtr"
#: How ``--model`` is written, shown in the messages.
MODEL_FORM = "`--model pix2vox`, `--model lrgt` or `--model module.Class` (e.g. `--model mymodel.MyVoxelNet`)"


#: The opt-in that reads a checkpoint ``weights_only`` loading refuses, named in the messages.
TRUST_HINT = "--trust-checkpoint (trust_checkpoint=True in Python)"


def _check_class_path_form(path: str, named: str) -> tuple[str, str]:
    """``(module, attribute)`` of an absolute class path ``module.Class`` of Python names; nothing is imported.

    Raises:
        UsageError: no module part, a relative path (``.mod.Class``) or a part that is not a Python name.
    """
    module, _, attribute = path.rpartition(".")
    if not module or not attribute:
        raise UsageError(f"{named} must be a class path module.Class, got {path!r} (no module part)")
    if path.startswith("."):
        raise UsageError(f"{named} must be an absolute class path module.Class, got {path!r} (a relative import)")
    if not all(part.isidentifier() for part in path.split(".")):
        raise UsageError(f"{named} must be a class path module.Class of Python names, got {path!r}")
    return module, attribute


#: Subpackages of ``lightning_vtr`` whose classes a checkpoint may not name by itself.
_NOT_NAMEABLE = frozenset({"cli"})


def is_package_class_path(path: object) -> bool:
    """Whether ``path`` is a class path ``lightning_vtr.<module>.Class``: the only classes a checkpoint may name
    by itself. Nothing is imported.

    Example:
        >>> is_package_class_path("lightning_vtr.models.pix2vox.Pix2VoxPlusPlus"), is_package_class_path("evil.Net")
        (True, False)
        >>> is_package_class_path("lightning_vtr.cli.__main__.Net")
        False
    """
    if not isinstance(path, str) or not path.startswith(f"{PACKAGE}."):
        return False
    parts = path.split(".")
    # Not a private or dunder module (`lightning_vtr.cli.__main__` runs the command line when imported), nor the
    # command line's modules: a checkpoint names a model, selector or synthesizer class of the library.
    return (
        len(parts) >= 3
        and all(part.isidentifier() and not part.startswith("_") for part in parts)
        and parts[1] not in _NOT_NAMEABLE
    )


def import_class(path: str, option: str = "--model", *, working_folder: bool = True) -> type:
    """The class an import path ``module.Class`` names, the current directory importable as under ``python -m``.

    Only for class paths the user gives (``--model``, a config, a strategies file): a class path read from a
    checkpoint goes through :func:`check_recorded_classes` first.

    Args:
        path: ``package.module.Class``.
        option: the command-line option (or argument) that named it, quoted in the messages.
        working_folder: put the working folder on ``sys.path`` first (as ``python -m`` does), so that
            ``mymodel.MyVoxelNet`` finds ``./mymodel.py``.

    Returns:
        The class.

    Raises:
        UsageError: ``path`` has no module part, is relative (``.mod.Class``), the module does not import, it has
            no such attribute, or the attribute is not a class; the message names the option, the path and what
            went wrong.

    Example:
        >>> import_class("collections.OrderedDict").__name__
        'OrderedDict'
    """
    import os

    named = f"`{option}`" if option.startswith("-") else option  # an option, or a file and row
    module, attribute = _check_class_path_form(path, named)
    cwd = os.getcwd()
    if working_folder and cwd not in sys.path:  # as `python -m` would run it: the working folder imports
        sys.path.insert(0, cwd)
    try:
        found = getattr(importlib.import_module(module), attribute)
    except ModuleNotFoundError as err:
        where = f"module {err.name!r} not found" if err.name else str(err)
        raise UsageError(
            f"{named} must be an importable class path module.Class, got {path!r}: {where} "
            f"(run from the folder holding {module.split('.')[0]}.py, or install it)"
        ) from None
    except AttributeError:
        raise UsageError(
            f"{named} must be an importable class path, got {path!r}: {module} has no {attribute!r}"
        ) from None
    if not isinstance(found, type):
        raise UsageError(f"{named} must name a class, got {path!r} (a {type(found).__name__})")
    return found


def check_model_class(cls: type, option: str = "--model", *, training: bool = False) -> type:
    """``cls`` if it is a ``LightningModule`` class with ``predict_voxels`` (and, ``training``, its own
    ``training_step`` and ``configure_optimizers``).

    The attributes ``image_size``, ``num_views`` and ``voxel_resolution`` are set in ``__init__``, so an instance
    is checked with :func:`check_model` once it exists.

    Raises:
        UsageError: one line naming the class and everything it lacks.
    """
    import lightning as L

    name = f"{cls.__module__}.{cls.__qualname__}"
    if not issubclass(cls, L.LightningModule):
        raise UsageError(f"`{option}` must name a LightningModule class, got {name} (a subclass of {cls.__mro__[1:2]})")
    missing = [] if callable(getattr(cls, "predict_voxels", None)) else ["predict_voxels(images) -> (B, R, R, R)"]
    if training:
        for method in ("training_step", "configure_optimizers"):
            if getattr(cls, method) is getattr(L.LightningModule, method):
                missing.append(method)
    if missing:
        raise UsageError(
            f"`{option}` {name} does not satisfy lightning_vtr.ReconstructionModel: missing {', '.join(missing)} "
            "(see lightning_vtr.protocol)"
        )
    return cls


def check_model(model: Any, option: str = "--model") -> Any:
    """``model`` if it has ``image_size``, ``num_views``, ``voxel_resolution`` and ``predict_voxels``.

    Raises:
        UsageError: one line naming the class and the missing members.
    """
    from lightning_vtr.protocol import check_reconstruction_model

    try:
        check_reconstruction_model(model)
    except TypeError as err:
        raise UsageError(f"`{option}` {type(model).__module__}.{err}") from None
    return model


def model_class(name: str, option: str = "--model", *, training: bool = False) -> type[Any]:
    """The class a model name stands for: a key of :data:`MODELS` or an import path ``module.Class``.

    The current directory is importable (as under ``python -m``), so ``mymodel.MyVoxelNet`` finds
    ``./mymodel.py``.

    Args:
        name: ``"pix2vox"``, ``"lrgt"`` or an importable ``module.Class`` path of a ``LightningModule`` with
            ``predict_voxels``.
        option: the command-line option that named it, quoted in the messages.
        training: also require the class's own ``training_step`` and ``configure_optimizers``.

    Returns:
        The class.

    Raises:
        UsageError: neither a registered name nor an importable class path, or a class that does not satisfy
            the protocol (the message names what is missing).

    Example:
        >>> model_class("lrgt").__name__
        'LRGT'
    """
    if name in MODELS:
        return MODELS[name]
    if "." not in name:
        raise UsageError(f"`{option}` must be pix2vox, lrgt or a class path module.Class, got {name!r}")
    return check_model_class(import_class(name, option), option, training=training)


def class_path(cls: type) -> str:
    """``module.Class`` of a class, as :func:`model_class` reads it back."""
    return f"{cls.__module__}.{cls.__qualname__}"


def _refused_globals(path: Path, err: BaseException) -> list[str]:
    """The globals ``weights_only`` loading refused in ``path``, sorted: every one a scan of the pickle finds
    (nothing is imported or run), else the one torch's message names."""
    try:
        from torch.serialization import get_unsafe_globals_in_checkpoint  # torch >= 2.5

        found = list(get_unsafe_globals_in_checkpoint(path))
    except Exception:  # a legacy (not zip) file, or one the scan cannot read: the message is all there is
        found = []
    if not found:
        found = re.findall(r"GLOBAL (\S+) was not an allowed global", str(err))
    if not found:
        found = re.findall(r"call reduce for (\S+) ", str(err))
    return sorted(set(found))


def _load_error(path: Path, err: BaseException, expected: str, remedy: str | None = None) -> DataError:
    """The one-line :class:`DataError` for a file ``torch.load(weights_only=True)`` refused with ``err``; ``remedy``
    replaces the hint at the opt-in."""
    size = path.stat().st_size if path.is_file() else 0
    names = _refused_globals(path, err) if isinstance(err, pickle.UnpicklingError) else []
    if names:  # a pickle of objects, not a damaged file
        which = (
            f"the global {names[0]!r}"
            if len(names) == 1
            else f"the globals {', '.join(repr(n) for n in names[:4])}{', ...' if len(names) > 4 else ''}"
        )
        remedy = remedy or f"load it only if you made it or trust who did: {TRUST_HINT}"
        return DataError(
            f"{expected}: it holds {which}, which weights_only loading refuses (a full pickle can run code when "
            f"loaded; {remedy})"
        )
    return DataError(f"{expected}: {size} bytes torch cannot read (a truncated copy, or not a torch file)")


def read_checkpoint(ckpt: str | Path, option: str = "--ckpt", *, remedy: str | None = None) -> dict[str, Any]:
    """The content of a Lightning checkpoint file, read with ``torch.load(weights_only=True)`` on the CPU.

    Tensors, plain Python containers and numbers load; a file that needs any other global (a full pickle, which
    can run code when loaded) is refused, naming the global.

    Args:
        ckpt: the checkpoint file.
        option: the command-line option that named it (``--ckpt``), or words saying where it comes from,
            quoted in the messages.
        remedy: what the message of a refused full pickle advises (default: the opt-in, :data:`TRUST_HINT`).

    Returns:
        The checkpoint's dict.

    Raises:
        FileNotFoundError: no file there.
        DataError: an empty, truncated or non-torch file, a file ``weights_only`` loading refuses (the message
            names the globals it holds), or a file that does not hold a dict.

    Example::

        state_dict = read_checkpoint("runs/vtr/pretrain/pretrained.ckpt")["state_dict"]
    """
    path = checkpoint_path(ckpt, option)
    named = f"`{option}`" if option.startswith("-") else option
    expected = f"{named} must be a Lightning checkpoint (a file `Trainer.fit` saved), got {str(ckpt)!r}"
    if path.stat().st_size == 0:
        raise DataError(f"{expected}: an empty file (0 bytes)")
    try:
        checkpoint = torch.load(path, map_location="cpu", weights_only=True)
    except (pickle.UnpicklingError, RuntimeError, OSError, EOFError, ValueError, AttributeError, KeyError) as err:
        raise _load_error(path, err, expected, remedy) from None
    except (IndexError, TypeError, ImportError) as err:  # a damaged pickle stream
        raise _load_error(path, err, expected, remedy) from None
    if not isinstance(checkpoint, dict):
        raise DataError(f"{expected}: a plain torch.save file holding a {type(checkpoint).__name__}")
    return checkpoint


def checkpoint_hyperparameters(path: str | Path) -> tuple[dict[str, Any], dict[str, Any]]:
    """The hyperparameters a checkpoint stores for its model and for its datamodule.

    Args:
        path: a checkpoint file (read with ``weights_only=True``).

    Returns:
        ``(model hyperparameters, datamodule hyperparameters)``; both empty when the file cannot be read
        with ``weights_only=True`` (a full pickle, or not a torch file).

    Example::

        model_hparams, datamodule_hparams = checkpoint_hyperparameters("last.ckpt")
    """
    checkpoint = _readable_checkpoint(path)
    if checkpoint is None:
        return {}, {}
    model_hparams, datamodule_hparams = (
        checkpoint.get(key) for key in ("hyper_parameters", "datamodule_hyper_parameters")
    )
    return (
        dict(model_hparams) if isinstance(model_hparams, dict) else {},
        dict(datamodule_hparams) if isinstance(datamodule_hparams, dict) else {},
    )


def checkpoint_path(ckpt: str | Path, option: str = "--ckpt") -> Path:
    """``ckpt`` as a path when a file is there; nothing is read (:func:`check_checkpoint` reads it).

    Args:
        ckpt: the checkpoint file.
        option: the command-line option (or argument) that named it, quoted in the message.

    Returns:
        The path, ``~`` expanded.

    Raises:
        FileNotFoundError: no file there (a folder, or nothing).

    Example::

        path = checkpoint_path("runs/vtr/last.ckpt")
    """
    path = Path(ckpt).expanduser()
    if not path.is_file():
        found = "a folder" if path.is_dir() else "no such file"
        raise FileNotFoundError(f"`{option}` must be a checkpoint file, got {str(ckpt)!r} ({found})")
    return path


def check_checkpoint(
    ckpt: str | Path, option: str = "--ckpt", *, trust_checkpoint: bool = False, remedy: str | None = None
) -> Path:
    """``ckpt`` as a path if it is a Lightning checkpoint file that ``torch.load(weights_only=True)`` reads.

    Args:
        ckpt: the checkpoint file.
        option: the command-line option (or argument) that named it, quoted in the messages.
        trust_checkpoint: also accept a file that only a full pickle load reads (objects other than tensors and
            plain containers): the caller trusts where it came from, since loading it can run code in it.
        remedy: what the message of a refused full pickle advises (default: the opt-in, :data:`TRUST_HINT`).

    Returns:
        The path, ``~`` expanded.

    Raises:
        FileNotFoundError: no file there (a usage error).
        DataError: an empty, truncated or non-torch file, a file ``weights_only`` loading refuses (without
            ``trust_checkpoint``; the message names the globals it holds), or a ``torch.save`` file that is not a
            Lightning checkpoint (no ``state_dict`` / ``pytorch-lightning_version``); the message names the file.

    Example::

        path = check_checkpoint("runs/vtr/last.ckpt", "--checkpoint")
    """
    return _lightning_checkpoint(ckpt, option, trust_checkpoint=trust_checkpoint, remedy=remedy)[0]


def _lightning_checkpoint(
    ckpt: str | Path, option: str, *, trust_checkpoint: bool = False, remedy: str | None = None
) -> tuple[Path, dict[str, Any] | None]:
    """:func:`check_checkpoint`'s path and the content it read; ``None`` for a full pickle the caller trusts
    (Lightning's to load)."""
    path = checkpoint_path(ckpt, option)
    expected = f"`{option}` must be a Lightning checkpoint (a file `Trainer.fit` saved), got {str(ckpt)!r}"
    try:
        checkpoint = read_checkpoint(ckpt, option, remedy=remedy)
    except DataError as err:
        if trust_checkpoint and "weights_only loading refuses" in str(err):
            return path, None
        raise
    if any(key not in checkpoint for key in _LIGHTNING_KEYS):
        what = f"a plain torch.save file holding a dict of {len(checkpoint)} keys without " + " / ".join(
            repr(k) for k in _LIGHTNING_KEYS if k not in checkpoint
        )
        raise DataError(f"{expected}: {what}; save models with Trainer.fit / trainer.save_checkpoint")
    return path, checkpoint


def _readable_checkpoint(path: str | Path) -> dict[str, Any] | None:
    """The content of ``path`` read as :func:`read_checkpoint` does, ``None`` when it cannot be read so."""
    try:
        return read_checkpoint(path)
    except (DataError, FileNotFoundError):
        return None


def _class_paths(value: Any, found: list[str], depth: int = 0) -> list[str]:
    """Every ``class_path`` string in nested dicts and lists (as jsonargparse would resolve them)."""
    if depth > 32:
        return found
    if isinstance(value, dict):
        for key, item in value.items():
            if key in ("class_path", "_class_path") and isinstance(item, str):
                found.append(item)
            else:
                _class_paths(item, found, depth + 1)
    elif isinstance(value, (list, tuple)):
        for item in value:
            _class_paths(item, found, depth + 1)
    return found


def _recorded_model_paths(checkpoint: dict[str, Any]) -> list[str]:
    """The model class paths a checkpoint records: :data:`CLASS_PATH_KEY`, then the hyperparameters'
    ``_class_path`` (LightningCLI's), each once."""
    hparams = checkpoint.get("hyper_parameters")
    found = [checkpoint.get(CLASS_PATH_KEY), hparams.get("_class_path") if isinstance(hparams, dict) else None]
    return list(dict.fromkeys(p for p in found if p is not None))


def check_recorded_classes(
    checkpoint: dict[str, Any],
    ckpt: str | Path,
    named: Sequence[str] = (),
    *,
    trust_checkpoint: bool = False,
) -> None:
    """Refuse a checkpoint that names code outside ``lightning_vtr`` the user did not name; nothing is imported.

    A checkpoint never chooses the code that runs: its model class paths (:data:`CLASS_PATH_KEY`, the
    hyperparameters' ``_class_path``) must name classes of ``lightning_vtr`` (:func:`is_package_class_path`)
    or be one of ``named`` (the user's ``--model``). Any other ``class_path`` in its hyperparameters (an argument
    LightningCLI would instantiate) must be a class of ``lightning_vtr``, of ``named``, of a module already
    imported, or the user passes ``trust_checkpoint``.

    Args:
        checkpoint: the checkpoint's content (:func:`read_checkpoint`).
        ckpt: its file, quoted in the messages.
        named: class paths the user named (``--model``, the config's model).
        trust_checkpoint: accept class paths in the hyperparameters other than the model's.

    Raises:
        UsageError: one line naming the file and the class, and how to name it if the user trusts it.

    Example::

        check_recorded_classes(read_checkpoint("last.ckpt"), "last.ckpt", named=["mymodel.MyVoxelNet"])
    """
    allowed = set(named)
    model_paths = _recorded_model_paths(checkpoint)
    for recorded in model_paths:
        if not isinstance(recorded, str) or not recorded:
            raise UsageError(
                f"the checkpoint {str(ckpt)!r} records the model class as {recorded!r}, not a class path "
                f"module.Class: pass {MODEL_FORM}"
            )
        if not is_package_class_path(recorded) and recorded not in allowed:
            hint = f"`--model {recorded}`" if all(p.isidentifier() for p in recorded.split(".")) else MODEL_FORM
            raise UsageError(
                f"the checkpoint {str(ckpt)!r} names the model class {recorded!r}, outside lightning_vtr; a "
                f"checkpoint does not choose the code that runs: pass {hint} if you trust it"
            )
    if trust_checkpoint:
        return
    for recorded in _class_paths(checkpoint.get("hyper_parameters"), []):
        module = recorded.rpartition(".")[0]
        if recorded in model_paths or recorded in allowed or is_package_class_path(recorded):
            continue
        if module and module in sys.modules and all(p.isidentifier() for p in recorded.split(".")):
            continue  # imported already: resolving it runs nothing new
        raise UsageError(
            f"the checkpoint {str(ckpt)!r} names the class {recorded!r} in its hyperparameters, outside "
            f"lightning_vtr; a checkpoint does not choose the code that runs: import it yourself or pass "
            f"{TRUST_HINT} if you trust the file"
        )


def checkpoint_class_path(path: str | Path) -> str | None:
    """The model class path a checkpoint records: ``lightning-vtr fit``'s :data:`CLASS_PATH_KEY`, else the
    ``_class_path`` LightningCLI stores with the hyperparameters; ``None`` when it records none (or cannot be
    read with ``weights_only=True``). Nothing is imported."""
    checkpoint = _readable_checkpoint(path)
    if checkpoint is None:
        return None
    found = [p for p in _recorded_model_paths(checkpoint) if isinstance(p, str)]
    return found[0] if found else None


def _package_model_class(recorded: str, path: Path) -> type:
    """The class of ``lightning_vtr`` a checkpoint records (:func:`is_package_class_path` checked first), imported
    without the working folder on ``sys.path``."""
    named = f"the class path {recorded!r} recorded in {str(path)!r}"
    cls = import_class(recorded, named, working_folder=False)
    if not (cls.__module__ == PACKAGE or cls.__module__.startswith(f"{PACKAGE}.")):
        raise UsageError(f"{named} must name a class defined in lightning_vtr, got one of {cls.__module__}")
    return check_model_class(cls, named)


def load_model(
    ckpt: str | Path,
    model: str | None = None,
    map_location: Any = "cpu",
    option: str = "--ckpt",
    *,
    trust_checkpoint: bool = False,
) -> Any:
    """Load a reconstruction model from a Lightning checkpoint, in eval mode.

    The class is ``model`` when given, else the one the checkpoint records (:func:`checkpoint_class_path`) when
    that is a class of ``lightning_vtr``, else the first of :data:`MODELS` whose ``load_from_checkpoint``
    accepts the checkpoint. Any ``LightningModule`` with ``predict_voxels``, ``image_size``, ``num_views`` and
    ``voxel_resolution`` loads; a class of one's own is always named with ``model``, since a checkpoint never
    chooses the code that runs. The file is read with ``weights_only=True`` unless ``trust_checkpoint``.

    Args:
        ckpt: the checkpoint file (checked with :func:`check_checkpoint`).
        model: ``"pix2vox"``, ``"lrgt"`` or a class path ``module.Class`` (see :func:`model_class`).
        map_location: where the weights go, as for ``torch.load``.
        option: the option that named ``ckpt``, quoted in the messages.
        trust_checkpoint: read a file that only a full pickle load reads (which can run code in it), and accept
            class paths outside ``lightning_vtr`` in its hyperparameters; only for a file you made or whose
            maker you trust.

    Returns:
        The model, in eval mode.

    Raises:
        FileNotFoundError: no file at ``ckpt``.
        UsageError: ``model`` names no class, or one without the protocol's members; or the checkpoint names a
            class outside ``lightning_vtr`` that ``model`` does not name (the message shows the ``--model``).
        DataError: not a Lightning checkpoint, a file ``weights_only`` loading refuses (without
            ``trust_checkpoint``), or no class loads it (the message lists each class's error and, without
            ``model``, shows the ``--model`` form).

    Example::

        model = load_model("runs/vtr/last.ckpt", "pix2vox")
        model = load_model("runs/mine/last.ckpt", "mymodel.MyVoxelNet")
    """
    path, checkpoint = _lightning_checkpoint(ckpt, option, trust_checkpoint=trust_checkpoint)
    given = model_class(model) if model is not None else None
    recorded = None
    if checkpoint is not None:
        named = [class_path(given), model] if given is not None and model is not None else []
        check_recorded_classes(checkpoint, path, named, trust_checkpoint=trust_checkpoint)
        recorded = next(iter(_recorded_model_paths(checkpoint)), None)
        del checkpoint
    if given is not None:
        candidates = [given]
    elif recorded is not None:
        candidates = [_package_model_class(recorded, path)]
    else:
        candidates = list(MODELS.values())
    errors = []
    for cls in candidates:
        try:
            loaded = cls.load_from_checkpoint(path, map_location=map_location, weights_only=not trust_checkpoint)
        except (RuntimeError, TypeError, KeyError, ValueError, pickle.UnpicklingError) as err:
            errors.append(f"{cls.__name__}: {(str(err).splitlines() or [type(err).__name__])[0][:600]}")
            continue
        return check_model(loaded.eval(), "--model" if model is not None else option)
    hint = f"; a checkpoint of your own model needs {MODEL_FORM}" if model is None and recorded is None else ""
    raise DataError(f"no model class loads the checkpoint {str(path)!r}{hint}: " + "; ".join(errors))
