"""LRGT, the Long-Range Grouping Transformer (Yang et al., ICCV 2023), as a voxel reconstruction model.

The paper's second reconstruction model, in three parts as published:

1. Encoder: a DeiT-B (distilled) whose class and distillation tokens are dropped at the input
   (``pos_embed[:, 2:]``), so each view is its ``P`` patch tokens (196 at 224 px). Blocks 5, 7, 9
   and 11 (0-based) use *long-range grouping attention*: the patch tokens of each view are split
   by the residue of their row and column modulo a stride (7 at 14x14 tokens: 49 groups of 4
   tokens per view, 7 tokens apart), and each group attends across all the sample's views. An
   *inter-view feature signature*, a depthwise 3x3 convolution of the values laid out on each
   view's patch grid, is added to the attention output so tokens from different views stay
   distinguishable. The other blocks attend within each view.
2. Similar-Token Merger (:mod:`~lightning_vtr.models.lrgt_merger`): two blocks that score the
   ``V * P`` tokens, cluster them by DPC-kNN into 196, merge each cluster weighted by the score
   and let the merged tokens attend to all tokens with the score added to the attention logits.
3. Progressive upsampling decoder (:mod:`~lightning_vtr.models.lrgt_decoder`): ``4^3`` learned
   queries read the merged tokens; transposed convolutions upsample ``4^3 -> 8^3 -> 16^3 ->
   32^3``, each stage followed by transformer blocks; a sigmoid gives occupancy probabilities.

Training minimises the Dice loss of the paper. The ``paper`` preset has 129,802,211 parameters: encoder
85,830,912, merger 14,172,674, decoder 29,798,625. The encoder builds the signature convolution only in the
grouping blocks.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, ClassVar, cast

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from lightning_vtr.models.base import VoxelReconstructionModule, build_adam
from lightning_vtr.models.lrgt_decoder import ProgressiveUpsamplingDecoder, decoder_stage_layout
from lightning_vtr.models.lrgt_merger import SimilarTokenMerger
from lightning_vtr.models.vit import Attention, Block, DistilledVisionTransformer, load_timm_deit
from lightning_vtr.models.weights import fetch_weights, is_restoring_checkpoint
from lightning_vtr.utils.validation import check_choice, check_float, check_int

if TYPE_CHECKING:
    from lightning.pytorch.utilities.parsing import AttributeDict
    from lightning.pytorch.utilities.types import OptimizerLRSchedulerConfig

__all__ = [
    "LRGT",
    "LRGT_PRESETS",
    "LRGTNetwork",
    "LRGTSpec",
    "LongRangeGroupingAttention",
    "ProgressiveUpsamplingDecoder",
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
        num_heads: attention heads of the encoder and of the merger blocks.
        grouping_blocks: 0-based indices of the encoder blocks that use long-range grouping attention.
        group_stride: the grouping's residue stride; it divides the token grid side ``image_size / patch_size``.
        num_merged_tokens: tokens ``M`` each similar-token merger block keeps.
        merger_k: DPC-kNN neighbours of the merger's density (the token itself included).
        merger_depth: similar-token merger blocks.
        decoder_depth: query blocks of the decoder (self-attention, cross-attention to the merged tokens, MLP).
        decoder_stage_depth: self-attention blocks after the queries and after each upsampling stage.
        decoder_heads: attention heads of every decoder block; divides ``D`` and every stage width
            (:func:`~lightning_vtr.models.lrgt_decoder.decoder_stage_layout`).
        query_grid: ``q``: the decoder's ``q^3`` learned queries.
        upsample_channels: channels of the 2x upsampling stages; ``R = q 2^len(upsample_channels)``.

    Raises:
        TypeError: a field of the wrong type (names the field and the value).
        ValueError: a size below its minimum, a grouping block outside ``[0, depth)``, head counts that do not
            divide ``embed_dim`` or the decoder's stage widths, or a one-channel last stage with no stage blocks.

    Example:
        >>> spec = dataclasses.replace(LRGT_PRESETS["tiny"], upsample_channels=[16, 4])
        >>> spec.grid_size, spec.voxel_resolution, spec.upsample_channels
        (8, 16, (16, 4))
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
    merger_depth: int
    decoder_depth: int
    decoder_stage_depth: int
    decoder_heads: int
    query_grid: int
    upsample_channels: tuple[int, ...]

    def __post_init__(self) -> None:
        for name in ("depth", "decoder_stage_depth"):
            check_int(name, getattr(self, name), minimum=0)
        for name in (
            "image_size",
            "patch_size",
            "embed_dim",
            "num_heads",
            "group_stride",
            "num_merged_tokens",
            "merger_k",
            "merger_depth",
            "decoder_depth",
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
        channels = _int_tuple("upsample_channels", self.upsample_channels, minimum=1)
        object.__setattr__(self, "upsample_channels", channels)
        for name in ("num_heads", "decoder_heads"):
            if self.embed_dim % getattr(self, name) != 0:
                raise ValueError(f"`{name}` must divide `embed_dim` {self.embed_dim}, got {getattr(self, name)}")
        if self.decoder_stage_depth == 0 and channels[-1] == 1:
            # No blocks after the last stage's ReLU: a one-channel head would give sigmoid(0) = 0.5 wherever it is 0.
            raise ValueError(
                "`upsample_channels` must end in 2 or more channels when `decoder_stage_depth` is 0: the last "
                "stage ends in a ReLU, and one channel of it cannot give probabilities below 0.5 where it is zero; "
                f"got {list(channels)}"
            )
        widths = [width for _, _, width in decoder_stage_layout(self.query_grid, channels)]
        if any(width % self.decoder_heads for width in widths):
            raise ValueError(
                f"`decoder_heads` must divide the decoder stage widths {widths} (`upsample_channels` "
                f"{list(channels)} x patch^3), got {self.decoder_heads}"
            )

    @property
    def grid_size(self) -> int:
        """Side of each view's patch-token grid (14 for the paper)."""
        return self.image_size // self.patch_size

    @property
    def voxel_resolution(self) -> int:
        """``R`` of the ``(B, R, R, R)`` output: ``query_grid * 2 ** len(upsample_channels)``."""
        return self.query_grid * 2 ** len(self.upsample_channels)


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
        merger_depth=2,
        decoder_depth=1,
        decoder_stage_depth=2,
        decoder_heads=12,
        query_grid=4,
        upsample_channels=(96, 12, 3),
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
        merger_depth=2,
        decoder_depth=1,
        decoder_stage_depth=0,
        decoder_heads=1,
        query_grid=4,
        upsample_channels=(16, 4, 6),
    ),
}
"""The named presets. ``paper``: the published model (DeiT-B distilled, 224 px, 14x14 tokens, 129.8 M
parameters). ``tiny``: the same encoder, merger and query decoder at small widths, 64 px input, sized to train
on a CPU; 8x8 tokens with stride 4 keep groups of 4 tokens per view, and the decoder has one attention head. Its
decoder upsamples the queries with transposed convolutions alone (``decoder_stage_depth=0``, no attention
blocks in the stages). Without blocks after it, the last stage's ReLU output reaches the sigmoid head directly,
so the head's initial weights alternate in sign (see
:class:`~lightning_vtr.models.lrgt_decoder.ProgressiveUpsamplingDecoder`), and the last stage has 6 channels.
Checkpoints record the whole architecture, so a model loads with the architecture it was trained with."""


