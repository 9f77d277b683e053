"""Tests for the plain-torch DeiT encoder and its timm checkpoint loader."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

from lightning_vtr.models.vit import Attention, Block, CrossAttention, DistilledVisionTransformer, load_timm_deit

DIM, DEPTH, HEADS, PATCH, IMAGE = 8, 2, 2, 4, 16


def _timm_deit_keys(dim: int, depth: int, patch: int, grid: int, num_classes: int = 5) -> dict[str, tuple[int, ...]]:
    """timm's deit_*_distilled key list, written out from timm's naming, not from our module."""
    keys: dict[str, tuple[int, ...]] = {
        "cls_token": (1, 1, dim),
        "dist_token": (1, 1, dim),
        "pos_embed": (1, grid * grid + 2, dim),
        "patch_embed.proj.weight": (dim, 3, patch, patch),
        "patch_embed.proj.bias": (dim,),
        "norm.weight": (dim,),
        "norm.bias": (dim,),
        "head.weight": (num_classes, dim),
        "head.bias": (num_classes,),
        "head_dist.weight": (num_classes, dim),
        "head_dist.bias": (num_classes,),
    }
    for i in range(depth):
        p = f"blocks.{i}."
        keys |= {
            p + "norm1.weight": (dim,),
            p + "norm1.bias": (dim,),
            p + "attn.qkv.weight": (3 * dim, dim),
            p + "attn.qkv.bias": (3 * dim,),
            p + "attn.proj.weight": (dim, dim),
            p + "attn.proj.bias": (dim,),
            p + "norm2.weight": (dim,),
            p + "norm2.bias": (dim,),
            p + "mlp.fc1.weight": (4 * dim, dim),
            p + "mlp.fc1.bias": (4 * dim,),
            p + "mlp.fc2.weight": (dim, 4 * dim),
            p + "mlp.fc2.bias": (dim,),
        }
    return keys


def _timm_state(grid: int = IMAGE // PATCH) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(0)
    return {k: torch.randn(s, generator=g) for k, s in _timm_deit_keys(DIM, DEPTH, PATCH, grid).items()}


def _small_vit(image: int = IMAGE) -> DistilledVisionTransformer:
    return DistilledVisionTransformer(image_size=image, patch_size=PATCH, embed_dim=DIM, depth=DEPTH, num_heads=HEADS)


def test_timm_state_dict_lands_in_the_right_parameters(tmp_path):
    state = _timm_state()
    # The official DeiT release wraps the weights in {"model": ...}.
    path = tmp_path / "deit.pth"
    torch.save({"model": state}, path)
    vit = _small_vit()
    load_timm_deit(vit, path)
    assert torch.equal(vit.blocks[1].attn.qkv.weight, state["blocks.1.attn.qkv.weight"])
    assert torch.equal(vit.blocks[0].mlp.fc2.bias, state["blocks.0.mlp.fc2.bias"])
    assert torch.equal(vit.patch_embed.proj.weight, state["patch_embed.proj.weight"])
    assert torch.equal(vit.dist_token, state["dist_token"])
    own = vit.state_dict()
    for key, value in state.items():
        if key.startswith("head"):
            assert key not in own
        else:
            assert torch.equal(own[key], value), key


def test_pos_embed_is_resized_for_another_image_size():
    state = _timm_state(grid=4)
    # A constant patch grid stays constant under bicubic resizing; the prefix is copied as is.
    state["pos_embed"][:, 2:] = 0.25
    vit = _small_vit(image=32)  # 8x8 grid
    load_timm_deit(vit, state)
    assert vit.pos_embed.shape == (1, 2 + 64, DIM)
    assert torch.allclose(vit.pos_embed[:, 2:], torch.full((1, 64, DIM), 0.25), atol=1e-6)
    assert torch.equal(vit.pos_embed[:, :2], state["pos_embed"][:, :2])


def test_missing_unexpected_and_mismatched_keys_raise():
    vit = _small_vit()
    state = _timm_state()
    del state["blocks.0.attn.proj.bias"]
    with pytest.raises(KeyError, match="blocks.0.attn.proj.bias"):
        load_timm_deit(vit, state)
    state = _timm_state() | {"blocks.9.norm1.weight": torch.zeros(DIM)}
    with pytest.raises(KeyError, match="blocks.9.norm1.weight"):
        load_timm_deit(vit, state)
    state = _timm_state()
    state["blocks.0.mlp.fc1.weight"] = torch.zeros(3 * DIM, DIM)
    with pytest.raises(ValueError, match=r"blocks.0.mlp.fc1.weight: expected \(32, 8\), got \(24, 8\)"):
        load_timm_deit(vit, state)
    with pytest.raises(FileNotFoundError, match="nope.pth"):
        load_timm_deit(vit, "nope.pth")


def test_attention_matches_softmax_formula():
    torch.manual_seed(0)
    attn = Attention(DIM, HEADS)
    x = torch.randn(3, 5, DIM)
    q, k, v = attn.qkv(x).split(DIM, dim=-1)
    hd = DIM // HEADS
    heads = []
    for h in range(HEADS):
        sl = slice(h * hd, (h + 1) * hd)
        w = torch.softmax(q[..., sl] @ k[..., sl].transpose(1, 2) / math.sqrt(hd), dim=-1)
        heads.append(w @ v[..., sl])
    expected = attn.proj(torch.cat(heads, dim=-1))
    assert torch.allclose(attn(x), expected, atol=1e-5)


def test_forward_shape_and_token_order():
    vit = _small_vit().eval()
    images = torch.randn(2, 3, IMAGE, IMAGE)
    tokens = vit(images)
    assert tokens.shape == (2, 2 + 16, DIM)
    # Row-major patches: the first patch token is computed from the top-left 4x4 patch only.
    emb = vit.embed(images)
    top_left = torch.einsum("dcij,cij->d", vit.patch_embed.proj.weight, images[0, :, :PATCH, :PATCH])
    expected = top_left + vit.patch_embed.proj.bias + vit.pos_embed[0, 2]
    assert torch.allclose(emb[0, 2], expected, atol=1e-5)
    with pytest.raises(ValueError, match="must be 16x16"):
        vit(torch.randn(1, 3, 8, 8))


def test_deit_base_parameter_count():
    with torch.device("meta"):
        vit = DistilledVisionTransformer()
    # DeiT-B distilled is 87.34 M with its two 1000-way heads (2 x 769,000 parameters).
    assert sum(p.numel() for p in vit.parameters()) == 87_338_192 - 2 * 769_000


def test_cross_attention_adds_the_logit_bias_hand_computed():
    # One head, identity projections, memory = the 4 unit vectors: the output row is the attention weights.
    attn = CrossAttention(4, num_heads=1, qkv_bias=False)
    eye = torch.eye(4)
    with torch.no_grad():
        attn.q.weight.copy_(eye)
        attn.kv.weight.copy_(torch.cat([eye, eye]))
        attn.proj.weight.copy_(eye)
        attn.proj.bias.zero_()
    query = torch.tensor([[[2.0, 0.0, 0.0, 0.0]]])  # logits q.k / sqrt(4) = (1, 0, 0, 0)
    memory = eye[None]
    e = math.e
    assert torch.allclose(attn(query, memory), torch.tensor([[[e, 1, 1, 1]]]) / (e + 3), atol=1e-6)
    # Bias ln 3 on token 2: weights (e, 1, 3, 1) / (e + 5), i.e. softmax(logits + bias).
    bias = torch.tensor([0.0, 0.0, math.log(3.0), 0.0])
    assert torch.allclose(attn(query, memory, bias), torch.tensor([[[e, 1, 3, 1]]]) / (e + 5), atol=1e-6)
    with pytest.raises(ValueError, match=r"`dim` must be divisible by `num_heads` 3, got 4"):
        CrossAttention(4, num_heads=3)


@pytest.mark.parametrize(("dim", "heads"), [(64, 4), (768, 12)])
def test_cross_attention_with_a_learned_bias_equals_torch_attention_with_that_mask(dim, heads):
    # The merger's token scores enter as a bias that needs a gradient; the layer writes that case out. Outputs and
    # gradients (inputs, memory, bias) must equal scaled_dot_product_attention given the bias as its mask.
    torch.manual_seed(0)
    attn = CrossAttention(dim, heads, qkv_bias=False)
    x, memory = torch.randn(2, 5, dim, requires_grad=True), torch.randn(2, 9, dim, requires_grad=True)
    scores = torch.randn(2, 9, requires_grad=True)
    out = attn(x, memory, scores[:, None, None, :])
    hd = dim // heads
    q = attn.q(x).reshape(2, 5, heads, hd).transpose(1, 2)
    k, v = attn.kv(memory).reshape(2, 9, 2, heads, hd).permute(2, 0, 3, 1, 4).unbind(0)
    mask = scores[:, None, None, :].expand(2, heads, 5, 9)
    ref = attn.proj(F.scaled_dot_product_attention(q, k, v, attn_mask=mask).transpose(1, 2).reshape(2, 5, dim))
    torch.testing.assert_close(out, ref, atol=1e-5, rtol=1e-5)
    grads = torch.autograd.grad(out.square().sum(), (x, memory, scores))
    expected = torch.autograd.grad(ref.square().sum(), (x, memory, scores))
    assert expected[2].abs().max() > 1e-3  # the bias does receive a gradient
    for got, want in zip(grads, expected, strict=True):
        torch.testing.assert_close(got, want, atol=1e-5, rtol=1e-5)


def test_cross_attention_matches_softmax_formula_with_heads_and_bias():
    torch.manual_seed(0)
    attn = CrossAttention(DIM, HEADS)
    x, memory, bias = torch.randn(3, 5, DIM), torch.randn(3, 7, DIM), torch.randn(3, 1, 1, 7)
    q = attn.q(x)
    k, v = attn.kv(memory).split(DIM, dim=-1)
    hd = DIM // HEADS
    heads = []
    for h in range(HEADS):
        sl = slice(h * hd, (h + 1) * hd)
        w = torch.softmax(q[..., sl] @ k[..., sl].transpose(1, 2) / math.sqrt(hd) + bias[:, 0], dim=-1)
        heads.append(w @ v[..., sl])
    assert torch.allclose(attn(x, memory, bias), attn.proj(torch.cat(heads, dim=-1)), atol=1e-5)


def test_block_layer_norm_eps_and_bias_free_qkv():
    block = Block(DIM, HEADS, qkv_bias=False, norm_eps=1e-5)
    assert block.norm1.eps == block.norm2.eps == 1e-5 and block.attn.qkv.bias is None
    assert Block(DIM, HEADS).norm1.eps == 1e-6  # DeiT's


def test_without_prefix_tokens_blocks_see_only_patches_and_timm_weights_still_load():
    vit = DistilledVisionTransformer(IMAGE, PATCH, DIM, DEPTH, HEADS, use_prefix_tokens=False).eval()
    state = _timm_state()
    load_timm_deit(vit, state)
    assert torch.equal(vit.cls_token, state["cls_token"]) and torch.equal(vit.pos_embed, state["pos_embed"])
    assert not vit.cls_token.requires_grad and not vit.dist_token.requires_grad and vit.pos_embed.requires_grad
    assert vit.num_output_prefix_tokens == 0
    images = torch.randn(2, 3, IMAGE, IMAGE)
    with torch.no_grad():
        assert torch.allclose(vit.embed(images), vit.patch_embed(images) + state["pos_embed"][:, 2:], atol=1e-6)
        tokens = vit(images)
    assert tokens.shape == (2, 16, DIM)
    # The same weights with the prefix tokens: different patch features (the prefix tokens take part).
    with_prefix = _small_vit().eval()
    load_timm_deit(with_prefix, state)
    with torch.no_grad():
        assert with_prefix(images).shape == (2, 2 + 16, DIM)
        assert not torch.allclose(with_prefix(images)[:, 2:], tokens, atol=1e-3)
    with pytest.raises(TypeError, match=r"`use_prefix_tokens` must be a bool, got int 0"):
        DistilledVisionTransformer(IMAGE, PATCH, DIM, DEPTH, HEADS, use_prefix_tokens=0)
