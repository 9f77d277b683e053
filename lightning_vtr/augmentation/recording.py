"""What a selection round leaves behind for people: the selection records and the settings record (JSON files
under the run's log directory, described in ``docs/records.md``), the grid of new views and the error sheets
logged as images."""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import lightning as L
import numpy as np
import torch
from lightning.pytorch.utilities import rank_zero_info

from lightning_vtr.augmentation.prediction import predict_probabilities
from lightning_vtr.augmentation.selection_round import Selection
from lightning_vtr.data.dataset import GeneratedSample
from lightning_vtr.protocol import AugmentableDataModule
from lightning_vtr.utils.compositing import alpha_composite
from lightning_vtr.utils.io import atomic_write
from lightning_vtr.utils.paths import join_under

__all__ = [
    "RECORDS_DIR",
    "RECORD_VERSION",
    "error_sheets",
    "log_dir",
    "log_round",
    "new_views_grid",
    "record_name",
    "selection_record",
    "write_record",
    "write_settings",
]

RECORD_VERSION = 1
"""The ``version`` of the selection records and of the settings record."""
RECORDS_DIR = "vtr_selection"
"""The folder of the records under the run's log directory."""


def record_name(epoch: int) -> str:
    """The file stem of a round's record.

    Args:
        epoch: the epoch whose end made the round (``-1``: before epoch 0).

    Returns:
        ``"start"`` for ``epoch == -1``, else ``"epoch_<EEEE>"``.

    Example:
        >>> record_name(-1), record_name(3)
        ('start', 'epoch_0003')
    """
    return "start" if epoch < 0 else f"epoch_{epoch:04d}"


def selection_record(
    epoch: int, targets: Sequence[Selection], view_sets: Sequence[np.ndarray], searched: Sequence[Selection]
) -> dict[str, Any]:
    """The record of one round (the fields of ``docs/records.md``, format :data:`RECORD_VERSION`).

    Args:
        epoch: the epoch whose end made the round.
        targets: the objects given new views.
        view_sets: the view set each target was synthesized at.
        searched: every searched object (for ``mean_error`` and ``searched``).

    Returns:
        The record, a JSON-serialisable dict.

    Example:
        >>> s = Selection(0, "chair", "c0", np.array([[10.0, 20.0]]), error=0.25)
        >>> record = selection_record(0, [s], [np.array([[30.0, 40.0]])], [s])
        >>> record["objects"], record["view_sets"], record["mean_error"], record["searched"]
        (['chair/c0'], [[[30.0, 40.0]]], 0.25, 1)
    """
    return {
        "version": RECORD_VERSION,
        "epoch": int(epoch),
        "objects": [f"{s.category}/{s.object_id}" for s in targets],
        "selected": [np.asarray(s.viewpoints).round(3).tolist() for s in targets],
        "view_sets": [np.asarray(v).round(3).tolist() for v in view_sets],
        "mean_error": float(np.mean([s.error for s in searched])) if searched else 0.0,
        "searched": len(searched),
    }


def write_record(log_dir: str | Path, record: dict[str, Any]) -> Path:
    """Write ``record`` atomically to ``<log_dir>/vtr_selection/<record_name(epoch)>.json``.

    Args:
        log_dir: the run's log directory.
        record: a :func:`selection_record`.

    Returns:
        The path written.

    Example::

        write_record(trainer.log_dir, selection_record(0, targets, view_sets, searched))
    """
    path = join_under(Path(log_dir), RECORDS_DIR, f"{record_name(record['epoch'])}.json", replace_link=True)
    atomic_write(path, json.dumps(record, indent=1))
    return path


def write_settings(log_dir: str | Path, description: str, settings: dict[str, Any]) -> Path:
    """Write the callback's settings atomically to ``<log_dir>/vtr_selection/settings.json``.

    Args:
        log_dir: the run's log directory.
        description: the callback's ``repr``.
        settings: the callback's ``settings()``.

    Returns:
        The path written; it holds ``{"version", "callback": description, "settings": settings}``.

    Example::

        write_settings(trainer.log_dir, repr(callback), callback.settings())
    """
    path = join_under(Path(log_dir), RECORDS_DIR, "settings.json", replace_link=True)
    atomic_write(path, json.dumps({"version": RECORD_VERSION, "callback": description, "settings": settings}, indent=1))
    return path


def new_views_grid(samples: Sequence[GeneratedSample]) -> np.ndarray:
    """Rows = samples, columns = views, composited on white; rows with fewer views are padded with white.

    Args:
        samples: generated samples, each ``images (T, H, W, 4)`` uint8 of one size ``H, W``.

    Returns:
        ``(rows * H, max T * W, 3)`` uint8.

    Example:
        >>> sample = GeneratedSample("chair", "c0", np.zeros((2, 4, 4, 4), np.uint8), np.zeros((2, 2)))
        >>> new_views_grid([sample]).shape
        (4, 8, 3)
    """
    width = max(s.images.shape[0] for s in samples)
    rows = []
    for s in samples:
        rgb = alpha_composite(np.asarray(s.images, dtype=np.uint8))  # (T, H, W, 3)
        pad = width - rgb.shape[0]
        if pad:
            rgb = np.concatenate([rgb, np.full((pad, *rgb.shape[1:]), 255, np.uint8)])
        rows.append(np.concatenate(list(rgb), axis=1))
    return np.concatenate(rows, axis=0)


