"""Models, factories and readers shared by several test modules (tests import them, never each other).

pytest puts ``tests/`` on the path (``pythonpath = ["tests"]``), so a test module does
``from helpers import TinyUserModel, make_trainer``.
"""

from __future__ import annotations

import json
import textwrap
from pathlib import Path
from typing import Any

import lightning as L
import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image
from torch import nn

from lightning_vtr.callback import ErrorGuidedViewAugmentation
from lightning_vtr.data.datamodule import VTRDataModule
from lightning_vtr.synthesis.base import SynthesisRequest, Synthesizer
from lightning_vtr.synthesis.render import RenderSynthesizer

__all__ = [
    "EmptyPredictionModel",
    "TinyUserModel",
    "assert_same_training_state",
    "build_odd_dataset",
    "fit_pix2vox",
    "generated_contents",
    "generated_index",
    "make_callback",
    "make_datamodule",
    "make_trainer",
    "odd_model",
    "one_thread",
    "write_rendering_layout",
]


class TinyUserModel(L.LightningModule):
    """A user's own model: satisfies the protocol without inheriting anything from lightning_vtr."""

    image_size = 32
    num_views = 3
    voxel_resolution = 32

    def __init__(self) -> None:
        super().__init__()
        self.encoder = nn.Sequential(nn.Conv2d(3, 8, 4, 4), nn.ReLU(), nn.Flatten(), nn.Linear(8 * 8 * 8, 64))
        self.decoder = nn.Linear(64, 8**3)

    def predict_voxels(self, images):
        b, v = images.shape[:2]
        feats = self.encoder(images.flatten(0, 1)).view(b, v, -1).mean(1)
        coarse = self.decoder(feats).view(b, 1, 8, 8, 8)
        return torch.sigmoid(F.interpolate(coarse, size=32, mode="trilinear"))[:, 0]

    def training_step(self, batch, batch_idx):
        return F.binary_cross_entropy(self.predict_voxels(batch["images"]), batch["voxels"])

    def validation_step(self, batch, batch_idx):
        self.log("val_loss", F.binary_cross_entropy(self.predict_voxels(batch["images"]), batch["voxels"]))

    def configure_optimizers(self):
        return torch.optim.Adam(self.parameters(), lr=1e-3)


class EmptyPredictionModel(TinyUserModel):
    """Predicts nothing anywhere: the error volume is exactly the ground truth."""

    def predict_voxels(self, images):
        return super().predict_voxels(images) * 0.0


def make_datamodule(root: Any, tmp_path: Path, **kw: Any) -> VTRDataModule:
    """A 32-px datamodule over ``root`` that writes generated samples under ``tmp_path / "gen"``."""
    return VTRDataModule(str(root), image_size=32, batch_size=8, generated_dir=str(tmp_path / "gen"), **kw)


def make_trainer(tmp_path: Path, epochs: int, callbacks: list, **kw: Any) -> L.Trainer:
    """A quiet CPU Trainer of ``epochs`` short epochs (2 train batches) that reloads its loaders every epoch.

    ``devices=2, strategy="ddp_spawn"`` gives the 2-process DDP runs of the equality tests.
    """
    kw.setdefault("reload_dataloaders_every_n_epochs", 1)
    kw.setdefault("devices", 1)
    kw.setdefault("num_sanity_val_steps", 1)
    kw.setdefault("limit_train_batches", 2)
    return L.Trainer(
        max_epochs=epochs,
        accelerator="cpu",
        callbacks=callbacks,
        default_root_dir=str(tmp_path),
        logger=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        limit_val_batches=1,
        **kw,
    )


def make_callback(**kw: Any) -> ErrorGuidedViewAugmentation:
    """The augmentation callback with 32-px mesh rendering, 20 % of the objects and no progress bar by default.

    ``selector="paper"`` gives :meth:`ErrorGuidedViewAugmentation.paper`; another selector given (an instance or a
    name) gets the paper's callback settings unless ``kw`` say otherwise: as many objects searched as given views,
    and a pool keeping every round's sets when the selector uses one (none otherwise). No selector (or ``None``):
    the callback's defaults, the measured default rule.
    """
    kw.setdefault("synthesizer", RenderSynthesizer(image_size=32))
    kw.setdefault("fraction", 0.2)
    kw.setdefault("progress_bar", False)
    selector = kw.pop("selector", None)
    if selector == "paper":
        return ErrorGuidedViewAugmentation.paper(**kw)
    if selector is None:
        return ErrorGuidedViewAugmentation(**kw)
    if isinstance(selector, str):
        from lightning_vtr.selection.registry import make_selector

        selector = make_selector(selector)
    kw.setdefault("search_fraction", kw["fraction"])
    kw.setdefault("pool", {"refresh": False} if selector.uses_pool else None)
    return ErrorGuidedViewAugmentation(selector, **kw)


