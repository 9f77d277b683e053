"""VIATSelector against a fake synthesizer/model pair whose loss is a known function of the viewpoint."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from helpers import ViewpointSynthesizer, decode_viewpoints, one_thread, viewpoint_transform

from lightning_vtr.geometry import angular_distance, wrap_yaw
from lightning_vtr.selection.base import SelectionContext, ViewSelector
from lightning_vtr.selection.viat import VIATSelector, _nes_utilities
from lightning_vtr.synthesis.base import SynthesisRequest

# These tensors are tiny: on the shared 2-core machine intra-op threads only add contention.
_one_thread = pytest.fixture(autouse=True, name="_one_thread")(one_thread)

ADVERSARIAL = torch.tensor([90.0, -45.0])  # where the fake model fails most (degrees)
WIDTH = 40.0  # degrees
R = 4


class _AngleModel:
    """Predicts a constant volume equal to a Gaussian bump of the FIRST view's distance to ADVERSARIAL."""

    image_size, num_views, voxel_resolution = 2, 3, R

    def __init__(self) -> None:
        self.calls = 0
        self.seen: list[torch.Tensor] = []

    def predict_voxels(self, images: torch.Tensor) -> torch.Tensor:
        self.calls += 1
        views = torch.stack([decode_viewpoints(images[:, v]) for v in range(images.shape[1])], 1)  # (N, V, 2)
        self.seen.append(views)
        d = angular_distance(views[:, 0], ADVERSARIAL.to(views.dtype))
        value = torch.exp(-0.5 * (d / WIDTH) ** 2)
        return value[:, None, None, None].expand(-1, R, R, R)


