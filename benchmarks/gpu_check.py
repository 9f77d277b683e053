"""One prepared check for a short GPU run: a Markdown + JSON table written row by row.

Rows, most valuable first (nothing is downloaded; every model has random weights):

* ``train: <model> bf16-mixed``: paper-preset Pix2Vox++ and LRGT training samples/s and peak memory at batch 8,
  autocast to bfloat16 around forward and loss (as Lightning's ``bf16-mixed`` does), random inputs.
* ``zero123``: Zero-1-to-3 at full size (SD 1.x UNet, SD VAE, CLIP ViT-L/14; ``benchmarks/zero123.py``'s
  components) in fp16, 50 DDIM steps with guidance 3.0: seconds per image at batch 1 and 8, peak memory.
* ``selection: <score>``: :class:`~lightning_vtr.selection.ErrorGuidedSelector` objects/s at K = 30 for the
  ``paper``, ``released`` and ``visible`` scores (``benchmarks/view_selection.py``'s objects and timer).
* ``fit: Pix2Vox++ tiny + callback`` and ``fit: LRGT tiny + callback``: the tiny preset trained 2 epochs in
  ``bf16-mixed`` with :class:`~lightning_vtr.ErrorGuidedViewAugmentation`: generated samples (asserted > 0),
  seconds, final loss (asserted finite). The dataset is ``--dataset DIR`` (built beforehand with
  ``--build-dataset DIR``, as ``benchmarks/gpu_prepare.sh`` does: 3 procedural categories x 6 objects, 64 px,
  3 views per set, R = 32), else one rendered in a temporary folder. The synthesizer is mesh rendering; when
  the renderer probe fails (or with ``--no-render``) and ``--dataset`` is given, it is Zero-1-to-3 with the
  tests' tiny random model (float16 on CUDA, 2 DDIM steps), and neither pyrender nor OpenGL is imported. The
  table names the synthesizer: ``fit: LRGT tiny + callback (bf16-mixed, zero123 tiny)``.
* ``train: <model> 32-true``: the training rows in float32, for reference.

How it runs, so that a run stopped anywhere still leaves a table:

* The script needs no install: it puts the repository root on ``sys.path`` (and, for its child processes, on
  ``PYTHONPATH``). ``--wheels DIR`` installs the wheels in ``DIR`` (``benchmarks/gpu_prepare.sh`` fetches them)
  with ``pip install --no-index --no-deps --target DIR/site`` and appends ``DIR/site`` to ``sys.path`` *after*
  site-packages, so they add the packages the machine lacks and shadow none of its own. Where ``DIR`` holds
  several wheels of one project, the newest whose requirements the installed packages meet is used.
* Every row runs in a fresh child process with a timeout (``--row-timeout-s``, and never past the budget);
  on expiry its whole process group (data-loader and spawn workers included) is killed and the row records
  it. A row that raises, or a CUDA error that ends its process, is recorded in that row; the next row starts
  in a new process with a fresh CUDA context.
* Each finished row is appended to ``OUT/gpu_check.jsonl`` (flushed) and ``OUT/gpu_check.md`` is rewritten
  with the whole table; each child's output goes to ``OUT/logs/<row>.log``.
* After ``--budget-s`` seconds no row starts; the rows left are listed as skipped, by name.
* The first row that renders starts with a renderer probe (pyrender with EGL, one 32 px view of a box, in a
  child process with a timeout); if the probe fails, the fit rows run with Zero-1-to-3 instead (with
  ``--dataset``) or are skipped with its error (without). ``--no-render`` skips the probe and goes the same way.
* On a CPU the full-size rows are refused; ``--tiny`` shrinks every row for a CPU smoke run (without
  ``--dataset`` a 10-object dataset; one training batch per epoch, selection on 4 objects at R = 16, the tests'
  tiny Zero-1-to-3 in float32 at 2 DDIM steps, tiny presets at batch 1). The exit status is 0 when every row
  ran without error (the renderer probe's row skipped by ``--no-render`` aside).

Run::

    benchmarks/gpu_prepare.sh        # here: fetch the wheels into .gpu_wheels, build .gpu_dataset
    python3 benchmarks/gpu_check.py --wheels .gpu_wheels --dataset .gpu_dataset --out OUT --budget-s 420  # GPU
    python benchmarks/gpu_check.py --tiny --device cpu --budget-s 120 --out OUT     # CPU smoke run
    python benchmarks/gpu_check.py --rows zero123,"fit: Pix2Vox++ tiny + callback" --out OUT  # some rows only
    python benchmarks/gpu_check.py --build-dataset .gpu_dataset  # only the fit rows' dataset (needs OpenGL)
    python3 benchmarks/gpu_check.py --wheels .gpu_wheels --dataset .gpu_dataset --out OUT --budget-s 300 \
        --no-render --rows "fit: Pix2Vox++ tiny + callback,fit: LRGT tiny + callback"  # fit rows, no OpenGL
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import importlib.util
import json
import math
import os
import re
import signal
import subprocess
import sys
import tempfile
import time
import traceback
import zipfile
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from types import ModuleType
from typing import Any

_HERE = Path(__file__).resolve().parent
ROOT = _HERE.parent
if str(ROOT) not in sys.path:  # `python benchmarks/gpu_check.py` puts benchmarks/, not the root, first
    sys.path.insert(0, str(ROOT))

#: share of the training objects given new views per selection in the fit rows; their 2 epochs select twice
#: (before epoch 0 and after it), so they generate ``2 * round(FIT_FRACTION * train objects)`` samples
FIT_FRACTION = 0.34
#: the fit rows' dataset: ``--build-dataset DIR`` (run by benchmarks/gpu_prepare.sh) builds it for ``--dataset DIR``;
#: without ``--dataset`` a fit row renders it in a temporary folder (3 x 6 objects split 4/1/1 per category)
FIT_DATASET: dict[str, Any] = dict(
    categories=["chair", "table", "airplane"], objects_per_category=6, image_size=64, resolution=32, views_per_set=3
)
#: ``--tiny`` without ``--dataset``: 2 x 5 objects split 3/1/1 per category, 32 px
TINY_FIT_DATASET: dict[str, Any] = dict(
    categories=["chair", "table"], objects_per_category=5, split=(0.6, 0.2, 0.2), image_size=32, resolution=32,
    views_per_set=4,
)  # fmt: skip
#: check name (as ``--rows`` takes it) -> model of the fit rows; the table adds the precision and synthesizer,
#: e.g. ``fit: LRGT tiny + callback (bf16-mixed, zero123 tiny)``
FIT_ROWS = {"fit: Pix2Vox++ tiny + callback": "pix2vox", "fit: LRGT tiny + callback": "lrgt"}
#: the fit rows' synthesizers and their names in the table: ``render`` (mesh rendering; needs OpenGL) and
#: ``zero123`` (Zero-1-to-3 with the random model of :func:`tiny_zero123_components`; float16 on CUDA; no OpenGL)
FIT_SYNTHS = {"render": "render", "zero123": "zero123 tiny"}
SCORES = ("paper", "released", "visible")
MODELS = {"pix2vox": "Pix2Vox++", "lrgt": "LRGT"}
#: seconds a probe child process may take (environment report, renderer probe)
PROBE_TIMEOUT_S = 90.0
#: seconds between SIGTERM and SIGKILL of a row's process group
KILL_GRACE_S = 5.0


@dataclass
class Row:
    """One line of the table: what was checked, how, its numbers, and the error or reason that stopped it.

    ``error`` is set when the row ran and failed (exception, crash, timeout); ``skipped`` when it never ran
    (budget spent, renderer missing, full size refused on a CPU). ``wall_s`` counts the child process's start.
    """

    check: str
    setup: str = ""
    results: dict[str, float] = field(default_factory=dict)
    error: str | None = None
    skipped: str | None = None
    wall_s: float | None = None


@dataclass
class RowSpec:
    """How to run one row: ``command`` plus ``["--result", path]`` is run as a child process, which writes the
    row's JSON (``{"setup", "results"}`` or ``{"error"}``) to that path."""

    check: str
    command: list[str]
    timeout_s: float
    needs_renderer: bool = False
    full_size: bool = False
    #: run instead of this row when the renderer failed or is off (``needs_renderer`` rows); ``None``: skip it
    without_renderer: RowSpec | None = None
    #: added to the skip reason of a ``needs_renderer`` row without ``without_renderer``
    without_renderer_hint: str = ""


