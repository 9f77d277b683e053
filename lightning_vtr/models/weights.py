"""Where pretrained weights come from: a local file, a URL (through torch.hub's cache) or ``"imagenet"``.

Every ``*_weights`` / ``pretrained_*`` argument of the package's models resolves through
:func:`load_weights`. A URL is downloaded once into torch.hub's checkpoint directory
(``$TORCH_HOME/hub/checkpoints``, see :func:`weights_cache_dir`) and read from there afterwards; on a
machine without network access the file can be put there by hand. :func:`restoring_checkpoint` marks a
model construction whose weights will come from a checkpoint's state dict, so no weight file is read.
"""

from __future__ import annotations

import contextlib
import contextvars
import os
import re
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any
from urllib.parse import unquote, urlparse

import torch
from torch import Tensor

from lightning_vtr.utils.paths import join_under
from lightning_vtr.utils.validation import check_choice, check_type

__all__ = [
    "IMAGENET_WEIGHTS",
    "WeightsDownloadError",
    "fetch_weights",
    "is_restoring_checkpoint",
    "load_weights",
    "restoring_checkpoint",
    "weights_cache_dir",
]

IMAGENET_WEIGHTS: dict[str, str] = {
    "resnet50": "https://download.pytorch.org/models/resnet50-0676ba61.pth",
    "deit_base_distilled": "https://dl.fbaipublicfiles.com/deit/deit_base_distilled_patch16_224-df68dfff.pth",
}
"""What ``"imagenet"`` means for each backbone ``kind``: the URLs torchvision (``ResNet50_Weights.IMAGENET1K_V1``)
and the DeiT release (``deit_base_distilled_patch16_224``) download their weights from."""

_URL_SCHEMES = ("http", "https", "file")
# torch.hub's naming convention: "<name>-<first hex digits of the file's SHA-256>.<ext>".
_HASH_IN_NAME = re.compile(r"-([a-f0-9]{8,})\.")
# Wrappers that release files put around a state dict: DeiT's {"model": ...}, Lightning's {"state_dict": ...}.
_WRAPPERS = ("model", "state_dict")

_RESTORING: contextvars.ContextVar[bool] = contextvars.ContextVar("lightning_vtr_restoring", default=False)


class WeightsDownloadError(OSError):
    """A weight file could not be downloaded (no network, a server error, or a hash mismatch)."""


def weights_cache_dir() -> Path:
    """torch.hub's checkpoint directory, ``<torch.hub.get_dir()>/checkpoints``.

    It follows ``$TORCH_HOME`` (default ``~/.cache/torch``) at every call, or ``torch.hub.set_dir``.
    """
    return Path(torch.hub.get_dir()) / "checkpoints"


def _is_url(source: str) -> bool:
    return urlparse(source).scheme in _URL_SCHEMES


def fetch_weights(
    source: str | os.PathLike,
    *,
    kind: str | None = None,
    check_hash: bool = True,
    progress: bool = True,
) -> Path:
    """The local file behind ``source``, downloading it into torch.hub's cache if it is a URL.

    Args:
        source: a local path; an ``http(s)://`` or ``file://`` URL; or ``"imagenet"``, the ImageNet weights
            of ``kind`` (:data:`IMAGENET_WEIGHTS`).
        kind: the backbone the weights are for, ``"resnet50"`` or ``"deit_base_distilled"``; needed for
            ``"imagenet"`` and used in messages.
        check_hash: when the URL's file name follows torch.hub's ``name-<sha256 prefix>.ext`` convention
            (both ImageNet files do), check a downloaded file against that prefix.
        progress: show a progress bar while downloading.

    Returns:
        the path of the file: ``source`` itself, or ``weights_cache_dir() / <file name of the URL>``.

    Raises:
        TypeError: if ``source`` is not a string or path.
        ValueError: for ``"imagenet"`` without a known ``kind``.
        FileNotFoundError: if ``source`` is neither a URL nor an existing file.
        WeightsDownloadError: if the download fails; the message names the URL and the cache path where
            the file can be placed by hand.
    """
    check_type("source", source, (str, os.PathLike), "path, a URL or 'imagenet'")
    what = f"{kind} weights" if kind else "weights"
    source = os.fspath(source)
    if source == "imagenet":
        source = IMAGENET_WEIGHTS[check_choice("kind", kind, IMAGENET_WEIGHTS)]
    if not _is_url(source):
        path = Path(source).expanduser()
        if not path.is_file():
            raise FileNotFoundError(
                f"{what} file not found: {source!r} (expected a local file, an http(s):// or file:// URL, or "
                "'imagenet')"
            )
        return path
    cache_dir = weights_cache_dir()
    name = os.path.basename(unquote(urlparse(source).path))
    cached = join_under(cache_dir, name)
    if cached.is_file():
        return cached
    match = _HASH_IN_NAME.search(name) if check_hash else None
    try:
        cache_dir.mkdir(parents=True, exist_ok=True)
        # Writes to a temporary name and renames, so a failed or concurrent download leaves no half file.
        torch.hub.download_url_to_file(source, str(cached), match.group(1) if match else None, progress=progress)
    except (OSError, RuntimeError) as err:  # URLError/HTTPError are OSErrors; a hash mismatch a RuntimeError
        raise WeightsDownloadError(
            f"could not download {what} from {source} to {cached} ({type(err).__name__}: {err}). Without network "
            f"access, download {source} on another machine and copy it to {cached} (the directory follows "
            "$TORCH_HOME, default ~/.cache/torch), or pass the file's local path instead."
        ) from err
    return cached


