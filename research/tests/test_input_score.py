"""``ErrorGuidedSelector.paper(score=InputScore())``: every candidate view is rendered and scored by the model's loss on it.

A fake synthesizer writes each viewpoint into its image and a fake model fails in proportion to how close its
one input view is to a known bad viewpoint, so the right scores and bins are known in closed form.
"""

from __future__ import annotations

import copy
import re

import lightning as L
import numpy as np
import pytest
import torch
from helpers import (
    TinyUserModel,
    ViewpointSynthesizer,
    decode_viewpoints,
    generated_contents,
    make_callback,
    make_datamodule,
    make_trainer,
    one_thread,
    viewpoint_transform,
)

from lightning_vtr.geometry import angular_distance, candidate_viewpoints
from lightning_vtr.selection import ErrorGuidedSelector
from lightning_vtr.selection.base import SelectionContext
from lightning_vtr.selection.diversity import bin_solid_angles
from lightning_vtr.synthesis.base import SynthesisRequest
from research.scores import InputScore

_one_thread = pytest.fixture(autouse=True, name="_one_thread")(one_thread)

BAD = torch.tensor([[70.0, -40.0], [-140.0, 70.0]], dtype=torch.float64)  # each object's worst viewpoint
WIDTH = 50.0
R = 4


class _OneViewModel:
    """Object ``b`` (told apart by the batch order) is reconstructed worse the closer its view is to ``BAD[b]``.

    It predicts a constant volume ``exp(-d^2 / 2 W^2)`` of the distance ``d`` from the one input view to the
    object's bad viewpoint; with an empty target and a mean-value loss, that value is the loss.
    """

    def __init__(self, views_per_object: int) -> None:
        self.views_per_object = views_per_object
        self.inputs: list[tuple[int, ...]] = []
        self.seen = 0

    def predict_voxels(self, images: torch.Tensor) -> torch.Tensor:
        self.inputs.append(tuple(images.shape))
        view = decode_viewpoints(images[:, 0])  # (N, 2)
        obj = (self.seen + torch.arange(len(view))) // self.views_per_object
        self.seen += len(view)
        d = angular_distance(view, BAD[obj].to(view.dtype))
        return torch.exp(-0.5 * (d / WIDTH) ** 2)[:, None, None, None].expand(-1, R, R, R)


