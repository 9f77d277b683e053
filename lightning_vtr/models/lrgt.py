"""LRGT, the Long-Range Grouping Transformer (Yang et al., ICCV 2023), as a voxel reconstruction model.

The paper's second reconstruction model. Images of all views go through a DeiT encoder whose
blocks 5, 7, 9 and 11 (0-based, so the last block is one of them and the final features mix
views) use *long-range grouping attention*: the patch tokens of each view are split by the
residue of their row and column modulo a stride (7 at 14x14 tokens: 49 groups of 4 tokens per
view, 7 tokens apart), and each group attends across all the sample's views. An *inter-view
feature signature*, a depthwise 3x3 convolution of the values laid out on each view's patch
grid, is added to the attention output so tokens from different views stay distinguishable.
The other blocks attend within each view. A *similar-token merger* clusters the ``V * P``
tokens into a fixed number (196 in the paper) and a decoder of ``4^3`` learned queries
cross-attends to them, then upsamples ``4^3 -> 8^3 -> 16^3 -> 32^3`` to occupancy
probabilities. Training minimises the Dice loss of the paper.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from lightning_vtr.models.base import VoxelReconstructionModule
from lightning_vtr.models.vit import Attention, DistilledVisionTransformer, Mlp, load_timm_deit
from lightning_vtr.utils.validation import check_choice, check_float, check_int

__all__ = [
    "LRGT",
    "LRGT_PRESETS",
    "LRGTNetwork",
    "LRGTSpec",
    "LongRangeGroupingAttention",
    "QueryVoxelDecoder",
    "SimilarTokenMerger",
    "dice_loss",
]


def _int_tuple(name: str, values: Sequence[int], minimum: int) -> tuple[int, ...]:
    """``values`` as a tuple of ints ``>= minimum``; the messages name ``name[i]``."""
    try:
        items = tuple(values)
    except TypeError:
        raise TypeError(f"`{name}` must be a sequence of ints, got {type(values).__name__} {values!r}") from None
    return tuple(check_int(f"{name}[{i}]", v, minimum=minimum) for i, v in enumerate(items))


@dataclass(frozen=True)
class LRGTSpec:
    """The architecture of one LRGT variant: what :data:`LRGT_PRESETS` holds and :class:`LRGT` is built from.

    Creating one checks every field (``TypeError`` for a wrong type, ``ValueError`` for a wrong value) and
    stores the sequences as tuples, so a spec is hashable and compares by value.

    Attributes:
        image_size: square input size in pixels (a multiple of ``patch_size``).
        patch_size: ViT patch side in pixels.
        embed_dim: token width ``D`` (divisible by ``num_heads`` and ``decoder_heads``).
        depth: encoder blocks.
        num_heads: encoder attention heads.
        grouping_blocks: 0-based indices of the encoder blocks that use long-range grouping attention.
        group_stride: the grouping's residue stride; it divides the token grid side ``image_size / patch_size``.
        num_merged_tokens: tokens ``M`` the similar-token merger keeps.
        merger_k: neighbours of the merger's density estimate.
        decoder_depth: layers of the query decoder.
        decoder_heads: attention heads of the decoder layers.
        query_grid: ``q``: the decoder's ``q^3`` learned queries.
        upsample_channels: widths of the 2x upsampling stages; ``R = q 2^len(upsample_channels)``.
    """

    image_size: int
    patch_size: int
    embed_dim: int
    depth: int
    num_heads: int
    grouping_blocks: tuple[int, ...]
    group_stride: int
    num_merged_tokens: int
    merger_k: int
    decoder_depth: int
    decoder_heads: int
    query_grid: int
    upsample_channels: tuple[int, ...]

    def __post_init__(self) -> None:
        for name in ("depth", "decoder_depth"):
            check_int(name, getattr(self, name), minimum=0)
        for name in (
            "image_size",
            "patch_size",
            "embed_dim",
            "num_heads",
            "group_stride",
            "num_merged_tokens",
            "merger_k",
            "decoder_heads",
            "query_grid",
        ):
            check_int(name, getattr(self, name), minimum=1)
        blocks = _int_tuple("grouping_blocks", self.grouping_blocks, minimum=0)
        if any(i >= self.depth for i in blocks):
            raise ValueError(
                f"`grouping_blocks` must be 0-based block indices in [0, {self.depth}), got {list(blocks)}"
            )
        # Frozen: normalise the sequences (lists from a config or a checkpoint) through object.__setattr__.
        object.__setattr__(self, "grouping_blocks", blocks)
        object.__setattr__(
            self, "upsample_channels", _int_tuple("upsample_channels", self.upsample_channels, minimum=1)
        )

    @property
    def grid_size(self) -> int:
        """Side of each view's patch-token grid (14 for the paper)."""
        return self.image_size // self.patch_size

    @property
    def voxel_resolution(self) -> int:
        """``R`` of the ``(B, R, R, R)`` output: ``query_grid * 2 ** len(upsample_channels)``."""
        return self.query_grid * 2 ** len(self.upsample_channels)