def _read(path: Path) -> Any:
    if path.suffix == ".safetensors":
        try:
            from safetensors.torch import load_file
        except ImportError as err:  # pragma: no cover - depends on the environment
            raise ImportError(f"reading {path} needs the 'safetensors' package") from err
        return load_file(str(path))
    return torch.load(path, map_location="cpu", weights_only=True)


def load_weights(
    source: str | os.PathLike | Mapping[str, Tensor],
    *,
    kind: str | None = None,
    check_hash: bool = True,
    progress: bool = True,
) -> dict[str, Tensor]:
    """A state dict from a local file, a URL, ``"imagenet"`` or a mapping (see :func:`fetch_weights`).

    Files are read with ``torch.load(..., weights_only=True)`` on the CPU (``.safetensors`` files with
    safetensors). A ``{"model": ...}`` (DeiT release) or ``{"state_dict": ...}`` (Lightning) wrapper is
    removed; no key is renamed.

    Args:
        source: a local path, an ``http(s)://`` or ``file://`` URL, ``"imagenet"``, or a state dict.
        kind: as in :func:`fetch_weights`.
        check_hash: as in :func:`fetch_weights`.
        progress: as in :func:`fetch_weights`.

    Returns:
        A new dict of parameter names to tensors (on the CPU when read from a file), wrapper removed.

    Raises:
        TypeError: if ``source`` is none of these.
        ValueError: if the file or mapping does not hold a mapping of tensors, or for ``"imagenet"`` without a
            known ``kind``.
        FileNotFoundError: see :func:`fetch_weights`.
        WeightsDownloadError: see :func:`fetch_weights`.

    Example::

        state = load_weights("imagenet", kind="resnet50")  # downloads once, then reads the cache
        state = load_weights("/data/weights/resnet50-0676ba61.pth")
    """
    check_type("source", source, (str, os.PathLike, Mapping), "path, a URL, 'imagenet' or a state dict")
    name = "state dict"
    if isinstance(source, Mapping):
        state: Any = source
    else:
        path = fetch_weights(source, kind=kind, check_hash=check_hash, progress=progress)
        name = str(path)
        state = _read(path)
    for wrapper in _WRAPPERS:
        if isinstance(state, Mapping) and isinstance(state.get(wrapper), Mapping):
            state = state[wrapper]
    if not isinstance(state, Mapping) or not all(isinstance(v, Tensor) for v in state.values()):
        found = type(state).__name__ if not isinstance(state, Mapping) else "a mapping with non-tensor values"
        raise ValueError(f"{name} must hold a state dict (a mapping of names to tensors), got {found}")
    return dict(state)


@contextlib.contextmanager
def restoring_checkpoint() -> Iterator[None]:
    """Within this block, models skip reading pretrained weight files: a checkpoint's state dict follows.

    :meth:`VoxelReconstructionModule.load_from_checkpoint
    <lightning_vtr.models.base.VoxelReconstructionModule.load_from_checkpoint>` constructs the model inside
    it, so a checkpoint loads on a machine without the weight file its hyperparameters name.
    """
    token = _RESTORING.set(True)
    try:
        yield
    finally:
        _RESTORING.reset(token)


def is_restoring_checkpoint() -> bool:
    """Whether the caller runs inside :func:`restoring_checkpoint` (a model should then not read weight files)."""
    return _RESTORING.get()