def generated_contents(dm: VTRDataModule) -> list[tuple]:
    """``(epoch, category, object_id, viewpoints rounded to 1e-4, image bytes)`` of every generated sample."""
    out = []
    for s in dm.generated_samples:
        images = [np.asarray(Image.open(Path(s["root"]) / s["dir"] / n)) for n in s["images"]]
        viewpoints = np.round(s["viewpoints"], 4).tolist()
        out.append((s["epoch"], s["category"], s["object_id"], viewpoints, np.stack(images).tobytes()))
    return out


def generated_index(gen_dir: Path) -> list[tuple]:
    """The same tuples as :func:`generated_contents`, read from a generated directory's ``index.json`` and files."""
    entries = json.loads((gen_dir / "index.json").read_text())
    return [
        (
            e["epoch"],
            e["category"],
            e["object_id"],
            np.round(e["viewpoints"], 4).tolist(),
            b"".join((gen_dir / e["dir"] / n).read_bytes() for n in e["images"]),
        )
        for e in entries
    ]


def one_thread():
    """Generator body of a fixture that runs its tests with one torch intra-op thread.

    Tiny tensors gain nothing from splitting; on the shared 2-core test machine extra threads only add
    contention (OpenMP barriers made the tiny Zero-1-to-3 model about 20x slower). Use as
    ``_one_thread = pytest.fixture(autouse=True)(one_thread)``.
    """
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


def fit_pix2vox(root: Any, tmp_path: Path, epochs: int, ckpt_path: str | None = None, **callback_kw: Any) -> L.Trainer:
    """Fit tiny Pix2Vox++ (64 px, seeded) with the augmentation callback (64-px mesh rendering, 15 % of the
    objects) for ``epochs`` epochs of 2 batches, saving ``last.ckpt`` under ``tmp_path / "ckpt"`` after every
    epoch; resume from ``ckpt_path`` when given. Returns the Trainer (its ``lightning_module``, ``datamodule``
    and ``optimizers`` are the run's final state)."""
    from lightning_vtr.models import Pix2VoxPlusPlus

    L.seed_everything(0, verbose=False)
    dm = VTRDataModule(str(root), image_size=64, batch_size=4, generated_dir=str(tmp_path / "gen"))
    model = Pix2VoxPlusPlus(preset="tiny", validation_fscore=False)
    checkpoint = L.pytorch.callbacks.ModelCheckpoint(dirpath=tmp_path / "ckpt", save_last=True)
    callback_kw.setdefault("synthesizer", RenderSynthesizer(image_size=64))
    callback_kw.setdefault("fraction", 0.15)
    callback_kw.setdefault("progress_bar", False)
    callback_kw.setdefault("log_images", False)
    trainer = make_trainer(tmp_path, epochs, [ErrorGuidedViewAugmentation(**callback_kw), checkpoint])
    trainer.fit(model, datamodule=dm, ckpt_path=ckpt_path)
    return trainer


def assert_same_training_state(a: L.Trainer, b: L.Trainer) -> None:
    """Assert two Trainers end with exactly equal model state (parameters and buffers), optimizer state
    (every state tensor, every param-group hyperparameter) and learning-rate scheduler state."""
    state_a, state_b = a.lightning_module.state_dict(), b.lightning_module.state_dict()
    assert state_a.keys() == state_b.keys()
    differing = [k for k in state_a if not torch.equal(state_a[k], state_b[k])]
    assert not differing, f"model tensors differ: {differing}"
    assert len(a.optimizers) == len(b.optimizers)
    for opt_a, opt_b in zip(a.optimizers, b.optimizers):
        sd_a, sd_b = opt_a.state_dict(), opt_b.state_dict()
        assert sd_a["param_groups"] == sd_b["param_groups"]
        assert sd_a["state"].keys() == sd_b["state"].keys()
        for index, slots in sd_a["state"].items():
            assert slots.keys() == sd_b["state"][index].keys()
            for name, value in slots.items():
                other = sd_b["state"][index][name]
                same = torch.equal(value, other) if isinstance(value, torch.Tensor) else value == other
                assert same, f"optimizer state {index}/{name} differs"
    schedulers = [[c.scheduler.state_dict() for c in t.lr_scheduler_configs] for t in (a, b)]
    assert schedulers[0] == schedulers[1]


def write_rendering_layout(
    root: Path, splits: dict[str, str], image: np.ndarray, voxels: np.ndarray, views: int = 4
) -> dict[str, str]:
    """Write a 3D-R2N2 / ShapeNetRendering-layout chair dataset (images and voxels, no meshes) under ``root``.

    Args:
        splits: model id -> split (``"train"``, ``"val"`` or ``"test"``).
        image: the ``(H, W, 4)`` uint8 RGBA render every view gets.
        voxels: the ``(32, 32, 32)`` bool grid every model gets.

    Returns:
        ``VTRDataModule``'s ``shapenet_rendering`` argument for it.
    """
    from lightning_vtr.data.binvox import write_binvox

    render_root, vox_root = root / "ShapeNetRendering", root / "ShapeNetVox32"
    for model in splits:
        rdir = render_root / "03001627" / model / "rendering"
        rdir.mkdir(parents=True)
        (rdir / "rendering_metadata.txt").write_text("".join(f"{90 * i} 30 0 0.8 25\n" for i in range(views)))
        for i in range(views):
            Image.fromarray(image).save(rdir / f"{i:02d}.png")
        (vox_root / "03001627" / model).mkdir(parents=True)
        write_binvox(vox_root / "03001627" / model / "model.binvox", voxels)
    by_split = {s: [m for m, ms in splits.items() if ms == s] for s in ("train", "val", "test")}
    split_file = root / "split.json"
    split_file.write_text(json.dumps([{"taxonomy_id": "03001627", "taxonomy_name": "chair", **by_split}]))
    return {"rendering_root": str(render_root), "voxel_root": str(vox_root), "split_file": str(split_file)}


