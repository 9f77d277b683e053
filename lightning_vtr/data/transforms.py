"""Image transforms: RGBA renders to model input, and the published training recipes of Pix2Vox++ and LRGT.

The ops are plain torch functions on ``(..., 3, H, W)`` float images in ``[0, 1]``; none of them draws a
random number. :class:`ImageTransform` chains them and draws every random parameter of a sample from a
key such as ``(seed, epoch, index)``, so a sample's augmentation never depends on the worker, the process
or a global random state. Training views can also be composited over random crops of the images of a folder
(:class:`BackgroundFolder`, ``ImageRecipe(background_folder=...)``). :class:`ImageRecipe` holds the settings of
one recipe; :data:`IMAGE_RECIPES` names the reference ones.
"""

from __future__ import annotations

import dataclasses
import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType
from typing import Any, cast

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image
from torch import Tensor

from lightning_vtr.data.format import IMAGE_SUFFIXES
from lightning_vtr.utils.compositing import alpha_composite
from lightning_vtr.utils.limits import open_image
from lightning_vtr.utils.validation import check_choice, check_float, check_int, check_type

__all__ = [
    "BACKGROUND_EXTENSIONS",
    "IMAGENET_MEAN",
    "IMAGENET_PCA_EIGVAL",
    "IMAGENET_PCA_EIGVEC",
    "IMAGENET_STD",
    "IMAGE_RECIPES",
    "NORMALIZATIONS",
    "SHAPENET_RENDERING_CROP",
    "BackgroundFolder",
    "ImageRecipe",
    "ImageTransform",
    "adjust_brightness",
    "adjust_contrast",
    "adjust_saturation",
    "center_crop",
    "hflip",
    "normalize_image",
    "pca_lighting",
    "permute_channels",
    "rgb_to_grayscale",
]

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)

#: Eigenvalues of the covariance of ImageNet's RGB pixel values (in [0, 1]), largest first: the values the
#: AlexNet-style lighting noise of Pix2Vox++ uses.
IMAGENET_PCA_EIGVAL = (0.2175, 0.0188, 0.0045)
#: The matching eigenvectors as columns; row ``c`` is channel R, G or B.
IMAGENET_PCA_EIGVEC = (
    (-0.5675, 0.7192, 0.4009),
    (-0.5808, -0.0045, -0.8140),
    (-0.5836, -0.6948, 0.4203),
)

#: The centre crop of the published recipes as a fraction of the image side: 128 of ShapeNetRendering's
#: 137 px. On a 137 px image it keeps exactly the reference's 128 px (4 px off the top and left); on our own
#: renders it removes the same 3.3 % band around the object at any resolution.
SHAPENET_RENDERING_CROP = 128 / 137

#: The values of ``normalize``: ImageNet mean/std, ``"pm1"`` (``x * 2 - 1``, i.e. mean = std = 0.5, which
#: is Pix2Vox++'s normalisation too), or ``None`` (``[0, 1]`` as is).
NORMALIZATIONS: tuple[str | None, ...] = ("imagenet", "pm1", None)

# Appended to every key, so the augmentation stream never coincides with another stream drawn from the
# same (seed, epoch, index) (the dataset's choice of views is drawn from exactly that key).
_AUGMENTATION_STREAM = 7919
# Appended after the augmentation stream for folder backgrounds: their draws come from a generator of their
# own, so enabling them leaves every other draw of a key unchanged.
_BACKGROUND_STREAM = 104729
#: The image files a background folder contributes (suffix, case-insensitive; searched recursively): the
#: package's :data:`~lightning_vtr.data.format.IMAGE_SUFFIXES`.
BACKGROUND_EXTENSIONS: tuple[str, ...] = IMAGE_SUFFIXES
# Luma weights (ITU-R BT.601) of R, G, B: what the references' grayscale uses.
_LUMA = (0.299, 0.587, 0.114)


