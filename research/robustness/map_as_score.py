"""Does the training objects' robustness map, pooled per category, predict a test object's failures?

Run from the repository root (`python -m research.robustness.map_as_score`) after `python examples/pix2vox_vtr.py` and the `lightning-vtr robustness ...
--out robustness` command in research/notes/results.md; prints one validity table per checkpoint.
"""

import sys
from pathlib import Path

import numpy as np

from lightning_vtr.evaluation import RobustnessMap, robustness_map
from lightning_vtr.evaluation.predict import make_datamodule
from lightning_vtr.models import load_model
from research.score_validity import format_validity_table, validity_rows

DATA = Path.home() / ".cache/lightning_vtr/embedded-7362fcef56"
for name, ckpt in [
    ("None-VTR", "runs/pix2vox_vtr/none/checkpoints/last.ckpt"),
    ("VTR__default_rule", "runs/pix2vox_vtr/visible_tau10_search/checkpoints/last.ckpt"),
]:
    model = load_model(ckpt)
    dm = make_datamodule(ckpt, model, DATA)
    train = robustness_map(model, dm, split="train", k=30, seed=0, progress=False)
    train.to_csv(f"robustness/train_maps/{name}")
    test = RobustnessMap.from_csv(f"robustness/maps/{name}")
    loss = 1.0 - test.iou
    train_loss = 1.0 - train.iou
    cats = sorted(set(train.categories))
    cat_mean = {c: train_loss[[i for i, x in enumerate(train.categories) if x == c]].mean(0) for c in cats}
    by_category = np.stack([cat_mean[c] for c in test.categories])
    overall = np.broadcast_to(train_loss.mean(0), loss.shape).copy()
    rows = validity_rows(
        {"map (category, training objects)": by_category, "map (all training objects)": overall}, loss, test.categories
    )
    print(f"## {name}: train IoU over the sphere {train.overall():.4f} ({train.num_objects} objects)")
    print(format_validity_table(rows))
    sys.stdout.flush()
