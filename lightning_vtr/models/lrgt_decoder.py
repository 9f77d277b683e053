"""LRGT's progressive upsampling transformer decoder: merged tokens ``(B, M, D)`` to occupancy ``(B, R, R, R)``.

Learned queries, one per cell of a coarse ``q^3`` grid, read the merged tokens; the grid is then
doubled stage by stage with transposed convolutions, each stage followed by transformer blocks over
the grid (or over patches of it, once the grid is finer than ``2q``), and a last ``1^3`` transposed
convolution and a sigmoid give the probabilities.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor, nn

from lightning_vtr.models.layers import BatchNorm3d, VolumeHeadTransposed, channels_last_3d
from lightning_vtr.models.vit import Attention, Block, CrossAttention, Mlp
from lightning_vtr.utils.validation import check_int

__all__ = ["DecoderStage", "ProgressiveUpsamplingDecoder", "decoder_stage_layout", "patch_tokens", "unpatch_tokens"]


def decoder_stage_layout(query_grid: int, upsample_channels: Sequence[int]) -> list[tuple[int, int, int]]:
    """``(grid, patch, width)`` of each upsampling stage.

    Stage ``i`` (1-based) has a ``grid^3`` volume, ``grid = q 2^i``, with ``upsample_channels[i - 1]``
    channels. Its tokens form at most a ``(2q)^3`` grid: a finer volume is cut into ``patch^3``
    cubes, ``patch = grid / 2q``, each one token of ``width = channels * patch^3``. For the paper
    (``q = 4``, channels 96, 12, 3): ``[(8, 1, 96), (16, 2, 96), (32, 4, 192)]``, 512 tokens each.
    """
    layout = []
    for i, channels in enumerate(upsample_channels, start=1):
        grid = query_grid * 2**i
        patch = grid // min(grid, 2 * query_grid)
        layout.append((grid, patch, channels * patch**3))
    return layout


def patch_tokens(x: Tensor, patch: int) -> Tensor:
    """Cut a volume ``(B, C, G, G, G)`` into ``(G/p)^3`` tokens of ``C p^3`` features: ``(B, (G/p)^3, C p^3)``.

    Tokens are row-major over the ``(i, j, k)`` patch grid; features are ordered ``(c, di, dj, dk)``
    with ``c`` slowest, the voxel being ``(i p + di, j p + dj, k p + dk)``.
    """
    b, c, g = x.shape[:3]
    t = g // patch
    x = x.reshape(b, c, t, patch, t, patch, t, patch).permute(0, 2, 4, 6, 1, 3, 5, 7)
    return x.reshape(b, t**3, c * patch**3)


def unpatch_tokens(tokens: Tensor, patch: int, channels: int) -> Tensor:
    """Inverse of :func:`patch_tokens`: ``(B, T^3, C p^3) -> (B, C, T p, T p, T p)``."""
    b, n = tokens.shape[:2]
    t = round(n ** (1 / 3))
    x = tokens.reshape(b, t, t, t, channels, patch, patch, patch).permute(0, 4, 1, 5, 2, 6, 3, 7)
    return x.reshape(b, channels, t * patch, t * patch, t * patch)


class _QueryBlock(nn.Module):
    """Pre-norm: self-attention among the queries, cross-attention to the merged tokens, MLP.

    The merged tokens enter the cross-attention un-normalised, as in the released code.
    """

    def __init__(self, dim: int, num_heads: int, mlp_ratio: float = 4.0) -> None:
        super().__init__()
        self.norm1 = nn.LayerNorm(dim)
        self.self_attn = Attention(dim, num_heads, qkv_bias=False)
        self.norm2 = nn.LayerNorm(dim)
        self.cross_attn = CrossAttention(dim, num_heads, qkv_bias=False)
        self.norm3 = nn.LayerNorm(dim)
        self.mlp = Mlp(dim, int(dim * mlp_ratio))

    def forward(self, x: Tensor, memory: Tensor) -> Tensor:
        x = x + self.self_attn(self.norm1(x))
        x = x + self.cross_attn(self.norm2(x), memory)
        return x + self.mlp(self.norm3(x))


class DecoderStage(nn.Module):
    """One 2x upsampling stage: ``(B, C_in, G/2, G/2, G/2) -> (B, C, G, G, G)``.

    ``ConvTranspose3d(k4, s2, p1, no bias) -> BatchNorm3d -> ReLU``, then ``depth`` self-attention
    blocks of width ``C p^3`` over the tokens of :func:`patch_tokens`. With ``p = 1`` the blocks'
    output replaces the volume; with ``p > 1`` it is added to it as a residual (as in the released
    code; the blocks are residual themselves, so the volume is counted twice there).

    Args:
        in_channels, channels: ``C_in`` and ``C``.
        patch: ``p``, the side of a token's cube of voxels.
        num_heads: attention heads; must divide ``C p^3``.
        depth: transformer blocks (2 in the paper; 0 leaves the upsampled volume as it is).
    """

    def __init__(self, in_channels: int, channels: int, patch: int, num_heads: int, depth: int) -> None:
        super().__init__()
        self.channels = channels
        self.patch = patch
        self.upsample = nn.Sequential(
            nn.ConvTranspose3d(in_channels, channels, kernel_size=4, stride=2, padding=1, bias=False),
            BatchNorm3d(channels),
            nn.ReLU(inplace=True),  # on the normalised volume, which nothing else keeps: one volume less to allocate
        )
        width = channels * patch**3
        self.blocks = nn.ModuleList(Block(width, num_heads, qkv_bias=False, norm_eps=1e-5) for _ in range(depth))

    def forward(self, x: Tensor) -> Tensor:
        x = self.upsample(channels_last_3d(x))
        if not self.blocks:
            return x
        tokens = patch_tokens(x, self.patch)
        for block in self.blocks:
            tokens = block(tokens)
        y = unpatch_tokens(tokens, self.patch, self.channels)
        return x + y if self.patch > 1 else y


class ProgressiveUpsamplingDecoder(nn.Module):
    """LRGT's decoder: merged tokens ``(B, M, D)`` to occupancy probabilities ``(B, R, R, R)``, ``R = q 2^n``.

    1. ``q^3`` learned queries (64 in the paper) pass through ``query_depth`` blocks of
       self-attention, cross-attention to the un-normalised merged tokens and MLP, then a LayerNorm;
    2. ``stage_depth`` self-attention blocks of width ``D`` over the ``q^3`` query tokens; query
       ``n`` is cell ``(i, j, k)`` of the coarse grid with ``n = (i q + j) q + k`` (``i, j, k``
       along x, y, z as in :mod:`lightning_vtr.geometry`);
    3. one :class:`DecoderStage` per entry of ``upsample_channels`` (grid ``q 2^i``, token layout
       from :func:`decoder_stage_layout`);
    4. ``ConvTranspose3d(C_n -> 1, k1, no bias)`` and a sigmoid.

    The paper's decoder (``D = 768``, ``q = 4``, channels 96, 12, 3, 12 heads, one query block,
    two blocks per stage) has 29,798,625 parameters, as the released code. Initialised as the
    released code does: queries ``N(0, 1)``, linear weights ``N(0, 0.01)`` with zero biases,
    convolutions Kaiming-normal, BatchNorm ``1, 0``. Attention dropout is off (the released
    code configures 0.4 but never applies it). Without stage blocks (``stage_depth=0``, not in the paper) the head
    reads the last stage's ReLU output, which is never negative: a head whose weights all have one sign keeps
    every probability on one side of 0.5 where the features are zero, and a small learning rate takes thousands
    of steps to flip a sign, so the head's Kaiming draws get alternating signs.

    Args:
        dim: ``D``, the width of the merged tokens and queries.
        num_heads: attention heads of every block; must divide ``D`` and every stage width.
        query_depth: query blocks (1 in the paper).
        stage_depth: self-attention blocks per stage (2 in the paper).
        query_grid: ``q``.
        upsample_channels: channels of the 2x stages (96, 12, 3 in the paper).
    """

    def __init__(
        self,
        dim: int,
        num_heads: int,
        query_depth: int,
        stage_depth: int,
        query_grid: int,
        upsample_channels: Sequence[int],
    ) -> None:
        super().__init__()
        check_int("query_depth", query_depth, minimum=1)
        check_int("stage_depth", stage_depth, minimum=0)
        self.query_grid = check_int("query_grid", query_grid, minimum=1)
        layout = decoder_stage_layout(query_grid, upsample_channels)
        widths = [dim] + [width for _, _, width in layout]
        if any(width % num_heads for width in widths):
            raise ValueError(
                f"`num_heads` must divide the decoder widths {widths} (`dim` {dim}, then per stage "
                f"`upsample_channels` {list(upsample_channels)} x patch^3), got {num_heads}"
            )
        self.queries = nn.Parameter(torch.empty(1, query_grid**3, dim))
        self.query_blocks = nn.ModuleList(_QueryBlock(dim, num_heads) for _ in range(query_depth))
        self.query_norm = nn.LayerNorm(dim)
        self.coarse_blocks = nn.ModuleList(
            Block(dim, num_heads, qkv_bias=False, norm_eps=1e-5) for _ in range(stage_depth)
        )
        stages, c_in = [], dim
        for channels, (_, patch, _) in zip(upsample_channels, layout):
            stages.append(DecoderStage(c_in, channels, patch, num_heads, stage_depth))
            c_in = channels
        self.stages = nn.ModuleList(stages)
        self.head = VolumeHeadTransposed(c_in)
        self.resolution = query_grid * 2 ** len(upsample_channels)
        self.reset_parameters()
        # the upsampling convolutions in the layout of their inputs (see lightning_vtr.models.layers)
        self.stages.to(memory_format=torch.channels_last_3d)  # type: ignore[call-overload]  # Module.to takes it; stub lacks it

    def reset_parameters(self) -> None:
        """The released code's initialisation (see the class docstring)."""
        nn.init.normal_(self.queries, std=1.0)  # nn.Embedding's default, which the released code keeps
        for m in self.modules():
            if isinstance(m, nn.Linear):
                nn.init.normal_(m.weight, std=0.01)
                if m.bias is not None:
                    nn.init.zeros_(m.bias)
            elif isinstance(m, nn.ConvTranspose3d):
                nn.init.kaiming_normal_(m.weight)
            elif isinstance(m, (nn.BatchNorm3d, nn.LayerNorm)):
                nn.init.ones_(m.weight)
                nn.init.zeros_(m.bias)
        if self.stages and not self.stages[-1].blocks:
            # The head then reads the last stage's ReLU output, >= 0: with weights of one sign it could not move a
            # probability to the other side of 0.5 from where the features are zero, and a small learning rate
            # takes thousands of steps to flip a sign. Alternate the signs of its Kaiming draws.
            with torch.no_grad():
                weight = self.head.weight.view(-1)
                weight.abs_()[1::2].neg_()

    def forward(self, tokens: Tensor) -> Tensor:
        """Merged tokens ``(B, M, D)`` to probabilities ``(B, R, R, R)``."""
        b, d, q = tokens.shape[0], tokens.shape[2], self.query_grid
        x = self.queries.expand(b, -1, -1)
        for block in self.query_blocks:
            x = block(x, tokens)
        x = self.query_norm(x)
        for block in self.coarse_blocks:
            x = block(x)
        x = x.transpose(1, 2).reshape(b, d, q, q, q)
        for stage in self.stages:
            x = stage(x)
        return torch.sigmoid(self.head(x)).squeeze(1)
