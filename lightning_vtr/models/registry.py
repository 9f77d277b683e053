"""The model registry and checkpoint loading: which class a name or a checkpoint stands for.

:data:`MODELS` maps the names the command line and the experiments use to the model classes.
:func:`check_checkpoint` tells a Lightning checkpoint from any other file before anything loads it, and
:func:`load_model` finds the class that loads a checkpoint and returns the model in eval mode::

    from lightning_vtr.models.registry import load_model

    model = load_model("runs/vtr/last.ckpt")  # the class the checkpoint names, else the first that loads it
    probabilities = model.predict_voxels(images)  # (B, V, 3, H, W) -> (B, R, R, R)
"""

from __future__ import annotations

import importlib
import pickle
from pathlib import Path
from typing import Any

import torch

from lightning_vtr.errors import DataError
from lightning_vtr.models.lrgt import LRGT
from lightning_vtr.models.pix2vox import Pix2VoxPlusPlus

__all__ = [
    "CLASS_PATH_KEY",
    "MODELS",
    "MODEL_FORM",
    "check_checkpoint",
    "check_model",
    "check_model_class",
    "checkpoint_hyperparameters",
    "checkpoint_path",
    "class_path",
    "import_class",
    "load_model",
    "model_class",
]

MODELS: dict[str, type[Pix2VoxPlusPlus] | type[LRGT]] = {"pix2vox": Pix2VoxPlusPlus, "lrgt": LRGT}
"""Model name -> class: the names ``--model`` and the experiments accept (each class takes a ``preset``)."""

#: The keys every Lightning checkpoint holds.
_LIGHTNING_KEYS = ("state_dict", "pytorch-lightning_version")


#: The key of a checkpoint under which ``lightning-vtr fit`` records the model's class path
#: (:class:`~lightning_vtr.cli.lightning.RecordModelClass`), so that a checkpoint loads without ``--model``.
CLASS_PATH_KEY = "lightning_vtr_model_class"
#: How ``--model`` is written, shown in the messages.
MODEL_FORM = "`--model pix2vox`, `--model lrgt` or `--model module.Class` (e.g. `--model mymodel.MyVoxelNet`)"


def import_class(path: str, option: str = "--model") -> type:
    """The class an import path ``module.Class`` names, the current directory importable as under ``python -m``.

    Args:
        path: ``package.module.Class``.
        option: the command-line option (or argument) that named it, quoted in the messages.

    Returns:
        The class.

    Raises:
        UsageError: ``path`` has no module part, the module does not import, it has no such attribute, or the
            attribute is not a class; the message names the option, the path and what went wrong.

    Example:
        >>> import_class("collections.OrderedDict").__name__
        'OrderedDict'
    """
    import os
    import sys

    from lightning_vtr.errors import UsageError

    named = f"`{option}`" if option.startswith("-") else option  # an option, or a file and row
    module, _, attribute = path.rpartition(".")
    if not module or not attribute:
        raise UsageError(f"{named} must be a class path module.Class, got {path!r} (no module part)")
    cwd = os.getcwd()
    if cwd not in sys.path:  # `lightning-vtr` as the `python -m` form would run it: the working folder imports
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

    from lightning_vtr.errors import UsageError

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
    from lightning_vtr.errors import UsageError
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
        from lightning_vtr.errors import UsageError

        raise UsageError(f"`{option}` must be pix2vox, lrgt or a class path module.Class, got {name!r}")
    return check_model_class(import_class(name, option), option, training=training)


def class_path(cls: type) -> str:
    """``module.Class`` of a class, as :func:`model_class` reads it back."""
    return f"{cls.__module__}.{cls.__qualname__}"