# ============================================================================================ the child rows
def _load(path: Path, name: str) -> ModuleType:
    """Import a script by path (``benchmarks/`` and ``tests/`` are no packages), once."""
    if name not in sys.modules:
        spec = importlib.util.spec_from_file_location(name, path)
        assert spec is not None and spec.loader is not None, path
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        spec.loader.exec_module(module)
    return sys.modules[name]


def _sync(device: Any) -> None:
    import torch

    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _reset_peak(device: Any) -> None:
    import torch

    if device.type == "cuda":
        torch.cuda.synchronize(device)
        torch.cuda.reset_peak_memory_stats(device)


def _peak_gib(device: Any) -> float:
    import resource

    import torch

    if device.type == "cuda":
        return torch.cuda.max_memory_allocated(device) / 2**30
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20  # KiB on Linux


def _memory_name(device: Any) -> str:
    return "peak GiB" if device.type == "cuda" else "peak RSS GiB"


def tiny_zero123_components(seed: int = 0) -> dict[str, Any]:
    """A random 64 px Zero-1-to-3 model (the tests' tiny architecture; built here, as the device has no pytest).

    Returns:
        ``unet``, ``vae``, ``image_encoder``, ``projection`` and ``scheduler`` for
        :class:`~lightning_vtr.synthesis.zero123.Zero123Synthesizer`.
    """
    import torch
    from diffusers import AutoencoderKL, DDIMScheduler, UNet2DConditionModel
    from transformers import CLIPVisionConfig, CLIPVisionModelWithProjection

    from lightning_vtr.synthesis.zero123_checkpoint import REFERENCE_DDIM

    torch.manual_seed(seed)
    unet = UNet2DConditionModel(
        sample_size=8,
        in_channels=8,
        out_channels=4,
        block_out_channels=(32, 64),
        layers_per_block=1,
        down_block_types=("CrossAttnDownBlock2D", "DownBlock2D"),
        up_block_types=("UpBlock2D", "CrossAttnUpBlock2D"),
        cross_attention_dim=32,
        attention_head_dim=8,
        norm_num_groups=8,
    )
    vae = AutoencoderKL(
        in_channels=3,
        out_channels=3,
        down_block_types=("DownEncoderBlock2D",) * 4,
        up_block_types=("UpDecoderBlock2D",) * 4,
        block_out_channels=(8, 8, 16, 16),
        latent_channels=4,
        norm_num_groups=8,
        layers_per_block=1,
        sample_size=64,
    )
    clip = CLIPVisionConfig(
        hidden_size=32,
        intermediate_size=37,
        num_hidden_layers=2,
        num_attention_heads=4,
        image_size=224,
        patch_size=32,
        projection_dim=32,
    )
    image_encoder = CLIPVisionModelWithProjection(clip)
    projection = torch.nn.Linear(32 + 4, 32)
    scheduler = DDIMScheduler(**REFERENCE_DDIM)
    return dict(unet=unet, vae=vae, image_encoder=image_encoder, projection=projection, scheduler=scheduler)


def build_fit_dataset(root: Path, tiny: bool) -> None:
    """Build the fit rows' procedural dataset in ``root`` (:data:`FIT_DATASET`, :data:`TINY_FIT_DATASET` with
    ``tiny``); it renders, so it needs OpenGL."""
    from lightning_vtr.data.builder import build_dataset

    spec = TINY_FIT_DATASET if tiny else FIT_DATASET
    build_dataset(root, source="procedural", seed=0, workers=1, progress=False, **spec)


