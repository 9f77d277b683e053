"""The paper's reproduction harness: pretraining and fine-tuning runs, the robustness report, its tables.

Not needed to use the plugin: :class:`~lightning_vtr.callback.ErrorGuidedViewAugmentation` with any
Trainer and model is all the paper's method requires.
"""
