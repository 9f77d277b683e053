"""What a diffusers-format Zero-1-to-3 checkpoint folder holds: weight files, pose convention, noise schedule.

:meth:`~lightning_vtr.synthesis.zero123.Zero123Synthesizer.from_pretrained` reads a checkpoint component by
component; this module answers the questions it asks of the files: which weight files of a subfolder to load
(plain, ``*.{variant}.*`` or sharded), which pose embedding a checkpoint gets, whether its ``scheduler/`` is
the schedule every Zero-1-to-3 variant was trained with, and what to tell a user who passes an original
latent-diffusion ``.ckpt``. Nothing here imports ``diffusers`` or ``transformers``.
"""

from __future__ import annotations

import hashlib
import json
import math
import re
import shlex
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn

__all__ = [
    "CLIP_MEAN",
    "CLIP_STD",
    "COMPONENT_KINDS",
    "LDM_SUFFIXES",
    "OPTIONAL_FOLDERS",
    "PROJECTION_LAYOUTS",
    "REFERENCE_DDIM",
    "WeightFiles",
    "Zero123CheckpointError",
    "checkpoint_name",
    "describe_folder",
    "find_local_weights",
    "fingerprint_files",
    "ldm_checkpoint_error",
    "load_projection",
    "noise_schedule_mismatches",
    "pose_embedding_for",
    "read_feature_extractor",
    "says_stable",
    "select_weight_files",
]

#: OpenAI CLIP's normalisation, used when a checkpoint has no ``feature_extractor/``.
CLIP_MEAN: tuple[float, float, float] = (0.48145466, 0.4578275, 0.40821073)
CLIP_STD: tuple[float, float, float] = (0.26862954, 0.26130258, 0.27577711)

#: Model subfolder -> the library whose file names its weights use.
COMPONENT_KINDS: dict[str, str] = {"unet": "diffusers", "vae": "diffusers", "image_encoder": "transformers"}
#: Camera-projection subfolder -> name of its linear layer in the weights. The layout does not tell the
#: pose convention: threestudio's converter writes ``clip_camera_projection/`` for the original Zero-1-to-3,
#: Zero123-XL and Stable Zero123 alike.
PROJECTION_LAYOUTS: dict[str, str] = {"cc_projection": "projection", "clip_camera_projection": "proj"}
#: Subfolders read when present, with the config file each holds.
OPTIONAL_FOLDERS: dict[str, str] = {
    "scheduler": "scheduler_config.json",
    "feature_extractor": "preprocessor_config.json",
}
#: Suffixes of single-file (original latent-diffusion) checkpoints.
LDM_SUFFIXES: tuple[str, ...] = (".ckpt", ".pt", ".pth")

#: The DDIM sampler of the reference: the SD 1.x noise schedule every Zero-1-to-3 variant was trained with
#: (scaled_linear 0.00085 -> 0.012, 1000 steps, epsilon) and latent-diffusion's DDIM choices (timesteps
#: ``range(0, 1000, 1000 // steps) + 1``, ``alpha_prev`` of the last step = ``alphas_cumprod[0]``, no clipping).
REFERENCE_DDIM: dict[str, Any] = dict(
    num_train_timesteps=1000,
    beta_start=0.00085,
    beta_end=0.012,
    beta_schedule="scaled_linear",
    clip_sample=False,
    set_alpha_to_one=False,
    steps_offset=1,
    prediction_type="epsilon",
)
# entries a loaded DDIM config must match besides REFERENCE_DDIM (diffusers' defaults, which the reference uses)
_REFERENCE_EXTRA: dict[str, Any] = dict(
    trained_betas=None, timestep_spacing="leading", thresholding=False, rescale_betas_zero_snr=False
)

# weight file names: <stem>[.<variant>][-00001-of-00002].<ext>; shard indexes: <stem>.<ext>.index[.<variant>].json
_WEIGHT_FILE = re.compile(
    r"^(?P<stem>diffusion_pytorch_model|model|pytorch_model)(?:\.(?P<variant>[^.\-]+))?"
    r"(?P<shard>-\d+-of-\d+)?\.(?P<ext>safetensors|bin)$"
)
_INDEX_FILE = re.compile(
    r"^(?P<stem>diffusion_pytorch_model|model|pytorch_model)\.(?P<ext>safetensors|bin)\.index"
    r"(?:\.(?P<variant>[^.]+))?\.json$"
)
#: library -> the (stem, extension) pairs it saves, safetensors first (preferred when both exist)
_WEIGHT_STEMS: dict[str, tuple[tuple[str, str], ...]] = {
    "diffusers": (("diffusion_pytorch_model", "safetensors"), ("diffusion_pytorch_model", "bin")),
    "transformers": (("model", "safetensors"), ("pytorch_model", "bin")),
}
_HUB_SNAPSHOT = re.compile(r"^models--(?P<owner>.+?)--(?P<name>.+)$")


