"""Mixed precision under CUDA autocast's casting rules, on the CPU (:mod:`cuda_autocast`).

CPU autocast leaves ``exp``, ``softmax``, ``layer_norm``, ``sum``, ... in half precision where CUDA autocast runs
them in float32, so the CPU ``bf16-mixed`` tests cannot see a dtype mismatch that only a GPU run would hit. These
tests run the models, the callback's prediction and selection under CUDA's rules (the Zero-1-to-3 pipeline's:
``tests/synthesis/test_zero123_cuda_autocast.py``).
"""

from __future__ import annotations

import contextlib

import lightning as L
import pytest
import torch
import torch.nn.functional as F
from cuda_autocast import CudaAutocastRules, cuda_autocast_rules
from helpers import make_trainer, one_thread
from lightning.pytorch.plugins.precision import MixedPrecision

from lightning_vtr.callback import ErrorGuidedViewAugmentation
from lightning_vtr.data.datamodule import VTRDataModule
from lightning_vtr.models import LRGT, Pix2VoxPlusPlus
from lightning_vtr.models.lrgt_merger import SimilarTokenMerger, cluster_dpc_knn, merge_tokens
from lightning_vtr.selection import ErrorGuidedSelector
from lightning_vtr.synthesis.render import RenderSynthesizer

_one_thread = pytest.fixture(autouse=True)(one_thread)

HALF = [torch.bfloat16, torch.float16]
HALF_IDS = ["bf16", "fp16"]
#: relative precision of each half type (unit roundoff), the scale of the tolerances below
EPS = {torch.bfloat16: 2.0**-8, torch.float16: 2.0**-11}


# ---------------------------------------------------------------- the helper reproduces CUDA's rules


@pytest.mark.parametrize("dtype", HALF, ids=HALF_IDS)
def test_rules_float32_list_lower_precision_list_and_promotion(dtype):
    torch.manual_seed(0)
    x = torch.randn(4, 8)
    w, b = torch.randn(3, 8), torch.randn(3)
    half = x.to(dtype)
    with cuda_autocast_rules(dtype) as mode:
        exp, log_softmax = torch.exp(half), F.log_softmax(half, dim=-1)
        norm = F.layer_norm(half, (8,))
        total, total64 = half.sum(), x.double().sum()
        explicit = F.softmax(half, dim=-1, dtype=dtype)  # an explicit dtype is kept
        linear, matmul = F.linear(x, w, b), x @ w.T
        promoted = torch.addcmul(half, x, half)  # one float32 input: float32
        added = half + x  # unlisted: PyTorch's own promotion
        rpow = 2.0**half
        with torch.autocast("cpu", enabled=False):  # an autocast-off region turns the rules off
            off_exp, off_linear = torch.exp(half), F.linear(x, w, b)
    # float32 list: float32 results (CPU autocast would give `dtype`)
    assert exp.dtype == log_softmax.dtype == norm.dtype == total.dtype == rpow.dtype == torch.float32
    assert torch.equal(exp, torch.exp(half.float()))
    assert torch.equal(norm, F.layer_norm(half.float(), (8,)))
    assert total64.dtype == torch.float64  # float64 is never cast
    assert explicit.dtype == dtype
    # lower-precision list: inputs cast to `dtype`, computed in it
    assert linear.dtype == matmul.dtype == dtype
    assert torch.equal(linear, F.linear(x.to(dtype), w.to(dtype), b.to(dtype)))
    assert torch.equal(matmul, x.to(dtype) @ w.T.to(dtype))
    assert promoted.dtype == added.dtype == torch.float32
    assert off_exp.dtype == dtype and off_linear.dtype == torch.float32
    assert mode.cast_ops == ["exp", "log_softmax", "layer_norm", "sum", "linear", "matmul", "addcmul", "__rpow__"]