def fit_row(device: Any, tiny: bool, name: str, synth: str, dataset: Path | None) -> Row:
    """Tiny ``name`` (``pix2vox`` or ``lrgt``) with the callback, 2 epochs in bf16-mixed.

    Args:
        device: where to train (and synthesize).
        tiny: one training batch per epoch, batch 4 (else every batch, batch 8); without ``dataset``, the
            smaller :data:`TINY_FIT_DATASET`.
        name: the model, a key of :data:`MODELS`.
        synth: ``"render"`` (:class:`~lightning_vtr.synthesis.render.RenderSynthesizer`) or ``"zero123"``
            (:class:`~lightning_vtr.synthesis.zero123.Zero123Synthesizer` with :func:`tiny_zero123_components`,
            float16 on CUDA and float32 on a CPU, 2 DDIM steps); only ``"render"`` imports pyrender.
        dataset: a dataset folder (``--build-dataset``); ``None`` renders one in a temporary folder.

    Raises:
        RuntimeError: no sample was generated, or the final loss is not finite.
    """
    import lightning as L
    import torch

    from lightning_vtr import ErrorGuidedViewAugmentation, VTRDataModule
    from lightning_vtr.data.format import load_metadata
    from lightning_vtr.models import LRGT, Pix2VoxPlusPlus
    from lightning_vtr.synthesis.base import Synthesizer
    from lightning_vtr.utils.feedback import silence_lightning_tips

    silence_lightning_tips()
    with tempfile.TemporaryDirectory(prefix="gpu_check_") as tmp:
        build_s = 0.0
        if dataset is None:
            start = time.perf_counter()
            dataset = Path(tmp) / "data"
            build_fit_dataset(dataset, tiny)
            build_s = time.perf_counter() - start
        image_size = int(load_metadata(dataset)["image_size"])
        synthesizer: Synthesizer
        if synth == "render":
            from lightning_vtr.synthesis.render import RenderSynthesizer

            synthesizer = RenderSynthesizer(image_size=image_size)
            synth_setup = f"render {image_size} px"
        elif synth == "zero123":
            from lightning_vtr.synthesis.zero123 import Zero123Synthesizer

            dtype = torch.float16 if device.type == "cuda" else torch.float32
            components = tiny_zero123_components()
            for key, module in components.items():
                if isinstance(module, torch.nn.Module):
                    components[key] = module.to(device=device, dtype=dtype)
            synthesizer = Zero123Synthesizer(
                **components, num_inference_steps=2, image_size=image_size, device=device, dtype=dtype,
                weights_id="random tiny",
            )  # fmt: skip
            dtype_name = str(dtype).removeprefix("torch.")
            synth_setup = f"Zero-1-to-3 tiny random weights {synthesizer.resolution} px, {dtype_name}, 2 DDIM steps"
        else:
            raise ValueError(f"--fit-synth: expected one of {sorted(FIT_SYNTHS)}, got {synth!r}")
        L.seed_everything(0, verbose=False)
        model = {"pix2vox": Pix2VoxPlusPlus, "lrgt": LRGT}[name](preset="tiny", validation_fscore=False)
        dm = VTRDataModule(
            str(dataset),
            image_size=model.image_size,
            batch_size=4 if tiny else 8,
            recipe=type(model).image_recipe,
            generated_dir=f"{tmp}/gen",
        )
        callback = ErrorGuidedViewAugmentation(
            synthesizer=synthesizer, fraction=FIT_FRACTION, progress_bar=False, log_images=False
        )
        trainer = L.Trainer(
            max_epochs=2,
            accelerator=device.type,
            devices=[device.index] if device.type == "cuda" and device.index is not None else 1,
            precision="bf16-mixed",
            callbacks=[callback],
            default_root_dir=tmp,
            logger=False,
            enable_checkpointing=False,
            enable_progress_bar=False,
            enable_model_summary=False,
            num_sanity_val_steps=0,
            reload_dataloaders_every_n_epochs=1,
            limit_train_batches=1 if tiny else None,
        )
        start = time.perf_counter()
        trainer.fit(model, datamodule=dm)
        seconds = time.perf_counter() - start
        loss = trainer.callback_metrics["train/loss"]
        generated = len(dm.generated_samples)
        results: dict[str, float] = {
            "generated samples": generated,
            "seconds": seconds,
            "final loss": float(loss),
            "train objects": len(dm.split_records("train")),
        }
        if build_s:
            results["dataset build s"] = build_s
    if generated == 0:
        raise RuntimeError(f"the callback generated no sample in 2 epochs (fraction {FIT_FRACTION}, {synth_setup})")
    if not math.isfinite(results["final loss"]):
        raise RuntimeError(f"the final training loss is {results['final loss']} (not finite)")
    setup = (
        f"{device.type}, bf16-mixed, 2 epochs{' of 1 batch' if tiny else ''}, batch {dm.batch_size}, "
        f"fraction {FIT_FRACTION}, {synth_setup}, {image_size} px dataset, "
        f"loss dtype {str(loss.dtype).removeprefix('torch.')}"
    )
    return Row(fit_check(name, synth), setup, results)


def fit_check(name: str, synth: str) -> str:
    """The table's name of a fit row: ``fit: <model> tiny + callback (bf16-mixed, <synthesizer>)``."""
    return f"fit: {MODELS[name]} tiny + callback (bf16-mixed, {FIT_SYNTHS[synth]})"


def selection_row(device: Any, tiny: bool, score: str) -> Row:
    """ErrorGuidedSelector objects/s at K = 30 for ``score`` (view_selection.py's objects and timer)."""
    bench = _load(_HERE / "view_selection.py", "_gpu_check_view_selection")
    batch, res, repeats = (4, 16, 2) if tiny else (64, 32, 7)
    predicted, target, _ = bench.make_objects(batch, res)
    predicted, target = predicted.to(device), target.to(device)
    _reset_peak(device)
    build, median, best = bench.time_selector(predicted, target, 30, score, repeats)
    _sync(device)
    results = {
        "objects/s": median,
        "best objects/s": best,
        "table build s": build,
        _memory_name(device): _peak_gib(device),
    }
    return Row(f"selection: {score}", f"{device.type}, K = 30, {batch} objects, R = {res}, {repeats} repeats", results)


