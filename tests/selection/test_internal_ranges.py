"""The predictions selectors make or query internally are range-checked like the callback's own: VIAT's model
queries at candidate views must be probabilities; MVTN's network must predict finite views."""

from __future__ import annotations

import re

import numpy as np
import pytest
import torch
from helpers import ViewpointSynthesizer, one_thread, viewpoint_transform

from lightning_vtr.selection.base import SelectionContext
from lightning_vtr.selection.mvtn import MVTNSelector
from lightning_vtr.selection.viat import VIATSelector
from lightning_vtr.synthesis.base import SynthesisRequest

_one_thread = pytest.fixture(autouse=True, name="_one_thread")(one_thread)
R = 4


class _LogitModel:
    """Returns logits (values up to 3) instead of probabilities."""

    def predict_voxels(self, images: torch.Tensor) -> torch.Tensor:
        return torch.linspace(-3.0, 3.0, R**3).reshape(1, R, R, R).expand(len(images), -1, -1, -1)


def _context(batch: int = 2) -> SelectionContext:
    requests = [
        SynthesisRequest(f"obj{b}", "chair", np.zeros((0, 2, 2, 4), np.uint8), torch.zeros(0, 2), torch.zeros(0, 2))
        for b in range(batch)
    ]
    loss = lambda pred, target: (pred - target).abs().mean(dim=(1, 2, 3))  # noqa: E731
    return SelectionContext(
        _LogitModel(), ViewpointSynthesizer(), requests, viewpoint_transform, loss, torch.device("cpu")
    )


_MESSAGE = re.escape(
    "`predict_voxels` must return probabilities in [0, 1], got values in [-3, 3] (0 non-finite of "
) + (r"\d+" + re.escape("); at the selector's candidate views; did predict_voxels return logits?"))


def test_viat_refuses_a_model_that_returns_logits_at_its_candidate_views():
    selector = VIATSelector(num_views=1, population=2, iterations=1)
    volumes = torch.zeros(2, R, R, R)
    with pytest.raises(ValueError, match=_MESSAGE):
        selector.select(volumes, volumes, ["chair", "chair"], torch.Generator().manual_seed(0), _context())


def test_mvtn_refuses_non_finite_views_of_a_diverged_network(monkeypatch):
    selector = MVTNSelector(base_yaw=(0.0, 180.0), steps=0)
    monkeypatch.setattr(selector.network, "forward", lambda volumes: torch.full((len(volumes), 2, 2), float("nan")))
    volumes = torch.rand(1, 8, 8, 8)
    message = (
        "MVTN's network must predict finite views, got 2 of 2 non-finite (yaw, pitch) pairs after 0 training steps; "
        f"lower `lr` (now {selector.lr:g})"
    )
    with pytest.raises(ValueError, match=f"^{re.escape(message)}$"):
        selector.select(volumes, (volumes > 0.5).float(), ["chair"])
