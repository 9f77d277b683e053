"""A DeiT-style (distilled) Vision Transformer and its layers in plain torch, loadable from timm checkpoints.

LRGT's encoder, written in plain torch (timm is not a dependency). Module and
parameter names match timm's ``deit_base_distilled_patch16_224`` (``patch_embed.proj``,
``cls_token``, ``dist_token``, ``pos_embed``, ``blocks.N.{norm1,attn.qkv,attn.proj,norm2,
mlp.fc1,mlp.fc2}``, ``norm``), so :func:`load_timm_deit` can copy a timm state dict key for key.
The classification heads (``head``, ``head_dist``) are not built: the reconstruction models
only use the token features.

Every block takes ``num_views`` next to its tokens. A plain :class:`Attention` ignores it;
LRGT swaps some blocks' attention for one that groups tokens across the views of a sample,
keeping the ``qkv``/``proj`` names so pretrained weights still land in them. LRGT's merger and
decoder reuse :class:`Attention`, :class:`CrossAttention`, :class:`Mlp` and :class:`Block`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from lightning_vtr.utils.validation import check_int

__all__ = [
    "Attention",
    "Block",
    "CrossAttention",
    "DistilledVisionTransformer",
    "Mlp",
    "PatchEmbed",
    "load_timm_deit",
]

# timm keys that belong to the classifier, which we never build.
_HEAD_PREFIXES = ("head.", "head_dist.", "fc_norm.")


class PatchEmbed(nn.Module):
    """Non-overlapping ``patch_size`` patches to ``embed_dim`` tokens: ``(N, 3, H, W) -> (N, H/p * W/p, D)``."""

    def __init__(self, image_size: int, patch_size: int, in_chans: int, embed_dim: int) -> None:
        super().__init__()
        check_int("image_size", image_size, minimum=1)
        check_int("patch_size", patch_size, minimum=1)
        if image_size % patch_size != 0:
            raise ValueError(f"`image_size` must be a multiple of `patch_size` {patch_size}, got {image_size}")
        self.image_size = image_size
        self.patch_size = patch_size
        self.grid_size = image_size // patch_size
        self.proj = nn.Conv2d(in_chans, embed_dim, kernel_size=patch_size, stride=patch_size)

    def forward(self, images: Tensor) -> Tensor:
        if images.shape[-2:] != (self.image_size, self.image_size):
            raise ValueError(f"`images` must be {self.image_size}x{self.image_size}, got {tuple(images.shape[-2:])}")
        return self.proj(images).flatten(2).transpose(1, 2)


def _head_dim(dim: int, num_heads: int) -> int:
    """Width of one head; ``dim`` and ``num_heads`` checked (positive ints, ``num_heads`` dividing ``dim``)."""
    check_int("dim", dim, minimum=1)
    check_int("num_heads", num_heads, minimum=1)
    if dim % num_heads != 0:
        raise ValueError(f"`dim` must be divisible by `num_heads` {num_heads}, got {dim}")
    return dim // num_heads


class Attention(nn.Module):
    """Multi-head self-attention over each sequence separately: ``(N, T, D) -> (N, T, D)``."""

    def __init__(self, dim: int, num_heads: int, qkv_bias: bool = True) -> None:
        super().__init__()
        self.num_heads, self.head_dim = num_heads, _head_dim(dim, num_heads)
        self.qkv = nn.Linear(dim, 3 * dim, bias=qkv_bias)
        self.proj = nn.Linear(dim, dim)

    def split_heads(self, x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """``(N, T, D)`` tokens to q, k, v of shape ``(N, heads, T, head_dim)`` each."""
        n, t, _ = x.shape
        qkv = self.qkv(x).reshape(n, t, 3, self.num_heads, self.head_dim).permute(2, 0, 3, 1, 4)
        # unbind: one gradient buffer in backward (indexing qkv[i] three times zero-fills three)
        q, k, v = qkv.unbind(0)
        return q, k, v

    @staticmethod
    def merge_heads(x: Tensor) -> Tensor:
        """``(N, heads, T, head_dim) -> (N, T, heads * head_dim)``."""
        n, h, t, d = x.shape
        return x.transpose(1, 2).reshape(n, t, h * d)

    def forward(self, x: Tensor, num_views: int = 1) -> Tensor:
        q, k, v = self.split_heads(x)
        return self.proj(self.merge_heads(F.scaled_dot_product_attention(q, k, v)))


class CrossAttention(nn.Module):
    """Multi-head attention of queries ``(N, Q, D)`` to a memory ``(N, T, D)``, with an optional logit bias.

    ``softmax(q k^T / sqrt(head_dim) + logit_bias) v`` per head, then the output projection. The
    queries come from ``q``, the keys and values from ``kv`` (one linear, keys first).

    Args:
        dim: token width ``D`` of queries and memory.
        num_heads: attention heads; must divide ``dim``.
        qkv_bias: whether ``q`` and ``kv`` have biases (LRGT's merger and decoder have none).
    """

    def __init__(self, dim: int, num_heads: int, qkv_bias: bool = True) -> None:
        super().__init__()
        self.num_heads, self.head_dim = num_heads, _head_dim(dim, num_heads)
        self.q = nn.Linear(dim, dim, bias=qkv_bias)
        self.kv = nn.Linear(dim, 2 * dim, bias=qkv_bias)
        self.proj = nn.Linear(dim, dim)

    def forward(self, x: Tensor, memory: Tensor, logit_bias: Tensor | None = None) -> Tensor:
        """``(N, Q, D)`` queries attend to ``(N, T, D)``; ``logit_bias`` broadcasts to ``(N, heads, Q, T)``."""
        n, nq, _ = x.shape
        h, d = self.num_heads, self.head_dim
        q = self.q(x).reshape(n, nq, h, d).transpose(1, 2)
        k, v = self.kv(memory).reshape(n, memory.shape[1], 2, h, d).permute(2, 0, 3, 1, 4).unbind(0)
        if logit_bias is None:
            out = F.scaled_dot_product_attention(q, k, v)
        else:
            # Written out: with a bias that needs a gradient, scaled_dot_product_attention takes its reference
            # path, which computes the same but is slower on the CPU (materialises the bias, checks every row).
            logits = torch.matmul(q, k.transpose(-2, -1)) * (1.0 / math.sqrt(d)) + logit_bias.to(q.dtype)
            out = torch.matmul(logits.softmax(dim=-1), v)
        return self.proj(Attention.merge_heads(out))


class Mlp(nn.Module):
    """Two-layer GELU MLP, ``(..., D) -> (..., D)``."""

    def __init__(self, dim: int, hidden_dim: int) -> None:
        super().__init__()
        self.fc1 = nn.Linear(dim, hidden_dim)
        self.act = nn.GELU()
        self.fc2 = nn.Linear(hidden_dim, dim)

    def forward(self, x: Tensor) -> Tensor:
        return self.fc2(self.act(self.fc1(x)))


class Block(nn.Module):
    """Pre-norm transformer block. ``x`` is ``(B * V, T, D)``, views of a sample contiguous.

    ``norm_eps`` defaults to 1e-6, what DeiT was trained with (the torch default 1e-5 shifts
    pretrained features); LRGT's decoder blocks use 1e-5.
    """

    def __init__(
        self, dim: int, num_heads: int, mlp_ratio: float = 4.0, qkv_bias: bool = True, norm_eps: float = 1e-6
    ) -> None:
        super().__init__()
        self.norm1 = nn.LayerNorm(dim, eps=norm_eps)
        self.attn: Attention = Attention(dim, num_heads, qkv_bias)
        self.norm2 = nn.LayerNorm(dim, eps=norm_eps)
        self.mlp = Mlp(dim, int(dim * mlp_ratio))

    def forward(self, x: Tensor, num_views: int = 1) -> Tensor:
        x = x + self.attn(self.norm1(x), num_views)
        return x + self.mlp(self.norm2(x))


class DistilledVisionTransformer(nn.Module):
    """DeiT (distilled) ViT trunk: images ``(N, 3, H, W)`` to normalised tokens ``(N, 2 + P, D)`` or ``(N, P, D)``.

    Token order is ``[cls, dist, patch_0, ..., patch_{P-1}]`` with patches row-major over the
    ``grid_size x grid_size`` patch grid (``P = grid_size^2``), as in timm.

    With ``use_prefix_tokens=False`` (LRGT's encoder) the class and distillation tokens are dropped
    at the input: the blocks see only the ``P`` patch tokens plus ``pos_embed[:, 2:]``. The
    ``cls_token``, ``dist_token`` and the prefix rows of ``pos_embed`` then stay in the state dict,
    so a timm checkpoint still loads key for key, but take no part in the forward; the two tokens
    are frozen (``requires_grad=False``) so distributed training does not find unused parameters.

    Args:
        image_size: square input size in pixels; ``pos_embed`` is built for it.
        patch_size: patch side in pixels.
        embed_dim: token width ``D``.
        depth: number of blocks.
        num_heads: attention heads per block.
        mlp_ratio: MLP hidden width as a multiple of ``D``.
        in_chans: input channels.
        use_prefix_tokens: whether the cls/dist tokens enter the blocks (timm's DeiT) or not (LRGT).

    The defaults are DeiT-B (86 M parameters without the heads).

    Raises:
        TypeError: ``use_prefix_tokens`` is not a bool, or ``image_size``, ``patch_size`` or ``embed_dim`` is
            not an int.
        ValueError: ``image_size`` is not a multiple of ``patch_size``, or ``num_heads`` does not divide
            ``embed_dim``; on call, images of another size than ``image_size``.

    Example:
        >>> vit = DistilledVisionTransformer(image_size=32, patch_size=8, embed_dim=32, depth=1, num_heads=2)
        >>> vit(torch.zeros(2, 3, 32, 32)).shape  # cls, dist and 4 x 4 patch tokens
        torch.Size([2, 18, 32])
    """

    #: cls and dist: the rows of ``pos_embed`` (and of a timm checkpoint) before the patch grid.
    num_prefix_tokens = 2

    def __init__(
        self,
        image_size: int = 224,
        patch_size: int = 16,
        embed_dim: int = 768,
        depth: int = 12,
        num_heads: int = 12,
        mlp_ratio: float = 4.0,
        in_chans: int = 3,
        use_prefix_tokens: bool = True,
    ) -> None:
        super().__init__()
        if not isinstance(use_prefix_tokens, bool):
            raise TypeError(
                f"`use_prefix_tokens` must be a bool, got {type(use_prefix_tokens).__name__} {use_prefix_tokens!r}"
            )
        self.embed_dim = embed_dim
        self.use_prefix_tokens = use_prefix_tokens
        self.patch_embed = PatchEmbed(image_size, patch_size, in_chans, embed_dim)
        self.grid_size = self.patch_embed.grid_size
        num_patches = self.grid_size**2
        self.cls_token = nn.Parameter(torch.zeros(1, 1, embed_dim), requires_grad=use_prefix_tokens)
        self.dist_token = nn.Parameter(torch.zeros(1, 1, embed_dim), requires_grad=use_prefix_tokens)
        self.pos_embed = nn.Parameter(torch.zeros(1, num_patches + self.num_prefix_tokens, embed_dim))
        self.blocks = nn.ModuleList(Block(embed_dim, num_heads, mlp_ratio) for _ in range(depth))
        self.norm = nn.LayerNorm(embed_dim, eps=1e-6)
        self.reset_parameters()

    @property
    def num_output_prefix_tokens(self) -> int:
        """Prefix tokens before the patches in the output: 2 (cls, dist), or 0 without prefix tokens."""
        return self.num_prefix_tokens if self.use_prefix_tokens else 0

    def reset_parameters(self) -> None:
        """timm's DeiT initialisation: truncated normal (std 0.02) for tokens and linears."""
        for p in (self.cls_token, self.dist_token, self.pos_embed):
            nn.init.trunc_normal_(p, std=0.02)
        for m in self.modules():
            if isinstance(m, nn.Linear):
                nn.init.trunc_normal_(m.weight, std=0.02)
                if m.bias is not None:
                    nn.init.zeros_(m.bias)
            elif isinstance(m, nn.LayerNorm):
                nn.init.ones_(m.weight)
                nn.init.zeros_(m.bias)

    def embed(self, images: Tensor) -> Tensor:
        """Patch tokens (after the prefix tokens, if used) plus position embedding.

        ``(N, 3, H, W) -> (N, 2 + P, D)``, or ``(N, P, D)`` with ``use_prefix_tokens=False``.
        """
        x = self.patch_embed(images)
        if not self.use_prefix_tokens:
            return x + self.pos_embed[:, self.num_prefix_tokens :]
        n = x.shape[0]
        prefix = torch.cat([self.cls_token.expand(n, -1, -1), self.dist_token.expand(n, -1, -1)], dim=1)
        return torch.cat([prefix, x], dim=1) + self.pos_embed

    def forward(self, images: Tensor, num_views: int = 1) -> Tensor:
        """Tokens ``(N, 2 + P, D)`` (or ``(N, P, D)`` without prefix tokens) for images ``(N, 3, H, W)``.

        ``num_views`` tells the blocks that ``N = B * num_views`` with each sample's views
        contiguous; plain attention blocks ignore it.
        """
        x = self.embed(images)
        for block in self.blocks:
            x = block(x, num_views)
        return self.norm(x)


def resize_pos_embed(pos_embed: Tensor, grid_size: int, num_prefix_tokens: int = 2) -> Tensor:
    """Bicubically resize the patch part of a ``(1, prefix + g^2, D)`` position embedding to ``grid_size^2``.

    The prefix (cls, dist) embeddings are kept as they are. The old grid is read as square.
    """
    prefix, grid = pos_embed[:, :num_prefix_tokens], pos_embed[:, num_prefix_tokens:]
    old = math.isqrt(grid.shape[1])
    if old * old != grid.shape[1]:
        raise ValueError(f"`pos_embed` must hold a square grid of patch positions, got {grid.shape[1]}")
    if old == grid_size:
        return pos_embed
    d = grid.shape[-1]
    grid = grid.reshape(1, old, old, d).permute(0, 3, 1, 2).float()
    grid = F.interpolate(grid, size=(grid_size, grid_size), mode="bicubic", align_corners=False)
    grid = grid.permute(0, 2, 3, 1).reshape(1, grid_size * grid_size, d).to(pos_embed.dtype)
    return torch.cat([prefix, grid], dim=1)


def _read_state_dict(source: str | Path | Mapping[str, Tensor]) -> dict[str, Tensor]:
    if isinstance(source, Mapping):
        state = dict(source)
    else:
        path = Path(source)
        if not path.is_file():
            raise FileNotFoundError(f"DeiT checkpoint {str(path)!r} does not exist or is not a file")
        if path.suffix == ".safetensors":
            try:
                from safetensors.torch import load_file
            except ImportError as err:  # pragma: no cover - depends on the environment
                raise ImportError(f"reading {path} needs the 'safetensors' package") from err
            state = load_file(str(path))
        else:
            state = torch.load(path, map_location="cpu", weights_only=True)
    # The official DeiT release wraps the weights as {"model": ...}; Lightning-style files use "state_dict".
    for wrapper in ("model", "state_dict"):
        if wrapper in state and isinstance(state[wrapper], Mapping):
            state = dict(state[wrapper])
    return state


def load_timm_deit(
    module: DistilledVisionTransformer,
    path_or_state_dict: str | Path | Mapping[str, Tensor],
    allow_missing: Sequence[str] = (),
) -> None:
    """Copy a timm-format DeiT (distilled) state dict into ``module`` in place.

    Args:
        module: the encoder to fill.
        path_or_state_dict: a local ``.pth``/``.pt`` (``torch.save`` of a state dict, optionally
            wrapped as ``{"model": ...}``), a ``.safetensors`` file, or a state dict.
        allow_missing: substrings of ``module`` parameter names that may be absent from the
            checkpoint and keep their initial values (LRGT's inter-view signature convs).

    ``head.*`` and ``head_dist.*`` are ignored. If ``module`` was built for another image size
    than the checkpoint (same patch size), ``pos_embed``'s patch grid is resized bicubically
    (``align_corners=False``) and the cls/dist embeddings are kept, as timm does when it
    adapts a checkpoint to a new resolution.

    Raises:
        FileNotFoundError: ``path_or_state_dict`` is a path that is not a file.
        KeyError: a parameter of ``module`` is missing from the checkpoint (and not allowed to be),
            or the checkpoint has a key that ``module`` does not.
        ValueError: a tensor's shape differs from the parameter it should fill, or the checkpoint's
            ``pos_embed`` does not hold a square patch grid.

    Example:
        >>> source = DistilledVisionTransformer(32, 8, 32, depth=1, num_heads=2)  # a 4 x 4 patch grid
        >>> target = DistilledVisionTransformer(64, 8, 32, depth=1, num_heads=2)  # an 8 x 8 patch grid
        >>> load_timm_deit(target, source.state_dict())  # pos_embed resized to the 8 x 8 grid
        >>> target.pos_embed.shape
        torch.Size([1, 66, 32])
    """
    state = {k: v for k, v in _read_state_dict(path_or_state_dict).items() if not k.startswith(_HEAD_PREFIXES)}
    if "pos_embed" in state:
        state["pos_embed"] = resize_pos_embed(state["pos_embed"], module.grid_size, module.num_prefix_tokens)
    own = module.state_dict()
    missing = [k for k in own if k not in state and not any(s in k for s in allow_missing)]
    unexpected = [k for k in state if k not in own]
    if missing or unexpected:
        raise KeyError(
            "DeiT checkpoint does not match the encoder: "
            f"missing {missing[:8]}{' ...' if len(missing) > 8 else ''} ({len(missing)} keys), "
            f"unexpected {unexpected[:8]}{' ...' if len(unexpected) > 8 else ''} ({len(unexpected)} keys)"
        )
    mismatched = [
        f"{k}: expected {tuple(own[k].shape)}, got {tuple(v.shape)}"
        for k, v in state.items()
        if v.shape != own[k].shape
    ]
    if mismatched:
        raise ValueError("DeiT checkpoint shapes do not match the encoder: " + "; ".join(mismatched))
    module.load_state_dict(state, strict=False)