def zero123_row(device: Any, tiny: bool) -> Row:
    """Zero-1-to-3 with random weights: seconds per image at batch 1 and 8 (guidance 3.0)."""
    import torch

    from lightning_vtr.synthesis.zero123 import Zero123Synthesizer

    bench = _load(_HERE / "zero123.py", "_gpu_check_zero123")
    torch.manual_seed(0)
    if tiny:  # the tests' tiny model: 64 x 64
        components, dtype, steps, size = tiny_zero123_components(), torch.float32, 2, "tiny 64 px"
    else:  # built on the device: random initialisation of ~1.2 G parameters is slow on the CPU
        with torch.device(device):
            components = bench.full_size_components()
        dtype, steps, size = torch.float16 if device.type == "cuda" else torch.float32, 50, "full size 256 px"
    for name, module in components.items():
        if isinstance(module, torch.nn.Module):
            components[name] = module.to(device=device, dtype=dtype)
    synth = Zero123Synthesizer(**components, device=device, dtype=dtype, weights_id="random")
    unet_m = sum(p.numel() for p in synth.unet.parameters()) / 1e6
    _reset_peak(device)
    results = {}
    for batch in (1, 8):
        synth.batch_size = batch
        results[f"s/image batch {batch}"] = bench._time(synth, batch, steps, sync=device.type == "cuda")
    results[_memory_name(device)] = _peak_gib(device)
    dtype_name = str(dtype).removeprefix("torch.")
    return Row(
        "zero123",
        f"{device.type}, {size}, {unet_m:.0f} M UNet, {dtype_name}, {steps} DDIM steps, guidance 3.0",
        results,
    )


def train_row(device: Any, tiny: bool, name: str, precision: str) -> Row:
    """Training samples/s and peak memory of a preset (``pix2vox`` or ``lrgt``) in ``precision`` on random inputs.

    ``precision`` is ``"bf16-mixed"`` (autocast to bfloat16 around forward and loss) or ``"32-true"``.
    """
    import torch

    from lightning_vtr.models import LRGT, Pix2VoxPlusPlus

    preset, batch, warmup, steps = ("tiny", 1, 1, 1) if tiny else ("paper", 8, 3, 10)
    torch.manual_seed(0)
    model = {"pix2vox": Pix2VoxPlusPlus, "lrgt": LRGT}[name](preset=preset).to(device).train()
    optimizers = model.configure_optimizers()
    optimizer = optimizers["optimizer"] if isinstance(optimizers, dict) else optimizers
    s, r = model.image_size, model.voxel_resolution
    images = torch.randn(batch, model.num_views, 3, s, s, device=device)
    voxels = (torch.rand(batch, r, r, r, device=device) > 0.7).float()
    _reset_peak(device)
    start = time.perf_counter()
    for step in range(warmup + steps):
        if step == warmup:
            _sync(device)
            start = time.perf_counter()
        optimizer.zero_grad(set_to_none=True)
        if precision == "bf16-mixed":
            autocast: Any = torch.autocast(device_type=device.type, dtype=torch.bfloat16)
        else:
            autocast = contextlib.nullcontext()
        with autocast:
            loss = model.loss(model(images), voxels)
        loss.backward()
        optimizer.step()
    _sync(device)
    rate = batch * steps / (time.perf_counter() - start)
    results = {"samples/s": rate, _memory_name(device): _peak_gib(device), "loss": float(loss.detach())}
    params = sum(p.numel() for p in model.parameters()) / 1e6
    setup = (
        f"{device.type}, {preset} preset ({params:.1f} M params, {s} px, {model.num_views} views), {precision}, "
        f"batch {batch}, {warmup} warm-up + {steps} timed steps"
    )
    return Row(f"train: {MODELS[name]} {precision}", setup, results)


def row_functions(
    tiny: bool, fit_synth: str = "render", dataset: Path | None = None
) -> dict[str, tuple[Callable[[Any], Row], float, bool]]:
    """``check -> (function of the device, full-size timeout in s, needs the renderer)``, in table order.

    ``fit_synth`` and ``dataset`` are the fit rows' synthesizer and dataset (see :func:`fit_row`); their rows
    need the renderer when either renders.
    """
    out: dict[str, tuple[Callable[[Any], Row], float, bool]] = {}
    for name, label in MODELS.items():
        out[f"train: {label} bf16-mixed"] = (lambda d, n=name: train_row(d, tiny, n, "bf16-mixed"), 150.0, False)
    out["zero123"] = (lambda d: zero123_row(d, tiny), 240.0, False)
    for score in SCORES:
        out[f"selection: {score}"] = (lambda d, s=score: selection_row(d, tiny, s), 90.0, False)
    renders = fit_synth == "render" or dataset is None
    for check, name in FIT_ROWS.items():
        out[check] = (lambda d, n=name: fit_row(d, tiny, n, fit_synth, dataset), 150.0, renders)
    for name, label in MODELS.items():
        out[f"train: {label} 32-true"] = (lambda d, n=name: train_row(d, tiny, n, "32-true"), 150.0, False)
    return out


CHECKS = tuple(row_functions(tiny=True))
"""Every row's name, in table order."""


def _error_text(err: BaseException) -> str:
    first = str(err).splitlines()[0] if str(err) else ""
    return f"{type(err).__name__}: {first}"[:300]


