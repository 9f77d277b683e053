"""CUDA autocast's casting rules, applied on the CPU: :func:`cuda_autocast_rules`.

CPU autocast (``torch.autocast("cpu")``, what ``precision="bf16-mixed"`` uses on a CPU) casts a different set of
ops than CUDA autocast: on a CUDA device ``torch.exp``, ``softmax``, ``layer_norm`` or ``sum`` of a bfloat16 tensor
return float32, on a CPU they stay bfloat16. Code that mixes those results with half-precision tensors in an op
that does not promote (an in-place ``index_add_``, ``copy`` into a preallocated buffer, ...) therefore fails on a
GPU only. :class:`CudaAutocastRules` reproduces CUDA's rules on CPU tensors so a CPU test sees those failures.

The op lists are CUDA autocast's, as registered for the CUDA autocast dispatch key in PyTorch's
``aten/src/ATen/autocast_mode.h`` (the ``AT_FORALL_LOWER_PRECISION_FP``, ``AT_FORALL_FP32``,
``AT_FORALL_FP32_SET_OPT_DTYPE``, ``AT_FORALL_DIFFERENT_REDISPATCH_SIGNATURE`` and ``AT_FORALL_PROMOTE`` macros of
torch 2.13, shipped in the wheel's ``torch/include``) and documented in PyTorch's AMP page, section "Autocast Op
Reference": "CUDA Ops that can autocast to float16", "CUDA Ops that can autocast to float32" and "CUDA Ops that
promote to the widest input type". Each aten op is matched through the Python callables that reach it
(``torch.exp``, ``Tensor.exp``, ``F.layer_norm``, ...):

- lower precision (:data:`LOWER_PRECISION_OPS`): ``linear``, ``matmul``/``@``, ``mm``, ``mv``, ``bmm``,
  ``baddbmm``, ``addbmm``, ``addmm``, ``addmv``, ``addr``, ``einsum``, ``chain_matmul``, ``linalg.multi_dot``,
  ``linalg.vecdot``, ``conv1d/2d/3d``, ``conv_transpose1d/2d/3d``, ``convolution``, ``conv_tbc``, ``prelu``,
  ``scaled_dot_product_attention``, the RNN cells: every floating-point (not float64) tensor argument is cast to
  the autocast dtype.
- float32 (:data:`FLOAT32_OPS`): ``acos``, ``asin``, ``cosh``, ``erfinv``, ``exp``, ``expm1``, ``log``,
  ``log10``, ``log2``, ``log1p``, ``reciprocal``, ``rsqrt``, ``sinh``, ``tan``, ``pow`` (and ``**``, the
  reflected ``**`` and ``/``), ``softplus``, ``layer_norm``, ``rms_norm``, ``group_norm``, ``norm``,
  ``nuclear_norm``, ``normalize``, ``cosine_similarity``, the losses (``nll_loss``, ``cross_entropy``,
  ``mse_loss``, ``l1_loss``, ``smooth_l1_loss``, ``huber_loss``, ``kl_div``,
  ``binary_cross_entropy_with_logits``, ...), ``dist``, ``pdist``, ``cdist``, ``renorm``, ``logsumexp`` and the
  upsampling of ``F.interpolate`` (every mode but ``"area"``): every floating-point (not float64) tensor argument
  is cast to float32.
- float32 unless a ``dtype`` is given (:data:`FLOAT32_DTYPE_OPS`): ``softmax``, ``log_softmax``, ``sum``,
  ``prod``, ``cumsum``, ``cumprod``, ``linalg.vector_norm``, ``linalg.matrix_norm``: when the first argument is an
  eligible tensor and no ``dtype`` keyword is passed, ``dtype=torch.float32`` is added.
- widest input type (:data:`PROMOTE_OPS`): ``addcdiv``, ``addcmul``, ``atan2``, ``bilinear``, ``cross``,
  ``dot``, ``vdot``, ``grid_sample``, ``index_put``, ``tensordot``, ``scatter_add``: float32 if any eligible
  argument is float32, else the autocast dtype.
- refused: ``binary_cross_entropy`` raises, as CUDA autocast does.

Everything else runs on its inputs unchanged (an op for which the CPU has no half-precision kernel, say
``avg_pool3d`` in bfloat16, runs in float32 and returns its result in the half type, as CUDA's kernel would), as under CUDA autocast: in-place ops (``index_add_``,
``scatter_add_``, ``copy_``, ``x[i] = v``), ops with an explicit ``out=``, and unlisted ops (``cat``, ``add``,
``mean``, ``sigmoid``, ...), whose own type promotion or dtype checks apply. Tensors of other devices and float64
tensors are never cast.

Limits: an op is matched where Python code calls it. The body of a Python-level composite that is on no list (for
example ``F.multi_head_attention_forward``) runs without the rules, whereas CUDA autocast would cast the aten ops
inside it. The rules apply while CPU autocast is enabled (``torch.is_autocast_enabled("cpu")``), so a region of
``torch.autocast("cpu", enabled=False)`` (what the code does to compute in float32) turns them off as
``torch.autocast("cuda", enabled=False)`` does on a GPU; CPU autocast's own op lists never apply inside the mode.

Example:
    >>> x = torch.randn(4, 8, dtype=torch.bfloat16)
    >>> with cuda_autocast_rules(torch.bfloat16):
    ...     torch.exp(x).dtype, F.linear(x.float(), torch.randn(3, 8)).dtype
    (torch.float32, torch.bfloat16)
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor
from torch.overrides import TorchFunctionMode
from torch.utils._pytree import tree_leaves, tree_map

__all__ = [
    "FLOAT32_DTYPE_OPS",
    "FLOAT32_OPS",
    "LOWER_PRECISION_OPS",
    "PROMOTE_OPS",
    "CudaAutocastRules",
    "cuda_autocast_rules",
]


def _callables(*names: str) -> frozenset[Callable[..., Any]]:
    """The callables named ``"torch.x"``, ``"Tensor.x"``, ``"F.x"``, ``"linalg.x"``, ``"special.x"``,
    ``"_nn.x"`` that exist in this torch (a name missing from it is skipped)."""
    roots = {
        "torch": torch,
        "Tensor": torch.Tensor,
        "F": F,
        "linalg": torch.linalg,
        "special": torch.special,
        "_nn": torch._C._nn,
    }
    found = []
    for name in names:
        root, _, attr = name.partition(".")
        obj = getattr(roots[root], attr, None)
        if obj is not None:
            found.append(obj)
    return frozenset(found)


def _everywhere(*ops: str) -> tuple[str, ...]:
    """``torch.op`` and ``Tensor.op`` for each op."""
    return tuple(f"{root}.{op}" for op in ops for root in ("torch", "Tensor"))


#: CUDA's "autocast to float16" list (AT_FORALL_LOWER_PRECISION_FP): inputs cast to the autocast dtype.
LOWER_PRECISION_OPS = _callables(
    *_everywhere("matmul", "mm", "mv", "bmm", "baddbmm", "addbmm", "addmm", "addmv", "addr", "prelu"),
    "Tensor.__matmul__",
    "Tensor.__rmatmul__",
    "torch.einsum",
    "torch.chain_matmul",
    "linalg.multi_dot",
    "linalg.vecdot",
    "F.linear",
    "torch.conv1d",
    "torch.conv2d",
    "torch.conv3d",
    "torch.conv_transpose1d",
    "torch.conv_transpose2d",
    "torch.conv_transpose3d",
    "torch.convolution",
    "torch.conv_tbc",
    "F.conv1d",
    "F.conv2d",
    "F.conv3d",
    "F.conv_transpose1d",
    "F.conv_transpose2d",
    "F.conv_transpose3d",
    "F.prelu",
    "F.scaled_dot_product_attention",
    "torch.lstm_cell",
    "torch.gru_cell",
    "torch.rnn_tanh_cell",
    "torch.rnn_relu_cell",
)

#: CUDA's "autocast to float32" list (AT_FORALL_FP32 and the norm overloads): inputs cast to float32.
FLOAT32_OPS = _callables(
    *_everywhere(
        "acos",
        "arccos",
        "asin",
        "arcsin",
        "cosh",
        "erfinv",
        "exp",
        "expm1",
        "log",
        "log10",
        "log2",
        "log1p",
        "reciprocal",
        "rsqrt",
        "sinh",
        "tan",
        "pow",
        "renorm",
        "logsumexp",
        "norm",
        "dist",
    ),
    "Tensor.__pow__",
    "Tensor.__rpow__",
    "Tensor.__rdiv__",
    "Tensor.__rtruediv__",
    "special.erfinv",
    "special.expm1",
    "special.log1p",
    "special.logsumexp",
    "torch.nuclear_norm",
    "torch.frobenius_norm",
    "torch.layer_norm",
    "torch.native_layer_norm",
    "torch.rms_norm",
    "torch.group_norm",
    "torch.cosine_similarity",
    "torch.cdist",
    "torch.pdist",
    "torch.binary_cross_entropy_with_logits",
    "torch.poisson_nll_loss",
    "torch.cosine_embedding_loss",
    "torch.hinge_embedding_loss",
    "torch.kl_div",
    "torch.margin_ranking_loss",
    "torch.triplet_margin_loss",
    "F.softplus",
    "F.layer_norm",
    "F.rms_norm",
    "F.group_norm",
    "F.normalize",
    "F.cosine_similarity",
    "F.pdist",
    "F.poisson_nll_loss",
    "F.cosine_embedding_loss",
    "F.nll_loss",
    "F.cross_entropy",
    "F.hinge_embedding_loss",
    "F.kl_div",
    "F.l1_loss",
    "F.smooth_l1_loss",
    "F.huber_loss",
    "F.mse_loss",
    "F.margin_ranking_loss",
    "F.multilabel_margin_loss",
    "F.soft_margin_loss",
    "F.triplet_margin_loss",
    "F.multi_margin_loss",
    "F.binary_cross_entropy_with_logits",
    "_nn.softplus",
    "_nn.l1_loss",
    "_nn.mse_loss",
    "_nn.smooth_l1_loss",
    "_nn.huber_loss",
    "_nn.nll_loss",
    "_nn.nll_loss2d",
    "_nn.soft_margin_loss",
    "_nn.multilabel_margin_loss",
    "_nn.multi_margin_loss",
    "_nn.upsample_nearest1d",
    "_nn.upsample_nearest2d",
    "_nn.upsample_nearest3d",
    "_nn._upsample_nearest_exact1d",
    "_nn._upsample_nearest_exact2d",
    "_nn._upsample_nearest_exact3d",
    "_nn.upsample_linear1d",
    "_nn.upsample_bilinear2d",
    "_nn._upsample_bilinear2d_aa",
    "_nn.upsample_trilinear3d",
    "_nn.upsample_bicubic2d",
    "_nn._upsample_bicubic2d_aa",
)

#: CUDA's float32 ops with an output ``dtype`` argument (AT_FORALL_FP32_SET_OPT_DTYPE): ``dtype=float32`` unless set.
FLOAT32_DTYPE_OPS = _callables(
    *_everywhere("softmax", "log_softmax", "sum", "prod", "cumsum", "cumprod"),
    "F.softmax",
    "F.log_softmax",
    "special.softmax",
    "special.log_softmax",
    "linalg.vector_norm",
    "linalg.matrix_norm",
)

#: CUDA's "promote to the widest input type" list (AT_FORALL_PROMOTE).
PROMOTE_OPS = _callables(
    *_everywhere("addcdiv", "addcmul", "atan2", "arctan2", "cross", "dot", "vdot", "index_put", "scatter_add"),
    "torch.bilinear",
    "F.bilinear",
    "torch.grid_sampler",
    "F.grid_sample",
    "torch.tensordot",
)

#: Refused by CUDA autocast (``binary_cross_entropy`` is unsafe in float16 and raises there).
_BANNED_OPS = _callables("F.binary_cross_entropy", "torch.binary_cross_entropy", "_nn.binary_cross_entropy")

_HALF_TYPES = (torch.float16, torch.bfloat16)


def _eligible(x: object) -> bool:
    """A tensor CUDA autocast would cast: floating point and not float64 (here on the CPU, CUDA's device)."""
    return isinstance(x, Tensor) and x.is_floating_point() and x.dtype != torch.float64 and x.device.type == "cpu"


def _cast(args: Any, dtype: torch.dtype) -> Any:
    """Every eligible tensor in the (nested) ``args`` cast to ``dtype``; anything else as it is."""
    return tree_map(lambda a: a.to(dtype) if _eligible(a) and a.dtype != dtype else a, args)


def _promoted(args: Any, kwargs: dict[str, Any], lower: torch.dtype) -> torch.dtype:
    """The widest type of the eligible tensors, as CUDA autocast's ``promote`` policy picks it."""
    widest = lower
    for leaf in tree_leaves((args, kwargs)):
        if not _eligible(leaf) or leaf.dtype == widest:
            continue
        if torch.float32 in (leaf.dtype, widest):
            widest = torch.float32
        else:  # float16 and bfloat16 together: CUDA autocast refuses them too
            raise RuntimeError(f"Unexpected floating ScalarType in autocast::prioritize: {leaf.dtype} with {widest}")
    return widest


class CudaAutocastRules(TorchFunctionMode):
    """A torch-function mode that applies CUDA autocast's casting rules to CPU ops while CPU autocast is enabled.

    The lists and the policies are described in this module's docstring. Use :func:`cuda_autocast_rules`, which
    also enables CPU autocast with the same dtype (the on/off switch the rules follow).

    Args:
        dtype: the lower-precision type, ``torch.bfloat16`` or ``torch.float16`` (CUDA autocast's ``dtype``).

    Raises:
        ValueError: ``dtype`` is not ``torch.bfloat16`` or ``torch.float16``.
    """

    def __init__(self, dtype: torch.dtype) -> None:
        super().__init__()
        if dtype not in _HALF_TYPES:
            raise ValueError(f"`dtype` must be torch.bfloat16 or torch.float16, got {dtype}")
        self.dtype = dtype
        #: names of the listed ops the mode cast, in call order (for tests of the mode itself)
        self.cast_ops: list[str] = []

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = dict(kwargs or {})
        # Read the switch before the guard below: excluding the CPU autocast key also reads as disabled.
        enabled = torch.is_autocast_enabled("cpu")
        # CPU autocast's own lists must not apply: exclude its dispatch key for the op and everything it calls.
        with torch._C._ExcludeDispatchKeyGuard(torch._C.DispatchKeySet(torch._C.DispatchKey.AutocastCPU)):
            if not enabled or kwargs.get("out") is not None:
                return func(*args, **kwargs)
            if func in _BANNED_OPS:
                raise RuntimeError(
                    f"{getattr(func, '__name__', func)} is unsafe to autocast (CUDA autocast refuses it); compute it "
                    "in float32 with autocast off, or use binary_cross_entropy_with_logits"
                )
            if func in LOWER_PRECISION_OPS:
                return self._run(func, _cast(args, self.dtype), _cast(kwargs, self.dtype))
            if func in FLOAT32_OPS or (func is F.interpolate and _interpolate_mode(args, kwargs) != "area"):
                return self._run(func, _cast(args, torch.float32), _cast(kwargs, torch.float32))
            if func in FLOAT32_DTYPE_OPS:
                if args and _eligible(args[0]) and kwargs.get("dtype") is None:
                    kwargs["dtype"] = torch.float32
                    return self._run(func, args, kwargs)
                return func(*args, **kwargs)
            if func in PROMOTE_OPS:
                widest = _promoted(args, kwargs, self.dtype)
                return self._run(func, _cast(args, widest), _cast(kwargs, widest))
            try:
                return func(*args, **kwargs)
            except NotImplementedError as error:
                half = _half_input_type(args, kwargs)
                if half is None or f"for '{_KERNEL_NAMES[half]}'" not in str(error):
                    raise
            # a CPU op without a kernel for `half` (CUDA has one): computed in float32, returned in `half`
            out = func(*_cast(args, torch.float32), **_cast(kwargs, torch.float32))
            return tree_map(lambda t: t.to(half) if isinstance(t, Tensor) and t.dtype == torch.float32 else t, out)

    def _run(self, func: Callable[..., Any], args: Any, kwargs: dict[str, Any]) -> Any:
        self.cast_ops.append(getattr(func, "__name__", repr(func)))
        return func(*args, **kwargs)


_KERNEL_NAMES = {torch.bfloat16: "BFloat16", torch.float16: "Half"}


def _half_input_type(args: tuple, kwargs: dict[str, Any]) -> torch.dtype | None:
    """The half-precision type of the first half-precision tensor argument, if any."""
    return next(
        (t.dtype for t in tree_leaves((args, kwargs)) if isinstance(t, Tensor) and t.dtype in _HALF_TYPES), None
    )


def _interpolate_mode(args: tuple, kwargs: dict[str, Any]) -> str:
    """``F.interpolate``'s ``mode`` argument (4th positional or keyword; ``"nearest"`` by default)."""
    return kwargs.get("mode", args[3] if len(args) > 3 else "nearest")


@contextlib.contextmanager
def cuda_autocast_rules(dtype: torch.dtype) -> Iterator[CudaAutocastRules]:
    """Run the block as under ``torch.autocast("cuda", dtype=dtype)``, on CPU tensors.

    Enables CPU autocast with ``dtype`` (so ``torch.is_autocast_enabled("cpu")`` is true and a nested
    ``torch.autocast("cpu", enabled=False)`` turns the rules off) and pushes a :class:`CudaAutocastRules`.

    Args:
        dtype: ``torch.bfloat16`` (``precision="bf16-mixed"``) or ``torch.float16`` (``"16-mixed"``).

    Yields:
        The mode (its ``cast_ops`` lists the listed ops it cast).

    Raises:
        ValueError: ``dtype`` is not ``torch.bfloat16`` or ``torch.float16``.
    """
    mode = CudaAutocastRules(dtype)
    with torch.autocast("cpu", dtype=dtype), mode:
        yield mode