def test_rules_replace_cpu_autocast_lists_and_keep_in_place_ops_strict():
    x = torch.rand(1, 2, 4, 4, 4, dtype=torch.bfloat16)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        cpu_pool = F.avg_pool3d(x, 2)  # on CPU autocast's float32 list, on no CUDA list
        cpu_exp = torch.exp(x)  # on CUDA's float32 list, on no CPU list
    with cuda_autocast_rules(torch.bfloat16):
        pool, exp = F.avg_pool3d(x, 2), torch.exp(x)
        # in-place ops are never autocast: the dtype check of index_add_ applies, as on a GPU
        with pytest.raises(RuntimeError, match=r"index_add_\(\): self \(BFloat16\) and source \(Float\)"):
            x.new_zeros(4).index_add_(0, torch.arange(4), torch.exp(x.flatten()[:4]))
        # CUDA autocast refuses binary_cross_entropy
        with pytest.raises(RuntimeError, match="unsafe to autocast"):
            F.binary_cross_entropy(x.float().clamp(0.1, 0.9), torch.ones_like(x.float()))
    assert (cpu_pool.dtype, cpu_exp.dtype) == (torch.float32, torch.bfloat16)
    assert (pool.dtype, exp.dtype) == (torch.bfloat16, torch.float32)
    # the CPU has no bfloat16 avg_pool3d: computed in float32, returned in bfloat16 as CUDA's kernel would
    assert torch.equal(pool, F.avg_pool3d(x.float(), 2).bfloat16())


def test_rules_refuse_other_dtypes():
    with pytest.raises(ValueError, match=r"`dtype` must be torch.bfloat16 or torch.float16, got torch.float32"):
        CudaAutocastRules(torch.float32)


# ---------------------------------------------------------------- LRGT's token merger


@pytest.mark.parametrize("dtype", HALF, ids=HALF_IDS)
def test_merge_tokens_under_cuda_rules_matches_float32(dtype):
    torch.manual_seed(0)
    b, n, m, dim = 2, 40, 8, 16
    x = torch.randn(b, n, dim)
    _, assignment = cluster_dpc_knn(x, m, k=5)
    scores = 3.0 * torch.randn(b, n)
    expected = merge_tokens(x, assignment, scores, m)
    # what the merger block gives it under CUDA autocast: float32 normalised tokens, half-precision Linear scores
    with cuda_autocast_rules(dtype):
        merged = merge_tokens(x, assignment, scores.to(dtype), m)
    assert merged.dtype == torch.float32
    # the scores were rounded to `dtype`: exp(s) moves by |s| eps relatively, the weighted mean by as much
    tol = 4 * EPS[dtype] * float(scores.abs().max()) * float(x.abs().max())
    torch.testing.assert_close(merged, expected, rtol=0, atol=tol)
    # the half-precision path agrees with the float32 merge of the same rounded scores to float32 precision
    torch.testing.assert_close(merged, merge_tokens(x, assignment, scores.to(dtype).float(), m))


@pytest.mark.parametrize("dtype", HALF, ids=HALF_IDS)
def test_merge_tokens_with_half_tokens_and_float32_scores(dtype):
    torch.manual_seed(1)
    x, scores = torch.randn(1, 12, 8), torch.randn(1, 12)
    _, assignment = cluster_dpc_knn(x, 4, k=3)
    merged = merge_tokens(x.to(dtype), assignment, scores, 4)
    assert merged.dtype == dtype  # the tokens' dtype
    torch.testing.assert_close(merged.float(), merge_tokens(x, assignment, scores, 4), rtol=4 * EPS[dtype], atol=0)