def _loss(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    return pred.mean(dim=(1, 2, 3))


def _setup(categories: list[str]):
    synth, model = ViewpointSynthesizer(), _AngleModel()
    requests = [
        SynthesisRequest(
            object_id=f"obj{i}",
            category=c,
            source_images=np.zeros((1, 2, 2, 4), np.uint8),
            source_viewpoints=torch.zeros(1, 2),
            target_viewpoints=torch.zeros(0, 2),
        )
        for i, c in enumerate(categories)
    ]
    context = SelectionContext(
        model=model,
        synthesizer=synth,
        requests=requests,
        transform=viewpoint_transform,
        loss_fn=_loss,
        device=torch.device("cpu"),
    )
    volumes = torch.zeros(len(categories), R, R, R)
    return context, volumes


def _mean_distance(selector: VIATSelector, category: str, seed: int = 123) -> float:
    samples = selector.sample_viewpoints(category, 400, torch.Generator().manual_seed(seed))
    return angular_distance(samples, ADVERSARIAL.to(samples.dtype)).mean().item()


def test_viewpoint_encoding_round_trips():
    # The fake pair must decode what the fake synthesizer wrote, or the other tests prove nothing.
    vp = torch.tensor([[-180.0, -90.0], [12.5, 33.3], [179.9, 90.0]])
    req = SynthesisRequest("o", "c", np.zeros((0, 2, 2, 4), np.uint8), torch.zeros(0, 2), vp)
    img = ViewpointSynthesizer().synthesize([req])[0]
    assert torch.allclose(decode_viewpoints(viewpoint_transform(img)), vp.double(), atol=0.01)


def test_nes_utilities_rank_shaping():
    u = _nes_utilities(torch.tensor([0.3, 5.0, -1.0, 0.9]))
    # Hand computed: ranks (0-based) 2, 0, 3, 1 -> raw max(0, log 3 - log(rank + 1)) = .405, 1.099, 0, .693
    raw = torch.tensor([math.log(3) - math.log(3), math.log(3), 0.0, math.log(3) - math.log(2)])
    assert torch.allclose(u, raw / raw.sum() - 0.25, atol=1e-6)
    assert abs(u.sum().item()) < 1e-6
    # Invariant to monotone rescaling of the fitness.
    assert torch.allclose(_nes_utilities(torch.tensor([0.3, 5.0, -1.0, 0.9]) * 10 + 3), u)


def test_concentrates_on_the_adversarial_viewpoint():
    context, volumes = _setup(["chair", "chair"])
    selector = VIATSelector(num_components=2, population=16, lr=0.2, iterations=20, entropy_weight=0.01)
    assert isinstance(selector, ViewSelector) and selector.uses_pool is False and selector.needs_context is True
    views = selector.select(volumes, volumes, ["chair", "chair"], torch.Generator().manual_seed(0), context)
    initial = VIATSelector(num_components=2, iterations=0)  # the untrained starting distribution
    initial.select(volumes, volumes, ["chair", "chair"], torch.Generator().manual_seed(0), context)
    before, after = _mean_distance(initial, "chair"), _mean_distance(selector, "chair")
    assert after < 0.5 * before
    assert after < 30.0
    # The strongest component's mean sits near (90, -45).
    dist = selector.distribution("chair")
    best = dist["means"][dist["weights"].argmax()]
    assert angular_distance(best, ADVERSARIAL.double()).item() < 20.0
    # The returned first views follow the learned distribution.
    assert angular_distance(views[:, 0], ADVERSARIAL).max().item() < 60.0


def test_one_synthesizer_and_model_call_per_iteration():
    categories = ["a", "b", "a"]
    context, volumes = _setup(categories)
    selector = VIATSelector(population=4, iterations=3)
    selector.select(volumes, volumes, categories, torch.Generator().manual_seed(1), context)
    assert context.synthesizer.calls == 3
    assert context.model.calls == 3
    # Every model call scores all objects x all candidates, with view sets spaced 0/120/240 in yaw.
    seen = context.model.seen[0]
    assert seen.shape == (3 * 4, 3, 2)
    gaps = wrap_yaw(seen[:, 1:, 0] - seen[:, :1, 0])
    assert torch.allclose(gaps, torch.tensor([120.0, -120.0], dtype=gaps.dtype).expand_as(gaps), atol=0.02)
    # Objects 0 and 2 share category "a", so they were scored at the same candidates.
    per_object = seen.reshape(3, 4, 3, 2)
    assert torch.allclose(per_object[0], per_object[2])
    assert set(selector.state_dict()["categories"]) == {"a", "b"}


def test_output_shape_spacing_and_bounds():
    categories = ["a", "b", "a", "c", "b"]
    context, volumes = _setup(categories)
    selector = VIATSelector(population=4, iterations=2, lr=1.0)
    views = selector.select(volumes, volumes, categories, torch.Generator().manual_seed(2), context)
    assert views.shape == (5, 3, 2) and views.dtype == volumes.dtype
    assert (views[..., 0] >= -180).all() and (views[..., 0] < 180).all()
    assert (views[..., 1].abs() <= 90).all()
    assert torch.equal(views[:, 1, 1], views[:, 0, 1]) and torch.equal(views[:, 2, 1], views[:, 0, 1])
    expected = wrap_yaw(views[:, :1, 0] + torch.tensor([0.0, 120.0, 240.0]))
    assert torch.allclose(views[..., 0], expected, atol=1e-4)

    two = VIATSelector(population=4, iterations=1, num_views=2).select(
        volumes, volumes, categories, torch.Generator().manual_seed(2), context
    )
    assert two.shape == (5, 2, 2)
    assert torch.allclose(wrap_yaw(two[:, 1, 0] - two[:, 0, 0]).abs(), torch.full((5,), 180.0), atol=1e-4)


def test_deterministic_with_a_seeded_generator():
    categories = ["a", "b"]
    outs = []
    for _ in range(2):
        context, volumes = _setup(categories)
        selector = VIATSelector(population=4, iterations=3)
        outs.append(selector.select(volumes, volumes, categories, torch.Generator().manual_seed(7), context))
    assert torch.equal(outs[0], outs[1])
    context, volumes = _setup(categories)
    other = VIATSelector(population=4, iterations=3).select(
        volumes, volumes, categories, torch.Generator().manual_seed(8), context
    )
    assert not torch.equal(outs[0], other)
    # The callback may call selectors under inference mode: the NES steps still run, identically.
    context, volumes = _setup(categories)
    with torch.inference_mode():
        inside = VIATSelector(population=4, iterations=3).select(
            volumes, volumes, categories, torch.Generator().manual_seed(7), context
        )
    assert torch.equal(inside, outs[0])


def test_state_round_trip_and_warm_start(tmp_path):
    categories = ["a", "b"]
    context, volumes = _setup(categories)
    first = VIATSelector(population=6, iterations=4)
    first.select(volumes, volumes, categories, torch.Generator().manual_seed(3), context)
    path = tmp_path / "viat.pt"
    torch.save(first.state_dict(), path)

    second = VIATSelector(population=6, iterations=4)
    second.load_state_dict(torch.load(path, weights_only=False))
    for name in categories:
        for key, value in first.distribution(name).items():
            assert torch.equal(value, second.distribution(name)[key])
    # Continuing from the restored state (parameters and Adam moments) matches continuing the original.
    a = first.select(volumes, volumes, categories, torch.Generator().manual_seed(4), context)
    b = second.select(volumes, volumes, categories, torch.Generator().manual_seed(4), context)
    assert torch.equal(a, b)
    # A fresh selector (no warm start) ends elsewhere.
    c = VIATSelector(population=6, iterations=4).select(
        volumes, volumes, categories, torch.Generator().manual_seed(4), context
    )
    assert not torch.equal(a, c)

    fresh = VIATSelector()
    fresh.load_state_dict({})  # an older checkpoint without selector state
    assert fresh.state_dict()["categories"] == {}
    with pytest.raises(ValueError, match="num_components"):
        VIATSelector(num_components=2).load_state_dict(first.state_dict())


def test_clear_error_without_context():
    volumes = torch.zeros(2, R, R, R)
    with pytest.raises(ValueError, match="needs a SelectionContext with a model and a synthesizer"):
        VIATSelector().select(volumes, volumes, ["a", "b"])
    context, _ = _setup(["a", "b"])
    context.synthesizer = None
    with pytest.raises(ValueError, match="needs a SelectionContext"):
        VIATSelector().select(volumes, volumes, ["a", "b"], context=context)
    context, _ = _setup(["a"])
    with pytest.raises(ValueError, match="one SynthesisRequest per object"):
        VIATSelector().select(volumes, volumes, ["a", "b"], context=context)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"population": 1}, "population"),
        ({"lr": 0.0}, "lr"),
        ({"num_components": 0}, "num_components"),
        ({"entropy_weight": -1.0}, "entropy_weight"),
        ({"model_batch_size": 0}, "model_batch_size"),
    ],
)
def test_rejects_bad_arguments(kwargs, match):
    with pytest.raises(ValueError, match=match):
        VIATSelector(**kwargs)


def test_model_batch_size_chunks_without_changing_results():
    categories = ["a", "a", "b"]
    context, volumes = _setup(categories)
    whole = VIATSelector(population=4, iterations=2).select(
        volumes, volumes, categories, torch.Generator().manual_seed(5), context
    )
    context, volumes = _setup(categories)
    chunked = VIATSelector(population=4, iterations=2, model_batch_size=5).select(
        volumes, volumes, categories, torch.Generator().manual_seed(5), context
    )
    assert torch.equal(whole, chunked)
    assert context.model.calls == 2 * math.ceil(12 / 5)
