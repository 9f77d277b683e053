"""Tests for LRGT's progressive upsampling decoder: token layout, stages, query block, parameter counts."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

from lightning_vtr.models.lrgt_decoder import (
    DecoderStage,
    ProgressiveUpsamplingDecoder,
    decoder_stage_layout,
    patch_tokens,
    unpatch_tokens,
)


def test_stage_layout_of_the_paper_and_tiny_decoders():
    # The paper: 8^3 voxels as tokens of 96; 16^3 in 2^3 patches of 12 x 8 = 96; 32^3 in 4^3 patches of 3 x 64 = 192.
    assert decoder_stage_layout(4, (96, 12, 3)) == [(8, 1, 96), (16, 2, 96), (32, 4, 192)]
    assert decoder_stage_layout(4, (16, 4, 1)) == [(8, 1, 16), (16, 2, 32), (32, 4, 64)]
    assert decoder_stage_layout(2, (8, 8)) == [(4, 1, 8), (8, 2, 64)]


def test_patch_tokens_order_voxels_as_the_released_layout():
    b, c, g, p = 2, 3, 4, 2
    x = torch.randn(b, c, g, g, g)
    tokens = patch_tokens(x, p)
    assert tokens.shape == (b, (g // p) ** 3, c * p**3)
    t = g // p
    for i in range(t):
        for j in range(t):
            for k in range(t):
                for ch in range(c):
                    for di in range(p):
                        for dj in range(p):
                            for dk in range(p):
                                feature = ((ch * p + di) * p + dj) * p + dk
                                voxel = x[:, ch, i * p + di, j * p + dj, k * p + dk]
                                assert torch.equal(tokens[:, (i * t + j) * t + k, feature], voxel)
    assert torch.equal(unpatch_tokens(tokens, p, c), x)
    # Patch side 1: tokens are the voxels, features the channels.
    assert torch.equal(patch_tokens(x, 1), x.flatten(2).transpose(1, 2))


def _identity_blocks(stage: DecoderStage) -> None:
    """Zero every block's attention and MLP output so each (residual) block is the identity."""
    with torch.no_grad():
        for block in stage.blocks:
            for linear in (block.attn.proj, block.mlp.fc2):
                linear.weight.zero_()
                linear.bias.zero_()


def test_stage_adds_its_blocks_as_a_residual_only_on_patches():
    torch.manual_seed(0)
    x = torch.randn(2, 6, 4, 4, 4)
    for patch, factor in ((1, 1.0), (2, 2.0)):
        stage = DecoderStage(6, 3, patch=patch, num_heads=1, depth=2).eval()
        _identity_blocks(stage)
        with torch.no_grad():
            up = stage.upsample(x)
            # p = 1: the blocks' output replaces the volume; p > 1: it is added to it (x + blocks(x) = 2x here).
            assert torch.allclose(stage(x), factor * up, atol=1e-6)
    stage = DecoderStage(6, 3, patch=2, num_heads=1, depth=0).eval()
    with torch.no_grad():
        assert torch.equal(stage(x), stage.upsample(x))
    conv = stage.upsample[0]
    assert (conv.kernel_size, conv.stride, conv.padding, conv.bias) == ((4, 4, 4), (2, 2, 2), (1, 1, 1), None)


def _attend(q, k, v, heads):
    hd = q.shape[-1] // heads
    out = []
    for h in range(heads):
        sl = slice(h * hd, (h + 1) * hd)
        out.append(torch.softmax(q[..., sl] @ k[..., sl].transpose(-1, -2) / math.sqrt(hd), dim=-1) @ v[..., sl])
    return torch.cat(out, dim=-1)