#: The named presets. ``paper``: the published model (DeiT-B distilled, 224 px, 14x14 tokens, about 130 M
#: parameters). ``tiny``: small enough to train on 2 CPU cores (64 px); 8x8 tokens with stride 4 keep groups
#: of 4 tokens per view.
LRGT_PRESETS: dict[str, LRGTSpec] = {
    "paper": LRGTSpec(
        image_size=224,
        patch_size=16,
        embed_dim=768,
        depth=12,
        num_heads=12,
        grouping_blocks=(5, 7, 9, 11),
        group_stride=7,
        num_merged_tokens=196,
        merger_k=15,
        decoder_depth=3,
        decoder_heads=12,
        query_grid=4,
        upsample_channels=(256, 64, 16),
    ),
    "tiny": LRGTSpec(
        image_size=64,
        patch_size=8,
        embed_dim=64,
        depth=4,
        num_heads=4,
        grouping_blocks=(1, 3),
        group_stride=4,
        num_merged_tokens=64,
        merger_k=5,
        decoder_depth=1,
        decoder_heads=4,
        query_grid=4,
        upsample_channels=(32, 16, 8),
    ),
}


def dice_loss(probs: Tensor, target: Tensor, smooth: float = 1.0) -> Tensor:
    """LRGT's Dice loss ``1 - (sum(p t) + 1) / (sum(p^2) + sum(t^2) + 1)``, averaged over the batch.

    Args:
        probs: occupancy probabilities ``(B, ...)`` in ``[0, 1]``.
        target: ground truth ``(B, ...)`` in ``{0, 1}``, same shape.
        smooth: the ``+ 1`` of the formula.

    Returns:
        A scalar. Sums run over each sample's voxels. The published formula has no factor 2
        in the numerator, so a perfect prediction scores ``1 - (n + 1) / (2 n + 1)``, about 0.5,
        not 0; only the gradient matters for training.
    """
    if probs.shape != target.shape:
        raise ValueError(
            f"`target` must have the same shape as `probs` {tuple(probs.shape)}, got {tuple(target.shape)}"
        )
    p = probs.flatten(1)
    t = target.flatten(1).to(p.dtype)
    inter = (p * t).sum(1)
    return (1 - (inter + smooth) / ((p * p).sum(1) + (t * t).sum(1) + smooth)).mean()


