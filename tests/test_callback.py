from __future__ import annotations

import json
from pathlib import Path

import lightning as L
import numpy as np
import pytest
import torch
import torch.nn.functional as F
from lightning.pytorch.utilities.exceptions import MisconfigurationException
from PIL import Image
from torch import nn

from lightning_vtr.callback import ErrorGuidedViewAugmentation
from lightning_vtr.data.datamodule import VTRDataModule
from lightning_vtr.selection import ErrorGuidedSelector, NatureSelector, RandomSelector
from lightning_vtr.synthesis.render import RenderSynthesizer


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


def _dm(root, tmp_path, **kw):
    return VTRDataModule(str(root), image_size=32, batch_size=8, generated_dir=str(tmp_path / "gen"), **kw)


def _trainer(tmp_path, epochs, callbacks, **kw):
    kw.setdefault("reload_dataloaders_every_n_epochs", 1)
    return L.Trainer(
        max_epochs=epochs,
        accelerator="cpu",
        devices=1,
        callbacks=callbacks,
        default_root_dir=str(tmp_path),
        logger=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        limit_train_batches=2,
        limit_val_batches=1,
        num_sanity_val_steps=1,
        **kw,
    )


def _callback(**kw):
    kw.setdefault("synthesizer", RenderSynthesizer(image_size=32))
    kw.setdefault("fraction", 0.2)
    kw.setdefault("progress_bar", False)
    return ErrorGuidedViewAugmentation(**kw)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"fraction": 0.0}, "fraction"),
        ({"fraction": 1.5}, "fraction"),
        ({"min_objects": 0}, "min_objects"),
        ({"max_samples": 0}, "max_samples"),
        ({"selector": "error"}, "selector"),
    ],
)
def test_init_validates_arguments(kwargs, match):
    with pytest.raises(ValueError, match=match):
        ErrorGuidedViewAugmentation(**kwargs)


def test_setup_refuses_without_dataloader_reload(tiny_dataset, tmp_path):
    trainer = _trainer(tmp_path, 1, [_callback()], reload_dataloaders_every_n_epochs=0)
    with pytest.raises(MisconfigurationException, match="reload_dataloaders_every_n_epochs=1"):
        trainer.fit(TinyUserModel(), datamodule=_dm(tiny_dataset, tmp_path))


def test_setup_refuses_a_datamodule_without_add_samples(tiny_dataset, tmp_path):
    class Plain(L.LightningDataModule):
        def train_dataloader(self):
            return _dm(tiny_dataset, tmp_path).train_dataloader()

    with pytest.raises(MisconfigurationException, match="add_samples"):
        _trainer(tmp_path, 1, [_callback()]).fit(TinyUserModel(), datamodule=Plain())


def test_setup_refuses_a_model_without_the_protocol(tiny_dataset, tmp_path):
    class NoProtocol(TinyUserModel):
        predict_voxels = None

    with pytest.raises(MisconfigurationException, match="predict_voxels"):
        _trainer(tmp_path, 1, [_callback()]).fit(NoProtocol(), datamodule=_dm(tiny_dataset, tmp_path))


def test_generates_pool_samples_every_epoch_but_the_last(tiny_dataset, tmp_path):
    dm = _dm(tiny_dataset, tmp_path)
    callback = _callback(fraction=0.2)
    _trainer(tmp_path, 3, [callback]).fit(EmptyPredictionModel(), datamodule=dm)
    samples = dm.generated_samples
    # 21 training objects, round(0.2 * 21) = 4 per epoch, epochs 0 and 1 (not the last, not the sanity check)
    assert [s["epoch"] for s in samples] == [0] * 4 + [1] * 4
    assert callback.last_epoch == 1 and len(callback.pool) == 8
    # Every training view set is a set the selector found on some object of the same category.
    for s in samples:
        _, sets = callback.pool.view_sets(s["category"])
        assert any(np.allclose(v.numpy(), s["viewpoints"], atol=1e-4) for v in sets)
    # The images are renders of the object's mesh at exactly those viewpoints.
    rec = dm.record(samples[0]["category"], samples[0]["object_id"])
    expected = RenderSynthesizer(image_size=32).synthesize([callback._request(dm, rec, torch.tensor(samples[0]["viewpoints"]))])[0]
    got = np.stack([np.asarray(Image.open(dm.generated_dir / samples[0]["dir"] / n)) for n in samples[0]["images"]])
    assert np.array_equal(got, expected)
    # With an empty prediction the error is the ground truth: the logged error is the objects' occupancy.
    record = json.loads((Path(tmp_path) / "vtr_selection" / "epoch_0000.json").read_text())
    occupancy = np.mean([dm.object_voxels(dm.record(*o.split("/"))).mean().item() for o in record["objects"]])
    assert record["mean_error"] == pytest.approx(occupancy, rel=1e-6)
    # and the next epoch trained on them: the train set grew.
    assert len(dm.train_dataset()) == 21 + 8


@pytest.mark.parametrize("selector_cls", [RandomSelector, NatureSelector])
def test_any_selector_runs_through_the_same_callback(tiny_dataset, tmp_path, selector_cls):
    dm = _dm(tiny_dataset, tmp_path)
    callback = _callback(selector=selector_cls(), fraction=0.1)
    _trainer(tmp_path, 2, [callback]).fit(TinyUserModel(), datamodule=dm)
    assert callback.pool is None
    record = json.loads((Path(tmp_path) / "vtr_selection" / "epoch_0000.json").read_text())
    assert record["view_sets"] == record["selected"]  # no pool: trained on exactly what was selected
    pitches = np.array(record["selected"])[..., 1]
    if selector_cls is NatureSelector:
        assert np.all(pitches == 0.0)
    assert len(dm.generated_samples) == 2


