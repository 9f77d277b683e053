"""The parts of :class:`~lightning_vtr.callback.ErrorGuidedViewAugmentation` that need no hook of their own.

* :mod:`~lightning_vtr.augmentation.runner`: a whole round on a running Trainer (``run_round``: search, select,
  plan, synthesize), its steps sharded over processes;
* :mod:`~lightning_vtr.augmentation.selection_round`: which objects a selection round searches, which of them
  get new views and which view sets they get (pure functions of the seed, the epoch and the pool);
* :mod:`~lightning_vtr.augmentation.prediction`: the model's occupancy probabilities, checked;
* :mod:`~lightning_vtr.augmentation.distributed`: sharding work over processes and gathering the results;
* :mod:`~lightning_vtr.augmentation.rule`: the callback's ``pool`` argument and the rule stored with its state;
* :mod:`~lightning_vtr.augmentation.recording`: the selection records, the settings record, the image grids
  and error sheets.

A Lightning user needs none of them directly: the callback drives them.
"""
