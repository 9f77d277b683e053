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
* :mod:`~lightning_vtr.evaluation.robustness`: the viewpoint robustness map (:func:`robustness_map`,
  :class:`RobustnessMap`, :func:`view_sets_around_bins`, :func:`bin_area_fractions`, :func:`read_bins_csv`);
  :mod:`~lightning_vtr.evaluation.robustness_plot` draws it (:func:`plot_map`, :func:`plot_difference`,
  :func:`write_index_html`) and :class:`RobustnessMapLogger` logs it during training.
* :mod:`~lightning_vtr.evaluation.score_validity` and :mod:`~lightning_vtr.evaluation.robustness_scores`: do the
  selection scores point at the bins where the model fails (:func:`selection_scores`, :func:`validity_table`,
  :func:`spearman_per_object`, :func:`top_hit_rate`, :func:`mean_with_interval`, :func:`validity_rows`,
  :func:`format_validity_table`).

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
    from lightning_vtr.evaluation.robustness import (
        RobustnessMap,
        bin_area_fractions,
        read_bins_csv,
        robustness_map,
        view_sets_around_bins,
    )
    from lightning_vtr.evaluation.robustness_callback import RobustnessMapLogger
    from lightning_vtr.evaluation.robustness_plot import plot_difference, plot_map, write_index_html
    from lightning_vtr.evaluation.robustness_scores import selection_scores, validity_table
    from lightning_vtr.evaluation.score_validity import (
        format_validity_table,
        mean_with_interval,
        spearman_per_object,
        top_hit_rate,
        validity_rows,
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
    "robustness_map": "lightning_vtr.evaluation.robustness",
    "RobustnessMap": "lightning_vtr.evaluation.robustness",
    "view_sets_around_bins": "lightning_vtr.evaluation.robustness",
    "bin_area_fractions": "lightning_vtr.evaluation.robustness",
    "read_bins_csv": "lightning_vtr.evaluation.robustness",
    "plot_map": "lightning_vtr.evaluation.robustness_plot",
    "plot_difference": "lightning_vtr.evaluation.robustness_plot",
    "write_index_html": "lightning_vtr.evaluation.robustness_plot",
    "spearman_per_object": "lightning_vtr.evaluation.score_validity",
    "top_hit_rate": "lightning_vtr.evaluation.score_validity",
    "mean_with_interval": "lightning_vtr.evaluation.score_validity",
    "validity_rows": "lightning_vtr.evaluation.score_validity",
    "format_validity_table": "lightning_vtr.evaluation.score_validity",
    "selection_scores": "lightning_vtr.evaluation.robustness_scores",
    "validity_table": "lightning_vtr.evaluation.robustness_scores",
    "RobustnessMapLogger": "lightning_vtr.evaluation.robustness_callback",
}
__all__ = [
    "RobustnessMap",
    "RobustnessMapLogger",
    "bin_area_fractions",
    "evaluate_dataset",
    "evaluate_folder",
    "evaluate_pix3d",
    "evaluation_notes",
    "evaluation_rows",
    "export_predictions",
    "format_evaluation_table",
    "format_validity_table",
    "frame_check",
    "frame_check_summary",
    "make_datamodule",
    "mean_with_interval",
    "plot_difference",
    "plot_map",
    "predict_dataset",
    "predict_folders",
    "read_bins_csv",
    "read_view_folder",
    "robustness_map",
    "selection_scores",
    "spearman_per_object",
    "top_hit_rate",
    "validity_rows",
    "validity_table",
    "view_sets_around_bins",
    "write_evaluation",
    "write_index_html",
]


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'lightning_vtr.evaluation' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(__all__)