def _child_row(
    check: str, device_name: str, tiny: bool, result: Path, fit_synth: str = "render", dataset: Path | None = None
) -> int:
    """Run one row in this (child) process and write its JSON to ``result``; 0, or 1 when the row failed."""
    import torch

    device = torch.device(device_name)
    if device.type == "cuda" and device.index is None:
        device = torch.device("cuda", torch.cuda.current_device())
    fn = row_functions(tiny, fit_synth, dataset)[check][0]
    try:
        row = fn(device)
        payload: dict[str, Any] = {"setup": row.setup, "results": row.results}
        status = 0
    except Exception as err:
        traceback.print_exc()
        text = _error_text(err)
        if device.type == "cuda" and "CUDA" in str(err):
            text += " (CUDA error; the next row starts in a fresh process)"
        payload, status = {"error": text}, 1
    result.write_text(json.dumps(payload))
    return status


def _child_environment(result: Path) -> int:
    """Write the device, versions and optional imports of this interpreter to ``result`` (``{"results": ...}``)."""
    import platform

    info: dict[str, Any] = {"python": platform.python_version()}
    try:
        import torch

        info.update(torch=torch.__version__, cuda=torch.version.cuda, cuda_available=torch.cuda.is_available())
        if info["cuda_available"]:
            props = torch.cuda.get_device_properties(0)
            info.update(
                device=torch.cuda.get_device_name(0),
                capability=".".join(map(str, torch.cuda.get_device_capability(0))),
                memory_gib=round(props.total_memory / 2**30, 1),
                device_count=torch.cuda.device_count(),
            )
        else:
            info["device"] = f"CPU ({os.cpu_count()} cores)"
    except Exception as err:
        info["torch_error"] = _error_text(err)
    versions = {}
    for module in ("lightning", "torchmetrics", "numpy", "transformers", "huggingface_hub", "diffusers", "trimesh"):
        try:
            versions[module] = getattr(importlib.import_module(module), "__version__", "?")
        except Exception as err:
            versions[module] = f"absent ({_error_text(err)})"
    for module in ("pyrender", "jsonargparse"):
        try:
            importlib.import_module(module)
            versions[module] = "imports"
        except Exception as err:
            versions[module] = f"absent ({_error_text(err)})"
    info["packages"] = versions
    result.write_text(json.dumps({"results": info}))
    return 0


def _child_renderer(result: Path) -> int:
    """Render one 32 px view of a box with the package's renderer; write ``{"results"}`` or ``{"error"}``."""
    try:
        import trimesh

        from lightning_vtr.renderer import Renderer

        start = time.perf_counter()
        with Renderer(image_size=32) as renderer:
            rgba = renderer.render(trimesh.creation.box(extents=(0.6, 0.6, 0.6)), [[30.0, 20.0]])
        covered = float((rgba[..., 3] > 0).mean())
        if not covered > 0:
            raise RuntimeError(f"the rendered box covers no pixel (image shape {rgba.shape})")
        payload: dict[str, Any] = {
            "setup": f"pyrender, PYOPENGL_PLATFORM={os.environ.get('PYOPENGL_PLATFORM')}, one 32 px view",
            "results": {"s": time.perf_counter() - start, "covered share": covered},
        }
        status = 0
    except Exception as err:
        traceback.print_exc()
        payload, status = {"error": _error_text(err)}, 1
    result.write_text(json.dumps(payload))
    return status


# ============================================================================================ wheels
def _wheel_name(path: Path) -> tuple[str, str]:
    """``(normalised project name, version)`` from a wheel's file name."""
    name, version = path.name.split("-")[:2]
    return re.sub(r"[-_.]+", "-", name).lower(), version


def _installed_version(project: str) -> str | None:
    import importlib.metadata

    try:
        return importlib.metadata.version(project)
    except importlib.metadata.PackageNotFoundError:
        return None


def choose_wheels(
    wheels: Sequence[Path], installed: Callable[[str], str | None] = _installed_version
) -> tuple[list[Path], list[str]]:
    """The wheels to install: one per project.

    Where several wheels of one project are given, the newest whose requirements (those without an extra or
    environment marker that excludes them) on *installed* projects are all met is chosen; the newest if none is.

    Args:
        wheels: ``.whl`` paths.
        installed: the installed version of a project (normalised name), ``None`` when absent.

    Returns:
        ``(chosen wheels sorted by name, one line per choice made among several)``.
    """
    from packaging.requirements import Requirement
    from packaging.version import Version

    groups: dict[str, list[Path]] = {}
    for wheel in wheels:
        groups.setdefault(_wheel_name(wheel)[0], []).append(wheel)
    chosen, notes = [], []
    for project, paths in sorted(groups.items()):
        paths = sorted(paths, key=lambda p: Version(_wheel_name(p)[1]), reverse=True)
        if len(paths) == 1:
            chosen.append(paths[0])
            continue
        pick, reasons = paths[0], []
        for path in paths:
            with zipfile.ZipFile(path) as archive:
                meta = next(n for n in archive.namelist() if n.endswith(".dist-info/METADATA"))
                lines = archive.read(meta).decode().splitlines()
            unmet = []
            for line in lines:
                if not line.startswith("Requires-Dist:"):
                    continue
                req = Requirement(line.split(":", 1)[1].strip())
                if req.marker is not None and not req.marker.evaluate({"extra": ""}):
                    continue
                have = installed(re.sub(r"[-_.]+", "-", req.name).lower())
                if have is not None and not req.specifier.contains(have, prereleases=True):
                    unmet.append(f"{req.name}{req.specifier} (installed {have})")
            if not unmet:
                pick = path
                break
            reasons.append(f"{path.name}: {', '.join(unmet)}")
        chosen.append(pick)
        notes.append(f"{project}: {pick.name}" + (f" (not {'; '.join(reasons)})" if reasons else ""))
    return chosen, notes