@pytest.mark.parametrize("dtype", HALF, ids=HALF_IDS)
def test_similar_token_merger_forward_backward_under_cuda_rules(dtype):
    torch.manual_seed(0)
    merger = SimilarTokenMerger(dim=32, num_heads=4, num_tokens=8, k=5)
    tokens = torch.randn(2, 30, 32, requires_grad=True)
    expected = merger(tokens)
    with cuda_autocast_rules(dtype):
        out = merger(tokens)
    out.float().square().mean().backward()
    assert out.shape == expected.shape == (2, 8, 32)
    assert torch.isfinite(out).all() and torch.isfinite(tokens.grad).all()
    assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in merger.parameters())
    # an attention and an MLP on top of the merge, with half-precision matmuls: a few half-precision roundings
    torch.testing.assert_close(
        out.float(), expected, rtol=0, atol=64 * EPS[dtype] * float(expected.detach().abs().max())
    )


# ---------------------------------------------------------------- the models at their paper presets


def _forward_backward(model, images, target, dtype):
    """Training-step forward (under CUDA's rules) and backward (outside them), as Lightning runs them."""
    model.train()
    with cuda_autocast_rules(dtype):
        outputs = model(images)
        loss = model.loss(outputs, target)
    loss.backward()
    return outputs, loss


#: bfloat16 with two views; float16 (whose matrix products are slow on a CPU: ~15 s a model) with one, marked slow
PAPER_CASES = [
    pytest.param(torch.bfloat16, 2, id="bf16"),
    pytest.param(torch.float16, 1, id="fp16", marks=pytest.mark.slow),
]


@pytest.mark.parametrize(("dtype", "views"), PAPER_CASES)
def test_lrgt_paper_preset_trains_under_cuda_rules(dtype, views):
    torch.manual_seed(0)
    # the paper architecture (DeiT-B encoder, 2 merger blocks, decoder) on 112 px views: 7 x 7 tokens per view
    # (49 or 98 in all), merged to 32 so the clustering really merges
    model = LRGT(preset="paper", image_size=112, num_merged_tokens=32, validation_fscore=False)
    images = torch.rand(1, views, 3, 112, 112)
    target = (torch.rand(1, 32, 32, 32) > 0.7).float()
    outputs, loss = _forward_backward(model, images, target, dtype)
    voxels = outputs["voxels"]
    # the head's weighted channel sum is on CUDA's float32 list (`sum`): float32 probabilities, as on a GPU
    assert voxels.shape == (1, 32, 32, 32) and voxels.dtype == torch.float32
    voxels = voxels.detach()
    assert torch.isfinite(voxels).all() and float(voxels.min()) >= 0.0 and float(voxels.max()) <= 1.0
    assert loss.dtype == torch.float32 and torch.isfinite(loss)
    grads = [p.grad for p in model.parameters() if p.requires_grad]
    assert all(g is not None and g.dtype == torch.float32 and torch.isfinite(g).all() for g in grads)
    assert sum(float(g.abs().sum()) > 0 for g in grads) > 0.9 * len(grads)


@pytest.mark.parametrize(("dtype", "views"), PAPER_CASES)
def test_pix2vox_paper_preset_trains_under_cuda_rules(dtype, views):
    torch.manual_seed(0)
    model = Pix2VoxPlusPlus(preset="paper", validation_fscore=False)
    images = torch.rand(1, views, 3, 224, 224)
    target = (torch.rand(1, 32, 32, 32) > 0.7).float()
    outputs, loss = _forward_backward(model, images, target, dtype)
    for name in ("voxels", "coarse"):
        if name in outputs:
            assert outputs[name].shape == (1, 32, 32, 32) and torch.isfinite(outputs[name]).all(), name
    assert loss.dtype == torch.float32 and torch.isfinite(loss)
    grads = [p.grad for p in model.parameters() if p.requires_grad]
    assert all(g is not None and torch.isfinite(g).all() for g in grads)


# ---------------------------------------------------------------- the callback's prediction and selection


class CudaRulesPrecision(MixedPrecision):
    """Lightning's CPU mixed precision with CUDA autocast's casting rules in its forward context."""

    def __init__(self, precision: str) -> None:
        super().__init__(precision, device="cpu")
        self.cast_ops: set[str] = set()  # the listed ops cast in any forward context

    @contextlib.contextmanager
    def autocast_context_manager(self):
        with cuda_autocast_rules(torch.bfloat16 if self.precision == "bf16-mixed" else torch.float16) as mode:
            yield
        self.cast_ops.update(mode.cast_ops)