# ---------------------------------------------------------------------------------------------- functional ops
def _check_image(image: Tensor, channels: int = 3, name: str = "image") -> None:
    if not isinstance(image, Tensor):
        raise TypeError(f"`{name}` must be a Tensor, got {type(image).__name__}")
    if image.ndim < 3 or image.shape[-3] != channels:
        raise ValueError(f"`{name}` must be (..., {channels}, H, W), got shape {tuple(image.shape)}")


def _per_image(value: float | Tensor, image: Tensor) -> Tensor:
    """A scalar or a ``(...)`` tensor of per-image values as ``(..., 1, 1, 1)``, broadcastable over ``image``."""
    value = torch.as_tensor(value, dtype=image.dtype, device=image.device)
    return value.reshape(*value.shape, 1, 1, 1)


def center_crop(image: Tensor, fraction: float) -> Tensor:
    """The centred ``round(fraction * H) x round(fraction * W)`` window of ``(..., C, H, W)`` images.

    The window starts ``(H - h) // 2`` rows and ``(W - w) // 2`` columns in (the odd pixel is left at the
    bottom and right), so ``fraction = 128 / 137`` on a 137 px image is the references' 128 px crop.
    """
    fraction = check_float("fraction", fraction, minimum=0.0, maximum=1.0, min_open=True)
    height, width = image.shape[-2:]
    h, w = max(1, round(fraction * height)), max(1, round(fraction * width))
    top, left = (height - h) // 2, (width - w) // 2
    return image[..., top : top + h, left : left + w]


def rgb_to_grayscale(image: Tensor) -> Tensor:
    """``(..., 3, H, W)`` RGB -> ``(..., 1, H, W)`` luma ``0.299 R + 0.587 G + 0.114 B``."""
    _check_image(image)
    r, g, b = image.unbind(-3)
    return (_LUMA[0] * r + _LUMA[1] * g + _LUMA[2] * b).unsqueeze(-3)


def adjust_brightness(image: Tensor, factor: float | Tensor) -> Tensor:
    """``image * factor`` (a blend with black), unclamped; ``factor`` is a scalar or one per image ``(...)``."""
    _check_image(image)
    return image * _per_image(factor, image)


def adjust_contrast(image: Tensor, factor: float | Tensor) -> Tensor:
    """Blend with the image's mean luma: ``factor * image + (1 - factor) * mean(gray)``, unclamped."""
    _check_image(image)
    f = _per_image(factor, image)
    mean = rgb_to_grayscale(image).mean(dim=(-3, -2, -1), keepdim=True)
    return f * image + (1.0 - f) * mean


def adjust_saturation(image: Tensor, factor: float | Tensor) -> Tensor:
    """Blend with the image's own luma: ``factor * image + (1 - factor) * gray``, unclamped."""
    _check_image(image)
    f = _per_image(factor, image)
    return f * image + (1.0 - f) * rgb_to_grayscale(image)


def pca_lighting(
    image: Tensor,
    alpha: Sequence[float] | Tensor,
    eigval: Sequence[float] = IMAGENET_PCA_EIGVAL,
    eigvec: Sequence[Sequence[float]] = IMAGENET_PCA_EIGVEC,
) -> Tensor:
    """AlexNet-style lighting noise: add ``eigvec @ (alpha * eigval)`` to the R, G, B channels, unclamped.

    Args:
        image: ``(..., 3, H, W)``.
        alpha: ``(3,)`` or ``(..., 3)`` weights of the three principal components (drawn from
            ``N(0, std)`` in training).
        eigval: ``(3,)`` eigenvalues (default ImageNet's).
        eigvec: ``(3, 3)`` eigenvectors as columns, rows R, G, B (default ImageNet's).
    """
    _check_image(image)
    alpha = torch.as_tensor(alpha, dtype=torch.float64)
    if alpha.shape[-1:] != (3,):
        raise ValueError(f"`alpha` must be (..., 3), got shape {tuple(alpha.shape)}")
    values = torch.as_tensor(eigval, dtype=torch.float64)
    vectors = torch.as_tensor(eigvec, dtype=torch.float64)
    shift = ((alpha * values) @ vectors.T).to(dtype=image.dtype, device=image.device)  # (..., 3)
    return image + shift[..., :, None, None]