def install_wheels(wheel_dir: Path, site: Path, log: Path) -> list[str]:
    """Install the chosen wheels of ``wheel_dir`` into ``site`` (``pip --no-index --no-deps --target``).

    Returns:
        Lines for the table's header: the choices made and the installed wheels.

    Raises:
        FileNotFoundError: ``wheel_dir`` holds no wheel.
        RuntimeError: pip failed (its output is in ``log``).
    """
    wheels = sorted(wheel_dir.glob("*.whl"))
    if not wheels:
        raise FileNotFoundError(f"--wheels {wheel_dir}: no .whl file there (run benchmarks/gpu_prepare.sh)")
    chosen, notes = choose_wheels(wheels)
    command = [sys.executable, "-m", "pip", "install", "--no-index", "--no-deps", "--upgrade"]
    command += ["--disable-pip-version-check", "--target", str(site), *map(str, chosen)]
    with open(log, "w") as out:
        done = subprocess.run(command, stdout=out, stderr=subprocess.STDOUT, timeout=300, check=False)
    if done.returncode != 0:
        text = log.read_text()
        if "No module named pip" not in text:
            tail = text.strip().splitlines()[-1:] or [""]
            raise RuntimeError(f"pip install --target {site} ended with code {done.returncode}: {tail[0]}")
        for wheel in chosen:  # no pip: a wheel is a zip of its site-packages files (and *.data/ trees)
            _unpack_wheel(wheel, site)
        notes.append("no pip here: the wheels were unpacked with zipfile")
    return [*notes, "installed: " + ", ".join(p.name for p in chosen)]


def _unpack_wheel(wheel: Path, site: Path) -> None:
    """Unpack ``wheel`` into ``site`` as pip would place its library files (``*.data/purelib|platlib`` at top)."""
    with zipfile.ZipFile(wheel) as archive:
        for member in archive.namelist():
            parts = Path(member).parts
            if parts[0].endswith(".data"):
                if len(parts) < 3 or parts[1] not in ("purelib", "platlib"):
                    continue  # scripts, headers, data: not needed to import
                parts = parts[2:]
            target = site.joinpath(*parts)
            if member.endswith("/"):
                continue
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_bytes(archive.read(member))


# ============================================================================================ the runner
def _slug(check: str) -> str:
    return re.sub(r"[^A-Za-z0-9]+", "_", check).strip("_")


def _kill_group(process: subprocess.Popen) -> None:
    """SIGTERM, then SIGKILL, to the process group of ``process`` (started in a new session); never blocks long.

    A process stuck in the kernel (a hung driver call) may outlive SIGKILL for a while: it is left behind
    after ``2 * KILL_GRACE_S`` seconds rather than blocking the table.
    """
    for sig in (signal.SIGTERM, signal.SIGKILL):
        try:
            os.killpg(process.pid, sig)
        except ProcessLookupError:
            break
        with contextlib.suppress(subprocess.TimeoutExpired):
            process.wait(timeout=KILL_GRACE_S)


def _log_tail(log: Path, lines: int = 1) -> str:
    try:
        text = [line for line in log.read_text(errors="replace").splitlines() if line.strip()]
    except OSError:
        return ""
    return " / ".join(text[-lines:])[:300]


def run_child(spec: RowSpec, timeout_s: float, log_dir: Path, env: Mapping[str, str] | None = None) -> Row:
    """Run ``spec.command --result FILE`` in a new process group; kill the group after ``timeout_s``.

    Returns:
        The row from the child's JSON, or one whose ``error`` says how the child ended without it (timeout,
        exit code or signal, and the last line of its log ``log_dir/<check>.log``).
    """
    log = log_dir / f"{_slug(spec.check)}.log"
    with tempfile.TemporaryDirectory(prefix="gpu_check_row_") as tmp:
        result = Path(tmp) / "row.json"
        start = time.perf_counter()
        with open(log, "w") as out:
            process = subprocess.Popen(
                [*spec.command, "--result", str(result)],
                stdout=out,
                stderr=subprocess.STDOUT,
                stdin=subprocess.DEVNULL,
                start_new_session=True,
                env=None if env is None else dict(env),
                cwd=ROOT,
            )
            try:
                code: int | None = process.wait(timeout=max(timeout_s, 0.0))
            except subprocess.TimeoutExpired:
                code = None
            _kill_group(process)  # also ends workers the row left behind
        wall = time.perf_counter() - start
        payload: dict[str, Any] = {}
        if result.exists():
            try:
                payload = json.loads(result.read_text())
            except json.JSONDecodeError as err:
                payload = {"error": f"unreadable result ({err})"}
    row = Row(spec.check, payload.get("setup", ""), payload.get("results", {}), payload.get("error"), wall_s=wall)
    if not payload:
        if code is None:
            how = f"no result within {timeout_s:.0f} s; its processes were killed"
        elif code < 0:
            how = f"its process ended by {signal.Signals(-code).name} without a result"
        else:
            how = f"its process ended with code {code} without a result"
        tail = _log_tail(log)
        row.error = how + (f"; last log line: {tail}" if tail else "")
    return row


def _number(value: float) -> str:
    return str(value) if isinstance(value, int) else f"{value:.4g}"


def markdown(table: Sequence[Row], header: Sequence[str]) -> str:
    """The header lines and the table: one line per row, ``name value`` pairs, ``ERROR:`` or ``SKIPPED:``."""
    lines = [*header, "", "| check | setup | results | wall s |", "| --- | --- | --- | --- |"]
    for row in table:
        if row.error:
            cell = f"ERROR: {row.error}"
        elif row.skipped:
            cell = f"SKIPPED: {row.skipped}"
        else:
            cell = "; ".join(f"{k} {_number(v)}" for k, v in row.results.items())
        wall = "" if row.wall_s is None else f"{row.wall_s:.1f}"
        cells = (row.check, row.setup, cell, wall)
        lines.append("| " + " | ".join(part.replace("|", "/").replace("\n", " ") for part in cells) + " |")
    return "\n".join(lines)