@torch.no_grad()
def error_sheets(
    pl_module: L.LightningModule,
    dm: AugmentableDataModule,
    record: dict[str, Any],
    *,
    source_view_set: str,
    batch_size: int,
    count: int = 2,
) -> np.ndarray:
    """Sheets (views | prediction | truth | error | error projection at the selected views) of the first ``count``
    objects of ``record``, predicted again by the current model from the views the round predicted from.

    Args:
        pl_module: the model (predicts in eval mode, its mode restored after).
        dm: the datamodule.
        record: a :func:`selection_record`.
        source_view_set: the view set the round predicted from.
        batch_size: objects per prediction.
        count: how many of the record's objects.

    Returns:
        The sheets stacked vertically, ``(H, W, 3)`` uint8 (:func:`lightning_vtr.visualize.stack_sheets`).

    Example::

        log_image(trainer, "vtr/error_sheets", error_sheets(model, dm, record, source_view_set="aligned",
                                                            batch_size=16))
    """
    from lightning_vtr.visualize import object_sheet, stack_sheets

    seed = record["epoch"] + 1  # the views the round predicted from
    records = [dm.record(*name.split("/", 1)) for name in record["objects"][:count]]
    items = [dm.eval_item(rec, source_view_set, seed=seed) for rec in records]
    was_training = pl_module.training
    pl_module.eval()
    try:
        predicted = predict_probabilities(pl_module, [item["images"] for item in items], batch_size)
    finally:
        pl_module.train(was_training)
    normalize = getattr(dm.transform, "normalize", "auto")
    sheets = [
        object_sheet(
            predicted[i],
            item["voxels"],
            item["images"],
            input_viewpoints=item["viewpoints"],
            selected_viewpoints=record["selected"][i],
            panel_size=96,
            normalize=normalize,
            title=f"{record['objects'][i]} (epoch {record['epoch']}): views selected for it",
        )
        for i, item in enumerate(items)
    ]
    return stack_sheets(sheets)


def log_dir(trainer: L.Trainer) -> str:
    """The running Trainer's own log directory (``trainer.log_dir``; ``default_root_dir`` without a logger).

    A collective under DDP: every process must call it.

    Args:
        trainer: the running Trainer.

    Returns:
        The directory, as a string.

    Example::

        write_record(log_dir(trainer), record)
    """
    return str(trainer.log_dir or trainer.default_root_dir)


def log_round(
    trainer: L.Trainer,
    pl_module: L.LightningModule,
    dm: AugmentableDataModule,
    record: dict[str, Any],
    samples: Sequence[GeneratedSample],
    *,
    log_images: bool,
    source_view_set: str,
    batch_size: int,
) -> None:
    """Log a round: its values on every process, and on global rank 0 a summary line, its images and its record.

    ``vtr/samples_generated``, ``vtr/samples_total`` and ``vtr/mean_error`` go through ``pl_module.log`` (every
    logger gets them and ``ModelCheckpoint`` / ``EarlyStopping`` can monitor them; equal on every process). With
    ``log_images`` and a logger, :func:`new_views_grid` of the first 8 samples (``vtr/new_views``) and
    :func:`error_sheets` (``vtr/error_sheets``) are logged; the record is written with :func:`write_record`.

    Args:
        trainer: the running Trainer; every process calls this.
        pl_module: the model.
        dm: the datamodule, the round's samples added.
        record: the round's :func:`selection_record`.
        samples: the round's generated samples.
        log_images: log the image grid and the error sheets.
        source_view_set: the view set the round predicted from.
        batch_size: objects per prediction for the error sheets.

    Example::

        log_round(trainer, model, dm, result.record, result.samples, log_images=True, source_view_set="aligned",
                  batch_size=16)
    """
    total = len(dm.generated_samples)
    metrics = {
        "vtr/samples_generated": float(len(samples)),
        "vtr/samples_total": float(total),
        "vtr/mean_error": record["mean_error"],
    }
    # `sync_dist` keeps the equal values and keeps Lightning from warning under DDP
    for name, value in metrics.items():
        pl_module.log(name, value, on_step=False, on_epoch=True, sync_dist=True, batch_size=1)
    directory = log_dir(trainer)  # a collective: every process asks, before the rank-0 branch
    if not trainer.is_global_zero:
        return
    rank_zero_info(
        f"VTR {'before training' if record['epoch'] < 0 else 'epoch ' + str(record['epoch'])}: "
        f"{len(samples)} samples generated ({total} in total), "
        f"mean voxel error of searched objects {record['mean_error']:.4f}"
    )
    if log_images and samples and trainer.loggers:
        from lightning_vtr.utils.image_logging import log_image

        log_image(trainer, "vtr/new_views", new_views_grid(samples[:8]), step=trainer.global_step)
        sheets = error_sheets(pl_module, dm, record, source_view_set=source_view_set, batch_size=batch_size)
        log_image(trainer, "vtr/error_sheets", sheets, step=trainer.global_step)
    write_record(directory, record)
