"""Send a picture to every logger a Trainer has: TensorBoard, Weights & Biases, MLflow, Comet, or PNG files.

Lightning's loggers share ``log_metrics`` but not an image API: TensorBoard's writer has ``add_image``,
``WandbLogger`` has ``log_image``, MLflow's client ``log_image``. :func:`log_image` speaks each one's
language and, for a logger that takes no pictures (``CSVLogger``, or one this module does not know), writes a
PNG under that logger's run directory instead, so no picture is lost silently. An unknown logger type is
named in one warning per type.
"""

from __future__ import annotations

import io
import re
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np
import torch
from lightning.pytorch.loggers import CometLogger, CSVLogger, Logger, MLFlowLogger, TensorBoardLogger, WandbLogger
from lightning.pytorch.utilities import rank_zero_warn
from PIL import Image

from lightning_vtr.utils.compositing import alpha_composite
from lightning_vtr.utils.io import atomic_write
from lightning_vtr.utils.paths import join_under

__all__ = ["image_to_uint8", "log_image", "png_path"]

# Logger types already warned about (one warning per type and process).
_WARNED: set[str] = set()


def image_to_uint8(image: Any) -> np.ndarray:
    """A picture as ``(H, W, 3)`` uint8 RGB.

    Args:
        image: ``(H, W, 3|4)`` or ``(H, W)`` array or tensor (uint8, or float in ``[0, 1]``), a ``(3|4, H, W)``
            tensor (channels first, as torchvision makes them), or a PIL image. An alpha channel is composited
            on white.

    Raises:
        TypeError: not an array, tensor or PIL image.
        ValueError: another shape.
    """
    if isinstance(image, Image.Image):
        image = np.asarray(image.convert("RGBA"))
    if isinstance(image, torch.Tensor):
        image = image.detach().cpu()
        if image.ndim == 3 and image.shape[0] in (3, 4) and image.shape[-1] not in (3, 4):
            image = image.permute(1, 2, 0)
        image = image.numpy()
    if not isinstance(image, np.ndarray):
        raise TypeError(f"`image` must be a numpy array, torch tensor or PIL image, got {type(image).__name__}")
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, axis=-1)
    if image.ndim != 3 or image.shape[-1] not in (3, 4):
        raise ValueError(f"`image` must have shape (H, W, 3), (H, W, 4), (3, H, W) or (H, W), got {image.shape}")
    if image.dtype != np.uint8:
        image = (np.clip(image.astype(np.float32), 0.0, 1.0) * 255.0).round().astype(np.uint8)
    if image.shape[-1] == 4:
        image = alpha_composite(image)  # on white
    return np.ascontiguousarray(image)


def png_path(directory: str | Path, tag: str, step: int) -> Path:
    """Where the PNG fallback writes picture ``tag`` at ``step``: ``<directory>/images/<tag>/step_<step>.png``.

    The tag's ``/`` separate folders (as TensorBoard groups them); characters other than letters, digits,
    ``.``, ``_``, ``-`` become ``_``, and empty or ``..`` parts are dropped, so a tag never leaves ``images/``.
    """
    return join_under(Path(directory, "images"), *_tag_parts(tag), f"step_{int(step):06d}.png", replace_link=True)


def _tag_parts(tag: str) -> list[str]:
    parts = [re.sub(r"[^A-Za-z0-9._-]", "_", p) for p in str(tag).split("/")]
    return [p for p in parts if p and p not in (".", "..")] or ["image"]


def _write_png(path: Path, image: np.ndarray) -> Path:
    buffer = io.BytesIO()
    Image.fromarray(image).save(buffer, format="PNG")
    atomic_write(path, buffer.getvalue())
    return path


def _fallback_dir(logger: Logger, trainer: Any) -> Path:
    for name in ("log_dir", "save_dir"):
        try:
            value = getattr(logger, name, None)
        except Exception:  # a property that needs a run (e.g. an offline service) must not break logging
            value = None
        if value:
            return Path(value)
    if trainer is not None:
        return Path(trainer.log_dir or trainer.default_root_dir)
    return Path.cwd()


def _send(logger: Logger, tag: str, image: np.ndarray, step: int, trainer: Any) -> Path | None:
    """Log to one logger; returns the PNG written by the fallback, if any."""
    if isinstance(logger, TensorBoardLogger):
        logger.experiment.add_image(tag, image, global_step=step, dataformats="HWC")
        return None
    if isinstance(logger, WandbLogger):
        logger.log_image(key=tag, images=[image], step=step)
        return None
    if isinstance(logger, MLFlowLogger):
        name = "/".join(["images", *_tag_parts(tag), f"step_{step:06d}.png"])
        logger.experiment.log_image(logger.run_id, image, artifact_file=name)
        return None
    if isinstance(logger, CometLogger):
        logger.experiment.log_image(image, name=tag, step=step)
        return None
    if not isinstance(logger, CSVLogger):
        experiment = getattr(logger, "experiment", None)
        if experiment is not None and hasattr(
            experiment, "add_image"
        ):  # a TensorBoard-style writer (e.g. tensorboardX) behind another logger
            experiment.add_image(tag, image, global_step=step, dataformats="HWC")
            return None
        kind = type(logger).__name__
        if kind not in _WARNED:
            _WARNED.add(kind)
            rank_zero_warn(
                f"lightning_vtr cannot send images to a {kind} logger; writing them as PNG files under "
                f"{_fallback_dir(logger, trainer) / 'images'} instead."
            )
    return _write_png(png_path(_fallback_dir(logger, trainer), tag, step), image)


def log_image(target: Any, tag: str, image: Any, step: int | None = None) -> list[Path]:
    """Log one picture to every logger of a Trainer (or to the given loggers).

    Per logger: TensorBoard ``add_image``; Weights & Biases ``log_image``; MLflow ``log_image`` as an artifact
    ``images/<tag>/step_<step>.png``; Comet ``log_image``; any other logger whose ``experiment`` has
    ``add_image`` gets that; everything else (``CSVLogger``, unknown types, which are warned about once per
    type) gets a PNG file at :func:`png_path` under the logger's ``log_dir`` (else its ``save_dir``, else the
    trainer's log directory). A Trainer without loggers (``logger=False``) logs nothing.

    Args:
        target: an ``L.Trainer`` (its ``loggers``; only global rank 0 logs), a logger, or an iterable of loggers.
        tag: the picture's name, e.g. ``"vtr/new_views"``.
        image: the picture (see :func:`image_to_uint8`).
        step: the step it belongs to; default the trainer's ``global_step`` (0 without a trainer).

    Returns:
        the PNG files the fallback wrote (empty when every logger took the picture itself).
    """
    trainer = target if hasattr(target, "loggers") and hasattr(target, "is_global_zero") else None
    if trainer is not None:
        if not trainer.is_global_zero:
            return []
        loggers: list[Logger] = list(trainer.loggers)
    elif isinstance(target, Logger):
        loggers = [target]
    elif isinstance(target, Iterable):
        loggers = list(target)
    else:
        raise TypeError(f"`target` must be a Trainer, a Logger or an iterable of Loggers, got {type(target).__name__}")
    if not loggers:
        return []
    picture = image_to_uint8(image)
    if step is None:
        step = int(trainer.global_step) if trainer is not None else 0
    written = [_send(logger, str(tag), picture, int(step), trainer) for logger in loggers]
    return [path for path in written if path is not None]