class Table:
    """The rows so far, written to ``out`` after each one: ``gpu_check.jsonl`` appended, ``gpu_check.md`` rewritten."""

    def __init__(self, out: Path, header: list[str], info: Mapping[str, Any]) -> None:
        self.out, self.header = out, header
        self.rows: list[Row] = []
        self.jsonl = out / "gpu_check.jsonl"
        self.jsonl.write_text("")
        self._append({"header": header, "environment": dict(info)})
        self._write_markdown()

    def _append(self, record: Mapping[str, Any]) -> None:
        with open(self.jsonl, "a") as f:
            f.write(json.dumps(record) + "\n")
            f.flush()
            os.fsync(f.fileno())

    def _write_markdown(self) -> None:
        tmp = self.out / "gpu_check.md.tmp"
        tmp.write_text(markdown(self.rows, self.header) + "\n")
        os.replace(tmp, self.out / "gpu_check.md")

    def add(self, row: Row) -> None:
        """Keep ``row``, write it out and print its table line."""
        self.rows.append(row)
        self._append(asdict(row))
        self._write_markdown()
        print(markdown([row], []).splitlines()[-1], flush=True)


def run_table(
    specs: Sequence[RowSpec],
    out: Path,
    header: list[str],
    *,
    budget_s: float,
    start: float,
    renderer_probe: RowSpec | None = None,
    renderer_off: str | None = None,
    refuse_full_size: str | None = None,
    env: Mapping[str, str] | None = None,
    info: Mapping[str, Any] | None = None,
) -> list[Row]:
    """Run ``specs`` in order, one child process each, writing every row to ``out`` as it finishes.

    Args:
        specs: the rows.
        out: folder for ``gpu_check.md``, ``gpu_check.jsonl`` and ``logs/``.
        header: lines above the table.
        budget_s: seconds after ``start`` (a ``time.perf_counter()`` value) when no row may run any longer:
            a running row is stopped there, the rows after it are skipped by name.
        renderer_probe: run (once, as a row of the table) before the first row with ``needs_renderer``;
            when it fails, each of those rows runs its ``without_renderer`` row instead, or is skipped with
            the probe's error (and its ``without_renderer_hint``). ``None``: no probe.
        renderer_off: the reason the renderer is not to be used (e.g. ``--no-render``): the probe's row is
            skipped with it and the ``needs_renderer`` rows go as after a failed probe. ``None``: probe it.
        refuse_full_size: reason for skipping every row with ``full_size``; ``None`` runs them.
        env: environment of the child processes (``None``: this process's).
        info: the environment report, stored in the JSON's first line.

    Returns:
        The table's rows: ``specs`` in order (a ``without_renderer`` row in the place of its row), with the
        probe's row before the first row with ``needs_renderer``.
    """
    out.mkdir(parents=True, exist_ok=True)
    (out / "logs").mkdir(exist_ok=True)
    table = Table(out, header, info or {})
    renderer_error: str | None = None
    probed = False

    def remaining() -> float:
        return budget_s - (time.perf_counter() - start)

    def run(spec: RowSpec) -> Row:
        if remaining() <= 0:
            return Row(spec.check, skipped=f"the budget of {budget_s:.0f} s was spent before this row")
        print(f"[gpu_check] {spec.check} ...", file=sys.stderr, flush=True)
        left = remaining()
        row = run_child(spec, min(spec.timeout_s, left), out / "logs", env)
        if row.error and row.error.startswith("no result within") and left < spec.timeout_s:
            row.error = f"stopped when the budget of {budget_s:.0f} s ran out ({row.wall_s:.0f} s into the row)"
        print(f"[gpu_check] {spec.check}: {row.wall_s:.1f} s", file=sys.stderr, flush=True)
        return row

    for spec in specs:
        if refuse_full_size is not None and spec.full_size:
            table.add(Row(spec.check, skipped=refuse_full_size))
            continue
        if spec.needs_renderer and (renderer_probe is not None or renderer_off is not None):
            if not probed:
                probed = True
                if renderer_off is not None:
                    check = renderer_probe.check if renderer_probe is not None else "renderer probe"
                    table.add(Row(check, skipped=renderer_off))
                    renderer_error = renderer_off
                else:
                    assert renderer_probe is not None
                    probe = run(renderer_probe)
                    table.add(probe)
                    if probe.error:
                        renderer_error = f"renderer probe failed: {probe.error}"
                    elif probe.skipped:
                        renderer_error = probe.skipped
            if renderer_error is not None:
                if spec.without_renderer is not None:
                    table.add(run(spec.without_renderer))
                else:
                    table.add(Row(spec.check, skipped=renderer_error + spec.without_renderer_hint))
                continue
        table.add(run(spec))
    return table.rows