def _loss(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    return (pred - target).abs().mean(dim=(1, 2, 3))


def _context(selector: ErrorGuidedSelector, batch: int = 2) -> tuple[SelectionContext, _OneViewModel]:
    model = _OneViewModel(selector.candidates.shape[0])
    requests = [
        SynthesisRequest(f"obj{b}", "chair", np.zeros((0, 2, 2, 4), np.uint8), torch.zeros(0, 2), torch.zeros(0, 2))
        for b in range(batch)
    ]
    context = SelectionContext(model, ViewpointSynthesizer(), requests, viewpoint_transform, _loss, torch.device("cpu"))
    return context, model


def _expected_scores(k: int) -> torch.Tensor:
    centres = candidate_viewpoints(k).to(torch.float64)
    d = angular_distance(centres[None], BAD[:, None])  # (2, V)
    return torch.exp(-0.5 * (d / WIDTH) ** 2)


def test_input_score_is_the_models_loss_given_each_bin_centre_alone():
    selector = ErrorGuidedSelector.paper(k=30, score=InputScore())
    context, model = _context(selector)
    volumes = torch.zeros(2, R, R, R)
    scores = selector.score_views(volumes, volumes, context)
    assert scores.shape == (2, 72)
    # the viewpoint code is 16-bit: 0.006 degrees of round-off
    torch.testing.assert_close(scores.double(), _expected_scores(30), atol=2e-4, rtol=0)
    # one synthesizer call for every candidate of every object, and single-view model inputs
    assert context.synthesizer.calls == 1
    assert model.inputs == [(72, 1, 3, 2, 2), (72, 1, 3, 2, 2)]


def test_model_batch_size_chunks_the_predictions_without_changing_the_scores():
    volumes = torch.zeros(2, R, R, R)
    whole = ErrorGuidedSelector.paper(k=30, score=InputScore(model_batch_size=144))
    context, model = _context(whole)
    reference = whole.score_views(volumes, volumes, context)
    assert model.inputs == [(144, 1, 3, 2, 2)]
    chunked = ErrorGuidedSelector.paper(k=30, score=InputScore(model_batch_size=50))
    context, model = _context(chunked)
    torch.testing.assert_close(chunked.score_views(volumes, volumes, context), reference, rtol=0, atol=0)
    assert [shape[0] for shape in model.inputs] == [50, 50, 44]


def test_hard_selection_with_suppression_takes_the_worst_view_first_and_keeps_the_others_apart():
    selector = ErrorGuidedSelector.paper(k=30, score=InputScore(), min_separation=30.0)
    context, _ = _context(selector)
    volumes = torch.zeros(2, R, R, R)
    views = selector.select(volumes, volumes, ["chair", "chair"], torch.Generator().manual_seed(0), context)
    centres = candidate_viewpoints(30).to(torch.float64)
    expected = _expected_scores(30)
    for b in range(2):
        bins = selector.last_bins[b]
        assert int(bins[0]) == int(expected[b].argmax())  # the bin nearest the object's bad view
        # the next two are the best bins outside 30 degrees of a chosen one and of its antipode
        gaps = angular_distance(centres[bins][:, None], centres[bins][None])
        assert float(gaps[~torch.eye(3, dtype=torch.bool)].min()) > 30.0
    assert views.shape == (2, 3, 2)
    # views are drawn around their bins (sigma = K / 6 = 5 degrees)
    assert float(angular_distance(views.double(), centres[selector.last_bins]).max()) < 6 * 5.0


def test_temperature_sampling_prefers_the_bad_views_in_proportion():
    selector = ErrorGuidedSelector.paper(k=30, score=InputScore(), temperature=1.0, num_views=1)
    volumes = torch.zeros(2, R, R, R)
    first = []
    for seed in range(300):
        context, _ = _context(selector)
        selector.select(volumes, volumes, ["chair", "chair"], torch.Generator().manual_seed(seed), context)
        first.append(selector.last_bins[:, 0])
    picks = torch.stack(first)  # (300, 2)
    centres = candidate_viewpoints(30).to(torch.float64)
    near = angular_distance(centres[picks], BAD[None]) < 60.0
    # P(bin) is proportional to solid angle x loss: about 0.6 of the mass lies within 60 degrees of the bad
    # view for these losses, against 0.27 for area-uniform bins
    weights = _expected_scores(30) * bin_solid_angles(30)
    mass = (weights * (angular_distance(centres[None], BAD[:, None]) < 60.0)).sum(1) / weights.sum(1)
    assert torch.allclose(near.double().mean(0), mass, atol=0.1)
    assert bool((mass > 0.45).all())


def test_input_score_needs_a_context_and_takes_only_its_own_options():
    selector = ErrorGuidedSelector.paper(score=InputScore())
    assert selector.needs_context and not ErrorGuidedSelector.paper(score="visible").needs_context
    volumes = torch.zeros(1, R, R, R)
    with pytest.raises(ValueError, match="score='input'.*SelectionContext"):
        selector.select(volumes, volumes, ["chair"])
    context, _ = _context(selector, batch=2)
    with pytest.raises(ValueError, match="one SynthesisRequest per object: expected 1, got 2"):
        selector.select(volumes, volumes, ["chair"], context=context)
    assert InputScore().settings() == {"model_batch_size": 72}
    with pytest.raises(TypeError, match="mode"):
        InputScore(mode="soft")  # type: ignore[call-arg]
    with pytest.raises(ValueError, match="model_batch_size"):
        InputScore(model_batch_size=0)


def test_the_callback_scores_input_views_with_the_model_it_starts_from(tiny_dataset, tmp_path):
    """A one-epoch fit selects once, before epoch 0, from the initial model: each object's views sit around
    the three bins where that model, given one rendered view, reconstructs the object worst."""
    L.seed_everything(0, verbose=False)
    dm = make_datamodule(tiny_dataset, tmp_path)
    model = TinyUserModel()
    initial = copy.deepcopy(model)
    selector = ErrorGuidedSelector.paper(k=90, score=InputScore())
    callback = make_callback(selector=selector, fraction=0.15, pool=None)
    make_trainer(tmp_path, 1, [callback]).fit(model, datamodule=dm)

    samples = dm.generated_samples
    assert len(samples) == 3  # 15 % of 21 training objects
    records = {r.object_id: r for r in dm.split_records("train")}
    centres = candidate_viewpoints(90).to(torch.float64)

    class _Trainer:
        datamodule = dm

    initial.eval()
    for sample in samples:
        record = records[sample["object_id"]]
        target = dm.eval_item(record, "aligned", seed=0)["voxels"][None]
        context = callback._context(_Trainer, initial, [callback._request(dm, record)])
        scores = selector.score_views(target, target, context)[0]
        assert float(scores.max() - scores.min()) > 1e-4  # the views are told apart
        best = set(torch.argsort(scores, descending=True)[:3].tolist())
        views = torch.as_tensor(np.asarray(sample["viewpoints"]), dtype=torch.float64)
        nearest = angular_distance(views[:, None], centres[None]).argmin(1)
        assert set(nearest.tolist()) == best, (sample["object_id"], scores.tolist(), views.tolist())


class _LogitModel:
    """Returns logits (values up to 3) instead of probabilities."""

    def predict_voxels(self, images: torch.Tensor) -> torch.Tensor:
        return torch.linspace(-3.0, 3.0, R**3).reshape(1, R, R, R).expand(len(images), -1, -1, -1)


def test_the_input_score_refuses_a_model_that_returns_logits():
    requests = [
        SynthesisRequest(f"obj{b}", "chair", np.zeros((0, 2, 2, 4), np.uint8), torch.zeros(0, 2), torch.zeros(0, 2))
        for b in range(2)
    ]
    loss = lambda pred, target: (pred - target).abs().mean(dim=(1, 2, 3))  # noqa: E731
    context = SelectionContext(
        _LogitModel(), ViewpointSynthesizer(), requests, viewpoint_transform, loss, torch.device("cpu")
    )
    selector = ErrorGuidedSelector.paper(k=30, score=InputScore())
    volumes = torch.zeros(2, R, R, R)
    message = re.escape("`predict_voxels` must return probabilities in [0, 1], got values in [-3, 3] (0 non-finite of ")
    with pytest.raises(ValueError, match=message + r"\d+" + re.escape("); at the selector's candidate views")):
        selector.score_views(volumes, volumes, context)


def _fit(root, tmp_path, epochs, ckpt=None):
    L.seed_everything(0, verbose=False)
    dm = make_datamodule(root, tmp_path)
    checkpoint = L.pytorch.callbacks.ModelCheckpoint(dirpath=tmp_path / "ckpt", save_last=True)
    # renders every candidate view and queries the model: 8 bins at K = 90 keep it quick
    callback = make_callback(fraction=0.15, selector=ErrorGuidedSelector(k=90, score=InputScore()))
    make_trainer(tmp_path, epochs, [callback, checkpoint]).fit(TinyUserModel(), datamodule=dm, ckpt_path=ckpt)
    return dm


@pytest.mark.slow
def test_a_resumed_run_generates_exactly_what_an_uninterrupted_run_does(tiny_dataset, tmp_path):
    full = _fit(tiny_dataset, tmp_path / "full", 3)
    _fit(tiny_dataset, tmp_path / "part", 1)
    resumed = _fit(tiny_dataset, tmp_path / "part", 3, ckpt=str(tmp_path / "part" / "ckpt" / "last.ckpt"))
    assert generated_contents(resumed) == generated_contents(full)
    assert [s["epoch"] for s in full.generated_samples] == [-1] * 3 + [0] * 3 + [1] * 3