class ViewpointSynthesizer(Synthesizer):
    """Writes each target viewpoint into its image: red = yaw, green = pitch, in 16-bit across 2 pixels."""

    image_size = 2

    def __init__(self) -> None:
        self.calls = 0

    def synthesize(self, requests: list[SynthesisRequest]) -> list[np.ndarray]:
        self.calls += 1
        out = []
        for req in requests:
            vp = np.asarray(req.target_viewpoints, dtype=np.float64)
            code = np.round((vp + np.array([180.0, 90.0])) / [360.0, 180.0] * 65535).astype(np.int64)  # (T, 2)
            img = np.zeros((len(vp), 2, 2, 4), np.uint8)
            img[:, 0, 0, :2] = code // 256
            img[:, 0, 1, :2] = code % 256
            img[..., 3] = 255
            out.append(img)
        return out


def viewpoint_transform(images: np.ndarray) -> torch.Tensor:
    """(T, 2, 2, 4) uint8 images of :class:`ViewpointSynthesizer` -> (T, 3, 2, 2) float64, values kept."""
    return torch.from_numpy(images[..., :3].astype(np.float64)).permute(0, 3, 1, 2)  # (T, 3, 2, 2)


def decode_viewpoints(images: torch.Tensor) -> torch.Tensor:
    """(N, 3, 2, 2) images of :class:`ViewpointSynthesizer` -> (N, 2) viewpoints in degrees."""
    code = images[:, :2, 0, 0] * 256 + images[:, :2, 0, 1]
    return code / 65535 * torch.tensor([360.0, 180.0], dtype=images.dtype) - torch.tensor([180.0, 90.0])


def build_odd_dataset(root: Path, split: tuple[float, float, float]) -> Path:
    """3 categories x 5 objects at 32 px with 4 views per set; ``split`` (train, val, test) of 0.6 gives a split of
    9 objects, which 2 DDP ranks cannot share evenly (the padding sampler repeats one)."""
    from lightning_vtr.data.builder import build_dataset

    build_dataset(
        root,
        source="procedural",
        categories=["chair", "table", "airplane"],
        objects_per_category=5,
        image_size=32,
        resolution=32,
        views_per_set=4,
        split=split,
        workers=1,
        progress=False,
    )
    return root


def odd_model(fscore_points: int):
    """A seeded two-view tiny Pix2Vox++ over the categories of :func:`build_odd_dataset`."""
    from lightning_vtr.models import Pix2VoxPlusPlus

    torch.manual_seed(0)
    return Pix2VoxPlusPlus(
        preset="tiny", num_views=2, fscore_points=fscore_points, categories=("airplane", "chair", "table")
    )


def save_tiny_checkpoint(path: Path, *, seed: int | None = None, **datamodule_kw: Any) -> Path:
    """A checkpoint of a random tiny Pix2Vox++ (64 px) at ``path``, as ``Trainer.fit`` writes one: its weights, its
    hyperparameters and a datamodule's (``datamodule_kw`` over ``image_size=64, batch_size=4``)."""
    from lightning_vtr.models.pix2vox import Pix2VoxPlusPlus

    if seed is not None:
        torch.manual_seed(seed)
    model = Pix2VoxPlusPlus(preset="tiny")
    dm = VTRDataModule(None, **{"image_size": 64, "batch_size": 4, **datamodule_kw})
    checkpoint = {
        "state_dict": model.state_dict(),
        "hyper_parameters": dict(model.hparams),
        "datamodule_hyper_parameters": dict(dm.hparams),
        "pytorch-lightning_version": L.__version__,
    }
    model.on_save_checkpoint(checkpoint)
    torch.save(checkpoint, path)
    return path


#: A user's own ViewSelector subclass with no ``settings()`` method, as a module's source (tests write it to
#: ``myselector.py`` / ``sideviews.py`` and name ``SideViews`` by its class path).
USER_SELECTOR_SOURCE = textwrap.dedent(
    """
    import torch

    from lightning_vtr.selection import ViewSelector


    class SideViews(ViewSelector):
        def __init__(self, pitch: float = 10.0):
            self.pitch = pitch

        def select(self, predicted, target, categories, generator=None, context=None):
            yaw = torch.tensor([90.0, -90.0, 180.0])
            views = torch.stack([yaw, torch.full((3,), self.pitch)], dim=-1)
            return views.expand(predicted.shape[0], 3, 2).clone()
    """
)