def main(argv: list[str] | None = None) -> int:
    """Run the check (or, with the hidden ``--child-*`` options, one row in this process); the exit status."""
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--out", type=Path, required=True, help="folder for gpu_check.md, gpu_check.jsonl, logs/")
    parser.add_argument("--tiny", action="store_true", help="small shapes for a CPU smoke run")
    parser.add_argument(
        "--device", default="auto", help="'auto' (CUDA if available, else CPU), 'cuda', 'cuda:1', 'cpu'"
    )
    parser.add_argument("--budget-s", type=float, default=480.0, help="no row runs past this many seconds")
    parser.add_argument("--row-timeout-s", type=float, help="one timeout for every row (default: each row's own)")
    parser.add_argument("--rows", help="comma-separated checks to run, in table order (default: all)")
    parser.add_argument("--wheels", type=Path, help="folder of wheels to install into WHEELS/site first")
    parser.add_argument(
        "--dataset", type=Path, help="the fit rows' dataset, built by --build-dataset (default: rendered in the row)"
    )
    parser.add_argument(
        "--no-render",
        action="store_true",
        help="no renderer probe; the fit rows use zero123 tiny (needs --dataset) as after a failed probe",
    )
    parser.add_argument("--build-dataset", type=Path, metavar="DIR", help="only build the fit rows' dataset in DIR")
    parser.add_argument("--fit-synth", default="render", choices=sorted(FIT_SYNTHS), help=argparse.SUPPRESS)
    parser.add_argument("--site", type=Path, help=argparse.SUPPRESS)  # children: append to sys.path
    parser.add_argument("--child-row", help=argparse.SUPPRESS)
    parser.add_argument("--child-environment", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--child-renderer", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--result", type=Path, help=argparse.SUPPRESS)
    if argv is None:
        argv = sys.argv[1:]
    child = any(a.startswith(("--child-", "--build-dataset")) for a in argv)
    if child:  # a child (or a dataset build) needs no --out
        for action in parser._actions:
            action.required = False
    args = parser.parse_args(argv)
    if args.site is not None and str(args.site) not in sys.path:
        sys.path.append(str(args.site))  # after site-packages: adds, never shadows
    if args.child_environment:
        return _child_environment(args.result)
    if args.child_renderer:
        return _child_renderer(args.result)
    if args.child_row:
        return _child_row(args.child_row, args.device, args.tiny, args.result, args.fit_synth, args.dataset)
    if args.build_dataset is not None:
        build_fit_dataset(args.build_dataset, args.tiny)
        print(f"built the fit rows' dataset in {args.build_dataset} ({'tiny' if args.tiny else 'full'})")
        return 0
    dataset: Path | None = None
    if args.dataset is not None:
        dataset = args.dataset.resolve()
        if not (dataset / "metadata.json").is_file():
            parser.error(f"--dataset {args.dataset}: no metadata.json there (build it with --build-dataset DIR)")

    start = time.perf_counter()
    out: Path = args.out.resolve()
    (out / "logs").mkdir(parents=True, exist_ok=True)
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), *filter(None, [env.get("PYTHONPATH")])])
    env.setdefault("HF_HUB_OFFLINE", "1")
    env.setdefault("TRANSFORMERS_VERBOSITY", "error")
    env.setdefault("PYTHONUNBUFFERED", "1")
    notes: list[str] = []
    site: Path | None = None
    if args.wheels is not None:
        site = args.wheels.resolve() / "site"
        try:
            notes += install_wheels(args.wheels.resolve(), site, out / "logs" / "pip_install.log")
        except Exception as err:
            notes.append(f"wheel install failed: {_error_text(err)}")

    environment_command = [sys.executable, str(Path(__file__).resolve()), "--child-environment"]
    environment_command += ["--site", str(site)] if site is not None else []
    env_row = run_child(
        RowSpec("environment", environment_command, PROBE_TIMEOUT_S), PROBE_TIMEOUT_S, out / "logs", env
    )
    info: dict[str, Any] = {"error": env_row.error} if env_row.error else dict(env_row.results)
    device = args.device
    if device == "auto":
        device = "cuda" if info.get("cuda_available") else "cpu"
    refuse = None
    if device.startswith("cpu") and not args.tiny:
        refuse = "full-size row refused on a CPU (no CUDA device, or --device cpu); --tiny runs the small rows"

    functions = row_functions(args.tiny)
    wanted = list(functions)
    if args.rows:
        wanted = [c.strip() for c in args.rows.split(",") if c.strip()]
        unknown = [c for c in wanted if c not in functions]
        if unknown:
            parser.error(f"--rows: unknown check(s) {unknown}; the checks are {list(functions)}")
        wanted = [c for c in functions if c in wanted]
    base = [sys.executable, str(Path(__file__).resolve()), "--device", device]
    base += ["--tiny"] if args.tiny else []
    base += ["--site", str(site)] if site is not None else []
    specs = []
    for check in wanted:
        _, timeout, needs_renderer = functions[check]
        if args.row_timeout_s is not None:
            timeout = args.row_timeout_s
        elif args.tiny:
            timeout = 120.0
        command = [*base, "--child-row", check]
        if check not in FIT_ROWS:
            specs.append(RowSpec(check, command, timeout, needs_renderer, full_size=not args.tiny))
            continue
        command += ["--dataset", str(dataset)] if dataset is not None else []
        name = FIT_ROWS[check]
        fallback = None
        if dataset is not None:  # the zero123 row: no OpenGL anywhere on its path
            zero123 = [*command, "--fit-synth", "zero123"]
            fallback = RowSpec(fit_check(name, "zero123"), zero123, timeout, full_size=not args.tiny)
        spec = RowSpec(
            fit_check(name, "render"), [*command, "--fit-synth", "render"], timeout, needs_renderer,
            full_size=not args.tiny, without_renderer=fallback,
            without_renderer_hint="; without --dataset DIR (built by --build-dataset DIR) the row renders its dataset",
        )  # fmt: skip
        specs.append(spec)
    probe = RowSpec("renderer probe", [*base, "--child-renderer"], PROBE_TIMEOUT_S)
    renderer_off = None
    if args.no_render:
        renderer_off = "--no-render: the fit rows use zero123 tiny (with --dataset) instead of rendering"

    header = [_caption(info, device, args), *(f"- {note}" for note in notes)]
    table = run_table(
        specs, out, header, budget_s=args.budget_s, start=start, renderer_probe=probe, renderer_off=renderer_off,
        refuse_full_size=refuse, env=env, info=info,
    )  # fmt: skip
    header[0] += f"; {time.perf_counter() - start:.0f} s in all"
    text = markdown(table, header)
    (out / "gpu_check.md").write_text(text + "\n")
    print(text, flush=True)
    # the probe's row skipped by --no-render is no failure
    return 0 if all(row.error is None and row.skipped in (None, renderer_off) for row in table) else 1


def _caption(info: Mapping[str, Any], device: str, args: argparse.Namespace) -> str:
    """The table's first line: how it was run and on what."""
    if "error" in info:
        where = f"device {device} (environment report failed: {info['error']})"
    else:
        where = (
            f"{info.get('device', device)}"
            + (f" (sm {info['capability']}, {info['memory_gib']} GiB)" if "capability" in info else "")
            + f": torch {info.get('torch')}, CUDA {info.get('cuda')}, Python {info.get('python')}"
        )
        packages = info.get("packages", {})
        if packages:
            where += "; " + ", ".join(f"{k} {v}" for k, v in packages.items())
    return f"gpu_check{' --tiny' if args.tiny else ''} on {where}; budget {args.budget_s:.0f} s"


if __name__ == "__main__":
    sys.exit(main())