def hflip(image: Tensor) -> Tensor:
    """Mirror ``(..., C, H, W)`` images left to right (reverse the width axis)."""
    return image.flip(-1)


def permute_channels(image: Tensor, permutation: Sequence[int] | Tensor) -> Tensor:
    """Output channel ``c`` is input channel ``permutation[c]`` of ``(..., C, H, W)`` images."""
    perm = torch.as_tensor(permutation, dtype=torch.long, device=image.device)
    if perm.ndim != 1 or sorted(perm.tolist()) != list(range(image.shape[-3])):
        raise ValueError(f"`permutation` must be a permutation of range({image.shape[-3]}), got {perm.tolist()}")
    return image.index_select(-3, perm)


def normalize_image(image: Tensor, mode: str | None) -> Tensor:
    """``(..., 3, H, W)`` images in ``[0, 1]`` as a backbone expects them.

    ``"imagenet"``: ``(x - mean) / std`` with ImageNet's statistics; ``"pm1"``: ``x * 2 - 1`` (``[-1, 1]``;
    the same as mean = std = 0.5); ``None``: unchanged.
    """
    check_choice("normalize", mode, NORMALIZATIONS)
    if mode == "imagenet":
        shape = (1,) * (image.ndim - 3) + (3, 1, 1)
        mean = torch.tensor(IMAGENET_MEAN, dtype=image.dtype, device=image.device).view(shape)
        std = torch.tensor(IMAGENET_STD, dtype=image.dtype, device=image.device).view(shape)
        return (image - mean) / std
    if mode == "pm1":
        return image * 2.0 - 1.0
    return image


# ---------------------------------------------------------------------------------------------- argument checks
def _check_background(background: Sequence[int]) -> tuple[int, int, int]:
    """``background`` as three ints in ``[0, 255]`` (R, G, B)."""
    try:
        channels = tuple(background)
    except TypeError:
        raise TypeError(
            f"`background` must be a sequence of three ints (R, G, B), got {type(background).__name__} {background!r}"
        ) from None
    if len(channels) != 3:
        raise ValueError(f"`background` must be three ints (R, G, B) in [0, 255], got {background!r}")
    r, g, b = (check_int(f"background[{i}]", c, minimum=0, maximum=255) for i, c in enumerate(channels))
    return r, g, b


def _check_background_range(value: Any) -> tuple[tuple[int, int], ...] | None:
    """``None``, a pair ``(low, high)`` for every channel, or three pairs (R, G, B); ints in [0, 255], inclusive."""
    if value is None:
        return None
    what = "a pair (low, high) or three pairs (R, G, B) of ints in [0, 255]"
    try:
        items = tuple(value)
    except TypeError:
        raise TypeError(f"`background_range` must be {what}, got {type(value).__name__} {value!r}") from None
    if len(items) == 2 and not any(isinstance(v, (Sequence, np.ndarray)) for v in items):
        items = (items,) * 3
    if len(items) != 3:
        raise ValueError(f"`background_range` must be {what}, got {value!r}")
    ranges = []
    for c, pair in enumerate(items):
        try:
            low, high = pair
        except (TypeError, ValueError):
            raise ValueError(f"`background_range` must be {what}, got {value!r}") from None
        low = check_int(f"background_range[{c}][0]", low, minimum=0, maximum=255)
        high = check_int(f"background_range[{c}][1]", high, minimum=0, maximum=255)
        if low > high:
            raise ValueError(f"`background_range[{c}]` must satisfy low <= high, got {pair!r}")
        ranges.append((low, high))
    return tuple(ranges)


