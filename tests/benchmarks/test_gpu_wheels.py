"""benchmarks/gpu_prepare.sh: the wheels it fetches are exactly what the GPU image lacks, and they suffice.

The GPU image holds torch, lightning, torchmetrics, transformers, accelerate, huggingface_hub, scikit-image,
matplotlib and their requirements (``IMAGE``). The test downloads the wheel set (network), installs it the way
``gpu_check.py --wheels`` does (``pip install --no-index --no-deps --target``), and imports the package in a
process that may take every other installed distribution only from that folder.
"""

from __future__ import annotations

import importlib.metadata
import importlib.util
import json
import os
import re
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest
from packaging.requirements import Requirement
from packaging.tags import sys_tags
from packaging.utils import parse_wheel_filename

ROOT = Path(__file__).resolve().parents[2]
PREPARE = ROOT / "benchmarks" / "gpu_prepare.sh"
LIST = ROOT / "benchmarks" / "gpu_wheels.txt"
#: Needed by the package, but in the image or not depending on its versions (python-dateutil >= 4 dropped six).
MAYBE_IN_IMAGE = {"six"}
#: the packages the GPU image was described with; their requirements are on it too
IMAGE = [
    "torch", "lightning", "torchmetrics", "transformers", "accelerate", "huggingface_hub", "scikit-image",
    "matplotlib",
]  # fmt: skip
#: compiled wheels of the set (cp312 only): not installable on another Python, so left out here by name
COMPILED = {"charset-normalizer"}


