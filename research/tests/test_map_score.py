"""``ErrorGuidedSelector.paper(score=MapScore())``: bins chosen from the category's measured failure map.

A fake synthesizer writes each viewpoint into its image and a fake model reconstructs an object worse the closer
the first view of its set is to that object's bad viewpoint, with a loss (1 - IoU) known in closed form; with
``sigma=0`` every view of a set sits on its bin centre, so the expected maps are exact.
"""

from __future__ import annotations

import lightning as L
import numpy as np
import pytest
import torch
from helpers import (
    TinyUserModel,
    ViewpointSynthesizer,
    decode_viewpoints,
    make_callback,
    make_datamodule,
    make_trainer,
    one_thread,
    viewpoint_transform,
)

from lightning_vtr.geometry import angular_distance, candidate_viewpoints
from lightning_vtr.selection import ErrorGuidedSelector
from lightning_vtr.selection.base import SelectionContext
from lightning_vtr.synthesis.base import SynthesisRequest
from research.scores import MapScore

_one_thread = pytest.fixture(autouse=True, name="_one_thread")(one_thread)

WIDTH = 50.0
R = 4
CELLS = R**3


class _SetModel:
    """Object ``b`` of the call (in request order) fails around ``bad[b]``: given a view set whose first view is
    at distance ``d`` from it, it predicts ``round(64 exp(-d^2 / 2 W^2))`` of the 64 voxels empty, the rest full,
    so against a full target its loss 1 - IoU is that count over 64."""

    def __init__(self, bad: torch.Tensor, sets_per_object: int) -> None:
        self.bad = bad
        self.sets_per_object = sets_per_object
        self.seen = 0
        self.sets = 0

    def predict_voxels(self, images: torch.Tensor) -> torch.Tensor:
        view = decode_viewpoints(images[:, 0])  # (N, 2) the first view of each set
        obj = (self.seen + torch.arange(len(view))) // self.sets_per_object
        self.seen += len(view)
        self.sets += len(view)
        empty = _expected_loss(view, self.bad[obj]) * CELLS
        cells = torch.arange(CELLS, dtype=torch.float64)
        return (cells[None] >= empty.round()[:, None]).to(torch.float32).view(-1, R, R, R)


def _expected_loss(views: torch.Tensor, bad: torch.Tensor) -> torch.Tensor:
    d = angular_distance(views.to(torch.float64), bad.to(torch.float64))
    return (torch.exp(-0.5 * (d / WIDTH) ** 2) * CELLS).round() / CELLS


