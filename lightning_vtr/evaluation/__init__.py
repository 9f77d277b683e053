"""Evaluation: result tables, dataset and folder evaluation, Pix3D evaluation, and prediction with a trained model.

* :mod:`~lightning_vtr.evaluation.tables`: the robustness-table layout and metric naming.
* :mod:`~lightning_vtr.evaluation.dataset`: :func:`evaluate_dataset` (a model's IoU and F-score on any test set,
  overall and per category), :func:`evaluate_folder` (on a folder test set), and the Table 5 layout
  (:func:`format_evaluation_table`, :func:`evaluation_rows`, :func:`write_evaluation`).
* :mod:`~lightning_vtr.evaluation.pix3d`: :func:`evaluate_pix3d` and the frame check of the Pix3D reader
  (:func:`frame_check`).
* :mod:`~lightning_vtr.evaluation.predict`: prediction on image folders or a dataset split
  (:func:`predict_folders`, :func:`predict_dataset`, :func:`read_view_folder`, :func:`make_datamodule`) and
  its exports (:func:`export_predictions`).

Example::

    from lightning_vtr.evaluation import evaluate_folder, format_evaluation_table
    from lightning_vtr.models import load_model

    model = load_model("runs/vtr/last.ckpt")
    print(format_evaluation_table({"Ours": evaluate_folder(model, "VTR_test/Spherical", "ShapeNetVox32")}))

Names are imported lazily, so importing :mod:`~lightning_vtr.evaluation.tables` does not import Lightning.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # what IDEs and type checkers see; at runtime __getattr__ imports on first use
    from lightning_vtr.evaluation.dataset import (
        evaluate_dataset,
        evaluate_folder,
        evaluation_notes,
        evaluation_rows,
        format_evaluation_table,
        write_evaluation,
    )
    from lightning_vtr.evaluation.pix3d import evaluate_pix3d, frame_check, frame_check_summary
    from lightning_vtr.evaluation.predict import (
        export_predictions,
        make_datamodule,
        predict_dataset,
        predict_folders,
        read_view_folder,
    )

_EXPORTS = {
    "evaluate_dataset": "lightning_vtr.evaluation.dataset",
    "evaluate_folder": "lightning_vtr.evaluation.dataset",
    "evaluation_notes": "lightning_vtr.evaluation.dataset",
    "evaluation_rows": "lightning_vtr.evaluation.dataset",
    "format_evaluation_table": "lightning_vtr.evaluation.dataset",
    "write_evaluation": "lightning_vtr.evaluation.dataset",
    "evaluate_pix3d": "lightning_vtr.evaluation.pix3d",
    "frame_check": "lightning_vtr.evaluation.pix3d",
    "frame_check_summary": "lightning_vtr.evaluation.pix3d",
    "export_predictions": "lightning_vtr.evaluation.predict",
    "make_datamodule": "lightning_vtr.evaluation.predict",
    "predict_dataset": "lightning_vtr.evaluation.predict",
    "predict_folders": "lightning_vtr.evaluation.predict",
    "read_view_folder": "lightning_vtr.evaluation.predict",
}
__all__ = [
    "evaluate_dataset",
    "evaluate_folder",
    "evaluate_pix3d",
    "evaluation_notes",
    "evaluation_rows",
    "export_predictions",
    "format_evaluation_table",
    "frame_check",
    "frame_check_summary",
    "make_datamodule",
    "predict_dataset",
    "predict_folders",
    "read_view_folder",
    "write_evaluation",
]


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'lightning_vtr.evaluation' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(__all__)
