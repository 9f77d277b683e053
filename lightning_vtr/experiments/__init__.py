"""The paper's reproduction harness: pretraining and fine-tuning runs, the robustness report, its tables.

* :mod:`~lightning_vtr.experiments.config`: :class:`~lightning_vtr.experiments.config.ExperimentConfig`, whose
  fields are also the command-line flags (:mod:`~lightning_vtr.experiments.flags` generates them).
* :mod:`~lightning_vtr.experiments.strategies`: the named view strategies, the rows of ``strategies.yaml``.
* :mod:`~lightning_vtr.experiments.training`: pretrain, fine-tune with a view strategy, evaluate, time the stages.
* :mod:`~lightning_vtr.experiments.comparison`: one model with and without the callback (the examples).
* :mod:`~lightning_vtr.experiments.report`: ``lightning-vtr report``: Table 1 over seeds with confidence
  intervals, paired differences, the training views' distribution, the time split and the ablations; its steps
  are the ``report_*`` modules (config, plan, run, tables, render, timing, files).
* :mod:`~lightning_vtr.experiments.statistics`: confidence intervals, paired differences, view spread.

Not needed to use the plugin: :class:`~lightning_vtr.callback.ErrorGuidedViewAugmentation` with any
Trainer and model is all the paper's method requires (``examples/quickstart.py``).
"""
