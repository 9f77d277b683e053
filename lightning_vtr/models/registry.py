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
from lightning_vtr.models.base import VoxelReconstructionModule
from lightning_vtr.models.lrgt import LRGT
from lightning_vtr.models.pix2vox import Pix2VoxPlusPlus

__all__ = [
    "MODELS",
    "check_checkpoint",
    "checkpoint_hyperparameters",
    "checkpoint_path",
    "load_model",
    "model_class",
]

MODELS: dict[str, type[Pix2VoxPlusPlus] | type[LRGT]] = {"pix2vox": Pix2VoxPlusPlus, "lrgt": LRGT}
"""Model name -> class: the names ``--model`` and the experiments accept (each class takes a ``preset``)."""

#: The keys every Lightning checkpoint holds.
_LIGHTNING_KEYS = ("state_dict", "pytorch-lightning_version")


def model_class(name: str) -> type[Any]:
    """The class a model name stands for: a key of :data:`MODELS` or a dotted class path.

    Args:
        name: ``"pix2vox"``, ``"lrgt"`` or an importable ``module.Class`` path.

    Returns:
        The class.

    Raises:
        ValueError: neither a registered name nor an importable class path.

    Example:
        >>> model_class("lrgt").__name__
        'LRGT'
    """
    if name in MODELS:
        return MODELS[name]
    module, _, attribute = name.rpartition(".")
    if module:
        try:
            return getattr(importlib.import_module(module), attribute)
        except (ImportError, AttributeError):
            pass
    raise ValueError(f"`--model` must be pix2vox, lrgt or an importable class path (module.Class), got {name!r}")


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


def load_model(ckpt: str | Path, model: str | None = None, map_location: Any = "cpu") -> VoxelReconstructionModule:
    """Load a reconstruction model from a Lightning checkpoint, in eval mode.

    The class is ``model`` when given, else the one a LightningCLI checkpoint names (``_class_path``), else
    the first of :data:`MODELS` whose ``load_from_checkpoint`` accepts the checkpoint.

    Args:
        ckpt: the checkpoint file (checked with :func:`check_checkpoint`).
        model: ``"pix2vox"``, ``"lrgt"`` or a dotted class path (see :func:`model_class`).
        map_location: where the weights go, as for ``torch.load``.

    Returns:
        The model, in eval mode.

    Raises:
        FileNotFoundError: no file at ``ckpt``.
        ValueError: ``model`` names no class.
        DataError: not a Lightning checkpoint, or no class loads it (the message lists each class's error).

    Example::

        model = load_model("runs/vtr/last.ckpt", "pix2vox")
    """
    path = check_checkpoint(ckpt)
    hparams, _ = checkpoint_hyperparameters(path)
    if model is not None:
        candidates = [model_class(model)]
    elif isinstance(hparams.get("_class_path"), str):
        candidates = [model_class(hparams["_class_path"])]
    else:
        candidates = list(MODELS.values())
    errors = []
    for cls in candidates:
        try:
            loaded = cls.load_from_checkpoint(path, map_location=map_location)
        except (RuntimeError, TypeError, KeyError, ValueError) as err:
            errors.append(f"{cls.__name__}: {(str(err).splitlines() or [type(err).__name__])[0][:600]}")
            continue
        return loaded.eval()
    raise DataError(f"no model class loads the checkpoint {str(path)!r}: " + "; ".join(errors))