# ---------------------------------------------------------------------------------------------- backgrounds
class BackgroundFolder:
    """The images under a folder, as backgrounds to composite training views over.

    The folder is scanned once, recursively, for :data:`BACKGROUND_EXTENSIONS` files, sorted by their path
    relative to the folder (so every process and every machine numbers them alike). :meth:`crop` cuts an
    ``height x width`` window out of image ``index`` at a relative position; an image smaller than the window
    in either side is first scaled up (bilinear, aspect ratio kept) until it covers it.

    Args:
        path: the folder (e.g. SUN397's images).

    Raises:
        FileNotFoundError: ``path`` is not a directory.
        ValueError: it holds no image file.
    """

    def __init__(self, path: str | os.PathLike) -> None:
        self.root = Path(path).expanduser()
        if not self.root.is_dir():
            raise FileNotFoundError(f"`background` folder {str(self.root)!r} is not a directory")
        found = [p for p in self.root.rglob("*") if p.suffix.lower() in BACKGROUND_EXTENSIONS and p.is_file()]
        self.paths = sorted(found, key=lambda p: p.relative_to(self.root).as_posix())
        if not self.paths:
            raise ValueError(
                f"`background` folder {str(self.root)!r} has no images: expected files ending in "
                f"{', '.join(BACKGROUND_EXTENSIONS)} (searched recursively), found none"
            )

    def __len__(self) -> int:
        return len(self.paths)

    def __repr__(self) -> str:
        return f"BackgroundFolder({str(self.root)!r}, {len(self.paths)} images)"

    def load(self, index: int) -> np.ndarray:
        """Image ``index`` as ``(h, w, 3)`` uint8 RGB."""
        with self._open(index) as img:
            return np.asarray(img.convert("RGB"))

    def _open(self, index: int) -> Image.Image:
        path = self.paths[index]
        try:
            return open_image(path)  # its size checked before decoding
        except (OSError, ValueError) as err:
            raise OSError(f"Cannot read background image {path}: {err}") from err

    def crop(self, index: int, position: tuple[float, float], height: int, width: int) -> np.ndarray:
        """A ``(height, width, 3)`` uint8 window of image ``index``.

        ``position = (u, v)`` in ``[0, 1)`` places it: the window starts at row ``floor(u * (h - height + 1))``
        and column ``floor(v * (w - width + 1))`` of the (scaled-up if needed) ``h x w`` image, so every
        position is equally likely for uniform ``(u, v)``.
        """
        path = self.paths[index]
        with self._open(index) as img:
            try:
                w, h = img.size
                if h < height or w < width:
                    scale = max(height / h, width / w)
                    h, w = max(height, math.ceil(h * scale)), max(width, math.ceil(w * scale))
                    img = img.convert("RGB").resize((w, h), Image.BILINEAR)  # type: ignore[attr-defined]  # PIL sets the alias at runtime
                top = min(int(position[0] * (h - height + 1)), h - height)
                left = min(int(position[1] * (w - width + 1)), w - width)
                # Crop before converting: only the window is converted and copied.
                return np.asarray(img.crop((left, top, left + width, top + height)).convert("RGB"))
            except (OSError, ValueError) as err:
                raise OSError(f"Cannot read background image {path}: {err}") from err


def _check_background_folder(value: Any) -> str | None:
    if value is None:
        return None
    if not isinstance(value, (str, os.PathLike)) or not str(value).strip():
        raise TypeError(f"`background_folder` must be None or a folder path, got {type(value).__name__} {value!r}")
    return str(value)