def _architecture_hparams(spec: LRGTSpec) -> dict[str, object]:
    """The fields of ``spec`` as :class:`LRGT` hyperparameters: the sequences as lists, as a config writes them."""
    return {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(spec).items()}


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

    Tokens are ``(B * V, g^2, D)``: the row-major ``g x g`` patch grid of each view (no class or
    distillation token; LRGT drops them at the input), the ``V`` views of a sample contiguous.
    Patch ``(r, c)`` belongs to group ``(r mod s, c mod s)``: ``s^2`` groups of ``(g / s)^2``
    tokens per view, and each group attends over its tokens of all ``V`` views (``V (g/s)^2``
    tokens). With one view the groups are those of the single view; adding views widens them.

    The signature ``S = DWConv3x3(values on each view's g x g grid)`` is added to the attention
    output before the output projection. It is initialised to zero so a pretrained DeiT block
    starts out computing exactly grouped attention (the released code keeps PyTorch's default
    convolution initialisation there).

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
        nn.init.zeros_(cast(Tensor, self.signature.bias))  # a Conv2d with bias

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
        if t != self.grid_size**2 or bv % num_views != 0:
            raise ValueError(
                f"`x` must be (B * {num_views}, {self.grid_size**2}, D) patch tokens, got {tuple(x.shape)}"
            )
        q, k, v = self.split_heads(x)
        # 1. attention inside each residue group, across views.
        qg, kg, vg = (self._to_groups(z, num_views) for z in (q, k, v))
        groups = F.scaled_dot_product_attention(qg, kg, vg)
        out = self.merge_heads(self._from_groups(groups, num_views))
        # 2. inter-view feature signature from each view's value map.
        g = self.grid_size
        values = self.merge_heads(v).transpose(1, 2).reshape(bv, dim, g, g)
        return self.proj(out + self.signature(values).flatten(2).transpose(1, 2))


class LRGTNetwork(nn.Module):
    """The whole LRGT network: images ``(B, V, 3, H, W)`` to probabilities ``(B, R, R, R)``.

    ``encoder`` (DeiT with grouping attention, prefix tokens dropped) -> ``merger``
    (:class:`~lightning_vtr.models.lrgt_merger.SimilarTokenMerger`) -> ``decoder``
    (:class:`~lightning_vtr.models.lrgt_decoder.ProgressiveUpsamplingDecoder`). Works with any
    ``V >= 1``; the prediction does not depend on the order of the views (grouping attention, the
    merger and the decoder are all permutation-invariant over views, up to ties in the clustering).

    Args:
        spec: the architecture, e.g. a preset of :data:`LRGT_PRESETS`.

    Attributes:
        spec: the :class:`LRGTSpec` of the network.
        image_size: input side ``H = W`` in pixels.
        voxel_resolution: ``R`` of the output.

    Raises:
        TypeError: if ``spec`` is not an :class:`LRGTSpec`.

    Example:
        >>> net = LRGTNetwork(LRGT_PRESETS["tiny"])
        >>> net(torch.zeros(2, 3, 3, 64, 64)).shape
        torch.Size([2, 32, 32, 32])
    """

    def __init__(self, spec: LRGTSpec) -> None:
        super().__init__()
        if not isinstance(spec, LRGTSpec):
            raise TypeError(f"`spec` must be an LRGTSpec, got {type(spec).__name__} {spec!r}")
        self.spec = spec
        self.encoder = DistilledVisionTransformer(
            spec.image_size, spec.patch_size, spec.embed_dim, spec.depth, spec.num_heads, use_prefix_tokens=False
        )
        self.grouping_blocks = spec.grouping_blocks
        for i in self.grouping_blocks:
            block = cast(Block, self.encoder.blocks[i])
            old = block.attn
            new = LongRangeGroupingAttention(spec.embed_dim, spec.num_heads, self.encoder.grid_size, spec.group_stride)
            # Keep the block's (possibly pretrained) qkv/proj; only the signature conv is new.
            new.qkv, new.proj = old.qkv, old.proj
            block.attn = new
        self.merger = SimilarTokenMerger(
            spec.embed_dim, spec.num_heads, spec.num_merged_tokens, spec.merger_k, spec.merger_depth
        )
        self.decoder = ProgressiveUpsamplingDecoder(
            spec.embed_dim,
            spec.decoder_heads,
            spec.decoder_depth,
            spec.decoder_stage_depth,
            spec.query_grid,
            spec.upsample_channels,
        )
        self.image_size = spec.image_size
        self.voxel_resolution = self.decoder.resolution

    def load_pretrained_encoder(self, path_or_state_dict) -> None:
        """Load a timm-format DeiT (distilled) checkpoint into the encoder (see :func:`load_timm_deit`).

        The checkpoint's ``cls_token``, ``dist_token`` and full ``pos_embed`` load as they are; the
        forward uses only the patch rows of ``pos_embed``.
        """
        load_timm_deit(self.encoder, path_or_state_dict, allow_missing=(".attn.signature.",))

    def encode(self, images: Tensor) -> Tensor:
        """Images ``(B, V, 3, H, W)`` to all views' patch tokens ``(B, V * P, D)``, view by view."""
        b, v = images.shape[:2]
        tokens = self.encoder(images.flatten(0, 1), num_views=v)  # (B * V, P, D)
        return tokens.reshape(b, v * tokens.shape[1], tokens.shape[2])

    def forward(self, images: Tensor) -> Tensor:
        # 1. check inputs
        if images.ndim != 5 or images.shape[2] != 3:
            raise ValueError(f"`images` must be (B, V, 3, H, W), got {tuple(images.shape)}")
        # 2. encode: (B, V * P, D); 3. merge: (B, M, D); 4. decode: (B, R, R, R)
        return self.decoder(self.merger(self.encode(images)))


class LRGT(VoxelReconstructionModule):
    """LRGT as a LightningModule satisfying :class:`~lightning_vtr.protocol.ReconstructionModel`.

    ``preset`` picks an architecture from :data:`LRGT_PRESETS` (``"paper"``: the published model,
    DeiT-B encoder, 224 px input, 129.8 M parameters; ``"tiny"``: its encoder, merger and query decoder at
    small widths with a decoder that upsamples without attention, 64 px input, 0.46 M parameters, trains on a
    CPU); any architecture argument left at
    ``None`` takes the preset's value. The resolved
    architecture is :attr:`spec`, an :class:`LRGTSpec`. Training
    minimises :func:`dice_loss` with AdamW and a MultiStepLR schedule (milestones in epochs),
    as published. Any number of views works at train and test time.

    Args:
        preset: ``"paper"`` or ``"tiny"``.
        num_views: views per training sample (the protocol's ``num_views``; 3 in the paper).
        image_size: architecture override of :class:`LRGTSpec`'s field; ``None`` keeps the preset's.
        patch_size: architecture override of :class:`LRGTSpec`'s field; ``None`` keeps the preset's.
        embed_dim: architecture override of :class:`LRGTSpec`'s field; ``None`` keeps the preset's.
        depth: architecture override of :class:`LRGTSpec`'s field; ``None`` keeps the preset's.
        num_heads: architecture override of :class:`LRGTSpec`'s field; ``None`` keeps the preset's.
        grouping_blocks: architecture override of :class:`LRGTSpec`'s field (0-based block indices); ``None``
            keeps the preset's.
        group_stride: architecture override of :class:`LRGTSpec`'s field; ``None`` keeps the preset's.
        num_merged_tokens: architecture override of :class:`LRGTSpec`'s field; ``None`` keeps the preset's.
        merger_k: architecture override of :class:`LRGTSpec`'s field; ``None`` keeps the preset's.
        merger_depth: architecture override of :class:`LRGTSpec`'s field; ``None`` keeps the preset's.
        decoder_depth: architecture override of :class:`LRGTSpec`'s field; ``None`` keeps the preset's.
        decoder_stage_depth: architecture override of :class:`LRGTSpec`'s field; ``None`` keeps the preset's.
        decoder_heads: architecture override of :class:`LRGTSpec`'s field; ``None`` keeps the preset's.
        query_grid: architecture override of :class:`LRGTSpec`'s field; ``None`` keeps the preset's.
        upsample_channels: architecture override of :class:`LRGTSpec`'s field; ``None`` keeps the preset's.
        pretrained_encoder: timm-format DeiT (distilled) weights loaded into the encoder at construction
            (see :func:`~lightning_vtr.models.vit.load_timm_deit`): a local file, a URL (downloaded once into
            torch.hub's cache) or ``"imagenet"`` (DeiT-B distilled 224, :data:`~lightning_vtr.models.weights.
            IMAGENET_WEIGHTS`); ``None`` keeps the random initialisation. Not re-read when a checkpoint is
            loaded (:meth:`load_from_checkpoint`), so checkpoints load where the file is absent.
        lr: AdamW learning rate (1e-4 published).
        weight_decay: AdamW weight decay (torch's default; the paper does not state one).
        milestones: epochs at which the learning rate is multiplied by ``gamma`` ([60, 90], 0.1).
        gamma: the decay factor.
        validation_fscore: as in :class:`~lightning_vtr.models.base.VoxelReconstructionModule`.
        categories: as in :class:`~lightning_vtr.models.base.VoxelReconstructionModule`.
        log_sheets: as in :class:`~lightning_vtr.models.base.VoxelReconstructionModule`.

    Attributes:
        spec: the resolved architecture (the preset with the overrides applied).

    Raises:
        TypeError: an architecture field or size of the wrong type (see :class:`LRGTSpec`).
        ValueError: an unknown ``preset``, an architecture that does not fit together (see :class:`LRGTSpec`), or
            a ``lr`` that is not positive.
        FileNotFoundError: ``pretrained_encoder`` is neither a URL nor an existing file.
        WeightsDownloadError: ``pretrained_encoder`` is a URL that cannot be downloaded.
        KeyError: the ``pretrained_encoder`` checkpoint's keys do not match the encoder (see
            :func:`~lightning_vtr.models.vit.load_timm_deit`).

    Example::

        model = LRGT(preset="tiny")
        probs = model.predict_voxels(torch.randn(2, 3, 3, 64, 64))  # (2, 32, 32, 32)
    """

    image_recipe: ClassVar[str] = "lrgt"

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
        merger_depth: int | None = None,
        decoder_depth: int | None = None,
        decoder_stage_depth: int | None = None,
        decoder_heads: int | None = None,
        query_grid: int | None = None,
        upsample_channels: list[int] | None = None,
        pretrained_encoder: str | None = None,
        lr: float = 1e-4,
        weight_decay: float = 0.01,
        milestones: list[int] | None = None,
        gamma: float = 0.1,
        validation_fscore: bool = True,
        log_sheets: int = 0,
        categories: list[str] | None = None,
    ) -> None:
        check_choice("preset", preset, LRGT_PRESETS)
        arguments = locals()
        overrides = {f.name: arguments[f.name] for f in dataclasses.fields(LRGTSpec) if arguments[f.name] is not None}
        spec = dataclasses.replace(LRGT_PRESETS[preset], **overrides)
        network = LRGTNetwork(spec)
        super().__init__(
            image_size=spec.image_size,
            num_views=num_views,
            voxel_resolution=spec.voxel_resolution,
            validation_fscore=validation_fscore,
            categories=categories,
            log_sheets=log_sheets,
        )
        check_float("lr", lr, minimum=0.0, min_open=True)
        self.save_hyperparameters()
        # Record the resolved architecture in place of the `None` overrides: the checkpoint then describes it
        # fully, and the DataModule's `image_size` hparam agrees with ours when Lightning merges the two for logging.
        self.save_hyperparameters({**self.hparams, **_architecture_hparams(spec)})
        self.spec = spec
        self.network = network
        # A checkpoint being restored holds the encoder's weights: the file need not exist on this machine.
        if pretrained_encoder is not None and not is_restoring_checkpoint():
            self.network.load_pretrained_encoder(fetch_weights(pretrained_encoder, kind="deit_base_distilled"))

    def reconstruct(self, images: Tensor) -> dict[str, Tensor]:
        """``{"voxels": (B, R, R, R)}`` probabilities for images ``(B, V, 3, H, W)``."""
        return {"voxels": self.network(images)}

    def loss(self, outputs: dict[str, Tensor], target: Tensor) -> Tensor:
        """:func:`dice_loss` of the probabilities, in float32 with autocast off.

        Under ``precision="bf16-mixed"`` / ``"16-mixed"`` the network's output may be half precision; sums over the
        ``R^3`` voxels in it would lose the loss's digits (bfloat16 keeps 8 bits), so probabilities and target are
        cast to float32 first, as :meth:`Pix2VoxPlusPlus.loss <lightning_vtr.models.Pix2VoxPlusPlus.loss>` does.
        """
        probs = outputs["voxels"]
        with torch.autocast(device_type=probs.device.type, enabled=False):
            return dice_loss(probs.float(), target.float())

    def configure_optimizers(self) -> OptimizerLRSchedulerConfig:
        hp = cast("AttributeDict", self.hparams)
        optimizer = build_adam(torch.optim.AdamW, self.parameters(), lr=hp.lr, weight_decay=hp.weight_decay)
        milestones = list(hp.milestones) if hp.milestones is not None else [60, 90]
        scheduler = torch.optim.lr_scheduler.MultiStepLR(optimizer, milestones=milestones, gamma=hp.gamma)
        return {"optimizer": optimizer, "lr_scheduler": {"scheduler": scheduler, "interval": "epoch"}}
