"""Tests for LRGT's Similar-Token Merger: DPC-kNN clustering, score-weighted merging, the scored transformer block."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

from lightning_vtr.models.lrgt_merger import (
    SimilarTokenMerger,
    SimilarTokenMergerBlock,
    cluster_dpc_knn,
    merge_tokens,
)


def _loop_dpc_knn(pts: torch.Tensor, m: int, k: int) -> tuple[list[int], list[int]]:
    """DPC-kNN written out token by token: the published rules, with ties in density going to the lower index."""
    n, dim = pts.shape
    d = [[float(torch.linalg.norm(pts[i] - pts[j])) / math.sqrt(dim) for j in range(n)] for i in range(n)]
    # The k nearest include the token itself (distance 0), as in the released code.
    rho = [math.exp(-sum(v * v for v in sorted(d[i])[:k]) / k) for i in range(n)]
    dmax = max(max(row) for row in d)
    delta = []
    for i in range(n):
        denser = [d[i][j] for j in range(n) if rho[j] > rho[i] or (rho[j] == rho[i] and j < i)]
        delta.append(min(denser) if denser else dmax)
    centres = sorted(range(n), key=lambda i: -rho[i] * delta[i])[:m]
    assign = [centres.index(i) if i in centres else min(range(m), key=lambda c: d[centres[c]][i]) for i in range(n)]
    return centres, assign


def test_dpc_knn_matches_a_token_by_token_reference():
    torch.manual_seed(1)
    x = torch.randn(2, 20, 3)
    centres, assign = cluster_dpc_knn(x, num_clusters=5, k=4)
    assert centres.shape == (2, 5) and assign.shape == (2, 20)
    for b in range(2):
        want_centres, want_assign = _loop_dpc_knn(x[b], 5, 4)
        assert centres[b].tolist() == want_centres  # in decreasing order of rho * delta
        assert assign[b].tolist() == want_assign


def test_dpc_knn_hand_computed_with_a_density_tie():
    # 1-D tokens 0, 1, 3 with k = 2 (the token and its nearest other): rho = e^-0.5, e^-0.5, e^-2.
    # Tokens 0 and 1 tie; the lower index counts as denser, so delta = (max distance 3, 1, 2) and
    # rho * delta = (1.82, 0.61, 0.27): centres 0 then 1; token 2 is nearer to 1 (distance 2) than to 0 (3).
    x = torch.tensor([[[0.0], [1.0], [3.0]]])
    centres, assign = cluster_dpc_knn(x, num_clusters=2, k=2)
    assert centres.tolist() == [[0, 1]]
    assert assign.tolist() == [[0, 1, 1]]
    centres, assign = cluster_dpc_knn(x, num_clusters=1, k=2)
    assert centres.tolist() == [[0]] and assign.tolist() == [[0, 0, 0]]


def test_dpc_knn_with_fewer_tokens_than_clusters_keeps_every_token():
    torch.manual_seed(0)
    x = torch.randn(2, 3, 4)
    centres, assign = cluster_dpc_knn(x, num_clusters=5, k=15)  # k is capped at N as well
    assert centres.shape == (2, 3)
    for b in range(2):
        assert sorted(centres[b].tolist()) == [0, 1, 2]
        assert [centres[b, assign[b, i]].item() for i in range(3)] == [0, 1, 2]


def test_dpc_knn_rejects_bad_arguments():
    x = torch.randn(1, 4, 2)
    with pytest.raises(ValueError, match=r"`num_clusters` must be an int >= 1, got 0"):
        cluster_dpc_knn(x, num_clusters=0, k=2)
    with pytest.raises(ValueError, match=r"`k` must be an int >= 1, got 0"):
        cluster_dpc_knn(x, num_clusters=2, k=0)
    with pytest.raises(ValueError, match=r"`x` must be \(B, N, D\) tokens with N >= 1, got \(4, 2\)"):
        cluster_dpc_knn(x[0], num_clusters=2, k=2)


def test_merge_tokens_hand_computed():
    x = torch.tensor([[[1.0, 0.0], [0.0, 1.0], [2.0, 2.0]]])
    assign = torch.tensor([[0, 0, 1]])
    scores = torch.tensor([[0.0, math.log(3.0), 5.0]])
    merged = merge_tokens(x, assign, scores, num_clusters=2)
    # exp(s) weights 1 and 3 over (1 + 3 + 1e-6); the lone token keeps e^5 / (e^5 + 1e-6) of itself.
    want = torch.tensor([[[1 / (4 + 1e-6), 3 / (4 + 1e-6)], [2 / (1 + 1e-6 * math.exp(-5))] * 2]])
    assert torch.allclose(merged, want, rtol=1e-6, atol=0)


def test_merge_tokens_does_not_overflow_and_matches_the_formula_in_double():
    x = torch.randn(1, 4, 3, dtype=torch.float64)
    assign = torch.tensor([[0, 1, 0, 1]])
    scores = torch.tensor([[1000.0, -5.0, 990.0, -7.0]], dtype=torch.float64)
    merged = merge_tokens(x, assign, scores, num_clusters=2)
    assert torch.isfinite(merged).all()
    w0 = torch.tensor([1.0, math.exp(-10)], dtype=torch.float64)  # e^1000 and e^990, scaled by e^-1000
    assert torch.allclose(merged[0, 0], (w0[:, None] * x[0, [0, 2]]).sum(0) / w0.sum(), rtol=1e-12)
    w1 = torch.tensor([math.exp(-5), math.exp(-7)], dtype=torch.float64)
    assert torch.allclose(merged[0, 1], (w1[:, None] * x[0, [1, 3]]).sum(0) / (w1.sum() + 1e-6), rtol=1e-12)


def test_merge_tokens_gradients():
    torch.manual_seed(0)
    x = torch.randn(2, 6, 3, dtype=torch.float64, requires_grad=True)
    scores = torch.randn(2, 6, dtype=torch.float64, requires_grad=True)
    assign = torch.tensor([[0, 1, 2, 0, 1, 2], [2, 2, 0, 1, 0, 1]])
    assert torch.autograd.gradcheck(lambda a, s: merge_tokens(a, assign, s, 3), (x, scores))
    with pytest.raises(ValueError, match=r"`assignment` and `scores` must be \(B, N\) = \(2, 6\)"):
        merge_tokens(x, assign[:, :5], scores, 3)


def _attention_reference(q_in, kv_in, attn, scores):
    """Per-head softmax(q k^T / sqrt(d) + score) v, then proj, with the block's weights: the paper's formula."""
    dim = q_in.shape[-1]
    h = attn.num_heads
    hd = dim // h
    q = q_in @ attn.q.weight.T
    k, v = (kv_in @ attn.kv.weight.T).split(dim, dim=-1)
    heads = []
    for i in range(h):
        sl = slice(i * hd, (i + 1) * hd)
        logits = q[..., sl] @ k[..., sl].transpose(-1, -2) / math.sqrt(hd) + scores[:, None, :]
        heads.append(torch.softmax(logits, dim=-1) @ v[..., sl])
    return attn.proj(torch.cat(heads, dim=-1))


def _random_block(dim=8, heads=2, tokens=4, k=3) -> SimilarTokenMergerBlock:
    torch.manual_seed(0)
    block = SimilarTokenMergerBlock(dim, heads, tokens, k)
    with torch.no_grad():
        for p in block.parameters():
            p.copy_(torch.randn_like(p) * 0.5)  # LayerNorm affine and the score included
    return block


def test_merger_block_equals_the_published_formula():
    block = _random_block()
    tokens = torch.randn(2, 10, 8)
    with torch.no_grad():
        out = block(tokens)
        x = F.layer_norm(tokens, (8,), block.norm1.weight, block.norm1.bias)
        s = x @ block.score.weight[0] + block.score.bias  # (B, N) token scores
        _, assign = cluster_dpc_knn(x, 4, 3)
        w = torch.exp(s)
        merged = torch.stack(
            [
                torch.stack([(w[b, assign[b] == c, None] * x[b, assign[b] == c]).sum(0) for c in range(4)])
                / (torch.stack([w[b, assign[b] == c].sum() for c in range(4)])[:, None] + 1e-6)
                for b in range(2)
            ]
        )
        y = merged + _attention_reference(merged, x, block.attn, s)
        want = y + block.mlp(F.layer_norm(y, (8,), block.norm2.weight, block.norm2.bias))
        assert out.shape == (2, 4, 8)
        assert torch.allclose(out, want, atol=1e-5)
        # The formula without the score in the logits is measurably different: the score matters there.
        y_unscored = merged + _attention_reference(merged, x, block.attn, torch.zeros_like(s))
        unscored = y_unscored + block.mlp(F.layer_norm(y_unscored, (8,), block.norm2.weight, block.norm2.bias))
        assert (out - unscored).abs().max() > 1e-2


def test_token_score_shifts_the_merger_attention_logits_exactly():
    """A hand-built block: one head, identity projections, no MLP, as many clusters as tokens.

    Its attention weights then read off the output, and raising one token's score by ``ln 3`` must
    multiply that token's attention weight by 3 relative to the others, for every query.
    """
    dim, n = 5, 4
    block = SimilarTokenMergerBlock(dim, num_heads=1, num_tokens=n, k=1)
    eye = torch.eye(dim)
    with torch.no_grad():
        block.attn.q.weight.copy_(eye)
        block.attn.kv.weight.copy_(torch.cat([eye, eye]))
        block.attn.proj.weight.copy_(eye)
        block.attn.proj.bias.zero_()
        block.mlp.fc2.weight.zero_()
        block.mlp.fc2.bias.zero_()
    x = torch.tensor(
        [
            [
                [2.0, -1.0, 0.5, -1.5, 0.0],
                [0.0, 1.0, -2.0, 1.0, 0.5],
                [1.0, 1.0, -1.0, -1.0, 2.0],
                [-2.0, 0.5, 1.0, 0.5, -1.0],
            ]
        ]
    )
    xn = F.layer_norm(x, (dim,))[0]  # (4, 5), rank 4
    pinv = torch.linalg.pinv(xn)

    def attention_weights(score_bias: float, score_weight: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        with torch.no_grad():
            block.score.weight.copy_(score_weight)
            block.score.bias.fill_(score_bias)
            out = block(x)[0]
        s = xn @ score_weight[0] + score_bias
        _, assign = cluster_dpc_knn(xn[None], n, 1)
        merged = merge_tokens(xn[None], assign, s[None], n)[0]
        # out = merged + A @ xn, with A the attention weights (queries x tokens).
        a = (out - merged) @ pinv
        return a, torch.softmax(merged @ xn.T / math.sqrt(dim) + s, dim=-1)

    zero = torch.zeros(1, dim)
    a0, want0 = attention_weights(0.0, zero)
    assert torch.allclose(a0, want0, atol=1e-5)
    assert torch.allclose(a0.sum(-1), torch.ones(n), atol=1e-5)
    # A constant score changes nothing (softmax is shift-invariant, and so is the merge).
    a_const, _ = attention_weights(4.0, zero)
    assert torch.allclose(a_const, a0, atol=1e-5)
    # A score weight that gives token 2 the score ln 3 and the others 0.
    direction = pinv @ torch.tensor([0.0, 0.0, math.log(3.0), 0.0])
    a1, want1 = attention_weights(0.0, direction[None])
    assert torch.allclose(a1, want1, atol=1e-5)
    ratio = (a1 / a0) / (a1 / a0)[:, [0]]
    assert torch.allclose(ratio, torch.tensor([1.0, 1.0, 3.0, 1.0]).expand(n, n), atol=1e-4)


def test_merger_stacks_blocks_and_is_initialised_like_the_released_code():
    torch.manual_seed(0)
    merger = SimilarTokenMerger(dim=16, num_heads=2, num_tokens=5, k=3, depth=2)
    assert len(merger.blocks) == 2
    weights = torch.cat([m.weight.flatten() for m in merger.modules() if isinstance(m, torch.nn.Linear)])
    assert 0.009 < weights.std().item() < 0.011
    assert all(not m.bias.any() for m in merger.modules() if isinstance(m, torch.nn.Linear) and m.bias is not None)
    tokens = torch.randn(3, 12, 16)
    with torch.no_grad():
        assert torch.equal(merger(tokens), merger.blocks[1](merger.blocks[0](tokens)))
        assert merger(tokens).shape == (3, 5, 16)
        assert merger(tokens[:, :4]).shape == (3, 4, 16)  # fewer tokens than clusters: every token kept
    with pytest.raises(ValueError, match=r"`depth` must be an int >= 1, got 0"):
        SimilarTokenMerger(16, 2, 5, 3, depth=0)


def test_paper_merger_parameter_count():
    with torch.device("meta"):
        merger = SimilarTokenMerger(dim=768, num_heads=12, num_tokens=196, k=15, depth=2)
    # The released Merger (LiyingCV/Long-Range-Grouping-Transformer, config.py defaults) instantiated
    # outside this repository: 14,172,674 = 2 x (LayerNorm 1,536 + score 769 + attention 2,360,064 +
    # LayerNorm 1,536 + MLP 4,722,432).
    assert sum(p.numel() for p in merger.parameters()) == 14_172_674
    assert sum(p.numel() for p in merger.blocks[0].attn.parameters()) == 2_360_064
    assert sum(p.numel() for p in merger.blocks[0].score.parameters()) == 769
