"""LRGT's Similar-Token Merger: DPC-kNN clustering of the views' tokens, score-weighted merging, scored attention.

The encoder leaves ``V * P`` tokens per sample (588 for three views at 224 px). The merger reduces them
to a fixed number ``M`` (196 in the paper) whatever ``V`` is, so the decoder's cost does not grow with
the number of views. :func:`cluster_dpc_knn` and :func:`merge_tokens` hold the math;
:class:`SimilarTokenMergerBlock` is one published block and :class:`SimilarTokenMerger` the stack of them.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from lightning_vtr.models.vit import CrossAttention, Mlp
from lightning_vtr.utils.validation import check_int

__all__ = ["SimilarTokenMerger", "SimilarTokenMergerBlock", "cluster_dpc_knn", "merge_tokens"]

# The released code adds 1e-6 to each cluster's weight sum; kept so that its trained weights give its outputs.
_MERGE_EPS = 1e-6


def _check_tokens(name: str, x: Tensor) -> None:
    if not isinstance(x, Tensor):
        raise TypeError(f"`{name}` must be a Tensor, got {type(x).__name__}")
    if x.ndim != 3 or x.shape[1] == 0:
        raise ValueError(f"`{name}` must be (B, N, D) tokens with N >= 1, got {tuple(x.shape)}")


@torch.no_grad()
def cluster_dpc_knn(x: Tensor, num_clusters: int, k: int) -> tuple[Tensor, Tensor]:
    """Density-peak clustering with k-nearest-neighbour density (DPC-kNN) of each sample's tokens.

    With ``d_ij = ||x_i - x_j|| / sqrt(D)``:

    1. density ``rho_i = exp(-mean of d_ij^2 over the k nearest tokens)``, the token itself (at
       distance 0) being one of the ``k``, as in the released code;
    2. ``delta_i`` = distance to the nearest denser token; the densest token gets the largest
       distance of the whole sample. Ties in ``rho`` go to the lower index, which keeps the
       result deterministic (the released code adds uniform noise of 1e-6 to ``rho`` instead);
    3. the ``M`` tokens with the largest ``rho_i delta_i`` are the centres, in decreasing order of
       that score, and every token joins its nearest centre (a centre always joins itself).

    No gradient flows through the clustering.

    Args:
        x: tokens ``(B, N, D)``.
        num_clusters: ``M``. With ``N <= M`` every token is a centre of its own, so the result has
            ``M' = min(M, N)`` clusters.
        k: neighbours of the density (15 in the paper), capped at ``N``.

    Returns:
        ``(centres, assignment)``: centre token indices ``(B, M')`` and each token's cluster index
        ``(B, N)`` in ``[0, M')``.
    """
    _check_tokens("x", x)
    check_int("num_clusters", num_clusters, minimum=1)
    check_int("k", k, minimum=1)
    b, n, dim = x.shape
    m = min(num_clusters, n)
    xf = x.float()
    dist = torch.cdist(xf, xf) / math.sqrt(dim)  # (B, N, N)
    knn = dist.topk(min(k, n), dim=-1, largest=False).values
    density = torch.exp(-(knn**2).mean(-1))  # (B, N)
    index = torch.arange(n, device=x.device)
    rho_i, rho_j = density[:, :, None], density[:, None, :]
    denser = (rho_j > rho_i) | ((rho_j == rho_i) & (index[None, None, :] < index[None, :, None]))
    dist_max = dist.flatten(1).amax(-1)[:, None, None]
    delta = torch.where(denser, dist, dist_max).amin(-1)  # the densest token has no denser one: dist_max
    centres = (density * delta).topk(m, dim=-1).indices  # (B, M')
    to_centres = torch.gather(dist, 1, centres[:, :, None].expand(b, m, n))  # (B, M', N): rows of the centres
    assignment = to_centres.argmin(dim=1)
    assignment.scatter_(1, centres, torch.arange(m, device=x.device).expand(b, m))
    return centres, assignment


def merge_tokens(x: Tensor, assignment: Tensor, scores: Tensor, num_clusters: int) -> Tensor:
    """Score-weighted average of each cluster's tokens: ``(B, N, D) -> (B, M, D)``.

    Cluster ``m`` becomes ``sum_i exp(s_i) x_i / (sum_i exp(s_i) + 1e-6)`` over its members ``i``
    (the released code's formula, the 1e-6 included). It is computed with each cluster's largest
    score subtracted, which changes nothing but cannot overflow. Differentiable in ``x`` and ``scores``. The
    weights and sums are computed in float32 (float64 if either input is float64) whatever the dtypes of ``x``
    and ``scores`` (e.g. half-precision scores from a Linear under autocast); the result has ``x``'s dtype.

    Args:
        x: tokens ``(B, N, D)``.
        assignment: cluster index of each token ``(B, N)`` in ``[0, num_clusters)``; every
            cluster must have at least one member.
        scores: token scores ``s`` ``(B, N)``.
        num_clusters: ``M``.

    Returns:
        The merged tokens ``(B, M, D)`` in ``x``'s dtype.
    """
    _check_tokens("x", x)
    b, n, dim = x.shape
    if assignment.shape != (b, n) or scores.shape != (b, n):
        raise ValueError(
            f"`assignment` and `scores` must be (B, N) = {(b, n)}, got {tuple(assignment.shape)} and "
            f"{tuple(scores.shape)}"
        )
    m = num_clusters
    flat = (assignment + torch.arange(b, device=x.device)[:, None] * m).flatten()
    # Weights and sums in float32 at least, whatever the inputs' dtypes: under autocast the scores come from a
    # Linear in half precision while exp() and the normalised tokens are float32 (CUDA's rules), and index_add_ (in
    # place, never autocast) needs one dtype; a half-precision sum over a cluster's members would lose precision.
    acc = torch.promote_types(torch.promote_types(x.dtype, scores.dtype), torch.float32)
    s = scores.flatten().to(acc)
    # A constant shift per cluster: detaching it leaves the function, and so its gradient, exact.
    shift = s.new_full((b * m,), -math.inf).scatter_reduce(0, flat, s, "amax").detach()
    w = torch.exp(s - shift[flat])
    den = s.new_zeros(b * m).index_add_(0, flat, w) + _MERGE_EPS * torch.exp(-shift)
    num = s.new_zeros(b * m, dim).index_add_(0, flat, w[:, None] * x.reshape(b * n, dim).to(acc))
    return (num / den[:, None]).to(x.dtype).reshape(b, m, dim)


class SimilarTokenMergerBlock(nn.Module):
    """One Similar-Token Merger block: ``(B, N, D)`` tokens to ``(B, min(M, N), D)``.

    1. ``x = LayerNorm(tokens)``; a token score ``s = Linear(x)``, one number per token;
    2. DPC-kNN (:func:`cluster_dpc_knn`) groups the normalised tokens into ``M`` clusters;
    3. each cluster is merged into one token weighted by ``exp(s)`` (:func:`merge_tokens`);
    4. a transformer block whose queries are the merged tokens ``y`` and whose keys and values are
       all ``N`` normalised tokens, the token score added to the attention logits:
       ``y = y + Attn(y, x, logits + s)``, then ``y = y + MLP(LayerNorm(y))``. The merged tokens
       enter the attention as they are (they come from normalised tokens already).

    The score thus reaches the output twice: through the merge weights and as an attention bias
    that makes high-scoring tokens count more for every merged token.

    Args:
        dim: token width ``D``.
        num_heads: attention heads (12 in the paper).
        num_tokens: ``M``, tokens kept (196 in the paper).
        k: DPC-kNN neighbours (15 in the paper).
        mlp_ratio: MLP hidden width as a multiple of ``D``.
    """

    def __init__(self, dim: int, num_heads: int, num_tokens: int, k: int, mlp_ratio: float = 4.0) -> None:
        super().__init__()
        self.num_tokens = check_int("num_tokens", num_tokens, minimum=1)
        self.k = check_int("k", k, minimum=1)
        self.norm1 = nn.LayerNorm(dim)
        self.score = nn.Linear(dim, 1)
        self.attn = CrossAttention(dim, num_heads, qkv_bias=False)
        self.norm2 = nn.LayerNorm(dim)
        self.mlp = Mlp(dim, int(dim * mlp_ratio))

    def forward(self, tokens: Tensor) -> Tensor:
        """``(B, N, D) -> (B, min(M, N), D)``; merged tokens in decreasing order of their centre's DPC score."""
        _check_tokens("tokens", tokens)
        x = self.norm1(tokens)
        scores = self.score(x).squeeze(-1)  # (B, N)
        centres, assignment = cluster_dpc_knn(x, self.num_tokens, self.k)
        merged = merge_tokens(x, assignment, scores, centres.shape[1])
        y = merged + self.attn(merged, x, logit_bias=scores[:, None, None, :])
        return y + self.mlp(self.norm2(y))


class SimilarTokenMerger(nn.Module):
    """LRGT's Similar-Token Merger: ``depth`` :class:`SimilarTokenMergerBlock` s, ``(B, N, D) -> (B, M, D)``.

    The paper stacks two blocks of ``M = 196`` (about 14.2 M parameters at ``D = 768``): the first
    reduces the ``V * 196`` tokens, the second, with as many tokens as clusters, keeps every token
    as its own cluster and acts as a transformer block with score-biased attention. With fewer
    input tokens than ``M`` (possible only in small configurations: ``V`` views of ``P < M``
    tokens) every token is its own cluster and the merger returns ``N`` tokens; the decoder's
    cross-attention takes any number.

    Initialised as the released code does: linear weights ``N(0, 0.01)``, zero biases.

    Args:
        dim: token width ``D``.
        num_heads: attention heads of each block.
        num_tokens: ``M``.
        k: DPC-kNN neighbours.
        depth: blocks (2 in the paper).
    """

    def __init__(self, dim: int, num_heads: int, num_tokens: int, k: int, depth: int = 2) -> None:
        super().__init__()
        check_int("depth", depth, minimum=1)
        self.num_tokens = check_int("num_tokens", num_tokens, minimum=1)
        self.blocks = nn.ModuleList(SimilarTokenMergerBlock(dim, num_heads, num_tokens, k) for _ in range(depth))
        for module in self.modules():
            if isinstance(module, nn.Linear):
                nn.init.normal_(module.weight, std=0.01)
                if module.bias is not None:
                    nn.init.zeros_(module.bias)

    def forward(self, tokens: Tensor) -> Tensor:
        """All views' tokens ``(B, V * P, D)`` to merged tokens ``(B, min(M, V * P), D)``."""
        for block in self.blocks:
            tokens = block(tokens)
        return tokens