def test_query_block_cross_attends_to_the_unnormalised_tokens():
    torch.manual_seed(0)
    dim, heads = 8, 2
    block = ProgressiveUpsamplingDecoder(dim, heads, 1, 0, 2, (4,)).query_blocks[0]
    with torch.no_grad():
        for p in block.parameters():
            p.copy_(torch.randn_like(p) * 0.5)
    x, memory = torch.randn(2, 5, dim), 3.0 * torch.randn(2, 7, dim) + 1.0

    def ln(t, norm):
        return F.layer_norm(t, (dim,), norm.weight, norm.bias)

    with torch.no_grad():
        h = ln(x, block.norm1)
        q, k, v = (h @ block.self_attn.qkv.weight.T).split(dim, dim=-1)
        y = x + block.self_attn.proj(_attend(q, k, v, heads))
        q = ln(y, block.norm2) @ block.cross_attn.q.weight.T
        k, v = (memory @ block.cross_attn.kv.weight.T).split(dim, dim=-1)  # memory as it is
        y = y + block.cross_attn.proj(_attend(q, k, v, heads))
        want = y + block.mlp(ln(y, block.norm3))
        assert torch.allclose(block(x, memory), want, atol=1e-5)


def test_decoder_shapes_query_layout_and_errors():
    torch.manual_seed(0)
    decoder = ProgressiveUpsamplingDecoder(16, 2, query_depth=1, stage_depth=1, query_grid=2, upsample_channels=(8, 2))
    decoder.eval()
    tokens = torch.randn(3, 5, 16)
    with torch.no_grad():
        out = decoder(tokens)
        assert out.shape == (3, 8, 8, 8) and decoder.resolution == 8
        assert ((out > 0) & (out < 1)).all()
        # Any number of merged tokens works (the merger keeps fewer when there are fewer tokens than clusters).
        assert decoder(tokens[:, :2]).shape == (3, 8, 8, 8)
    with pytest.raises(ValueError, match=r"`num_heads` must divide the decoder widths \[16, 8, 16\].*got 3"):
        ProgressiveUpsamplingDecoder(16, 3, 1, 1, 2, (8, 2))
    with pytest.raises(ValueError, match=r"`query_depth` must be an int >= 1, got 0"):
        ProgressiveUpsamplingDecoder(16, 2, 0, 1, 2, (8, 2))


def test_decoder_is_initialised_like_the_released_code():
    torch.manual_seed(0)
    decoder = ProgressiveUpsamplingDecoder(64, 4, 1, 2, 4, (16, 4, 1))
    assert 0.95 < decoder.queries.std().item() < 1.05  # nn.Embedding's N(0, 1)
    linears = [m for m in decoder.modules() if isinstance(m, torch.nn.Linear)]
    assert 0.009 < torch.cat([m.weight.flatten() for m in linears]).std().item() < 0.011
    assert all(not m.bias.any() for m in linears if m.bias is not None)
    conv = decoder.stages[0].upsample[0].weight  # Kaiming normal, fan-in = 16 x 4^3 for ConvTranspose3d
    assert conv.std().item() == pytest.approx(math.sqrt(2 / (16 * 64)), rel=0.05)
    assert decoder.head.bias is None and decoder.head.kernel_size == (1, 1, 1)


def test_paper_decoder_parameter_count_part_by_part():
    with torch.device("meta"):
        decoder = ProgressiveUpsamplingDecoder(768, 12, 1, 2, 4, (96, 12, 3))

    def count(module):
        return sum(p.numel() for p in module.parameters())

    # The released Decoder (LiyingCV/Long-Range-Grouping-Transformer, config.py defaults) instantiated
    # outside this repository: 29,798,625 in all; queries + query block ("prepare") 9,496,320, LayerNorm
    # 1,536, blocks1-4 14,171,136 / 223,104 / 223,104 / 888,576, upconv1-4 4,718,784 / 73,752 / 2,310 / 3.
    assert count(decoder) == 29_798_625
    assert decoder.queries.numel() + count(decoder.query_blocks) == 9_496_320
    assert count(decoder.query_norm) == 1_536
    assert count(decoder.coarse_blocks) == 14_171_136
    assert [count(s.blocks) for s in decoder.stages] == [223_104, 223_104, 888_576]
    assert [count(s.upsample) for s in decoder.stages] == [4_718_784, 73_752, 2_310]
    assert count(decoder.head) == 3