class Zero123CheckpointError(ValueError):
    """A Zero-1-to-3 checkpoint directory (or a set of components) is missing parts or they do not fit."""


def describe_folder(folder: Path) -> str:
    """``"found [names]"``, ``"folder empty"`` or ``"folder missing"``, for error messages."""
    if not folder.is_dir():
        return "folder missing"
    names = sorted(p.name for p in folder.iterdir())
    return f"found {names}" if names else "folder empty"


# ---------------------------------------------------------------------------------------------- weight files


@dataclass(frozen=True)
class WeightFiles:
    """The weight files of one component: one file, or a shard index followed by its shards.

    Attributes:
        variant: the ``*.{variant}.*`` infix (``"fp16"``), ``None`` for plain files.
        files: names relative to the component's folder; with shards, the index comes first.
    """

    variant: str | None
    files: tuple[str, ...]

    @property
    def sharded(self) -> bool:
        return self.files[0].endswith(".json")


def _expected_names(kind: str) -> str:
    stems = ", ".join(f"{stem}[.<variant>].{ext}" for stem, ext in _WEIGHT_STEMS[kind])
    return f"{stems} (or shards with an .index.json)"


def select_weight_files(names: Iterable[str], kind: str, variant: str | None, where: str) -> WeightFiles:
    """Pick the weight files of one component from the file names of its folder.

    Plain files win when they exist and no ``variant`` is asked for; a folder holding a single variant only
    (``diffusion_pytorch_model.fp16.safetensors``) gets that variant. An asked-for variant is used where the
    folder has it; a folder with plain files only falls back to them. Safetensors win over ``.bin``.

    Args:
        names: file names in the folder (no subdirectories).
        kind: ``"diffusers"`` or ``"transformers"`` (their weight file names differ).
        variant: the variant asked for, ``None`` to detect it.
        where: the folder as it should appear in messages (``"unet/"``).

    Raises:
        Zero123CheckpointError: no usable weights, several variants and none asked for, or the asked-for
            variant missing while other variants exist; the message lists what was found.
    """
    names = sorted(set(names))
    # (variant, stem, ext) -> single file and/or index + shards
    singles: dict[tuple[str | None, str, str], str] = {}
    indexes: dict[tuple[str | None, str, str], str] = {}
    shards: dict[tuple[str | None, str, str], list[str]] = {}
    allowed = set(_WEIGHT_STEMS[kind])
    for name in names:
        if m := _INDEX_FILE.match(name):
            key = (m["variant"], m["stem"], m["ext"])
            if key[1:] in allowed:
                indexes[key] = name
        elif m := _WEIGHT_FILE.match(name):
            key = (m["variant"], m["stem"], m["ext"])
            if key[1:] not in allowed:
                continue
            if m["shard"]:
                shards.setdefault(key, []).append(name)
            else:
                singles[key] = name
    usable = set(singles) | set(indexes)
    variants = {key[0] for key in usable}
    found = f"found {names}" if names else "folder empty"
    if not variants:
        raise Zero123CheckpointError(f"{where}: expected weights named {_expected_names(kind)}; {found}")
    if variant is not None and variant in variants:
        chosen = variant
    elif None in variants:
        chosen = None  # plain files: the default, and the fallback for a folder without the asked-for variant
    elif variant is not None:
        raise Zero123CheckpointError(
            f"{where}: expected weights of variant {variant!r} (or plain ones), found only the variants "
            f"{sorted(variants, key=str)}: {found}"
        )
    elif len(variants) == 1:
        (chosen,) = variants
    else:
        raise Zero123CheckpointError(
            f"{where}: holds several weight variants {sorted(variants, key=str)} and no plain files; pass `variant=` "
            f"to choose one ({found})"
        )
    for stem, ext in _WEIGHT_STEMS[kind]:
        key = (chosen, stem, ext)
        if key in singles:
            return WeightFiles(chosen, (singles[key],))
        if key in indexes:
            return WeightFiles(chosen, (indexes[key], *shards.get(key, [])))
    raise AssertionError("unreachable: a usable variant has a single file or an index")  # pragma: no cover


