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
  :func:`write_index_html`, :func:`map_file_stem`) and :class:`RobustnessMapLogger` logs it during training.

Example::

    from lightning_vtr.evaluation import evaluate_folder, format_evaluation_table
    from lightning_vtr.models import load_model

    model = load_model("runs/vtr/last.ckpt")
    print(format_evaluation_table({"Ours": evaluate_folder(model, "VTR_test/Spherical", "ShapeNetVox32")}))
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from lightning_vtr.utils.exports import lazy_exports

if TYPE_CHECKING:  # what type checkers, IDEs and the API reference read
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
    from lightning_vtr.evaluation.robustness_plot import map_file_stem, plot_difference, plot_map, write_index_html
else:  # at run time each name is imported from its module on first use
    __getattr__, __dir__ = lazy_exports(
        __name__,
        {
            "lightning_vtr.evaluation.dataset": [
                "evaluate_dataset",
                "evaluate_folder",
                "evaluation_notes",
                "evaluation_rows",
                "format_evaluation_table",
                "write_evaluation",
            ],
            "lightning_vtr.evaluation.pix3d": ["evaluate_pix3d", "frame_check", "frame_check_summary"],
            "lightning_vtr.evaluation.predict": [
                "export_predictions",
                "make_datamodule",
                "predict_dataset",
                "predict_folders",
                "read_view_folder",
            ],
            "lightning_vtr.evaluation.robustness": [
                "RobustnessMap",
                "bin_area_fractions",
                "read_bins_csv",
                "robustness_map",
                "view_sets_around_bins",
            ],
            "lightning_vtr.evaluation.robustness_callback": ["RobustnessMapLogger"],
            "lightning_vtr.evaluation.robustness_plot": [
                "map_file_stem",
                "plot_difference",
                "plot_map",
                "write_index_html",
            ],
        },
    )

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
    "frame_check",
    "frame_check_summary",
    "make_datamodule",
    "map_file_stem",
    "plot_difference",
    "plot_map",
    "predict_dataset",
    "predict_folders",
    "read_bins_csv",
    "read_view_folder",
    "robustness_map",
    "view_sets_around_bins",
    "write_evaluation",
    "write_index_html",
]