def checkpoint_hyperparameters(path: str | Path) -> tuple[dict[str, Any], dict[str, Any]]:
    """The hyperparameters a checkpoint stores for its model and for its datamodule.

    Args:
        path: a checkpoint file.

    Returns:
        ``(model hyperparameters, datamodule hyperparameters)``; both empty when the file cannot be read
        with ``weights_only=True`` (a full pickle, or not a torch file).

    Example::

        model_hparams, datamodule_hparams = checkpoint_hyperparameters("last.ckpt")
    """
    try:
        checkpoint = torch.load(Path(path).expanduser(), map_location="cpu", weights_only=True)
    except (pickle.UnpicklingError, RuntimeError, AttributeError):
        return {}, {}
    return dict(checkpoint.get("hyper_parameters", {}) or {}), dict(
        checkpoint.get("datamodule_hyper_parameters", {}) or {}
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


def check_checkpoint(ckpt: str | Path, option: str = "--ckpt") -> Path:
    """``ckpt`` as a path if it is a readable Lightning checkpoint file.

    Args:
        ckpt: the checkpoint file.
        option: the command-line option (or argument) that named it, quoted in the messages.

    Returns:
        The path, ``~`` expanded.

    Raises:
        FileNotFoundError: no file there (a usage error).
        DataError: an empty, truncated or non-torch file, or a ``torch.save`` file that is not a Lightning
            checkpoint (no ``state_dict`` / ``pytorch-lightning_version``); the message names the file.

    Example::

        path = check_checkpoint("runs/vtr/last.ckpt", "--checkpoint")
    """
    path = checkpoint_path(ckpt, option)
    size = path.stat().st_size
    expected = f"`{option}` must be a Lightning checkpoint (a file `Trainer.fit` saved), got {str(ckpt)!r}"
    if size == 0:
        raise DataError(f"{expected}: an empty file (0 bytes)")
    try:
        checkpoint = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as err:
        if "Unsupported global" in str(err):
            return path  # a full pickle (objects in the hyperparameters): Lightning loads it, trust it
        raise DataError(f"{expected}: {size} bytes torch cannot read (a truncated copy, or not a torch file)") from None
    except (RuntimeError, OSError, EOFError, ValueError, AttributeError, KeyError, IndexError, TypeError):
        raise DataError(f"{expected}: {size} bytes torch cannot read (a truncated copy, or not a torch file)") from None
    if not isinstance(checkpoint, dict) or any(key not in checkpoint for key in _LIGHTNING_KEYS):
        what = (
            f"a plain torch.save file holding a dict of {len(checkpoint)} keys without "
            + " / ".join(repr(k) for k in _LIGHTNING_KEYS if k not in checkpoint)
            if isinstance(checkpoint, dict)
            else f"a plain torch.save file holding a {type(checkpoint).__name__}"
        )
        raise DataError(f"{expected}: {what}; save models with Trainer.fit / trainer.save_checkpoint")
    return path


def checkpoint_class_path(path: str | Path) -> str | None:
    """The model class path a checkpoint records: ``lightning-vtr fit``'s :data:`CLASS_PATH_KEY`, else the
    ``_class_path`` LightningCLI stores with the hyperparameters; ``None`` when it records none (or cannot be
    read with ``weights_only=True``)."""
    try:
        checkpoint = torch.load(Path(path).expanduser(), map_location="cpu", weights_only=True)
    except (pickle.UnpicklingError, RuntimeError, AttributeError):
        return None
    recorded = checkpoint.get(CLASS_PATH_KEY)
    if isinstance(recorded, str):
        return recorded
    hparams = checkpoint.get("hyper_parameters") or {}
    found = hparams.get("_class_path") if isinstance(hparams, dict) else None
    return found if isinstance(found, str) else None


def load_model(ckpt: str | Path, model: str | None = None, map_location: Any = "cpu", option: str = "--ckpt") -> Any:
    """Load a reconstruction model from a Lightning checkpoint, in eval mode.

    The class is ``model`` when given, else the one the checkpoint records (:func:`checkpoint_class_path`),
    else the first of :data:`MODELS` whose ``load_from_checkpoint`` accepts the checkpoint. Any
    ``LightningModule`` with ``predict_voxels``, ``image_size``, ``num_views`` and ``voxel_resolution`` loads.

    Args:
        ckpt: the checkpoint file (checked with :func:`check_checkpoint`).
        model: ``"pix2vox"``, ``"lrgt"`` or a class path ``module.Class`` (see :func:`model_class`).
        map_location: where the weights go, as for ``torch.load``.
        option: the option that named ``ckpt``, quoted in the messages.

    Returns:
        The model, in eval mode.

    Raises:
        FileNotFoundError: no file at ``ckpt``.
        UsageError: ``model`` (or the recorded class path) names no class, or one without the protocol's members.
        DataError: not a Lightning checkpoint, or no class loads it (the message lists each class's error and,
            without ``model``, shows the ``--model`` form).

    Example::

        model = load_model("runs/vtr/last.ckpt", "pix2vox")
        model = load_model("runs/mine/last.ckpt", "mymodel.MyVoxelNet")
    """
    path = check_checkpoint(ckpt, option)
    recorded = checkpoint_class_path(path) if model is None else None
    if model is not None:
        candidates = [model_class(model)]
    elif recorded is not None:
        candidates = [model_class(recorded, f"the class path {recorded!r} recorded in {str(path)!r}")]
    else:
        candidates = list(MODELS.values())
    errors = []
    for cls in candidates:
        try:
            loaded = cls.load_from_checkpoint(path, map_location=map_location)
        except (RuntimeError, TypeError, KeyError, ValueError) as err:
            errors.append(f"{cls.__name__}: {(str(err).splitlines() or [type(err).__name__])[0][:600]}")
            continue
        return check_model(loaded.eval(), "--model" if model is not None else option)
    hint = (
        f"; a checkpoint of your own model needs {MODEL_FORM}, run from the folder holding the module"
        if model is None and recorded is None
        else ""
    )
    raise DataError(f"no model class loads the checkpoint {str(path)!r}{hint}: " + "; ".join(errors))
