"""One prepared check for the first time a GPU is available: prints one Markdown table.

Rows (nothing is downloaded; every model has random weights):

* ``fit``: tiny Pix2Vox++ trained 2 epochs in ``bf16-mixed`` with :class:`~lightning_vtr.ErrorGuidedViewAugmentation`
  and mesh rendering, on a procedural dataset built in a temporary folder: seconds, final loss, generated samples.
* ``selection <score>``: :class:`~lightning_vtr.selection.ErrorGuidedSelector` objects/s at K = 30 for the
  ``paper``, ``released`` and ``visible`` scores, on the device (``benchmarks/view_selection.py``'s objects and timer).
* ``zero123``: Zero-1-to-3 at full size (SD 1.x UNet, SD VAE, CLIP ViT-L/14; ``benchmarks/zero123.py``'s
  components) in fp16, 50 DDIM steps with guidance 3.0: seconds per image at batch 1 and 8, peak memory.
* ``train <model>``: paper-preset Pix2Vox++ and LRGT training samples/s and peak memory at batch 8 in
  bf16-mixed (autocast to bfloat16 around forward and loss, as Lightning's ``bf16-mixed`` does), random inputs.

A row that fails shows its error in the table; the other rows still run. Peak memory is
``torch.cuda.max_memory_allocated`` of the row on CUDA, the process's peak resident size on CPU.

``--tiny`` shrinks every row for a CPU smoke run: a 10-object dataset and one training batch per epoch, selection
on 4 objects at R = 16, the tests' tiny Zero-1-to-3 in float32 at 2 DDIM steps, tiny presets at batch 1::

    python benchmarks/gpu_check.py                      # on the GPU (sized to finish within 8 minutes)
    python benchmarks/gpu_check.py --tiny --device cpu  # smoke run
    python benchmarks/gpu_check.py --out gpu_check.md   # also write the table to a file
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import resource
import sys
import tempfile
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from types import ModuleType

os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("TRANSFORMERS_VERBOSITY", "error")

import torch

_HERE = Path(__file__).resolve().parent
#: share of the training objects given new views per selection in the fit row; its 2 epochs select twice (before
#: epoch 0 and after it), so it generates ``2 * round(FIT_FRACTION * train objects)`` samples
FIT_FRACTION = 0.34
SCORES = ("paper", "released", "visible")


@dataclass
class Row:
    """One line of the table: what was checked, how, and its numbers (or the error that stopped it)."""

    check: str
    setup: str = ""
    results: dict[str, float] = field(default_factory=dict)
    error: str | None = None


def _load(path: Path, name: str) -> ModuleType:
    """Import a script by path (``benchmarks/`` and ``tests/`` are no packages), once."""
    if name not in sys.modules:
        spec = importlib.util.spec_from_file_location(name, path)
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        spec.loader.exec_module(module)
    return sys.modules[name]


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _reset_peak(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)
        torch.cuda.reset_peak_memory_stats(device)


def _peak_gib(device: torch.device) -> float:
    if device.type == "cuda":
        return torch.cuda.max_memory_allocated(device) / 2**30
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20  # KiB on Linux


def _memory_name(device: torch.device) -> str:
    return "peak GiB" if device.type == "cuda" else "peak RSS GiB"


# ---------------------------------------------------------------------------------------------------- rows
def fit_row(device: torch.device, tiny: bool) -> Row:
    """Tiny Pix2Vox++ with the callback (render synthesizer), 2 epochs in bf16-mixed on a fresh procedural dataset."""
    import lightning as L

    from lightning_vtr import ErrorGuidedViewAugmentation, VTRDataModule
    from lightning_vtr.data.builder import build_dataset
    from lightning_vtr.models import Pix2VoxPlusPlus
    from lightning_vtr.synthesis.render import RenderSynthesizer
    from lightning_vtr.utils.feedback import silence_lightning_tips

    silence_lightning_tips()
    if tiny:  # 2 x 5 objects split 3/1/1 per category
        data = dict(categories=["chair", "table"], objects_per_category=5, split=(0.6, 0.2, 0.2), image_size=32)
        data.update(views_per_set=4, workers=1)
    else:  # the tests' dataset: 3 x 10 objects split 7/1/2
        data = dict(categories=["chair", "table", "airplane"], objects_per_category=10, image_size=64)
        data.update(views_per_set=8, workers=max(1, min(8, (os.cpu_count() or 1) // 2)))
    render_size = data["image_size"]
    with tempfile.TemporaryDirectory(prefix="gpu_check_") as tmp:
        start = time.perf_counter()
        build_dataset(Path(tmp) / "data", source="procedural", resolution=32, seed=0, progress=False, **data)
        build_s = time.perf_counter() - start
        L.seed_everything(0, verbose=False)
        model = Pix2VoxPlusPlus(preset="tiny", validation_fscore=False)
        dm = VTRDataModule(
            str(Path(tmp) / "data"),
            image_size=model.image_size,
            batch_size=4 if tiny else 8,
            generated_dir=f"{tmp}/gen",
        )
        callback = ErrorGuidedViewAugmentation(
            synthesizer=RenderSynthesizer(image_size=render_size),
            fraction=FIT_FRACTION,
            progress_bar=False,
            log_images=False,
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
        results = {
            "seconds": seconds,
            "final loss": float(loss),
            "generated samples": len(dm.generated_samples),
            "train objects": len(dm.split_records("train")),
            "dataset build s": build_s,
        }
    setup = (
        f"{device.type}, bf16-mixed, 2 epochs{' of 1 batch' if tiny else ''}, batch {dm.batch_size}, fraction {FIT_FRACTION}, "
        f"render {render_size} px, loss dtype {str(loss.dtype).removeprefix('torch.')}"
    )
    return Row("fit: Pix2Vox++ tiny + callback", setup, results)


def selection_row(device: torch.device, tiny: bool, score: str) -> Row:
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


def zero123_row(device: torch.device, tiny: bool) -> Row:
    """Zero-1-to-3 with random weights: seconds per image at batch 1 and 8 (50 DDIM steps, guidance 3.0)."""
    from lightning_vtr.synthesis.zero123 import Zero123Synthesizer

    bench = _load(_HERE / "zero123.py", "_gpu_check_zero123")
    torch.manual_seed(0)
    if tiny:  # the tests' tiny model: 64 x 64
        fixtures = _load(_HERE.parent / "tests" / "synthesis" / "conftest.py", "_gpu_check_zero123_fixtures")
        components, dtype, steps, size = fixtures.build_tiny_components(), torch.float32, 2, "tiny 64 px"
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


def train_row(device: torch.device, tiny: bool, name: str) -> Row:
    """Training samples/s and peak memory of a preset (``pix2vox`` or ``lrgt``) in bf16-mixed on random inputs."""
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
    for step in range(warmup + steps):
        if step == warmup:
            _sync(device)
            start = time.perf_counter()
        optimizer.zero_grad(set_to_none=True)
        with torch.autocast(device_type=device.type, dtype=torch.bfloat16):
            loss = model.loss(model(images), voxels)
        loss.backward()
        optimizer.step()
    _sync(device)
    rate = batch * steps / (time.perf_counter() - start)
    results = {"samples/s": rate, _memory_name(device): _peak_gib(device), "loss": float(loss.detach())}
    params = sum(p.numel() for p in model.parameters()) / 1e6
    setup = (
        f"{device.type}, {preset} preset ({params:.1f} M params, {s} px, {model.num_views} views), bf16-mixed, "
        f"batch {batch}, {warmup} warm-up + {steps} timed steps"
    )
    return Row(f"train: {'Pix2Vox++' if name == 'pix2vox' else 'LRGT'}", setup, results)


def rows(device: torch.device, tiny: bool) -> list[tuple[str, Callable[[], Row]]]:
    """``(check, function)`` for every row, in table order."""
    out = [("fit: Pix2Vox++ tiny + callback", lambda: fit_row(device, tiny))]
    out += [(f"selection: {s}", lambda s=s: selection_row(device, tiny, s)) for s in SCORES]
    out += [("zero123", lambda: zero123_row(device, tiny))]
    out += [
        (f"train: {label}", lambda n=n: train_row(device, tiny, n))
        for n, label in (("pix2vox", "Pix2Vox++"), ("lrgt", "LRGT"))
    ]
    return out


def run_row(check: str, fn: Callable[[], Row], device: torch.device) -> Row:
    """``fn()``, or a row holding its error (the traceback goes to stderr)."""
    print(f"[gpu_check] {check} ...", file=sys.stderr, flush=True)
    start = time.perf_counter()
    try:
        row = fn()
    except Exception as err:
        traceback.print_exc(file=sys.stderr)
        row = Row(check, error=f"{type(err).__name__}: {str(err).splitlines()[0] if str(err) else ''}"[:300])
    finally:
        if device.type == "cuda":
            torch.cuda.empty_cache()
    print(f"[gpu_check] {check}: {time.perf_counter() - start:.1f} s", file=sys.stderr, flush=True)
    return row


def _number(value: float) -> str:
    return str(value) if isinstance(value, int) else f"{value:.4g}"


def markdown(table: list[Row], caption: str) -> str:
    """The table: one line per row, results as ``name value`` pairs (``ERROR: ...`` for a failed row)."""
    lines = [caption, "", "| check | setup | results |", "| --- | --- | --- |"]
    for row in table:
        cell = f"ERROR: {row.error}" if row.error else "; ".join(f"{k} {_number(v)}" for k, v in row.results.items())
        lines.append("| " + " | ".join(part.replace("|", "/") for part in (row.check, row.setup, cell)) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> list[Row]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tiny", action="store_true", help="small shapes for a CPU smoke run")
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--out", type=Path, help="also write the table to this file")
    args = parser.parse_args(argv)
    device = torch.device(args.device)
    if device.type == "cuda" and device.index is None:
        device = torch.device("cuda", torch.cuda.current_device())
    start = time.perf_counter()
    table = [run_row(check, fn, device) for check, fn in rows(device, args.tiny)]
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else f"CPU, {torch.get_num_threads()} threads"
    caption = (
        f"gpu_check{' --tiny' if args.tiny else ''} on {name}: torch {torch.__version__}, "
        f"{time.perf_counter() - start:.0f} s in all"
    )
    text = markdown(table, caption)
    print(text, flush=True)
    if args.out is not None:
        args.out.write_text(text + "\n")
    return table


if __name__ == "__main__":
    main()