def _context(bad: torch.Tensor, k: int, categories: list[str]) -> tuple[SelectionContext, _SetModel]:
    n_bins = (180 // k) * (360 // k)
    model = _SetModel(bad, n_bins)
    requests = [
        SynthesisRequest(f"obj{b}", c, np.zeros((0, 2, 2, 4), np.uint8), torch.zeros(0, 2), torch.zeros(0, 2))
        for b, c in enumerate(categories)
    ]
    return SelectionContext(
        model, ViewpointSynthesizer(), requests, viewpoint_transform, None, torch.device("cpu")
    ), model


def _bin_losses(bad: torch.Tensor, k: int) -> torch.Tensor:
    """``(objects, V_c)`` loss of each object's view sets at every bin centre."""
    centres = candidate_viewpoints(k).to(torch.float64)
    return torch.stack([_expected_loss(centres, b.expand_as(centres)) for b in bad])


def _rescaled(loss: torch.Tensor) -> torch.Tensor:
    return (loss - loss.min()) / (loss.max() - loss.min())


def test_every_object_gets_its_categorys_mean_measured_loss_rescaled_to_0_1():
    bad = torch.tensor([[70.0, -40.0], [90.0, -20.0], [-140.0, 70.0]])
    categories = ["chair", "chair", "table"]
    selector = ErrorGuidedSelector.paper(k=30, score=MapScore(objects=2), spread=0.0)
    context, model = _context(bad, 30, categories)
    full = torch.ones(3, R, R, R)
    scores = selector.score_views(
        full, full, context, categories=categories, generator=torch.Generator().manual_seed(0)
    )

    losses = _bin_losses(bad, 30)
    chair, table = losses[:2].mean(0), losses[2]
    torch.testing.assert_close(selector.score_options.category_maps["chair"].double(), chair, atol=1e-6, rtol=0)
    torch.testing.assert_close(selector.score_options.category_maps["table"].double(), table, atol=1e-6, rtol=0)
    torch.testing.assert_close(scores[0].double(), _rescaled(chair), atol=1e-6, rtol=0)
    torch.testing.assert_close(scores[1], scores[0])  # both chairs score alike
    torch.testing.assert_close(scores[2].double(), _rescaled(table), atol=1e-6, rtol=0)
    # one synthesizer call; one set of 3 views per bin and measured object
    assert context.synthesizer.calls == 1
    assert model.sets == 3 * 72


def test_map_objects_caps_the_measured_objects_and_momentum_blends_the_calls():
    bad = torch.tensor([[70.0, -40.0], [90.0, -20.0], [0.0, 0.0]])
    categories = ["chair"] * 3
    selector = ErrorGuidedSelector.paper(k=30, score=MapScore(objects=1, momentum=0.25), spread=0.0)
    full = torch.ones(3, R, R, R)
    context, model = _context(bad, 30, categories)
    selector.score_views(full, full, context, categories=categories, generator=torch.Generator().manual_seed(0))
    assert model.sets == 72  # one object measured
    first = selector.score_options.category_maps["chair"].clone()
    losses = _bin_losses(bad, 30)
    which = [i for i in range(3) if torch.allclose(first.double(), losses[i], atol=1e-6)]
    assert len(which) == 1  # the map is exactly one object's loss

    # a second call with other failures: the map moves a quarter of the way to the new measurement
    moved = torch.tensor([[-150.0, 10.0]] * 3)
    context, _ = _context(moved, 30, categories)
    selector.score_views(full, full, context, categories=categories, generator=torch.Generator().manual_seed(1))
    new = _bin_losses(moved[:1], 30)[0]
    torch.testing.assert_close(
        selector.score_options.category_maps["chair"].double(),
        first.double() + 0.25 * (new - first.double()),
        atol=1e-6,
        rtol=0,
    )


def test_hard_selection_sends_every_object_of_a_category_to_its_worst_bins():
    bad = torch.tensor([[70.0, -40.0], [70.0, -40.0], [-140.0, 70.0], [-140.0, 70.0]])
    categories = ["chair", "chair", "table", "table"]
    selector = ErrorGuidedSelector.paper(k=30, score=MapScore(), spread=0.0, min_separation=30.0)
    context, _ = _context(bad, 30, categories)
    full = torch.ones(4, R, R, R)
    views = selector.select(full, full, categories, torch.Generator().manual_seed(0), context)
    centres = candidate_viewpoints(30).to(torch.float64)
    worst = _bin_losses(bad[[0, 2]], 30).argmax(1)  # chair's and table's worst bin
    for row, category in enumerate(categories):
        nearest = angular_distance(views[row].double()[:, None], centres[None]).argmin(1)
        assert int(nearest[0]) == int(worst[row // 2]), category  # the worst bin is chosen first
        assert torch.equal(selector.last_bins[row], selector.last_bins[row - row % 2])  # same bins per category
        chosen = centres[selector.last_bins[row]]
        apart = angular_distance(chosen[:, None], chosen[None]) + torch.eye(3) * 360
        assert float(apart.min()) > 30.0  # suppression keeps them apart
    assert not selector.last_fallback.any()


def test_a_flat_map_prefers_no_bin_and_falls_back_to_uniform_views():
    bad = torch.tensor([[0.0, 0.0]])
    selector = ErrorGuidedSelector.paper(k=30, score=MapScore(), spread=0.0)
    context, model = _context(bad, 30, ["chair"])
    model.predict_voxels = lambda images: torch.ones(len(images), R, R, R)  # never fails: a flat map
    full = torch.ones(1, R, R, R)
    selector.select(full, full, ["chair"], torch.Generator().manual_seed(0), context)
    assert torch.equal(selector.score_options.category_maps["chair"], torch.zeros(72))
    assert selector.last_fallback.tolist() == [True]


def test_the_maps_survive_a_state_round_trip_and_a_wrong_grid_is_refused():
    selector = ErrorGuidedSelector.paper(k=30, score=MapScore())
    selector.score_options.category_maps = {"chair": torch.linspace(0, 1, 72)}
    restored = ErrorGuidedSelector.paper(k=30, score=MapScore())
    restored.load_state_dict(selector.state_dict())
    assert torch.equal(restored.score_options.category_maps["chair"], selector.score_options.category_maps["chair"])
    assert ErrorGuidedSelector.paper(score="visible").state_dict() == {}
    with pytest.raises(ValueError, match=r"'chair' has shape \(72,\); this selector \(k=90\) has 8 bins"):
        ErrorGuidedSelector.paper(k=90, score=MapScore()).load_state_dict(selector.state_dict())


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"objects": 0}, "objects"),
        ({"momentum": 0.0}, "momentum"),
        ({"momentum": 1.5}, "momentum"),
    ],
)
def test_bad_map_settings_are_named(kwargs, match):
    with pytest.raises(ValueError, match=match):
        MapScore(**kwargs)
    with pytest.raises(ValueError, match="relative=True` does not apply to score='map'"):
        ErrorGuidedSelector.paper(score=MapScore(), relative=True)


def test_the_map_score_needs_a_context_and_whole_categories():
    selector = ErrorGuidedSelector.paper(score=MapScore())
    assert selector.needs_context and selector.batched
    full = torch.ones(1, R, R, R)
    with pytest.raises(ValueError, match="needs a SelectionContext"):
        selector.select(full, full, ["chair"], torch.Generator().manual_seed(0), None)
    with pytest.raises(ValueError, match="pass `categories`"):
        selector.score_views(full, full)


def test_the_callback_measures_the_category_maps_and_sends_each_category_to_its_worst_bins(tiny_dataset, tmp_path):
    """A one-epoch fit selects once, before epoch 0: the searched objects' views sit around the 3 worst bins of
    their category's map (measured by the initial model on the real renderer), the same bins for the whole
    category, and the maps are in the callback's saved state."""
    L.seed_everything(0, verbose=False)
    dm = make_datamodule(tiny_dataset, tmp_path)
    selector = ErrorGuidedSelector.paper(k=90, score=MapScore(objects=1), spread=0.0)
    callback = make_callback(selector=selector, fraction=0.3, pool=None, select_at_start=True)
    make_trainer(tmp_path, 1, [callback]).fit(TinyUserModel(), datamodule=dm)

    samples = dm.generated_samples
    assert samples
    centres = candidate_viewpoints(90).to(torch.float64)
    state = callback.state_dict()["selector"]["category_maps"]
    assert {s["category"] for s in samples} <= set(state)
    for sample in samples:
        loss = state[sample["category"]]
        assert float(loss.max() - loss.min()) > 0  # the bins are told apart
        worst = set(torch.argsort(loss, descending=True)[:3].tolist())
        views = torch.as_tensor(np.asarray(sample["viewpoints"]), dtype=torch.float64)
        nearest = angular_distance(views[:, None], centres[None]).argmin(1)
        assert set(nearest.tolist()) == worst, (sample["object_id"], loss.tolist(), views.tolist())