# ---------------------------------------------------------------------------------------------- recipes
@dataclass(frozen=True)
class ImageRecipe:
    """The image handling of one training recipe: what every image gets, and what training adds.

    Every image is composited on ``background``, centre-cropped to ``crop`` of its side, resized to the
    model's input size and normalised. In training (:meth:`train_transform`) the background is instead
    drawn per sample from ``background_range`` and, in this order, colour jitter (brightness, contrast and
    saturation factors drawn from ``[1 - b, 1 + b]``, applied in a random order), PCA lighting noise, a
    clamp to ``[0, 1]`` (unless ``clamp=False``), a horizontal flip of each image with probability 1/2 and one
    random permutation of the RGB channels follow the resize. Background, jitter, lighting and permutation are
    drawn once per sample (shared by its views), flips once per image. With ``background_folder``, training
    composites each view instead over its own random crop (the view's size, a random position) of a random
    image of that folder (:class:`BackgroundFolder`), drawn from the same key.

    Args:
        background: RGB (0-255) composited under transparent pixels; the only background outside training.
        background_range: training only: a per-sample random RGB background, each channel an int drawn
            uniformly from ``(low, high)`` inclusive; a pair applies to all three channels. ``None``:
            ``background``.
        crop: the side of the centred crop as a fraction of the image side, in ``(0, 1]``
            (:data:`SHAPENET_RENDERING_CROP` is the references' 128 of 137 px).
        brightness: training only: brightness jitter ``b`` in ``[0, 1]``.
        contrast: training only: contrast jitter in ``[0, 1]``.
        saturation: training only: saturation jitter in ``[0, 1]``.
        lighting_std: training only: standard deviation of the PCA lighting weights.
        hflip: training only: mirror each image with probability 1/2.
        permute_rgb: training only: permute the RGB channels of a sample at random.
        clamp: training only: clamp to ``[0, 1]`` after jitter and lighting (the published recipes do not).
        normalize: one of :data:`NORMALIZATIONS`.
        background_folder: training only: a folder of images (``.png``/``.jpg``/``.jpeg``, recursive) whose
            random crops replace ``background_range`` (e.g. SUN backgrounds, as in Pix2Vox++'s Pix3D protocol).
            Outside training the background stays ``background``.

    Raises:
        TypeError: a field of the wrong type (names the field and the value).
        ValueError: a field out of range, e.g. a channel outside ``[0, 255]``, a ``crop`` outside ``(0, 1]`` or
            an unknown ``normalize``.

    Example:
        >>> recipe = IMAGE_RECIPES["pix2vox"]
        >>> train, test = recipe.train_transform(224), recipe.eval_transform(224)
        >>> x = train(np.zeros((3, 137, 137, 4), np.uint8), key=(0, 5, 17))  # (seed, epoch, index)
        >>> tuple(x.shape)
        (3, 3, 224, 224)
    """

    background: tuple[int, int, int] = (255, 255, 255)
    background_range: tuple[tuple[int, int], ...] | None = None
    crop: float = 1.0
    brightness: float = 0.0
    contrast: float = 0.0
    saturation: float = 0.0
    lighting_std: float = 0.0
    hflip: bool = False
    permute_rgb: bool = False
    clamp: bool = True
    normalize: str | None = "imagenet"
    background_folder: str | None = None

    def __post_init__(self) -> None:
        # Normalised in place (the dataclass is frozen): equal recipes compare equal whatever types built them.
        values = {
            "background": _check_background(self.background),
            "background_range": _check_background_range(self.background_range),
            "crop": check_float("crop", self.crop, minimum=0.0, maximum=1.0, min_open=True),
            "brightness": check_float("brightness", self.brightness, minimum=0.0, maximum=1.0),
            "contrast": check_float("contrast", self.contrast, minimum=0.0, maximum=1.0),
            "saturation": check_float("saturation", self.saturation, minimum=0.0, maximum=1.0),
            "lighting_std": check_float("lighting_std", self.lighting_std, minimum=0.0),
            "background_folder": _check_background_folder(self.background_folder),
        }
        for name in ("hflip", "permute_rgb", "clamp"):
            check_type(name, getattr(self, name), bool)
        check_choice("normalize", self.normalize, NORMALIZATIONS)
        for name, value in values.items():
            object.__setattr__(self, name, value)

    @property
    def is_random(self) -> bool:
        """Whether training draws anything (then a training transform needs a key)."""
        varying = self.background_range is not None and any(lo != hi for lo, hi in self.background_range)
        jitter = self.brightness > 0 or self.contrast > 0 or self.saturation > 0
        folder = self.background_folder is not None
        return varying or folder or jitter or self.lighting_std > 0 or self.hflip or self.permute_rgb

    def train_transform(self, image_size: int) -> ImageTransform:
        """The training transform: every op of the recipe, random ones drawn from a per-sample key."""
        return ImageTransform(image_size, **dataclasses.asdict(self))

    def eval_transform(self, image_size: int) -> ImageTransform:
        """The validation/test transform: fixed background, centre crop, resize, normalisation; nothing random."""
        return ImageTransform(image_size, self.background, self.normalize, crop=self.crop)


