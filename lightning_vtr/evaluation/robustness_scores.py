"""Every error-guided selection score per object, aligned with a robustness map, and the score validity table.

:func:`selection_scores` computes, for each object, what
:class:`~lightning_vtr.selection.error_guided.ErrorGuidedSelector` would score each bin with (``paper``,
``released``, ``visible``, ``input``) from the object's training views and the same model, as ``(objects, bins)``
arrays in :func:`~lightning_vtr.geometry.candidate_viewpoints` order, the order of a
:class:`~lightning_vtr.evaluation.robustness.RobustnessMap`'s bins. :func:`validity_table` compares them with the
map's measured loss ``1 - IoU`` (:mod:`~lightning_vtr.evaluation.score_validity`) and returns a Markdown table.
"""

from __future__ import annotations

import zlib
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from lightning_vtr.evaluation.robustness import RobustnessMap, _model_device, _records_and_transform
from lightning_vtr.evaluation.score_validity import format_validity_table, validity_rows
from lightning_vtr.geometry import check_bin_interval
from lightning_vtr.protocol import DEFAULT_THRESHOLD
from lightning_vtr.selection.base import SelectionContext
from lightning_vtr.selection.error_guided import OBJECT_SCORES, ErrorGuidedSelector
from lightning_vtr.selection.scores import InputScore
from lightning_vtr.utils.validation import check_choice, check_int, check_probabilities

__all__ = ["bce_per_object", "selection_scores", "validity_table"]


def bce_per_object(pred: Tensor, target: Tensor) -> Tensor:
    """Mean binary cross-entropy per object ``(B,)`` of ``pred, target (B, R, R, R)``; the loss the augmentation
    callback gives the ``input`` score (predictions clamped to ``[1e-6, 1 - 1e-6]``)."""
    return F.binary_cross_entropy(pred.clamp(1e-6, 1 - 1e-6), target, reduction="none").flatten(1).mean(1)


def _training_images(objects: Any, record: Any, view_set: str, seed: int, num_views: int, transform: Any) -> Tensor:
    """``(V, 3, h, w)``: the views the callback predicts an object from (``eval_item``), or a seeded choice."""
    if hasattr(objects, "eval_item"):
        return torch.as_tensor(objects.eval_item(record, view_set, seed=seed)["images"])
    from lightning_vtr.data.dataset import load_rgba

    paths, _ = record.views[view_set]
    rng = np.random.default_rng([seed, zlib.crc32(f"{record.category}/{record.object_id}".encode())])
    chosen = rng.choice(len(paths), size=num_views, replace=False)
    return torch.as_tensor(transform(np.stack([load_rgba(paths[i]) for i in chosen])))