class LongRangeGroupingAttention(Attention):
    """Attention within stride-residue token groups across all views, plus the inter-view signature.

    Tokens are ``(B * V, 2 + g^2, D)`` (cls, dist, then the row-major ``g x g`` patch grid; the
    ``V`` views of a sample contiguous). Patch ``(r, c)`` belongs to group
    ``(r mod s, c mod s)``: ``s^2`` groups of ``(g / s)^2`` tokens per view, and each group
    attends over its tokens of all ``V`` views (``V (g/s)^2`` tokens). The two prefix tokens of
    every view form one more group of ``2 V`` tokens, so cls/dist keep exchanging information
    across views but not with patches (nothing downstream reads them).

    With one view the groups are those of the single view: attention within each group of
    ``(g/s)^2`` tokens and among the cls/dist pair. The output is the same as running the
    ``V``-view case on each view separately only when ``V = 1``; adding views widens groups.

    The signature ``S = DWConv3x3(values on each view's g x g grid)`` is added to the patch
    tokens' attention output before the output projection. It is initialised to zero so a
    pretrained DeiT block starts out computing exactly grouped attention.

    Args:
        dim: token width ``D``.
        num_heads: attention heads.
        grid_size: patch grid side ``g``.
        group_stride: residue stride ``s``; must divide ``g``.
    """

    def __init__(self, dim: int, num_heads: int, grid_size: int, group_stride: int, qkv_bias: bool = True) -> None:
        super().__init__(dim, num_heads, qkv_bias)
        check_int("group_stride", group_stride, minimum=1)
        if grid_size % group_stride != 0:
            raise ValueError(f"`group_stride` must divide the token grid size {grid_size}, got {group_stride}")
        self.grid_size = grid_size
        self.group_stride = group_stride
        self.signature = nn.Conv2d(dim, dim, kernel_size=3, padding=1, groups=dim)
        nn.init.zeros_(self.signature.weight)
        nn.init.zeros_(self.signature.bias)

    def _to_groups(self, t: Tensor, num_views: int) -> Tensor:
        """``(B V, h, g^2, d) -> (B s^2, h, V (g/s)^2, d)``, groups ordered by residue ``(a, b)``."""
        bv, h, _, d = t.shape
        g, s = self.grid_size, self.group_stride
        # Patch row r = i s + a, column c = j s + b: (i, a, j, b) splits the residue out.
        t = t.reshape(bv // num_views, num_views, h, g // s, s, g // s, s, d)
        t = t.permute(0, 4, 6, 2, 1, 3, 5, 7)  # (B, a, b, h, V, i, j, d)
        return t.reshape(-1, h, num_views * (g // s) ** 2, d)

    def _from_groups(self, t: Tensor, num_views: int) -> Tensor:
        """Inverse of :meth:`_to_groups`."""
        _, h, _, d = t.shape
        g, s = self.grid_size, self.group_stride
        t = t.reshape(-1, s, s, h, num_views, g // s, g // s, d)
        t = t.permute(0, 4, 3, 5, 1, 6, 2, 7)  # (B, V, h, i, a, j, b, d)
        return t.reshape(-1, h, g * g, d)

    def forward(self, x: Tensor, num_views: int = 1) -> Tensor:
        bv, t, dim = x.shape
        npre = t - self.grid_size**2
        if npre < 0 or bv % num_views != 0:
            raise ValueError(
                f"`x` must be (B * {num_views}, prefix + {self.grid_size**2}, D) tokens, got {tuple(x.shape)}"
            )
        q, k, v = self.split_heads(x)
        # 1. patch tokens: attention inside each residue group, across views.
        qp, kp, vp = (self._to_groups(z[:, :, npre:], num_views) for z in (q, k, v))
        patches = self._from_groups(F.scaled_dot_product_attention(qp, kp, vp), num_views)

        # 2. prefix tokens of all views of a sample together.
        def to_prefix_group(z: Tensor) -> Tensor:
            h, d = z.shape[1], z.shape[3]
            z = z[:, :, :npre].reshape(bv // num_views, num_views, h, npre, d).transpose(1, 2)
            return z.reshape(bv // num_views, h, num_views * npre, d)

        prefix = F.scaled_dot_product_attention(*(to_prefix_group(z) for z in (q, k, v)))
        h, d = prefix.shape[1], prefix.shape[3]
        prefix = prefix.reshape(bv // num_views, h, num_views, npre, d).transpose(1, 2).reshape(bv, h, npre, d)
        out = self.merge_heads(torch.cat([prefix, patches], dim=2))
        # 3. inter-view feature signature from each view's value map.
        g = self.grid_size
        values = self.merge_heads(v[:, :, npre:]).transpose(1, 2).reshape(bv, dim, g, g)
        signature = self.signature(values).flatten(2).transpose(1, 2)
        out = torch.cat([out[:, :npre], out[:, npre:] + signature], dim=1)
        return self.proj(out)


class SimilarTokenMerger(nn.Module):
    """Merge ``N`` tokens into ``M`` by DPC-kNN clustering and importance-weighted averaging.

    Clustering (no gradient; distances ``d_ij = ||x_i - x_j|| / sqrt(D)``):

    1. density ``rho_i = exp(-mean of d_ij^2 over the k nearest other tokens)``;
    2. ``delta_i`` = distance to the nearest denser token (ties in ``rho`` broken by the lower
       index, so the result is deterministic), or the largest ``d_ij`` for the densest token;
    3. the ``M`` tokens with the largest ``rho_i delta_i`` are cluster centres, and every token
       joins its nearest centre (a centre always joins itself).

    Merging (differentiable): cluster ``m`` becomes ``sum_i w_i x_i / sum_i w_i`` over its
    members, with ``w_i = exp(s_i)`` and ``s_i`` a learned linear score of the token. If
    ``N <= M`` every token is its own cluster, so the merger is the identity.

    Args:
        dim: token width ``D``.
        num_tokens: ``M``.
        k: neighbours for the density (15 in the paper), capped at ``N - 1``.
    """

    def __init__(self, dim: int, num_tokens: int, k: int) -> None:
        super().__init__()
        self.num_tokens = check_int("num_tokens", num_tokens, minimum=1)
        self.k = check_int("k", k, minimum=1)
        self.score = nn.Linear(dim, 1)

    @torch.no_grad()
    def cluster(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """Centres ``(B, M')`` (indices into N) and assignment ``(B, N)`` (indices into M'), ``M' = min(M, N)``."""
        b, n, dim = x.shape
        m = min(self.num_tokens, n)
        ar = torch.arange(n, device=x.device)
        if m == n:
            return ar.expand(b, n), ar.expand(b, n)
        dist = torch.cdist(x.float(), x.float()) / math.sqrt(dim)
        k = min(self.k, n - 1)
        # The smallest distance of each row is the token itself (0), hence k + 1.
        knn = dist.topk(k + 1, dim=-1, largest=False).values[..., 1:]
        density = torch.exp(-(knn**2).mean(-1))  # (B, N)
        rho_i, rho_j = density[:, :, None], density[:, None, :]
        denser = (rho_j > rho_i) | ((rho_j == rho_i) & (ar[None, None, :] < ar[None, :, None]))
        big = dist.amax(dim=(1, 2), keepdim=True) + 1
        delta = torch.where(denser, dist, big).amin(-1)
        peak = ~denser.any(-1)
        delta = torch.where(peak, dist.amax(-1), delta)
        centres = (density * delta).topk(m, dim=-1).indices  # (B, M)
        assign = torch.gather(dist, 2, centres[:, None, :].expand(b, n, m)).argmin(-1)
        assign.scatter_(1, centres, torch.arange(m, device=x.device).expand(b, m))
        return centres, assign

    def forward(self, x: Tensor) -> Tensor:
        """``(B, N, D) -> (B, min(M, N), D)``."""
        b, n, dim = x.shape
        _, assign = self.cluster(x)
        m = min(self.num_tokens, n)
        s = self.score(x).squeeze(-1)
        w = torch.exp(s - s.amax(dim=1, keepdim=True))  # scale-free, so subtracting the max is exact
        flat = (assign + torch.arange(b, device=x.device)[:, None] * m).flatten()
        num = x.new_zeros(b * m, dim).index_add_(0, flat, (w[..., None] * x).reshape(b * n, dim))
        den = x.new_zeros(b * m).index_add_(0, flat, w.flatten())
        return (num / den[:, None]).reshape(b, m, dim)


class _CrossAttention(nn.Module):
    """Queries ``(B, Q, D)`` attend to memory ``(B, M, D)``."""

    def __init__(self, dim: int, num_heads: int) -> None:
        super().__init__()
        self.num_heads = num_heads
        self.q = nn.Linear(dim, dim)
        self.kv = nn.Linear(dim, 2 * dim)
        self.proj = nn.Linear(dim, dim)

    def forward(self, x: Tensor, memory: Tensor) -> Tensor:
        b, nq, dim = x.shape
        h = self.num_heads
        q = self.q(x).reshape(b, nq, h, dim // h).transpose(1, 2)
        k, v = self.kv(memory).reshape(b, memory.shape[1], 2, h, dim // h).permute(2, 0, 3, 1, 4)
        return self.proj(Attention.merge_heads(F.scaled_dot_product_attention(q, k, v)))


class _DecoderLayer(nn.Module):
    """Pre-norm: query self-attention, cross-attention to the merged tokens, MLP."""

    def __init__(self, dim: int, num_heads: int, mlp_ratio: float = 4.0) -> None:
        super().__init__()
        self.norm1 = nn.LayerNorm(dim)
        self.self_attn = Attention(dim, num_heads)
        self.norm2 = nn.LayerNorm(dim)
        self.norm_memory = nn.LayerNorm(dim)
        self.cross_attn = _CrossAttention(dim, num_heads)
        self.norm3 = nn.LayerNorm(dim)
        self.mlp = Mlp(dim, int(dim * mlp_ratio))

    def forward(self, x: Tensor, memory: Tensor) -> Tensor:
        x = x + self.self_attn(self.norm1(x))
        x = x + self.cross_attn(self.norm2(x), self.norm_memory(memory))
        return x + self.mlp(self.norm3(x))


class QueryVoxelDecoder(nn.Module):
    """``q^3`` learned queries cross-attend to the tokens, then progressive 2x upsampling to voxels.

    Query ``n`` is voxel cell ``(i, j, k)`` of the coarse ``q^3`` grid with ``n = (i q + j) q + k``
    (``i, j, k`` along x, y, z as in :mod:`lightning_vtr.geometry`). Each upsampling stage is
    ``ConvTranspose3d(k4, s2, p1) -> BatchNorm3d -> ReLU -> Conv3d(k3) -> BatchNorm3d -> ReLU``.
    BatchNorm, as in Pix2Vox's decoder, rather than GroupNorm: at initialisation the queries
    attend almost uniformly, so an object's identity first arrives as a per-sample offset that
    is constant over the coarse grid, and GroupNorm's per-sample normalisation removed most of
    it (an overfitting run on four shapes stalled at the mean shape). In eval mode BatchNorm
    uses running statistics, so a prediction does not depend on the rest of its batch.

    Args:
        dim: token width ``D``.
        num_heads: attention heads of the decoder layers.
        depth: decoder layers.
        query_grid: ``q``.
        upsample_channels: channels after each 2x stage; ``R = q 2^len(upsample_channels)``.

    Output: occupancy probabilities ``(B, R, R, R)``.
    """

    def __init__(self, dim: int, num_heads: int, depth: int, query_grid: int, upsample_channels: Sequence[int]) -> None:
        super().__init__()
        self.query_grid = query_grid
        self.queries = nn.Parameter(torch.zeros(1, query_grid**3, dim))
        nn.init.trunc_normal_(self.queries, std=0.02)
        self.layers = nn.ModuleList(_DecoderLayer(dim, num_heads) for _ in range(depth))
        self.norm = nn.LayerNorm(dim)
        stages: list[nn.Module] = []
        c_in = dim
        for c in upsample_channels:
            stages.append(
                nn.Sequential(
                    nn.ConvTranspose3d(c_in, c, kernel_size=4, stride=2, padding=1),
                    nn.BatchNorm3d(c),
                    nn.ReLU(inplace=True),
                    nn.Conv3d(c, c, kernel_size=3, padding=1),
                    nn.BatchNorm3d(c),
                    nn.ReLU(inplace=True),
                )
            )
            c_in = c
        self.upsample = nn.Sequential(*stages)
        self.head = nn.Conv3d(c_in, 1, kernel_size=1)
        self.resolution = query_grid * 2 ** len(upsample_channels)

    def forward(self, tokens: Tensor) -> Tensor:
        """Merged tokens ``(B, M, D)`` to probabilities ``(B, R, R, R)``."""
        b = tokens.shape[0]
        x = self.queries.expand(b, -1, -1)
        for layer in self.layers:
            x = layer(x, tokens)
        q = self.query_grid
        x = self.norm(x).transpose(1, 2).reshape(b, -1, q, q, q)
        return torch.sigmoid(self.head(self.upsample(x))).squeeze(1)


class LRGTNetwork(nn.Module):
    """The whole LRGT network: images ``(B, V, 3, H, W)`` to probabilities ``(B, R, R, R)``.

    Works with any ``V >= 1``; the prediction does not depend on the order of the views
    (grouping attention, the merger and the decoder are all permutation-invariant over views,
    up to ties in the clustering).

    Args: the fields of :class:`LRGTSpec` (checked by it); :meth:`from_spec` builds the network of a spec,
    e.g. of a preset in :data:`LRGT_PRESETS`.

    Attributes:
        spec: the :class:`LRGTSpec` of the network.
    """

    def __init__(
        self,
        image_size: int,
        patch_size: int,
        embed_dim: int,
        depth: int,
        num_heads: int,
        grouping_blocks: Sequence[int],
        group_stride: int,
        num_merged_tokens: int,
        merger_k: int,
        decoder_depth: int,
        decoder_heads: int,
        query_grid: int,
        upsample_channels: Sequence[int],
    ) -> None:
        super().__init__()
        spec = LRGTSpec(
            image_size=image_size,
            patch_size=patch_size,
            embed_dim=embed_dim,
            depth=depth,
            num_heads=num_heads,
            grouping_blocks=grouping_blocks,
            group_stride=group_stride,
            num_merged_tokens=num_merged_tokens,
            merger_k=merger_k,
            decoder_depth=decoder_depth,
            decoder_heads=decoder_heads,
            query_grid=query_grid,
            upsample_channels=upsample_channels,
        )
        self.spec = spec
        self.encoder = DistilledVisionTransformer(
            spec.image_size, spec.patch_size, spec.embed_dim, spec.depth, spec.num_heads
        )
        self.grouping_blocks = spec.grouping_blocks
        for i in self.grouping_blocks:
            old = self.encoder.blocks[i].attn
            new = LongRangeGroupingAttention(spec.embed_dim, spec.num_heads, self.encoder.grid_size, spec.group_stride)
            # Keep the block's (possibly pretrained) qkv/proj; only the signature conv is new.
            new.qkv, new.proj = old.qkv, old.proj
            self.encoder.blocks[i].attn = new
        self.merger = SimilarTokenMerger(spec.embed_dim, spec.num_merged_tokens, spec.merger_k)
        self.decoder = QueryVoxelDecoder(
            spec.embed_dim, spec.decoder_heads, spec.decoder_depth, spec.query_grid, spec.upsample_channels
        )
        self.image_size = spec.image_size
        self.voxel_resolution = self.decoder.resolution

    @classmethod
    def from_spec(cls, spec: LRGTSpec) -> LRGTNetwork:
        """The network of ``spec`` (e.g. ``LRGTNetwork.from_spec(LRGT_PRESETS["tiny"])``)."""
        if not isinstance(spec, LRGTSpec):
            raise TypeError(f"`spec` must be an LRGTSpec, got {type(spec).__name__} {spec!r}")
        return cls(**dataclasses.asdict(spec))

    def load_pretrained_encoder(self, path_or_state_dict) -> None:
        """Load a timm-format DeiT (distilled) checkpoint into the encoder (see :func:`load_timm_deit`)."""
        load_timm_deit(self.encoder, path_or_state_dict, allow_missing=(".attn.signature.",))

    def forward(self, images: Tensor) -> Tensor:
        if images.ndim != 5 or images.shape[2] != 3:
            raise ValueError(f"`images` must be (B, V, 3, H, W), got {tuple(images.shape)}")
        b, v = images.shape[:2]
        tokens = self.encoder(images.flatten(0, 1), num_views=v)
        patches = tokens[:, self.encoder.num_prefix_tokens :]  # cls/dist are not used downstream
        patches = patches.reshape(b, v * patches.shape[1], patches.shape[2])
        return self.decoder(self.merger(patches))


class LRGT(VoxelReconstructionModule):
    """LRGT as a LightningModule satisfying :class:`~lightning_vtr.protocol.ReconstructionModel`.

    ``preset`` picks an architecture from :data:`LRGT_PRESETS` (``"paper"``: DeiT-B encoder,
    224 px input, about 130 M parameters; ``"tiny"``: 64 px input, 0.5 M parameters, trains on
    a CPU); any architecture argument left at ``None`` takes the preset's value. The resolved
    architecture is :attr:`spec`, an :class:`LRGTSpec`. Training
    minimises :func:`dice_loss` with AdamW and a MultiStepLR schedule (milestones in epochs),
    as published. Any number of views works at train and test time.

    Args:
        preset: ``"paper"`` or ``"tiny"``.
        num_views: views per training sample (the protocol's ``num_views``; 3 in the paper).
        image_size, patch_size, embed_dim, depth, num_heads, grouping_blocks, group_stride,
        num_merged_tokens, merger_k, decoder_depth, decoder_heads, query_grid,
        upsample_channels: architecture overrides (see :class:`LRGTNetwork`);
            ``grouping_blocks`` are 0-based block indices.
        pretrained_encoder: local timm-format DeiT (distilled) checkpoint loaded into the
            encoder at construction (see :func:`~lightning_vtr.models.vit.load_timm_deit`);
            ``None`` keeps the random initialisation.
        lr: AdamW learning rate (1e-4 published).
        weight_decay: AdamW weight decay (torch's default; the paper does not state one).
        milestones: epochs at which the learning rate is multiplied by ``gamma`` ([60, 90], 0.1).
        gamma: the decay factor.
        validation_fscore, categories: passed to
            :class:`~lightning_vtr.models.base.VoxelReconstructionModule`.

    Attributes:
        spec: the resolved architecture (the preset with the overrides applied).

    Example::

        model = LRGT(preset="tiny")
        probs = model.predict_voxels(torch.randn(2, 3, 3, 64, 64))  # (2, 32, 32, 32)
    """

    def __init__(
        self,
        preset: str = "tiny",
        num_views: int = 3,
        image_size: int | None = None,
        patch_size: int | None = None,
        embed_dim: int | None = None,
        depth: int | None = None,
        num_heads: int | None = None,
        grouping_blocks: list[int] | None = None,
        group_stride: int | None = None,
        num_merged_tokens: int | None = None,
        merger_k: int | None = None,
        decoder_depth: int | None = None,
        decoder_heads: int | None = None,
        query_grid: int | None = None,
        upsample_channels: list[int] | None = None,
        pretrained_encoder: str | None = None,
        lr: float = 1e-4,
        weight_decay: float = 0.01,
        milestones: list[int] | None = None,
        gamma: float = 0.1,
        validation_fscore: bool = True,
        categories: list[str] | None = None,
    ) -> None:
        check_choice("preset", preset, LRGT_PRESETS)
        overrides = dict(
            image_size=image_size,
            patch_size=patch_size,
            embed_dim=embed_dim,
            depth=depth,
            num_heads=num_heads,
            grouping_blocks=grouping_blocks,
            group_stride=group_stride,
            num_merged_tokens=num_merged_tokens,
            merger_k=merger_k,
            decoder_depth=decoder_depth,
            decoder_heads=decoder_heads,
            query_grid=query_grid,
            upsample_channels=upsample_channels,
        )
        spec = dataclasses.replace(LRGT_PRESETS[preset], **{k: v for k, v in overrides.items() if v is not None})
        network = LRGTNetwork.from_spec(spec)
        super().__init__(
            image_size=spec.image_size,
            num_views=num_views,
            voxel_resolution=spec.voxel_resolution,
            validation_fscore=validation_fscore,
            categories=categories,
        )
        check_float("lr", lr, minimum=0.0, min_open=True)
        # save_hyperparameters() reads the arguments' current values, so resolve them first: the
        # checkpoint then describes the architecture fully, and the DataModule's `image_size`
        # hparam agrees with ours when Lightning merges the two for logging.
        (
            image_size,
            patch_size,
            embed_dim,
            depth,
            num_heads,
            group_stride,
            num_merged_tokens,
            merger_k,
            decoder_depth,
            decoder_heads,
            query_grid,
        ) = (
            getattr(spec, k)
            for k in (
                "image_size",
                "patch_size",
                "embed_dim",
                "depth",
                "num_heads",
                "group_stride",
                "num_merged_tokens",
                "merger_k",
                "decoder_depth",
                "decoder_heads",
                "query_grid",
            )
        )
        grouping_blocks, upsample_channels = list(spec.grouping_blocks), list(spec.upsample_channels)
        self.save_hyperparameters()
        self.spec = spec
        self.network = network
        if pretrained_encoder is not None:
            self.network.load_pretrained_encoder(pretrained_encoder)

    def reconstruct(self, images: Tensor) -> dict[str, Tensor]:
        """``{"voxels": (B, R, R, R)}`` probabilities for images ``(B, V, 3, H, W)``."""
        return {"voxels": self.network(images)}

    def loss(self, outputs: dict[str, Tensor], target: Tensor) -> Tensor:
        return dice_loss(outputs["voxels"], target)

    def configure_optimizers(self):
        hp = self.hparams
        optimizer = torch.optim.AdamW(self.parameters(), lr=hp.lr, weight_decay=hp.weight_decay)
        milestones = list(hp.milestones) if hp.milestones is not None else [60, 90]
        scheduler = torch.optim.lr_scheduler.MultiStepLR(optimizer, milestones=milestones, gamma=hp.gamma)
        return {"optimizer": optimizer, "lr_scheduler": {"scheduler": scheduler, "interval": "epoch"}}