def _fit(root, tmp_path, epochs, ckpt=None):
    L.seed_everything(0, verbose=False)
    dm = _dm(root, tmp_path)
    checkpoint = L.pytorch.callbacks.ModelCheckpoint(dirpath=tmp_path / "ckpt", save_last=True)
    callback = _callback(fraction=0.15)
    _trainer(tmp_path, epochs, [callback, checkpoint]).fit(TinyUserModel(), datamodule=dm, ckpt_path=ckpt)
    return dm, callback


def _contents(dm):
    out = []
    for s in dm.generated_samples:
        images = [np.asarray(Image.open(dm.generated_dir / s["dir"] / n)) for n in s["images"]]
        out.append((s["epoch"], s["category"], s["object_id"], np.round(s["viewpoints"], 4).tolist(), np.stack(images).tobytes()))
    return out


@pytest.mark.slow
def test_resume_generates_exactly_what_an_uninterrupted_run_does(tiny_dataset, tmp_path):
    full, full_cb = _fit(tiny_dataset, tmp_path / "full", 4)
    _fit(tiny_dataset, tmp_path / "part", 2)
    resumed, resumed_cb = _fit(tiny_dataset, tmp_path / "part", 4, ckpt=str(tmp_path / "part" / "ckpt" / "last.ckpt"))
    assert [c[:4] for c in _contents(resumed)] == [c[:4] for c in _contents(full)]
    assert _contents(resumed) == _contents(full)
    assert [s["epoch"] for s in full.generated_samples] == [0] * 3 + [1] * 3 + [2] * 3
    assert resumed_cb.pool.categories() == full_cb.pool.categories()
    for category in full_cb.pool.categories():
        ids_a, sets_a = full_cb.pool.view_sets(category)
        ids_b, sets_b = resumed_cb.pool.view_sets(category)
        assert ids_a == ids_b and torch.equal(sets_a, sets_b)


class DatasetDigestProbe(L.Callback):
    """After each generation, checks every rank serves an identical train set (written to a file by rank 0)."""

    def __init__(self, out: str) -> None:
        self.out = out

    def on_train_epoch_start(self, trainer, pl_module):
        import hashlib

        ds = trainer.datamodule.train_dataset()
        digest = hashlib.sha1()
        for i in range(len(ds)):
            item = ds[i]
            digest.update(item["object_id"].encode() + item["images"].numpy().tobytes())
        gathered = [None] * trainer.world_size
        torch.distributed.all_gather_object(gathered, (len(ds), digest.hexdigest()))
        if trainer.is_global_zero:
            with open(self.out, "a") as f:
                f.write(json.dumps(gathered) + "\n")


def _index(gen_dir: Path) -> list:
    entries = json.loads((gen_dir / "index.json").read_text())
    return [
        (e["epoch"], e["category"], e["object_id"], np.round(e["viewpoints"], 4).tolist(),
         b"".join((gen_dir / e["dir"] / n).read_bytes() for n in e["images"]))
        for e in entries
    ]


@pytest.mark.slow
def test_two_process_ddp_generates_what_one_process_does(tiny_dataset, tmp_path):
    single = tmp_path / "single"
    dm = _dm(tiny_dataset, single)
    _trainer(single, 3, [_callback(fraction=0.2)]).fit(EmptyPredictionModel(), datamodule=dm)

    ddp = tmp_path / "ddp"
    probe = DatasetDigestProbe(str(tmp_path / "digests.jsonl"))
    trainer = L.Trainer(
        max_epochs=3, accelerator="cpu", devices=2, strategy="ddp_spawn", callbacks=[_callback(fraction=0.2), probe],
        default_root_dir=str(ddp), logger=False, enable_progress_bar=False, enable_model_summary=False,
        limit_train_batches=2, limit_val_batches=1, reload_dataloaders_every_n_epochs=1,
    )
    trainer.fit(EmptyPredictionModel(), datamodule=_dm(tiny_dataset, ddp))

    assert _index(ddp / "gen") == _index(single / "gen")
    assert len(_index(single / "gen")) == 8
    digests = [json.loads(line) for line in (tmp_path / "digests.jsonl").read_text().splitlines()]
    assert [d[0][0] for d in digests] == [21, 25, 29]  # epochs 0, 1, 2 see 0, 4, 8 generated samples
    assert all(d[0] == d[1] for d in digests)  # rank 0 and rank 1 serve identical data


def test_source_images_are_decoded_only_for_synthesizers_that_read_them(tiny_dataset, tmp_path):
    from lightning_vtr.synthesis.base import Synthesizer

    class NeedsImages(Synthesizer):
        def synthesize(self, requests):
            return [np.zeros((len(r.target_viewpoints), 8, 8, 4), np.uint8) for r in requests]

    dm = _dm(tiny_dataset, tmp_path)
    dm.setup("fit")
    rec = dm.split_records("train")[0]
    rendered = _callback()._request(dm, rec, torch.zeros(3, 2))
    diffused = _callback(synthesizer=NeedsImages())._request(dm, rec, torch.zeros(3, 2))
    assert rendered.source_images.shape[0] == 0  # the mesh renderer never looks at them
    assert diffused.source_images.shape == (8, 64, 64, 4)  # all 8 views of the tiny dataset's aligned set
    assert torch.equal(rendered.source_viewpoints, diffused.source_viewpoints)
    assert torch.allclose(diffused.source_viewpoints[:, 1], torch.full((8,), 30.0))