class RecordingSelector(ErrorGuidedSelector):
    """The paper's selector (K = 90) recording the predictions it gets."""

    def __init__(self) -> None:
        super().__init__(k=90)
        self.predictions: list[torch.Tensor] = []

    def select(self, predicted, target, categories, generator=None, context=None):
        self.predictions.append(predicted)
        return super().select(predicted, target, categories, generator=generator, context=context)


@pytest.mark.parametrize(
    ("model_cls", "precision"),
    [(LRGT, "bf16-mixed"), (Pix2VoxPlusPlus, "bf16-mixed"), (LRGT, "16-mixed")],
    ids=["lrgt-bf16", "pix2vox-bf16", "lrgt-fp16"],
)
def test_fit_with_the_callback_under_cuda_rules(tiny_dataset, tmp_path, model_cls, precision):
    L.seed_everything(0, verbose=False)
    model = model_cls(preset="tiny", validation_fscore=False)
    precision_plugin = CudaRulesPrecision(precision)
    selector = RecordingSelector()
    callback = ErrorGuidedViewAugmentation(
        selector, RenderSynthesizer(image_size=32), fraction=0.1, progress_bar=False, log_images=False
    )
    dm = VTRDataModule(
        str(tiny_dataset), image_size=model.image_size, batch_size=2, generated_dir=str(tmp_path / "gen")
    )
    trainer = make_trainer(
        tmp_path,
        1,
        [callback],
        plugins=[precision_plugin],
        enable_checkpointing=False,
        limit_train_batches=1,
        num_sanity_val_steps=0,
    )
    trainer.fit(model, datamodule=dm)
    # the forwards (training, validation, the callback's predictions) ran under CUDA's rules
    assert {"linear" if model_cls is LRGT else "conv2d", "conv_transpose3d", "sum"} <= precision_plugin.cast_ops
    if model_cls is LRGT:
        assert {"layer_norm", "exp", "scaled_dot_product_attention"} <= precision_plugin.cast_ops
    # objects searched and 2 (10 % of 21) selected before epoch 0, on float32 probabilities, 3 viewpoints each
    assert len(selector.predictions) >= 2
    assert all(p.dtype == torch.float32 and float(p.min()) >= 0 and float(p.max()) <= 1 for p in selector.predictions)
    assert [s["epoch"] for s in dm.generated_samples] == [-1, -1]
    assert all(len(s["viewpoints"]) == selector.num_views for s in dm.generated_samples)
    for key in ("train/loss", "val/loss"):
        assert trainer.callback_metrics[key].dtype == torch.float32 and torch.isfinite(trainer.callback_metrics[key])


@pytest.mark.parametrize("score", ["paper", "visible"])
def test_selection_of_bf16_predictions_under_cuda_rules(score):
    torch.manual_seed(0)
    target = torch.zeros(2, 16, 16, 16)
    target[:, 4:12, 4:12, 4:12] = 1.0
    predicted = (target * 0.8 + 0.2 * torch.rand(2, 16, 16, 16)).bfloat16()  # wrong above 0.4 outside the cube
    predicted[:, 4:12, 4:8, 4:12] = 0.1  # and a missed part
    selector = ErrorGuidedSelector(score=score, k=30)
    expected = selector.select(predicted.float(), target, ["a", "a"], generator=torch.Generator().manual_seed(3))
    expected_scores = selector.last_scores
    with cuda_autocast_rules(torch.bfloat16):
        views = selector.select(predicted, target, ["a", "a"], generator=torch.Generator().manual_seed(3))
    assert views.dtype == torch.float32 and torch.equal(views, expected)
    assert torch.equal(selector.last_scores.float(), expected_scores.float())
