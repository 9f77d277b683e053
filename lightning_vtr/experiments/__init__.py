"""The paper's reproduction harness: pretraining and fine-tuning runs, the robustness report, its tables.

* :mod:`~lightning_vtr.experiments.training`: the experiment config, pretrain, fine-tune with a view
  strategy, evaluate, time the stages; the registries of models and of named strategy variants.
* :mod:`~lightning_vtr.experiments.comparison`: one model with and without the callback (the examples).
* :mod:`~lightning_vtr.experiments.report`: ``lightning-vtr report``: Table 1 over seeds with confidence
  intervals, paired differences, the training views' distribution, the time split and the ablations.
* :mod:`~lightning_vtr.experiments.statistics`: confidence intervals, paired differences, view spread.

Not needed to use the plugin: :class:`~lightning_vtr.callback.ErrorGuidedViewAugmentation` with any
Trainer and model is all the paper's method requires (``examples/quickstart.py``).
"""