def _norm(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def _closure(roots: list[tuple[str, tuple[str, ...]]]) -> set[str]:
    """Installed distributions ``roots`` (name, extras) require, transitively, themselves included."""
    seen: set[tuple[str, str]] = set()
    names: set[str] = set()
    stack = list(roots)
    while stack:
        name, extras = stack.pop()
        for extra in ("", *extras):
            if (_norm(name), extra) in seen:
                continue
            seen.add((_norm(name), extra))
            try:
                dist = importlib.metadata.distribution(name)
            except importlib.metadata.PackageNotFoundError:
                continue
            names.add(_norm(name))
            for line in dist.requires or []:
                req = Requirement(line)
                if req.marker is None or req.marker.evaluate({"extra": extra}):
                    stack.append((req.name, tuple(req.extras)))
    return names


def _gpu_check():
    spec = importlib.util.spec_from_file_location("_gpu_wheels_gpu_check", ROOT / "benchmarks" / "gpu_check.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclasses look their module up
    try:
        spec.loader.exec_module(module)
    finally:
        del sys.modules[spec.name]
    return module


# Run with `python -S` (no site-packages) and PYTHONPATH = the repository and a view of the image's distributions;
# SITE (the installed wheels) is appended last, as gpu_check.py --wheels does.
CHILD = r"""
import json, sys
site = sys.argv[1]
sys.path.append(site)

import lightning_vtr.models, lightning_vtr.renderer, lightning_vtr.synthesis, lightning_vtr.cli.lightning
import jsonargparse, trimesh
from lightning_vtr.renderer import Renderer
from lightning_vtr.synthesis.zero123 import Zero123Synthesizer
from diffusers.models.autoencoders.autoencoder_kl import AutoencoderKL
from diffusers.models.unets.unet_2d_condition import UNet2DConditionModel
from diffusers.schedulers.scheduling_ddim import DDIMScheduler
import diffusers

unet = UNet2DConditionModel(
    sample_size=8, in_channels=8, out_channels=4, block_out_channels=(32, 64), layers_per_block=1,
    down_block_types=("CrossAttnDownBlock2D", "DownBlock2D"), up_block_types=("UpBlock2D", "CrossAttnUpBlock2D"),
    cross_attention_dim=32, attention_head_dim=8, norm_num_groups=8,
)
with Renderer(image_size=16) as renderer:
    rgba = renderer.render(trimesh.creation.box(extents=(0.6, 0.6, 0.6)), [[30.0, 20.0]])
files = [getattr(m, "__file__", None) for m in list(sys.modules.values())]
print(json.dumps({
    "files": sorted(f for f in files if f), "diffusers": diffusers.__version__,
    "unet_params": sum(p.numel() for p in unet.parameters()), "covered": float((rgba[..., 3] > 0).mean()),
    "scheduler": type(DDIMScheduler()).__name__,
}))
"""


@pytest.mark.slow
def test_wheel_set_is_what_the_image_lacks_and_the_package_imports_from_it(tmp_path):
    wheels, dataset = tmp_path / "wheels", tmp_path / "dataset"
    done = subprocess.run(
        ["bash", str(PREPARE), str(wheels), str(dataset)], capture_output=True, text=True, timeout=600
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert f'--wheels {wheels} --dataset {dataset} --out "$OUT" --budget-s 420' in done.stdout.splitlines()[-1]
    assert json.loads((dataset / "metadata.json").read_text())["image_size"] == 64  # the fit rows' dataset

    files = sorted(wheels.glob("*.whl"))
    listed = [line.split("#")[0].strip() for line in LIST.read_text().splitlines()]
    listed = [Requirement(line) for line in listed if line]
    assert sorted((_norm(p.name.split("-")[0]), p.name.split("-")[1]) for p in files) == sorted(
        (_norm(r.name), str(r.specifier).removeprefix("==")) for r in listed
    )
    assert not (wheels / "site").exists()

    # the distributions lightning-vtr[zero123] needs beyond the image, and no others but those the image may hold
    # or not depending on its versions
    image = _closure([(name, ()) for name in IMAGE])
    needed = _closure([("lightning-vtr", ("zero123",))]) - image - {"lightning-vtr"}
    names = {_norm(r.name) for r in listed}
    assert needed <= names, f"missing from {LIST.name}: {sorted(needed - names)}"
    assert names - needed <= MAYBE_IN_IMAGE, f"not needed by the package beyond the image: {sorted(names - needed)}"

    # install as gpu_check.py --wheels does (its choice among the two diffusers), minus wheels for another Python
    chosen, notes = _gpu_check().choose_wheels(files)
    hub = importlib.metadata.version("huggingface_hub")
    expected_diffusers = "0.42.1" if int(hub.split(".")[0]) >= 2 else "0.37.1"
    assert [p.name.split("-")[1] for p in chosen if p.name.startswith("diffusers-")] == [expected_diffusers], notes
    supported = set(sys_tags())
    foreign = {_norm(p.name.split("-")[0]) for p in chosen if not set(parse_wheel_filename(p.name)[3]) & supported}
    assert foreign <= COMPILED, foreign
    site = tmp_path / "site"
    install = [sys.executable, "-m", "pip", "install", "--no-index", "--no-deps", "--target", str(site)]
    install += [str(p) for p in chosen if _norm(p.name.split("-")[0]) not in foreign]
    done = subprocess.run(install, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]

    # a view of site-packages holding only the image's distributions (and the foreign wheels' own)
    view = tmp_path / "view"
    view.mkdir()
    for dist in importlib.metadata.distributions():
        if _norm(dist.metadata["Name"]) not in image | foreign:
            continue
        base = Path(dist.locate_file(""))
        for top in {Path(f).parts[0] for f in dist.files or [] if not str(f).startswith("..")}:
            if (base / top).exists() and not (view / top).exists() and top != "__pycache__":
                (view / top).symlink_to(base / top)
    done = subprocess.run(
        [sys.executable, "-S", "-c", CHILD, str(site)],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), str(view)]), "HF_HUB_OFFLINE": "1"},
    )
    assert done.returncode == 0, done.stderr[-3000:]
    report = json.loads(done.stdout.strip().splitlines()[-1])
    assert report["diffusers"] == expected_diffusers
    assert report["unet_params"] > 0 and report["covered"] > 0
    from_site = {Path(f).relative_to(site).parts[0] for f in report["files"] if f.startswith(str(site) + os.sep)}
    assert {"diffusers", "pyrender", "trimesh", "OpenGL", "pyglet", "jsonargparse", "freetype"} <= from_site
    system = sysconfig.get_paths()["purelib"]
    assert [f for f in report["files"] if f.startswith(system)] == []