def find_local_weights(folder: Path, kind: str, variant: str | None, config: str = "config.json") -> WeightFiles:
    """:func:`select_weight_files` on a local folder, also requiring ``config`` and every shard its index names.

    Raises:
        Zero123CheckpointError: the folder, its config, its weights or a listed shard is missing.
    """
    where = f"{folder.name}/"
    if not folder.is_dir():
        raise Zero123CheckpointError(
            f"{where}: expected {config} + weights named {_expected_names(kind)}; folder missing"
        )
    names = [p.name for p in folder.iterdir() if p.is_file()]
    if config not in names:
        raise Zero123CheckpointError(f"{where}: expected {config}; {describe_folder(folder)}")
    weights = select_weight_files(names, kind, variant, where)
    if weights.sharded:
        index = json.loads((folder / weights.files[0]).read_text())
        listed = sorted(set(index.get("weight_map", {}).values()))
        missing = [name for name in listed if not (folder / name).is_file()]
        if not listed or missing:
            raise Zero123CheckpointError(
                f"{where}{weights.files[0]}: expected a 'weight_map' whose shards all exist; "
                + (f"missing shards {missing}" if listed else "it lists no shards")
            )
        weights = WeightFiles(weights.variant, (weights.files[0], *listed))
    return weights


def _load_state_dict(file: Path) -> dict[str, Tensor]:
    if file.suffix == ".safetensors":
        from safetensors.torch import load_file

        return load_file(str(file))
    return torch.load(file, map_location="cpu", weights_only=True)


def load_projection(folder: Path, layer: str, weights: WeightFiles) -> nn.Linear:
    """Build the camera projection from its weights, inferring ``in``/``out`` sizes; raises with what was found.

    Args:
        folder: ``cc_projection/`` or ``clip_camera_projection/``.
        layer: the linear layer's name in the weights (``projection`` or ``proj``).
        weights: from :func:`find_local_weights`; shards are merged.

    Raises:
        Zero123CheckpointError: the weight tensors are missing, not 2-D, or disagree with ``config.json``.
    """
    state: dict[str, Tensor] = {}
    for name in weights.files[1:] if weights.sharded else weights.files:
        state.update(_load_state_dict(folder / name))
    label = f"{folder.name}/{weights.files[0]}"
    weight, bias = state.get(f"{layer}.weight"), state.get(f"{layer}.bias")
    if weight is None or weight.ndim != 2:
        raise Zero123CheckpointError(
            f"{label}: expected a 2-D tensor '{layer}.weight' (and '{layer}.bias'), found keys {sorted(state)}"
        )
    out_features, in_features = weight.shape
    config_file = folder / "config.json"
    if config_file.is_file():
        config = json.loads(config_file.read_text())
        # threestudio's layout states its sizes; the community pipeline's config has none to check
        if "embedding_dim" in config:
            expected = (config["embedding_dim"], config["embedding_dim"] + config.get("additional_embeddings", 4))
            if (out_features, in_features) != expected:
                raise Zero123CheckpointError(
                    f"{folder.name}/: config.json says (out, in) = {expected} (embedding_dim, "
                    f"embedding_dim + additional_embeddings), but '{layer}.weight' has shape {tuple(weight.shape)}"
                )
    linear = nn.Linear(in_features, out_features, bias=bias is not None)
    with torch.no_grad():
        linear.weight.copy_(weight.float())
        if bias is not None:
            linear.bias.copy_(bias.float())
    return linear


def read_feature_extractor(folder: Path) -> dict[str, Any]:
    """Normalisation and crop size from a ``CLIPImageProcessor`` config (read as JSON: we preprocess in torch)."""
    config = json.loads((folder / OPTIONAL_FOLDERS["feature_extractor"]).read_text())
    crop = config.get("crop_size", config.get("size", 224))
    if isinstance(crop, dict):
        crop = crop.get("height", crop.get("shortest_edge", 224))
    return {
        "image_mean": tuple(config.get("image_mean", CLIP_MEAN)),
        "image_std": tuple(config.get("image_std", CLIP_STD)),
        "clip_size": int(crop),
    }