IMAGE_RECIPES: Mapping[str, ImageRecipe] = MappingProxyType(
    {
        "plain": ImageRecipe(),
        "pix2vox": ImageRecipe(
            background=(240, 240, 240),
            background_range=((225, 255),) * 3,
            crop=SHAPENET_RENDERING_CROP,
            brightness=0.4,
            contrast=0.4,
            saturation=0.4,
            lighting_std=0.1,
            hflip=True,
            permute_rgb=True,
            clamp=False,
            normalize="pm1",
        ),
        "lrgt": ImageRecipe(
            background=(240, 240, 240),
            background_range=((225, 255),) * 3,
            crop=SHAPENET_RENDERING_CROP,
            normalize="pm1",
        ),
    }
)
"""The named recipes. ``"plain"``: white background, ImageNet normalisation, nothing else. ``"pix2vox"``:
Pix2Vox++'s published recipe; ``"lrgt"``: LRGT's (both with background 240 outside training)."""


# ---------------------------------------------------------------------------------------------- the transform
@dataclass(frozen=True)
class _Draw:
    """The random parameters of one sample."""

    background: tuple[int, int, int]  # RGB in 0..255
    factors: tuple[float, float, float]  # brightness, contrast, saturation
    order: tuple[int, ...]  # the order the three jitter ops are applied in
    lighting: tuple[float, float, float]  # PCA weights
    channels: tuple[int, ...]  # RGB permutation
    flips: tuple[bool, ...]  # one per image
    scenes: tuple[tuple[int, float, float], ...] = ()  # folder backgrounds: (image, row u, column v) per image