def selection_scores(
    model: Any,
    objects: Any,
    *,
    k: int = 30,
    scores: Sequence[str] = OBJECT_SCORES,
    source_view_set: str = "aligned",
    seed: int = 0,
    synthesizer: Any = None,
    transform: Any = None,
    split: str = "test",
    batch_size: int = 16,
    threshold: float = DEFAULT_THRESHOLD,
) -> dict[str, np.ndarray]:
    """Each selection score of every object, ``{score: (objects, 180/K * 360/K)}``, bins pitch-major.

    Each object is predicted from ``model.num_views`` of its ``source_view_set`` images (a datamodule's
    ``eval_item(record, source_view_set, seed)``, the views the augmentation callback predicts from; for records, a
    choice seeded by ``(seed, category/object_id)``), then scored by ``ErrorGuidedSelector(k, score=name,
    threshold=threshold).score_views``. The ``input`` score renders every bin centre with ``synthesizer`` and
    predicts from each alone (:func:`bce_per_object` as the loss, as in the callback).

    Args:
        model: a :class:`~lightning_vtr.protocol.ReconstructionModel`.
        objects: a datamodule (its ``split`` objects) or a sequence of records, as for
            :func:`~lightning_vtr.evaluation.robustness.robustness_map`; pass the same to both to align rows.
        k: bin interval in degrees (divides 180).
        scores: the score names, among ``paper``, ``released``, ``visible`` and ``input``.
        source_view_set: the view set the training views come from.
        seed: seeds the choice of training views.
        synthesizer: renders the ``input`` score's views; ``None``: ``RenderSynthesizer(model.image_size)``.
        transform: RGBA uint8 -> model input; ``None``: the datamodule's (``ImageTransform(model.image_size)``).
        split: the datamodule split.
        batch_size: objects per ``predict_voxels`` call (and single-view sets per call for ``input``).
        threshold: the selector's occupancy threshold.

    Returns:
        Score name -> float64 ``(objects, bins)`` array, objects in the order of ``objects``.

    Raises:
        ValueError: an unknown score name, no objects, or a model output that is not probabilities.

    Example::

        scores = selection_scores(model, dm, k=30)
        scores["paper"].shape  # (objects, 72)
    """
    k = check_bin_interval(k)
    for name in scores:
        check_choice("scores", name, OBJECT_SCORES)
    batch_size = check_int("batch_size", batch_size, minimum=1)
    records, default_transform, load_target = _records_and_transform(objects, split, model)
    transform = default_transform if transform is None else transform
    if not records:
        raise ValueError("`objects` must hold at least one object to score, got none")
    device = _model_device(model)
    num_views = int(model.num_views)
    was_training = bool(getattr(model, "training", False))
    if hasattr(model, "eval"):
        model.eval()
    try:
        images = [_training_images(objects, r, source_view_set, seed, num_views, transform) for r in records]
        preds = []
        with torch.inference_mode():
            for lo in range(0, len(images), batch_size):
                batch = model.predict_voxels(torch.stack(images[lo : lo + batch_size]).to(device))
                preds.append(check_probabilities("predict_voxels", batch.detach().float().cpu()))
        predicted = torch.cat(preds)
        target = torch.stack([torch.as_tensor(load_target(r)).float() for r in records])
        context = None
        if "input" in scores:
            from lightning_vtr.synthesis.base import SynthesisRequest

            if synthesizer is None:
                from lightning_vtr.synthesis.render import RenderSynthesizer

                synthesizer = RenderSynthesizer(image_size=int(model.image_size))
            requests = [
                SynthesisRequest(
                    object_id=r.object_id,
                    category=r.category,
                    source_images=np.zeros((0, 0, 0, 4), np.uint8),
                    source_viewpoints=torch.as_tensor(
                        np.asarray(r.views[source_view_set][1], dtype=np.float32).reshape(-1, 2)
                    ),
                    target_viewpoints=torch.zeros(0, 2),
                    mesh_path=getattr(r, "mesh_path", None),
                )
                for r in records
            ]
            context = SelectionContext(
                model=model,
                synthesizer=synthesizer,
                requests=requests,
                transform=transform,
                loss_fn=bce_per_object,
                device=device,
            )
        out: dict[str, np.ndarray] = {}
        for name in scores:
            score: Any = name  # one of OBJECT_SCORES, checked above
            if name == "input":
                score = InputScore(model_batch_size=batch_size)
            selector = ErrorGuidedSelector(score=score, k=k, threshold=threshold)
            out[name] = selector.score_views(predicted, target, context if name == "input" else None).double().numpy()
    finally:
        if hasattr(model, "train"):
            model.train(was_training)
    return out


def validity_table(
    rmap: RobustnessMap,
    scores: dict[str, np.ndarray],
    *,
    object_ids: Sequence[str] | None = None,
    n: int = 3,
    fraction: float = 0.1,
) -> str:
    """The score validity table (Markdown) of ``scores`` against the measured loss ``1 - rmap.iou``.

    Args:
        rmap: the robustness map (the truth).
        scores: score name -> ``(objects, bins)`` from :func:`selection_scores` on the same objects.
        object_ids: the ids the score rows belong to, checked against the map's (``None``: not checked).
        n: bins a selector keeps.
        fraction: share of bins that counts as the worst.

    Returns:
        The table of :func:`~lightning_vtr.evaluation.score_validity.format_validity_table`.

    Raises:
        ValueError: scores of another shape than the map, or rows of other objects.

    Example::

        print(validity_table(rmap, selection_scores(model, dm, k=rmap.k)))
    """
    if object_ids is not None and list(object_ids) != rmap.object_ids:
        raise ValueError("The scores' objects must be the map's objects, in the map's order")
    for name, values in scores.items():
        if np.shape(values) != rmap.iou.shape:
            raise ValueError(f"Score {name!r} must have the map's shape {rmap.iou.shape}, got {np.shape(values)}")
    rows = validity_rows(scores, 1.0 - rmap.iou, rmap.categories, n=n, fraction=fraction)
    return format_validity_table(rows, n=n, fraction=fraction)