def fingerprint_files(root: Path, files: Iterable[str]) -> str:
    """Hash of the given files under ``root``: JSON by content, weights by name and size (cheap, copy-stable)."""
    h = hashlib.sha256()
    for rel in sorted(set(files)):
        file = root / rel
        if file.suffix == ".json":
            h.update(rel.encode() + file.read_bytes())
        else:
            h.update(f"{rel}:{file.stat().st_size}".encode())
    return h.hexdigest()[:16]


# ---------------------------------------------------------------------------------------------- noise schedule


def noise_schedule_mismatches(config: Mapping[str, Any]) -> list[str]:
    """Where a DDIM scheduler config departs from the reference sampler, as ``"key: expected X, found Y"``.

    The training schedule (``num_train_timesteps``, ``beta_*``, ``trained_betas``, ``prediction_type``) must
    be SD 1.x's; the sampling choices (``clip_sample``, ``set_alpha_to_one``, ``steps_offset``,
    ``timestep_spacing``, thresholding, zero-SNR rescaling) latent-diffusion's DDIM. Absent keys count as
    diffusers' defaults, which is what ``DDIMScheduler`` would use.
    """
    defaults = dict(
        num_train_timesteps=1000,
        beta_start=0.0001,
        beta_end=0.02,
        beta_schedule="linear",
        clip_sample=True,
        set_alpha_to_one=True,
        steps_offset=0,
        prediction_type="epsilon",
        **_REFERENCE_EXTRA,
    )
    problems = []
    for key, expected in {**REFERENCE_DDIM, **_REFERENCE_EXTRA}.items():
        found = config.get(key, defaults[key])
        if isinstance(expected, float) and isinstance(found, (int, float)) and not isinstance(found, bool):
            same = math.isclose(found, expected, rel_tol=1e-6, abs_tol=0.0)
        else:
            same = found == expected
        if not same:
            problems.append(f"{key}: expected {expected!r}, found {found!r}")
    return problems


# ---------------------------------------------------------------------------------------------- pose convention


def says_stable(name: str) -> bool:
    """Whether a checkpoint name says it is Stable Zero123: ``stable`` at the start of a word, any case."""
    return re.search(r"(?:^|[^a-z])stable", name.lower()) is not None


def checkpoint_name(folder: Path) -> str:
    """The name a local checkpoint goes by: the repository name for a Hub cache snapshot, else the folder's."""
    folder = Path(folder).absolute()
    if folder.parent.name == "snapshots" and (m := _HUB_SNAPSHOT.match(folder.parent.parent.name)):
        return f"{m['owner']}/{m['name']}"
    return folder.name


def pose_embedding_for(requested: str, name: str) -> tuple[str, str]:
    """The pose embedding a checkpoint called ``name`` gets, and why (for the log).

    ``"auto"`` gives ``"stable"`` when the name (the repository name of a Hub id, the folder name of a local
    directory) says "stable" and ``"zero123"`` otherwise: the original Zero-1-to-3 and Zero123-XL are the
    checkpoints most conversions hold, and the folder layout cannot tell them from Stable Zero123.
    """
    if requested != "auto":
        return requested, "asked for"
    short = name.rsplit("/", 1)[-1]
    if says_stable(short):
        return "stable", f"the name {short!r} says 'stable'"
    return "zero123", f"the default: the name {short!r} does not say 'stable'"


# ---------------------------------------------------------------------------------------------- messages


def ldm_checkpoint_error(path: Path) -> Zero123CheckpointError:
    """The error for an original latent-diffusion checkpoint file: what it is and how to convert it."""
    dump = path.with_name(f"{path.stem}-diffusers")
    return Zero123CheckpointError(
        f"`path` must be a diffusers-format Zero-1-to-3 directory (unet/, vae/, image_encoder/, cc_projection/ "
        f"or clip_camera_projection/), got the single file {str(path)!r}, an original latent-diffusion checkpoint. "
        "Convert it once with threestudio's converter, from a threestudio checkout:\n"
        f"    python scripts/convert_zero123_to_diffusers.py --checkpoint_path {shlex.quote(str(path))} "
        "--original_config_file load/zero123/sd-objaverse-finetune-c_concat-256.yaml "
        f"--dump_path {shlex.quote(str(dump))}\n"
        "and pass the output directory (for Stable Zero123 add pose_embedding='stable' or keep 'stable' in the "
        "directory name). Converted copies are on the Hugging Face Hub: bennyguo/zero123-diffusers, "
        "bennyguo/zero123-xl-diffusers, ashawkey/stable-zero123-diffusers; pass the id instead."
    )
