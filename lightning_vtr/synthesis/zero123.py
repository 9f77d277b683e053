"""Zero-1-to-3 novel-view synthesis assembled from ``diffusers`` / ``transformers`` components.

diffusers ships no Zero-1-to-3 pipeline, and its community file cannot load the checkpoints found in the wild
as a whole, so :class:`Zero123Synthesizer` holds the five components explicitly (a UNet with 8 input
channels, a VAE, a CLIP vision encoder, a DDIM scheduler and the linear "camera projection") and runs the
sampling loop itself. ``diffusers`` and ``transformers`` are imported only when weights are loaded, so the
rest of the package works without them (``pip install lightning-vtr[zero123]``).

Checkpoint files (variants, shards, the noise schedule, the pose convention) are read by
:mod:`~lightning_vtr.synthesis.zero123_checkpoint`; Hub ids are resolved by :mod:`~lightning_vtr.synthesis.zero123_hub`.
The package's tests exercise tiny randomly initialised models only, not released checkpoints.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any, Literal, cast

import numpy as np
import torch
import torch.nn.functional as F
from lightning.pytorch.utilities import rank_zero_info, rank_zero_warn
from torch import Tensor, nn

from lightning_vtr.geometry import check_viewpoints
from lightning_vtr.synthesis.base import SynthesisRequest, Synthesizer
from lightning_vtr.synthesis.cache import viewpoint_key
from lightning_vtr.synthesis.pose import POSE_EMBEDDINGS, nearest_source_view, relative_pose
from lightning_vtr.synthesis.zero123_checkpoint import (
    CLIP_MEAN,
    CLIP_STD,
    COMPONENT_KINDS,
    OPTIONAL_FOLDERS,
    PROJECTION_LAYOUTS,
    REFERENCE_DDIM,
    Zero123CheckpointError,
    find_local_weights,
    fingerprint_files,
    load_projection,
    noise_schedule_mismatches,
    pose_embedding_for,
    read_feature_extractor,
)
from lightning_vtr.synthesis.zero123_hub import resolve_checkpoint
from lightning_vtr.utils.compositing import alpha_composite
from lightning_vtr.utils.validation import check_choice, check_float, check_int, check_type

if TYPE_CHECKING:  # pragma: no cover
    # the defining modules: mypy reads `from diffusers import ...` as diffusers' dummy (no-torch) classes
    from diffusers.models.autoencoders.autoencoder_kl import AutoencoderKL
    from diffusers.models.unets.unet_2d_condition import UNet2DConditionModel
    from diffusers.schedulers.scheduling_ddim import DDIMScheduler
    from transformers import CLIPVisionModelWithProjection

__all__ = ["CLIP_MEAN", "CLIP_STD", "Zero123CheckpointError", "Zero123Synthesizer"]


def _fingerprint_modules(modules: Sequence[nn.Module]) -> str:
    """Hash of parameter names, shapes and float64 moments: tells apart randomly built models, no weights needed."""
    h = hashlib.sha256()
    with torch.no_grad():
        for module in modules:
            for name, p in module.state_dict().items():
                q = p.detach().double()
                h.update(f"{name}{tuple(p.shape)}{q.sum().item():.9e}{q.abs().sum().item():.9e}".encode())
    return h.hexdigest()[:16]


def _center_fit(image: Tensor, size: int, fill: float = 1.0) -> Tensor:
    """Centre ``(C, h, w)`` on a ``(C, size, size)`` canvas of ``fill``, cropping what does not fit."""
    c, h, w = image.shape
    out = torch.full((c, size, size), fill, dtype=image.dtype)
    top, left = (size - h) // 2, (size - w) // 2
    src_r0, src_c0 = max(0, -top), max(0, -left)
    dst_r0, dst_c0 = max(0, top), max(0, left)
    rows, cols = min(h - src_r0, size - dst_r0), min(w - src_c0, size - dst_c0)
    out[:, dst_r0 : dst_r0 + rows, dst_c0 : dst_c0 + cols] = image[:, src_r0 : src_r0 + rows, src_c0 : src_c0 + cols]
    return out


def _resize(image: Tensor, size: int) -> Tensor:
    """Antialiased bilinear resize of ``(C, h, w)`` to ``(C, size, size)``."""
    if image.shape[-2:] == (size, size):
        return image
    return F.interpolate(image[None], size=(size, size), mode="bilinear", align_corners=False, antialias=True)[0]


class Zero123Synthesizer(Synthesizer):
    """Zero-1-to-3 / Stable Zero123 novel-view synthesis with classifier-free guidance and DDIM sampling.

    For each target viewpoint the nearest source view (great-circle angle) is the input image. The input is
    centred on its alpha bounding box, composited on white and resized to the model resolution
    (``unet.config.sample_size * 2 ** (len(vae.config.block_out_channels) - 1)``, 256 for real checkpoints).
    Its CLIP image embedding (bicubic resize to ``clip_size`` with ``align_corners=True`` and no antialiasing,
    as the reference; CLIP mean/std) concatenated with the relative pose ``T``
    (:func:`~lightning_vtr.synthesis.pose.relative_pose`) goes through the camera projection to one
    cross-attention token; its VAE latent (posterior mode, *not* multiplied by the VAE scaling factor) is
    concatenated to the noisy latent (4 + 4 channels). The unconditional branch of classifier-free guidance
    uses zeros for both; it is skipped only when ``guidance_scale == 1`` (as in the reference: a scale in
    ``[0, 1)`` mixes toward the unconditional prediction, ``0`` is unconditional).

    Outputs are decoded (``latents / scaling_factor``), clipped to ``[0, 1]``, mapped back to the input's
    framing (when ``restore_scale``: scaled by the inverse of the input crop's scale and centred, so objects
    keep the dataset's size), resized to ``image_size`` and returned as RGBA uint8. Alpha is 0 where every RGB
    channel is at least ``background_threshold`` (near white: the model paints the background white) and
    255 elsewhere, so pure white object parts are lost to the background.

    Noise is drawn per (object, target viewpoint) from a generator seeded by ``seed``, the object id and the
    viewpoint (rounded to 1e-3 degree), so a view does not change with the batch it was generated in.

    Args:
        unet: ``UNet2DConditionModel`` with ``in_channels = 2 * vae latent channels``.
        vae: ``AutoencoderKL``.
        image_encoder: ``CLIPVisionModelWithProjection``.
        projection: ``nn.Linear(projection_dim + 4, cross_attention_dim)``, the camera projection.
        scheduler: ``DDIMScheduler``; default: the SD 1.x schedule Zero-1-to-3 was trained with, sampled as the
            reference does (:data:`~lightning_vtr.synthesis.zero123_checkpoint.REFERENCE_DDIM`).
        pose_embedding: ``"zero123"`` (original Zero-1-to-3 and Zero123-XL; 4th pose entry: radius difference)
            or ``"stable"`` (Stable Zero123: the source polar angle), see :mod:`lightning_vtr.synthesis.pose`.
        num_inference_steps: DDIM steps (50 in the reference).
        guidance_scale: classifier-free guidance weight (3.0 in the reference; 1 skips the unconditional branch).
        eta: DDIM ``eta`` (1.0 in the reference: stochastic).
        seed: base seed of the per-view noise.
        image_size: side of the returned images (the dataset's image size).
        batch_size: (source, target) pairs per UNet call (twice as many rows with guidance).
        foreground_ratio: fraction of the model input's side the object's longer bbox side fills.
        background_threshold: in ``[0, 1]``; RGB at or above it on every channel counts as background.
        restore_scale: undo the input crop's scale on the output (else just resize the model output).
        image_mean: CLIP normalisation mean (RGB).
        image_std: CLIP normalisation std (RGB).
        clip_size: CLIP input side in pixels.
        device: where to run; default the current CUDA device at call time (each DDP rank's GPU), else CPU.
        dtype: default ``float16`` on CUDA, ``float32`` on CPU; ``bfloat16`` is allowed on both.
        weights_id: identifies the weights in :meth:`config_key` (set by :meth:`from_pretrained`); default: a
            hash of the components' parameters.

    Raises:
        Zero123CheckpointError: if the components do not fit together (every mismatch listed).
        TypeError: for an argument of the wrong type (e.g. a float ``image_size``).
        ValueError: for an out-of-range argument.

    Example::

        synth = Zero123Synthesizer.from_pretrained("bennyguo/zero123-xl-diffusers", image_size=128)
        images = synth.synthesize(requests)  # one (T, 128, 128, 4) uint8 array per request
    """

    def __init__(
        self,
        unet: UNet2DConditionModel,
        vae: AutoencoderKL,
        image_encoder: CLIPVisionModelWithProjection,
        projection: nn.Linear,
        scheduler: DDIMScheduler | None = None,
        *,
        pose_embedding: Literal["zero123", "stable"] = "zero123",
        num_inference_steps: int = 50,
        guidance_scale: float = 3.0,
        eta: float = 1.0,
        seed: int = 0,
        image_size: int = 256,
        batch_size: int = 8,
        foreground_ratio: float = 0.8,
        background_threshold: float = 0.94,
        restore_scale: bool = True,
        image_mean: Sequence[float] = CLIP_MEAN,
        image_std: Sequence[float] = CLIP_STD,
        clip_size: int = 224,
        device: str | torch.device | None = None,
        dtype: torch.dtype | None = None,
        weights_id: str | None = None,
    ) -> None:
        from diffusers.schedulers.scheduling_ddim import DDIMScheduler  # (its defining module: see the top)

        if scheduler is None:
            scheduler = DDIMScheduler(**REFERENCE_DDIM)
        problems = self._check_components(unet, vae, image_encoder, projection, scheduler)
        if problems:
            raise Zero123CheckpointError("Zero-1-to-3 components do not fit together:\n  - " + "\n  - ".join(problems))
        check_choice("pose_embedding", pose_embedding, POSE_EMBEDDINGS)
        self._check_generation_args(num_inference_steps, guidance_scale, eta)
        for name, value in (("image_size", image_size), ("batch_size", batch_size), ("clip_size", clip_size)):
            check_int(name, value, minimum=1)
        check_float("foreground_ratio", foreground_ratio, minimum=0.0, maximum=1.0, min_open=True)
        check_float("background_threshold", background_threshold, minimum=0.0, maximum=1.0, min_open=True)
        for name, entries in (("image_mean", image_mean), ("image_std", image_std)):
            if len(entries) != 3:
                raise ValueError(f"`{name}` must have 3 entries (RGB), got {entries!r}")

        self.unet, self.vae, self.image_encoder, self.projection, self.scheduler = (
            unet,
            vae,
            image_encoder,
            projection,
            scheduler,
        )
        for module in self._modules():
            module.eval().requires_grad_(False)
        self.pose_embedding = pose_embedding
        self.num_inference_steps = num_inference_steps
        self.guidance_scale = float(guidance_scale)
        self.eta = float(eta)
        self.seed = int(seed)
        self.image_size = image_size
        self.batch_size = batch_size
        self.foreground_ratio = float(foreground_ratio)
        self.background_threshold = float(background_threshold)
        self.restore_scale = bool(restore_scale)
        self.image_mean = tuple(float(m) for m in image_mean)
        self.image_std = tuple(float(s) for s in image_std)
        self.clip_size = clip_size
        self.vae_scale_factor = 2 ** (len(vae.config.block_out_channels) - 1)  # type: ignore[attr-defined]  # diffusers' FrozenDict config has attributes
        sample_size = unet.config.sample_size  # type: ignore[attr-defined]  # diffusers' FrozenDict config has attributes
        sample_size = sample_size[0] if isinstance(sample_size, (tuple, list)) else sample_size
        #: side of the model's input and output images in pixels
        self.resolution = int(sample_size) * self.vae_scale_factor
        self._device_arg = None if device is None else torch.device(device)
        self._dtype_arg = dtype
        self.weights_id = weights_id if weights_id is not None else _fingerprint_modules(self._modules())
        self._resolve_placement()  # fail early on an unsupported device/dtype pair

    # ------------------------------------------------------------------ loading

    @classmethod
    def from_pretrained(
        cls,
        path: str | os.PathLike,
        *,
        device: str | torch.device | None = None,
        dtype: torch.dtype | None = None,
        pose_embedding: Literal["auto", "zero123", "stable"] = "auto",
        variant: str | None = None,
        revision: str | None = None,
        cache_dir: str | os.PathLike | None = None,
        token: str | bool | None = None,
        local_files_only: bool = False,
        **kwargs: Any,
    ) -> Zero123Synthesizer:
        """Load a diffusers-format Zero-1-to-3 checkpoint, component by component, from a folder or the Hub.

        Expected subfolders: ``unet/``, ``vae/``, ``image_encoder/`` and either ``cc_projection/`` (linear
        ``projection``: the community pipeline's layout, kxic's conversions) or ``clip_camera_projection/``
        (linear ``proj``: threestudio's converter, used for Zero-1-to-3, Zero123-XL and Stable Zero123 alike).
        Optional: ``scheduler/`` (checked against the SD 1.x schedule, see below) and ``feature_extractor/``
        (its mean, std and crop size are used). Weights may be plain, a single ``*.{variant}.*`` set (detected:
        folders holding only ``diffusion_pytorch_model.fp16.safetensors`` load as they are) or sharded with an
        ``*.index.json``.

        The pose embedding (:func:`~lightning_vtr.synthesis.pose.relative_pose`) is ``"zero123"`` for either
        layout unless asked otherwise or the checkpoint's name (the repository name of a Hub id, else the
        folder's name) says "stable"; the choice and its reason are logged. Every Zero-1-to-3 variant was
        trained with the SD 1.x noise schedule (scaled_linear 0.00085 -> 0.012, 1000 steps, epsilon): a
        ``scheduler/`` that departs from it (the diffusers conversion script writes beta 0.02 -> 0.085) draws a
        warning and is replaced by it. Pass ``scheduler=`` to use your own, unchecked.

        Args:
            path: a checkpoint directory, or a Hub id ``"owner/name"`` (e.g. ``"bennyguo/zero123-xl-diffusers"``)
                that is not a local path. Only the files read are downloaded (configs plus one weight set per
                component); ``HF_HUB_OFFLINE=1`` restricts a Hub id to the Hub cache.
            device: see the class.
            dtype: see the class.
            pose_embedding: ``"auto"`` (see above), ``"zero123"`` or ``"stable"``.
            variant: weight variant to prefer (``"fp16"``); default: plain weights, or the only variant present.
            revision: Hub branch, tag or commit of a Hub id (default ``"main"``).
            cache_dir: Hub cache directory (default ``HF_HUB_CACHE``).
            token: Hub token for private or gated repositories.
            local_files_only: never reach the network for a Hub id.
            **kwargs: any other constructor argument (``num_inference_steps``, ``image_size``, ``scheduler``, ...).

        Raises:
            FileNotFoundError: ``path`` is neither a directory nor a Hub id that is cached or downloadable; the
                message names the id and the command that fetches it.
            ValueError: for an unknown ``pose_embedding`` (or a bad constructor argument in ``kwargs``).
            Zero123CheckpointError: for an original latent-diffusion ``.ckpt`` (the message says how to convert
                it), or listing every missing or mismatched component with what was expected in which subfolder
                and what was found.

        Warns:
            UserWarning: ``scheduler/`` departs from the SD 1.x schedule (each difference listed).
        """
        from diffusers import AutoencoderKL, DDIMScheduler, UNet2DConditionModel
        from transformers import CLIPVisionModelWithProjection

        # 1. check arguments, then find the files (a local folder, the Hub cache or a download)
        check_choice("pose_embedding", pose_embedding, ("auto", *POSE_EMBEDDINGS))
        if variant is not None:
            check_type("variant", variant, str)
        source = resolve_checkpoint(
            path,
            revision=revision,
            cache_dir=cache_dir,
            token=token,
            local_files_only=local_files_only,
            variant=variant,
        )
        folder = source.folder

        # 2. the model components; every problem is collected so one error lists them all
        problems: list[str] = []
        loaded: dict[str, Any] = {}
        used: list[str] = []  # files whose identity goes into the cache key
        variants: dict[str, str] = {}
        specs = [
            ("unet", UNet2DConditionModel),
            ("vae", AutoencoderKL),
            ("image_encoder", CLIPVisionModelWithProjection),
        ]
        for sub, model_cls in specs:
            try:
                weights = find_local_weights(folder / sub, COMPONENT_KINDS[sub], variant)
            except Zero123CheckpointError as err:
                problems.append(f"{err} [{model_cls.__name__}]")
                continue
            try:
                loaded[sub] = model_cls.from_pretrained(
                    folder, subfolder=sub, variant=weights.variant, local_files_only=True
                )
            except Exception as err:
                problems.append(f"{sub}/: expected a {model_cls.__name__}; loading failed: {type(err).__name__}: {err}")
                continue
            used += [f"{sub}/config.json", *(f"{sub}/{name}" for name in weights.files)]
            if weights.variant is not None:
                variants[sub] = weights.variant

        # 3. the camera projection, sized from its weights
        layouts = [sub for sub in PROJECTION_LAYOUTS if (folder / sub).is_dir()]
        if not layouts:
            problems.append(
                "cc_projection/ or clip_camera_projection/: expected the camera projection (config.json + "
                f"diffusion_pytorch_model[.<variant>].safetensors or .bin); neither folder exists "
                f"(top level has {sorted(p.name for p in folder.iterdir())})"
            )
        else:
            layout = layouts[0]
            try:
                weights = find_local_weights(folder / layout, "diffusers", variant)
                loaded["projection"] = load_projection(folder / layout, PROJECTION_LAYOUTS[layout], weights)
                used += [f"{layout}/{name}" for name in ("config.json", *weights.files)]
                if weights.variant is not None:
                    variants[layout] = weights.variant
            except Zero123CheckpointError as err:
                problems.append(str(err))

        # 4. the noise schedule: the SD 1.x one unless the caller brings a scheduler
        if "scheduler" not in kwargs and (folder / "scheduler").is_dir():
            config_file = folder / "scheduler" / OPTIONAL_FOLDERS["scheduler"]
            try:
                mismatches = noise_schedule_mismatches(json.loads(config_file.read_text()))
                if not mismatches:
                    kwargs["scheduler"] = DDIMScheduler.from_pretrained(folder, subfolder="scheduler")
                    used.append(f"scheduler/{config_file.name}")
            except Exception as err:
                problems.append(f"scheduler/: expected a readable {config_file.name}; loading failed: {err}")
            else:
                if mismatches:
                    rank_zero_warn(
                        f"Zero123Synthesizer: {source.name} scheduler/{config_file.name} departs from the SD 1.x "
                        "noise schedule every Zero-1-to-3 variant was trained with (" + "; ".join(mismatches) + "); "
                        "using the SD 1.x schedule instead (scaled_linear 0.00085 -> 0.012, 1000 steps, epsilon)"
                    )
        if (folder / "feature_extractor" / OPTIONAL_FOLDERS["feature_extractor"]).is_file():
            for key, value in read_feature_extractor(folder / "feature_extractor").items():
                kwargs.setdefault(key, value)
            used.append(f"feature_extractor/{OPTIONAL_FOLDERS['feature_extractor']}")

        if problems:
            raise Zero123CheckpointError(
                f"Cannot load a Zero-1-to-3 checkpoint from {str(folder)!r}:\n  - "
                + "\n  - ".join(problems)
                + (f"\n{source.hint}" if source.hint else "")
            )

        # 5. the pose convention: the folder layout cannot tell it, so "zero123" unless told otherwise
        pose, reason = pose_embedding_for(pose_embedding, source.name)
        meaning = "4th entry: source polar angle" if pose == "stable" else "4th entry: radius difference"
        weight_note = f", weight variants {variants}" if variants else ""
        rank_zero_info(
            f"Zero123Synthesizer: {source.name}: pose embedding {pose!r} ({meaning}) - {reason}{weight_note}"
        )
        kwargs.setdefault("weights_id", f"{source.ident}#{fingerprint_files(folder, used)}")
        return cls(
            loaded["unet"],
            loaded["vae"],
            loaded["image_encoder"],
            loaded["projection"],
            pose_embedding=cast(Literal["zero123", "stable"], pose),  # checked above
            device=device,
            dtype=dtype,
            **kwargs,
        )

    @staticmethod
    def _check_components(unet: Any, vae: Any, image_encoder: Any, projection: Any, scheduler: Any) -> list[str]:
        from diffusers import AutoencoderKL, DDIMScheduler, UNet2DConditionModel
        from transformers import CLIPVisionModelWithProjection

        problems = []
        expected_types = [
            ("unet", unet, UNet2DConditionModel),
            ("vae", vae, AutoencoderKL),
            ("image_encoder", image_encoder, CLIPVisionModelWithProjection),
            ("projection", projection, nn.Linear),
            ("scheduler", scheduler, DDIMScheduler),
        ]
        for name, obj, typ in expected_types:
            if not isinstance(obj, typ):
                problems.append(f"{name}: expected a {typ.__name__}, got {type(obj).__name__}")
        if problems:
            return problems
        latent = vae.config.latent_channels
        if unet.config.in_channels != 2 * latent:
            problems.append(
                f"unet: expected in_channels = 2 x vae latent_channels = {2 * latent} "
                f"(noisy latent + image latent), found {unet.config.in_channels}"
            )
        if unet.config.out_channels != latent:
            problems.append(
                f"unet: expected out_channels = vae latent_channels = {latent}, found {unet.config.out_channels}"
            )
        clip_dim = image_encoder.config.projection_dim
        if projection.in_features != clip_dim + 4:
            problems.append(
                f"camera projection: expected in_features = image_encoder projection_dim + 4 = {clip_dim + 4}, "
                f"found {projection.in_features}"
            )
        cross = unet.config.cross_attention_dim
        cross = cross[0] if isinstance(cross, (tuple, list)) else cross
        if projection.out_features != cross:
            problems.append(
                f"camera projection: expected out_features = unet cross_attention_dim = {cross}, "
                f"found {projection.out_features}"
            )
        return problems

    # ------------------------------------------------------------------ placement

    def _modules(self) -> list[nn.Module]:
        return [self.unet, self.vae, self.image_encoder, self.projection]

    def _resolve_placement(self) -> tuple[torch.device, torch.dtype]:
        device = self._device_arg
        if device is None:
            # the current CUDA device is each DDP rank's own GPU under Lightning
            cuda = torch.cuda.is_available()
            device = torch.device("cuda", torch.cuda.current_device()) if cuda else torch.device("cpu")
        dtype = self._dtype_arg
        if dtype is None:
            dtype = torch.float16 if device.type == "cuda" else torch.float32
        if dtype not in (torch.float32, torch.float16, torch.bfloat16):
            raise ValueError(f"`dtype` must be torch.float32, torch.float16 or torch.bfloat16, got {dtype}")
        if device.type == "cpu" and dtype == torch.float16:
            raise ValueError("`dtype` torch.float16 is not supported on CPU; use torch.float32 or torch.bfloat16")
        return device, dtype

    @property
    def device(self) -> torch.device:
        """The device the next call runs on."""
        return self._resolve_placement()[0]

    @property
    def dtype(self) -> torch.dtype:
        """The dtype the next call runs in."""
        return self._resolve_placement()[1]

    def to(self, device: str | torch.device | None = None, dtype: torch.dtype | None = None) -> Zero123Synthesizer:
        """Choose the device and/or dtype (moved lazily, on the next call); returns ``self``."""
        if device is not None:
            self._device_arg = torch.device(device)
        if dtype is not None:
            self._dtype_arg = dtype
        self._resolve_placement()
        return self

    def _place(self) -> tuple[torch.device, torch.dtype]:
        device, dtype = self._resolve_placement()
        for module in self._modules():
            # read the module's actual placement: modules may be shared with another synthesizer or moved by hand
            param = next(module.parameters())
            same_device = param.device.type == device.type and device.index in (None, param.device.index)
            if not same_device or param.dtype != dtype:
                # diffusers warns on every .to(dtype); only pass the dtype when it changes
                module.to(device=device, dtype=None if param.dtype == dtype else dtype)
        return device, dtype

    # ------------------------------------------------------------------ configuration

    def config_key(self) -> str:
        """Everything that changes the output: weights, pose embedding, sampling settings, framing, dtype."""
        sched_config = {k: v for k, v in dict(self.scheduler.config).items() if not k.startswith("_")}
        sched = json.dumps(sched_config, sort_keys=True, default=str)
        return (
            f"Zero123Synthesizer(weights={self.weights_id}, pose={self.pose_embedding}, "
            f"steps={self.num_inference_steps}, guidance={self.guidance_scale!r}, eta={self.eta!r}, seed={self.seed}, "
            f"image_size={self.image_size}, resolution={self.resolution}, foreground_ratio={self.foreground_ratio!r}, "
            f"background_threshold={self.background_threshold!r}, restore_scale={self.restore_scale}, "
            f"clip=({self.clip_size}, {self.image_mean}, {self.image_std}), "
            f"dtype={str(self.dtype).removeprefix('torch.')}, "
            f"scheduler={hashlib.sha256(sched.encode()).hexdigest()[:12]})"
        )

    @staticmethod
    def _check_generation_args(num_inference_steps: Any, guidance_scale: Any, eta: Any) -> None:
        check_int("num_inference_steps", num_inference_steps, minimum=1)
        check_float("guidance_scale", guidance_scale, minimum=0.0)
        check_float("eta", eta, minimum=0.0, maximum=1.0)

    def pair_seed(self, object_id: str, target_viewpoint: Tensor) -> int:
        """The noise seed of one (object, target viewpoint in degrees) pair, derived from ``seed``."""
        digest = hashlib.sha256(f"{self.seed}|{object_id}|{viewpoint_key(target_viewpoint)}".encode()).digest()
        return int.from_bytes(digest[:8], "little") & (2**63 - 1)

    # ------------------------------------------------------------------ the pipeline

    def check_inputs(
        self,
        source_images: Sequence[np.ndarray] | np.ndarray,
        source_viewpoints: Tensor,
        target_viewpoints: Tensor,
        seeds: Sequence[int] | None,
        num_inference_steps: int,
        guidance_scale: float,
        eta: float,
        output_size: int,
        output_type: str,
    ) -> tuple[list[np.ndarray], Tensor, Tensor, list[int]]:
        """Validate everything before any work starts; returns normalised ``(images, source, target, seeds)``.

        Raises:
            TypeError: a count or setting of the wrong type (e.g. a float ``output_size``).
            ValueError: a bad image, mismatched lengths or an out-of-range setting (named in the message).
        """
        images = list(source_images)
        for i, image in enumerate(images):
            if not isinstance(image, np.ndarray) or image.dtype != np.uint8 or image.ndim != 3 or image.shape[-1] != 4:
                shape = getattr(image, "shape", None)
                raise ValueError(
                    f"`source_images[{i}]` must be an (H, W, 4) uint8 RGBA array, got shape {shape} and "
                    f"dtype {getattr(image, 'dtype', type(image).__name__)}"
                )
        n = len(images)
        src = check_viewpoints(source_viewpoints, "source_viewpoints").reshape(-1, 2)
        tgt = check_viewpoints(target_viewpoints, "target_viewpoints").reshape(-1, 2)
        if src.shape[0] != n or tgt.shape[0] != n:
            raise ValueError(
                f"`source_images`, `source_viewpoints` and `target_viewpoints` must have one entry per pair, got "
                f"{n}, {src.shape[0]} and {tgt.shape[0]}"
            )
        seeds = [self.seed + i for i in range(n)] if seeds is None else [int(s) for s in seeds]
        if len(seeds) != n:
            raise ValueError(f"`seeds` must have one entry per pair ({n}), got {len(seeds)}")
        self._check_generation_args(num_inference_steps, guidance_scale, eta)
        check_int("output_size", output_size, minimum=1)
        check_choice("output_type", output_type, ("np", "pt"))
        return images, src, tgt, seeds

    @torch.no_grad()
    def __call__(
        self,
        source_images: Sequence[np.ndarray] | np.ndarray,
        source_viewpoints: Tensor,
        target_viewpoints: Tensor,
        *,
        seeds: Sequence[int] | None = None,
        num_inference_steps: int | None = None,
        guidance_scale: float | None = None,
        eta: float | None = None,
        output_size: int | None = None,
        output_type: Literal["np", "pt"] = "np",
    ) -> np.ndarray | Tensor:
        """Generate one view per (source image, source viewpoint, target viewpoint) triple.

        Args:
            source_images: ``N`` RGBA uint8 images ``(H_i, W_i, 4)`` (an ``(N, H, W, 4)`` array works too).
            source_viewpoints: ``(N, 2)`` (yaw, pitch) in degrees of the images.
            target_viewpoints: ``(N, 2)`` (yaw, pitch) in degrees to synthesize.
            seeds: one noise seed per pair; default ``seed + i``.
            num_inference_steps: override the instance's DDIM steps.
            guidance_scale: override the instance's guidance (``1`` skips the unconditional branch).
            eta: override the instance's DDIM ``eta``.
            output_size: side of the returned RGBA images; default ``image_size``.
            output_type: ``"np"``: ``(N, S, S, 4)`` uint8 RGBA after postprocessing; ``"pt"``: the decoded
                ``(N, 3, R, R)`` float RGB in ``[0, 1]`` at the model resolution ``R``, before postprocessing.
        """
        steps = self.num_inference_steps if num_inference_steps is None else num_inference_steps
        guidance = self.guidance_scale if guidance_scale is None else guidance_scale
        eta = self.eta if eta is None else eta
        output_size = self.image_size if output_size is None else output_size

        # 1. check inputs
        images, source, target, seeds = self.check_inputs(
            source_images, source_viewpoints, target_viewpoints, seeds, steps, guidance, eta, output_size, output_type
        )
        if not images:
            return (
                torch.zeros(0, 3, self.resolution, self.resolution)
                if output_type == "pt"
                else np.zeros((0, output_size, output_size, 4), dtype=np.uint8)
            )
        self._place()

        # 2. preprocess: centre the object, composite on white, resize to the model resolution
        pixel_list, sides = zip(*(self.preprocess(image) for image in images))
        pixels = torch.stack(pixel_list)  # (N, 3, R, R) in [0, 1]

        # 3. relative pose of each pair (radians)
        pose = relative_pose(source.double(), target.double(), self.pose_embedding).float()  # (N, 4)

        # 4. denoise in batches
        batches = [slice(i, i + self.batch_size) for i in range(0, len(images), self.batch_size)]
        decoded = torch.cat([self._generate(pixels[b], pose[b], seeds[b], steps, guidance, eta) for b in batches])
        if output_type == "pt":
            return decoded

        # 5. postprocess: back to the input's framing and the requested size, RGBA uint8
        return np.stack(
            [
                self.postprocess(rgb, side, max(image.shape[:2]), output_size)
                for rgb, side, image in zip(decoded, sides, images)
            ]
        )

    def preprocess(self, image: np.ndarray) -> tuple[Tensor, int]:
        """Centre one ``(H, W, 4)`` uint8 RGBA image for the model.

        The object's bounding box comes from the alpha channel (alpha > 0); a fully opaque image uses its
        non-white pixels instead, an empty one the whole image. The crop is centred on a white square whose
        side makes the longer bbox side ``foreground_ratio`` of it, then resized to the model resolution.

        Returns:
            ``(3, R, R)`` float RGB in ``[0, 1]`` composited on white, and the square's side in input pixels.
        """
        rgba = torch.from_numpy(np.ascontiguousarray(image)).permute(2, 0, 1).float() / 255.0  # (4, H, W)
        rgb = alpha_composite(rgba, channels_first=True)  # on white
        mask = rgba[3] > 0
        if bool(mask.all()):
            mask = (rgb < self.background_threshold).any(dim=0)
        if not bool(mask.any()):
            mask = torch.ones_like(mask)
        rows, cols = torch.nonzero(mask.any(dim=1))[:, 0], torch.nonzero(mask.any(dim=0))[:, 0]
        crop = rgb[:, int(rows[0]) : int(rows[-1]) + 1, int(cols[0]) : int(cols[-1]) + 1]
        side = max(1, math.ceil(max(crop.shape[1:]) / self.foreground_ratio))
        return _resize(_center_fit(crop, side), self.resolution).clamp(0.0, 1.0), side

    def postprocess(self, rgb: Tensor, side: int, source_size: int, output_size: int) -> np.ndarray:
        """Turn one decoded ``(3, R, R)`` RGB in ``[0, 1]`` into an ``(S, S, 4)`` uint8 RGBA image, ``S = output_size``.

        With ``restore_scale`` the model image, which spans ``side`` input pixels, is resized to span as many
        output pixels (``side * output_size / source_size``) and centred, so the object keeps its size.
        """
        rgb = rgb.float()
        if self.restore_scale:
            span = max(1, round(side * output_size / source_size))
            rgb = _center_fit(_resize(rgb, span), output_size)
        else:
            rgb = _resize(rgb, output_size)
        rgb = rgb.clamp(0.0, 1.0)
        background = (rgb >= self.background_threshold).all(dim=0)
        alpha = torch.where(background, 0.0, 1.0)[None]
        rgba = torch.cat([rgb, alpha]).permute(1, 2, 0)
        return (rgba * 255.0).round().to(torch.uint8).numpy()

    def encode_image(self, pixels: Tensor, pose: Tensor) -> Tensor:
        """The conditioning token ``(n, 1, cross_attention_dim)``.

        Args:
            pixels: ``(n, 3, R, R)`` RGB in ``[0, 1]`` composited on white.
            pose: ``(n, 4)`` relative poses (radians), see :func:`~lightning_vtr.synthesis.pose.relative_pose`.
        """
        device, dtype = self._place()
        # the reference resizes with kornia: bicubic, align_corners=True, no antialiasing (values may overshoot)
        x = F.interpolate(pixels.float(), size=(self.clip_size, self.clip_size), mode="bicubic", align_corners=True)
        mean = torch.tensor(self.image_mean).view(1, 3, 1, 1)
        std = torch.tensor(self.image_std).view(1, 3, 1, 1)
        x = ((x - mean) / std).to(device=device, dtype=dtype)
        embeds = self.image_encoder(pixel_values=x).image_embeds  # (n, projection_dim), not normalised
        token = torch.cat([embeds[:, None, :], pose[:, None, :].to(device=device, dtype=dtype)], dim=-1)
        return self.projection(token)

    def encode_latents(self, pixels: Tensor) -> Tensor:
        """VAE posterior mode ``(n, C, R/f, R/f)`` of ``(n, 3, R, R)`` pixels in [0, 1].

        Zero-1-to-3 concatenates this latent as is: it is *not* multiplied by the VAE scaling factor.
        """
        device, dtype = self._place()
        return self.vae.encode((pixels * 2.0 - 1.0).to(device=device, dtype=dtype)).latent_dist.mode()

    def _generate(
        self, pixels: Tensor, pose: Tensor, seeds: Sequence[int], steps: int, guidance: float, eta: float
    ) -> Tensor:
        """Sample one batch; returns decoded ``(n, 3, R, R)`` float32 RGB in [0, 1] on the CPU."""
        device, dtype = self._place()
        # the reference skips the unconditional branch only at exactly 1; below 1 guidance extrapolates away
        do_guidance = guidance != 1.0

        # a. conditioning: one cross-attention token and the image latent; zeros for the unconditional branch
        token = self.encode_image(pixels, pose)
        image_latents = self.encode_latents(pixels)
        if do_guidance:
            token = torch.cat([torch.zeros_like(token), token])
            image_latents = torch.cat([torch.zeros_like(image_latents), image_latents])

        # b. initial noise, drawn on the CPU from per-pair generators so results do not depend on the device
        #    or on which other pairs share the batch
        generators = [torch.Generator().manual_seed(int(s)) for s in seeds]
        side = self.resolution // self.vae_scale_factor
        shape = (self.unet.config.out_channels, side, side)  # type: ignore[attr-defined]  # diffusers' FrozenDict config has attributes

        def noise() -> Tensor:
            return torch.stack([torch.randn(shape, generator=g) for g in generators]).to(device=device, dtype=dtype)

        latents = noise() * self.scheduler.init_noise_sigma

        # c. DDIM with classifier-free guidance
        self.scheduler.set_timesteps(steps, device=device)
        for t in self.scheduler.timesteps:
            model_input = torch.cat([latents] * 2) if do_guidance else latents
            model_input = torch.cat([self.scheduler.scale_model_input(model_input, t), image_latents], dim=1)
            noise_pred = self.unet(model_input, t, encoder_hidden_states=token).sample
            if do_guidance:
                uncond, cond = noise_pred.chunk(2)
                noise_pred = uncond + guidance * (cond - uncond)
            variance_noise = noise() if eta > 0 else None
            step = self.scheduler.step(noise_pred, t, latents, eta=eta, variance_noise=variance_noise)
            latents = step.prev_sample  # type: ignore[union-attr]  # return_dict=True (the default): an output object

        # d. decode
        decoded = self.vae.decode(latents / self.vae.config.scaling_factor).sample  # type: ignore[attr-defined]  # diffusers' FrozenDict config has attributes
        return ((decoded.float() + 1.0) / 2.0).clamp(0.0, 1.0).cpu()

    # ------------------------------------------------------------------ Synthesizer interface

    def synthesize(self, requests: list[SynthesisRequest]) -> list[np.ndarray]:
        """Generate every request's target views from its nearest source view; one ``(T_i, S, S, 4)`` uint8 each."""
        images, sources, targets, seeds, counts = [], [], [], [], []
        for r, req in enumerate(requests):
            src_images = np.asarray(req.source_images)
            src_vp = check_viewpoints(req.source_viewpoints, f"requests[{r}].source_viewpoints").reshape(-1, 2)
            tgt_vp = check_viewpoints(req.target_viewpoints, f"requests[{r}].target_viewpoints").reshape(-1, 2)
            if src_images.ndim != 4 or src_images.shape[0] != src_vp.shape[0]:
                raise ValueError(
                    f"`requests[{r}].source_images` must be (S, H, W, 4) with S = {src_vp.shape[0]} source "
                    f"viewpoints, got shape {src_images.shape}"
                )
            counts.append(tgt_vp.shape[0])
            if tgt_vp.shape[0] == 0:
                continue
            nearest = nearest_source_view(src_vp, tgt_vp)
            for t in range(tgt_vp.shape[0]):
                images.append(src_images[int(nearest[t])])
                sources.append(src_vp[int(nearest[t])].double())
                targets.append(tgt_vp[t].double())
                seeds.append(self.pair_seed(req.object_id, tgt_vp[t]))
        if images:
            out = self(images, torch.stack(sources), torch.stack(targets), seeds=seeds)
        else:
            out = np.zeros((0, self.image_size, self.image_size, 4), dtype=np.uint8)
        return list(np.split(out, np.cumsum(counts)[:-1].astype(int))) if counts else []
