"""The score-validity study's scores: every selection score of an object, aligned with its robustness map."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from robustness_fixtures import N_BINS, ImageMeanModel, K, OracleModel

from lightning_vtr.data.dataset import load_voxels
from lightning_vtr.data.transforms import ImageTransform
from lightning_vtr.evaluation import robustness_map
from lightning_vtr.geometry import candidate_viewpoints
from lightning_vtr.synthesis.base import SynthesisRequest
from lightning_vtr.synthesis.render import RenderSynthesizer
from research.score_validity import bce_per_object, selection_scores, validity_table


def measure(model, objects, **kw):
    kw.setdefault("synthesizer", RenderSynthesizer(image_size=32))
    return robustness_map(model, objects, k=K, progress=False, **kw)


class SilhouetteModel(ImageMeanModel):
    """Occupancy ``sigmoid(10 (silhouette area - 0.15) + b)``: it depends on a single view too, unlike its parent."""

    def predict_voxels(self, images):
        area = (images[:, :, 0] < 2.0).float().mean(dim=(1, 2, 3))  # white is 2.25 after ImageNet normalisation
        return torch.sigmoid(10 * (area - 0.15)[:, None, None, None] + self.bias)


def test_selection_scores_are_aligned_with_the_map(objects):
    model = SilhouetteModel()
    synthesizer = RenderSynthesizer(image_size=32)
    scores = selection_scores(model, objects, k=K, synthesizer=synthesizer)
    assert sorted(scores) == ["input", "paper", "released", "visible"]
    assert all(v.shape == (3, N_BINS) for v in scores.values())
    # the input score of object 1 at bin 7 is the loss of the model given that bin centre's image alone
    centre = candidate_viewpoints(K)[7:8]
    rendered = synthesizer.synthesize(
        [
            SynthesisRequest(
                object_id=objects[1].object_id,
                category=objects[1].category,
                source_images=np.zeros((0, 0, 0, 4), np.uint8),
                source_viewpoints=torch.zeros(0, 2),
                target_viewpoints=centre,
                mesh_path=objects[1].mesh_path,
            )
        ]
    )[0]
    with torch.no_grad():
        pred = model.predict_voxels(ImageTransform(32)(rendered)[None])
    expected = bce_per_object(pred, load_voxels(objects[1])[None])
    assert scores["input"][1, 7] == pytest.approx(float(expected), rel=1e-5)
    assert scores["input"][1].std() > 1e-4  # the views differ, and so do their losses
    # a prediction equal to the truth has no error to project
    oracle = OracleModel(torch.stack([load_voxels(r) for r in objects]), per_object=1)
    exact = selection_scores(oracle, objects, k=K, scores=("paper", "released", "visible"))
    assert all((v == 0).all() for v in exact.values())
    rmap = measure(model, objects)
    table = validity_table(rmap, scores, object_ids=[r.object_id for r in objects])
    assert table.startswith("| score | Spearman")
    assert [line.split("|")[1].strip() for line in table.splitlines()[2:]] == list(scores)
    with pytest.raises(ValueError, match="shape"):
        validity_table(rmap, {"paper": scores["paper"][:2]})
