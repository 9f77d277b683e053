"""Evaluation: result tables, dataset and folder evaluation, Pix3D evaluation.

* :mod:`~lightning_vtr.evaluation.tables`: the robustness-table layout and metric naming.
"""