class ImageTransform:
    """RGBA uint8 images -> model input: composite on a background, centre-crop, resize, (augment,) normalise.

    With the defaults it is the plain transform (white background, ImageNet normalisation). The keyword
    arguments are the fields of :class:`ImageRecipe` (see there for what each op does); any random op makes
    the transform need a ``key`` per sample, from which every random parameter is drawn, so equal keys give
    bit-identical tensors whatever the worker, process or call order.

    Args:
        image_size: output side ``S`` in pixels.
        background: RGB background (0-255) composited under transparent pixels.
        normalize: one of :data:`NORMALIZATIONS`.
        crop: as in :class:`ImageRecipe` (deterministic).
        background_range: as in :class:`ImageRecipe` (random).
        brightness: as in :class:`ImageRecipe` (random).
        contrast: as in :class:`ImageRecipe` (random).
        saturation: as in :class:`ImageRecipe` (random).
        lighting_std: as in :class:`ImageRecipe` (random).
        hflip: as in :class:`ImageRecipe` (random).
        permute_rgb: as in :class:`ImageRecipe` (random).
        clamp: as in :class:`ImageRecipe` (deterministic).
        background_folder: as in :class:`ImageRecipe` (random); the folder is scanned once, here
            (:class:`BackgroundFolder`).

    Call it on ``(H, W, 4)`` or ``(T, H, W, 4)`` uint8 arrays (the ``T`` views of one sample); returns
    ``(3, S, S)`` or ``(T, 3, S, S)`` float32.

    Raises:
        TypeError: an argument of the wrong type (names the argument and the value).
        ValueError: an argument out of range, or a ``background_folder`` without images; on call, images that
            are not ``(H, W, 4)`` or ``(T, H, W, 4)``, or a random transform called without a ``key``.
        FileNotFoundError: ``background_folder`` is not a directory.

    Example:
        >>> images = np.zeros((3, 96, 96, 4), np.uint8)  # three RGBA views
        >>> ImageTransform(64)(images).shape
        torch.Size([3, 3, 64, 64])
        >>> train = ImageTransform(64, hflip=True)
        >>> train.is_random, torch.equal(train(images, key=(0, 0, 5)), train(images, key=(0, 0, 5)))
        (True, True)
    """

    def __init__(
        self,
        image_size: int = 224,
        background: Sequence[int] = (255, 255, 255),
        normalize: str | None = "imagenet",
        *,
        crop: float = 1.0,
        background_range: Sequence[int] | Sequence[Sequence[int]] | None = None,
        brightness: float = 0.0,
        contrast: float = 0.0,
        saturation: float = 0.0,
        lighting_std: float = 0.0,
        hflip: bool = False,
        permute_rgb: bool = False,
        clamp: bool = True,
        background_folder: str | os.PathLike | None = None,
    ) -> None:
        self.image_size = check_int("image_size", image_size, minimum=1)
        # ImageRecipe.__post_init__ checks and normalises the looser argument types given here
        self.recipe = ImageRecipe(
            background=cast("tuple[int, int, int]", background),
            background_range=cast("tuple[tuple[int, int], ...] | None", background_range),
            crop=crop,
            brightness=brightness,
            contrast=contrast,
            saturation=saturation,
            lighting_std=lighting_std,
            hflip=hflip,
            permute_rgb=permute_rgb,
            clamp=clamp,
            normalize=normalize,
            background_folder=cast("str | None", background_folder),
        )
        folder = self.recipe.background_folder
        #: the scanned folder of training backgrounds, or None
        self.backgrounds = BackgroundFolder(folder) if folder is not None else None
        self.background = self.recipe.background
        self.normalize = self.recipe.normalize

    @property
    def is_random(self) -> bool:
        """Whether a call needs a ``key``."""
        return self.recipe.is_random

    def __repr__(self) -> str:
        return f"ImageTransform(image_size={self.image_size}, recipe={self.recipe!r})"

    def draw(self, key: Sequence[int], num_images: int) -> _Draw:
        """The random parameters of the sample ``key`` (e.g. ``(seed, epoch, index)``) with ``num_images`` views.

        The same numbers are drawn in the same order whatever the recipe enables, so switching one op on or
        off leaves the draws of the others unchanged.
        """
        rng = np.random.default_rng([*(int(k) for k in key), _AUGMENTATION_STREAM])
        r = self.recipe
        ranges = r.background_range or tuple((c, c) for c in r.background)
        u = rng.random(3)
        background = tuple(lo + min(int(u[c] * (hi - lo + 1)), hi - lo) for c, (lo, hi) in enumerate(ranges))
        jitter = rng.uniform(-1.0, 1.0, 3) * np.array([r.brightness, r.contrast, r.saturation])
        order = rng.permutation(3)
        lighting = rng.standard_normal(3) * r.lighting_std
        channels = rng.permutation(3)
        flips = rng.random(num_images) < 0.5
        scenes: tuple[tuple[int, float, float], ...] = ()
        if self.backgrounds is not None:  # a stream of its own: the draws above stay as they were
            scene_rng = np.random.default_rng([*(int(k) for k in key), _AUGMENTATION_STREAM, _BACKGROUND_STREAM])
            picks = []
            for _ in range(num_images):  # view t's draws do not depend on how many views follow
                index = int(scene_rng.integers(len(self.backgrounds)))
                u, v = scene_rng.random(2)
                picks.append((index, float(u), float(v)))
            scenes = tuple(picks)
        return _Draw(
            background=background,  # type: ignore[arg-type]  # one value per RGB channel: three
            factors=tuple(float(1.0 + j) for j in jitter),  # type: ignore[arg-type]  # jitter has three values
            order=tuple(int(i) for i in order),
            lighting=tuple(float(a) for a in lighting),  # type: ignore[arg-type]  # lighting has three values
            channels=tuple(int(c) for c in channels) if r.permute_rgb else (0, 1, 2),
            flips=tuple(bool(f) for f in flips) if r.hflip else (False,) * num_images,
            scenes=scenes,
        )

    def __call__(self, rgba: np.ndarray, key: Sequence[int] | None = None) -> Tensor:
        # 1. check inputs
        single = rgba.ndim == 3
        batch = rgba[None] if single else rgba
        if batch.ndim != 4 or batch.shape[-1] not in (3, 4):
            raise ValueError(f"`rgba` must be (H, W, 4) or (T, H, W, 4) RGBA images, got shape {rgba.shape}")
        if self.is_random and key is None:
            raise ValueError(
                "`key` must be given for a random transform (e.g. (seed, epoch, index)): every random "
                f"parameter of a sample is drawn from it; got None for {self!r}"
            )
        r = self.recipe
        draw = self.draw(key, batch.shape[0]) if self.is_random and key is not None else None
        background: tuple[int, ...]
        if draw is not None:
            background = draw.background
        else:  # a one-colour range is a fixed training background
            background = tuple(lo for lo, _ in r.background_range) if r.background_range else r.background
        # 2. composite, crop, resize (the plain path is the package's original transform, bit for bit)
        x = torch.from_numpy(np.ascontiguousarray(batch)).float() / 255.0  # (T, H, W, C)
        if x.shape[-1] == 4:
            if draw is not None and draw.scenes:  # a crop of a folder image per view, the view's size
                height, width = batch.shape[1:3]
                assert self.backgrounds is not None, "draw makes scenes only with a background folder"
                crops = [self.backgrounds.crop(i, (u, v), height, width) for i, u, v in draw.scenes]
                bg = torch.from_numpy(np.stack(crops)).to(x.dtype) / 255.0  # (T, H, W, 3)
            else:
                bg = torch.tensor(background, dtype=x.dtype) / 255.0
            x = alpha_composite(x, bg)
        x = x.permute(0, 3, 1, 2)
        if r.crop < 1.0:
            x = center_crop(x, r.crop)
        if x.shape[-1] != self.image_size or x.shape[-2] != self.image_size:
            x = F.interpolate(
                x, size=(self.image_size, self.image_size), mode="bilinear", antialias=True, align_corners=False
            )
            x = x.clamp(0.0, 1.0)
        # 3. augment (training)
        if draw is not None:
            x = self._augment(x, draw)
        # 4. normalise
        x = normalize_image(x, r.normalize)
        return x[0] if single else x

    def _augment(self, x: Tensor, draw: _Draw) -> Tensor:
        r = self.recipe
        jitter = (adjust_brightness, adjust_contrast, adjust_saturation)
        amounts = (r.brightness, r.contrast, r.saturation)
        for op in draw.order:
            if amounts[op] > 0:
                x = jitter[op](x, draw.factors[op])
        if r.lighting_std > 0:
            x = pca_lighting(x, draw.lighting)
        if r.clamp and (any(a > 0 for a in amounts) or r.lighting_std > 0):
            x = x.clamp(0.0, 1.0)
        if any(draw.flips):
            flips = torch.tensor(draw.flips)
            x = torch.where(flips[:, None, None, None], hflip(x), x)
        if draw.channels != (0, 1, 2):
            x = permute_channels(x, draw.channels)
        return x
