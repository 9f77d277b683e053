"""ErrorGuidedViewAugmentation with the error-guided, Random and Nature selectors: arguments, setup checks,
generated samples, exact resume and DDP equivalence."""

from __future__ import annotations

import json
import re
from pathlib import Path

import lightning as L
import numpy as np
import pytest
import torch
from helpers import (
    EmptyPredictionModel,
    TinyUserModel,
    generated_contents,
    generated_index,
    make_callback,
    make_datamodule,
    make_trainer,
)
from lightning.pytorch.utilities.exceptions import MisconfigurationException
from PIL import Image

from lightning_vtr.callback import ErrorGuidedViewAugmentation
from lightning_vtr.data.datamodule import VTRDataModule
from lightning_vtr.selection import SELECTORS, ErrorGuidedSelector, NatureSelector, RandomSelector
from lightning_vtr.synthesis.render import RenderSynthesizer


@pytest.mark.parametrize(
    ("kwargs", "match"),
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


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"selector": 3}, "`selector` must be a lightning_vtr ViewSelector or a registry name, got int 3"),
        ({"synthesizer": "render"}, "`synthesizer` must be a lightning_vtr Synthesizer, got str 'render'"),
        ({"fraction": "0.1"}, "`fraction` must be a number, got str '0.1'"),
        ({"batch_size": 2.5}, "`batch_size` must be an int, got float 2.5"),
        ({"min_objects": None}, "`min_objects` must be an int, got NoneType None"),
    ],
)
def test_init_rejects_wrong_types(kwargs, message):
    with pytest.raises(TypeError, match=f"^{re.escape(message)}$"):
        ErrorGuidedViewAugmentation(**kwargs)


def test_init_messages_name_the_argument_and_value():
    with pytest.raises(ValueError, match=re.escape("`fraction` must be a number in (0, 1], got 1.5")):
        ErrorGuidedViewAugmentation(fraction=1.5)
    with pytest.raises(ValueError, match=re.escape("`capacity` must be an int >= 1, got 0")):
        ErrorGuidedViewAugmentation(pool={"capacity": 0})
    names = ", ".join(repr(name) for name in [*SELECTORS, "paper"])
    with pytest.raises(ValueError, match=re.escape(f"`selector` must be one of {names}, got 'error'")):
        ErrorGuidedViewAugmentation(selector="error")


@pytest.mark.parametrize("name", sorted(SELECTORS))
def test_selector_by_registry_name(name):
    # what a YAML config gives: `selector: random` (with `pool: null` for a selector that uses no pool)
    pool = ErrorGuidedViewAugmentation().pool if SELECTORS[name].uses_pool else None
    callback = ErrorGuidedViewAugmentation(selector=name, pool=None if pool is None else {"refresh": True})
    assert type(callback.selector) is SELECTORS[name]
    assert (callback.pool is not None) == SELECTORS[name].uses_pool == (name == "error_guided")
    # a selector named keeps the callback's own defaults: they never depend on the selector
    assert (callback.fraction, callback.search_fraction) == (0.05, 0.35)


def _settings(callback: ErrorGuidedViewAugmentation) -> dict:
    """The selection settings of a callback: its selector's and its own."""
    selector = callback.selector
    pool = callback.pool
    return {
        "selector": type(selector).__name__,
        "score": selector.settings().get("score"),
        "min_separation": getattr(selector, "min_separation", None),
        "temperature": getattr(selector, "temperature", None),
        "k": getattr(selector, "k", None),
        "num_views": selector.num_views,
        "fraction": callback.fraction,
        "search_fraction": callback.search_fraction,
        "pool_refresh": None if pool is None else pool.refresh,
        "use_pool": pool is not None,
        "pool_capacity": None if pool is None else pool.capacity,
        "pool_prefer_others": None if pool is None else pool.prefer_others,
        "select_at_start": callback.select_at_start,
    }


PAPER = {
    "selector": "ErrorGuidedSelector",
    "score": "paper",
    "min_separation": None,
    "temperature": None,
    "k": 30,
    "num_views": 3,
    "fraction": 0.05,
    "search_fraction": 0.05,
    "pool_refresh": False,
    "use_pool": True,
    "pool_capacity": None,
    "pool_prefer_others": True,
    "select_at_start": True,
}
DEFAULT = {**PAPER, "score": "visible", "min_separation": 30.0, "temperature": 10.0, "search_fraction": 0.35}
DEFAULT["pool_refresh"] = True


def test_the_default_is_the_tempered_side_aware_rule_with_the_released_search():
    assert _settings(ErrorGuidedViewAugmentation()) == DEFAULT == _settings(ErrorGuidedViewAugmentation.default())
    # each setting can be turned off on its own
    off = ErrorGuidedViewAugmentation(search_fraction=0.05, pool={"refresh": False})
    assert (off.search_fraction, off.pool.refresh, off.selector.temperature) == (0.05, False, 10.0)
    # the search never falls below the share given views: said, not silently raised
    with pytest.raises(ValueError, match=re.escape("`search_fraction` must be >= `fraction` (0.5)")):
        ErrorGuidedViewAugmentation(fraction=0.5)
    with pytest.raises(TypeError, match="takes no `selector`"):
        ErrorGuidedViewAugmentation.default(selector="random")


def test_the_papers_rule_is_one_preset_away():
    assert _settings(ErrorGuidedViewAugmentation.paper()) == PAPER
    tuned = ErrorGuidedViewAugmentation.paper(fraction=0.1, seed=3, pool={"capacity": 5})
    assert _settings(tuned) == {**PAPER, "fraction": 0.1, "search_fraction": 0.1, "pool_capacity": 5}
    assert tuned.seed == 3
    with pytest.raises(TypeError, match="takes no `selector`"):
        ErrorGuidedViewAugmentation.paper(selector="random")


def test_a_selector_given_keeps_the_callbacks_constant_defaults():
    # the defaults are the same whatever the selector: the paper's selector alone is not the paper's rule
    given = ErrorGuidedViewAugmentation(ErrorGuidedSelector.paper())
    assert (given.search_fraction, given.pool.refresh) == (0.35, True)
    assert _settings(given) == {**DEFAULT, "score": "paper", "min_separation": None, "temperature": None}
    random = ErrorGuidedViewAugmentation(RandomSelector(), fraction=0.1, search_fraction=0.1, pool=None)
    assert (random.search_fraction, random.pool) == (0.1, None)
    # a selector that uses no pool has none: the default pool is ignored for it, an explicit one refused
    assert ErrorGuidedViewAugmentation(RandomSelector()).pool is None
    assert "pool=None" in repr(ErrorGuidedViewAugmentation(RandomSelector()))
    with pytest.raises(ValueError, match=re.escape("`pool` must be None with RandomSelector")):
        ErrorGuidedViewAugmentation(RandomSelector(), pool={"capacity": 4})


def test_setup_refuses_without_dataloader_reload(tiny_dataset, tmp_path):
    trainer = make_trainer(tmp_path, 1, [make_callback()], reload_dataloaders_every_n_epochs=0)
    with pytest.raises(MisconfigurationException, match="reload_dataloaders_every_n_epochs=1"):
        trainer.fit(TinyUserModel(), datamodule=make_datamodule(tiny_dataset, tmp_path))


def test_setup_refuses_a_datamodule_without_add_samples(tiny_dataset, tmp_path):
    class Plain(L.LightningDataModule):
        def train_dataloader(self):
            return make_datamodule(tiny_dataset, tmp_path).train_dataloader()

    with pytest.raises(MisconfigurationException, match="add_samples"):
        make_trainer(tmp_path, 1, [make_callback()]).fit(TinyUserModel(), datamodule=Plain())


def test_setup_refuses_a_model_without_the_protocol(tiny_dataset, tmp_path):
    class NoProtocol(TinyUserModel):
        predict_voxels = None

    with pytest.raises(MisconfigurationException, match="predict_voxels"):
        make_trainer(tmp_path, 1, [make_callback()]).fit(
            NoProtocol(), datamodule=make_datamodule(tiny_dataset, tmp_path)
        )


class _PlainAugmentable(L.LightningDataModule):
    """A user's own augmentable datamodule (not a VTRDataModule) that declares the image size it serves."""

    def __init__(self, inner: VTRDataModule, image_size: int) -> None:
        super().__init__()
        self.inner, self.image_size = inner, image_size
        self.transform = inner.transform

    @property
    def generated_samples(self):
        return self.inner.generated_samples

    def setup(self, stage=None):
        self.inner.setup(stage)

    def train_dataloader(self):
        return self.inner.train_dataloader()

    def split_records(self, split):
        return self.inner.split_records(split)

    def record(self, category, object_id):
        return self.inner.record(category, object_id)

    def eval_item(self, record, view_set="aligned", seed=0):
        return self.inner.eval_item(record, view_set, seed)

    def object_views(self, record, view_set="aligned", indices=None):
        return self.inner.object_views(record, view_set, indices)

    def add_samples(self, samples, *, max_total=None):
        return self.inner.add_samples(samples, max_total=max_total)


def test_setup_refuses_a_plain_datamodule_serving_another_image_size(tiny_dataset, tmp_path):
    # VTRDataModule checks the model itself; a plain datamodule is checked by the callback
    dm = _PlainAugmentable(make_datamodule(tiny_dataset, tmp_path), image_size=64)
    callback = make_callback()
    with pytest.raises(MisconfigurationException) as info:
        make_trainer(tmp_path, 1, [callback]).fit(TinyUserModel(), datamodule=dm)
    assert "TinyUserModel.image_size is 32 but _PlainAugmentable.image_size is 64" in str(info.value)
    assert dm.inner.generated_samples == [] and callback.last_epoch == -2  # refused before any round
    # the same datamodule serving the model's size trains, and the callback generates
    dm = _PlainAugmentable(make_datamodule(tiny_dataset, tmp_path / "ok"), image_size=32)
    make_trainer(tmp_path / "ok", 1, [make_callback()]).fit(TinyUserModel(), datamodule=dm)
    assert len(dm.generated_samples) == 4


class TrainSetSizeProbe(L.Callback):
    """Records the size of the train loader's dataset at the start of every epoch."""

    def __init__(self) -> None:
        self.sizes: list[int] = []

    def on_train_epoch_start(self, trainer, pl_module) -> None:
        self.sizes.append(len(trainer.train_dataloader.dataset))


@pytest.fixture(scope="module")
def pool_run(tiny_dataset, tmp_path_factory):
    """One 3-epoch fit of EmptyPredictionModel with the paper's rule (error-guided, a pool keeping every selection,
    20 %, a selection before epoch 0), fitted once for the tests that read it: ``(datamodule, callback, run dir,
    train set sizes)``."""
    root = tmp_path_factory.mktemp("pool_run")
    dm = make_datamodule(tiny_dataset, root)
    callback = make_callback(selector="paper", fraction=0.2)
    probe = TrainSetSizeProbe()
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # tiny tensors; the selection of an empty prediction does not depend on it
    try:
        make_trainer(root, 3, [callback, probe]).fit(EmptyPredictionModel(), datamodule=dm)
    finally:
        torch.set_num_threads(threads)
    return dm, callback, root, probe.sizes


def test_generates_pool_samples_every_epoch_but_the_last(pool_run):
    dm, callback, tmp_path, _ = pool_run
    samples = dm.generated_samples
    # 21 training objects, round(0.2 * 21) = 4 per selection: before epoch 0 (from the model the fit starts
    # with, labelled -1) and after epochs 0 and 1 (not the last, not the sanity check)
    assert [s["epoch"] for s in samples] == [-1] * 4 + [0] * 4 + [1] * 4
    assert callback.last_epoch == 1 and len(callback.pool) == 12
    # Every training view set is a set the selector found on some object of the same category.
    for s in samples:
        _, sets = callback.pool.view_sets(s["category"])
        assert any(np.allclose(v.numpy(), s["viewpoints"], atol=1e-4) for v in sets)
    # The images are renders of the object's mesh at exactly those viewpoints.
    rec = dm.record(samples[0]["category"], samples[0]["object_id"])
    expected = RenderSynthesizer(image_size=32).synthesize(
        [callback._request(dm, rec, torch.tensor(samples[0]["viewpoints"]))]
    )[0]
    got = np.stack([np.asarray(Image.open(dm.generated_dir / samples[0]["dir"] / n)) for n in samples[0]["images"]])
    assert np.array_equal(got, expected)
    # With an empty prediction the error is the ground truth: the logged error is the objects' occupancy.
    record = json.loads((Path(tmp_path) / "vtr_selection" / "epoch_0000.json").read_text())
    occupancy = np.mean([dm.object_voxels(dm.record(*o.split("/"))).mean().item() for o in record["objects"]])
    assert record["mean_error"] == pytest.approx(occupancy, rel=1e-6)
    # and the next epoch trained on them: the train set grew.
    assert len(dm.train_dataset()) == 21 + 12


@pytest.mark.parametrize("selector_cls", [RandomSelector, NatureSelector])
def test_any_selector_runs_through_the_same_callback(tiny_dataset, tmp_path, selector_cls):
    dm = make_datamodule(tiny_dataset, tmp_path)
    callback = make_callback(selector=selector_cls(), fraction=0.1)
    make_trainer(tmp_path, 2, [callback]).fit(TinyUserModel(), datamodule=dm)
    assert callback.pool is None
    record = json.loads((Path(tmp_path) / "vtr_selection" / "epoch_0000.json").read_text())
    assert record["view_sets"] == record["selected"]  # no pool: trained on exactly what was selected
    pitches = np.array(record["selected"])[..., 1]
    if selector_cls is NatureSelector:
        assert np.all(pitches == 0.0)
    assert len(dm.generated_samples) == 4  # 2 before epoch 0, 2 after it


#: The per-object (sharded) default and the relative score, which the callback runs batched on rank 0.
GUIDED = {
    "per_object": lambda: "paper",
    # the callback's default: tempered sampling, 35 % searched, the pool rebuilt at every selection
    "default": lambda: None,
    "relative": lambda: ErrorGuidedSelector(relative=True),
}


def _fit(root, tmp_path, epochs, ckpt=None, selector=None):
    L.seed_everything(0, verbose=False)
    dm = make_datamodule(root, tmp_path)
    checkpoint = L.pytorch.callbacks.ModelCheckpoint(dirpath=tmp_path / "ckpt", save_last=True)
    callback = make_callback(fraction=0.15, selector=selector)
    make_trainer(tmp_path, epochs, [callback, checkpoint]).fit(TinyUserModel(), datamodule=dm, ckpt_path=ckpt)
    return dm, callback


@pytest.mark.slow
@pytest.mark.parametrize("guided", sorted(GUIDED))
def test_resume_generates_exactly_what_an_uninterrupted_run_does(tiny_dataset, tmp_path, guided):
    # Interrupted after epoch 0 (its last, which generates nothing): the resume catches up epoch 0's generation,
    # then trains epoch 1 and generates after it as the uninterrupted run does.
    full, full_cb = _fit(tiny_dataset, tmp_path / "full", 3, selector=GUIDED[guided]())
    _fit(tiny_dataset, tmp_path / "part", 1, selector=GUIDED[guided]())
    ckpt = str(tmp_path / "part" / "ckpt" / "last.ckpt")
    resumed, resumed_cb = _fit(tiny_dataset, tmp_path / "part", 3, ckpt=ckpt, selector=GUIDED[guided]())
    assert [c[:4] for c in generated_contents(resumed)] == [c[:4] for c in generated_contents(full)]
    assert generated_contents(resumed) == generated_contents(full)
    assert [s["epoch"] for s in full.generated_samples] == [-1] * 3 + [0] * 3 + [1] * 3
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


@pytest.mark.slow
@pytest.mark.parametrize("guided", sorted(GUIDED))
def test_two_process_ddp_generates_what_one_process_does(tiny_dataset, tmp_path, guided, request):
    if guided == "per_object":  # the paper's rule: the shared fit of the same arguments
        single = request.getfixturevalue("pool_run")[2]
    else:
        single = tmp_path / "single"
        dm = make_datamodule(tiny_dataset, single)
        callback = make_callback(fraction=0.2, selector=GUIDED[guided]())
        make_trainer(single, 3, [callback]).fit(EmptyPredictionModel(), datamodule=dm)

    ddp = tmp_path / "ddp"
    probe = DatasetDigestProbe(str(tmp_path / "digests.jsonl"))
    trainer = make_trainer(
        ddp,
        3,
        [make_callback(fraction=0.2, selector=GUIDED[guided]()), probe],
        devices=2,
        strategy="ddp_spawn",
        num_sanity_val_steps=2,
    )
    trainer.fit(EmptyPredictionModel(), datamodule=make_datamodule(tiny_dataset, ddp))

    assert generated_index(ddp / "gen") == generated_index(single / "gen")
    assert len(generated_index(single / "gen")) == 12
    digests = [json.loads(line) for line in (tmp_path / "digests.jsonl").read_text().splitlines()]
    assert [d[0][0] for d in digests] == [25, 29, 33]  # epochs 0, 1, 2 see 4, 8, 12 generated samples
    assert all(d[0] == d[1] for d in digests)  # rank 0 and rank 1 serve identical data


def test_source_images_are_decoded_only_for_synthesizers_that_read_them(tiny_dataset, tmp_path):
    from lightning_vtr.synthesis.base import Synthesizer

    class NeedsImages(Synthesizer):
        def synthesize(self, requests):
            return [np.zeros((len(r.target_viewpoints), 8, 8, 4), np.uint8) for r in requests]

    dm = make_datamodule(tiny_dataset, tmp_path)
    dm.setup("fit")
    rec = dm.split_records("train")[0]
    rendered = make_callback()._request(dm, rec, torch.zeros(3, 2))
    diffused = make_callback(synthesizer=NeedsImages())._request(dm, rec, torch.zeros(3, 2))
    assert rendered.source_images.shape[0] == 0  # the mesh renderer never looks at them
    assert diffused.source_images.shape == (8, 64, 64, 4)  # all 8 views of the tiny dataset's aligned set
    assert torch.equal(rendered.source_viewpoints, diffused.source_viewpoints)
    assert torch.allclose(diffused.source_viewpoints[:, 1], torch.full((8,), 30.0))


@pytest.mark.parametrize(("select_at_start", "expected"), [(True, [25, 29, 33]), (False, [21, 25, 29])])
def test_the_first_selection_is_trained_on_in_epoch_0(tiny_dataset, tmp_path, request, select_at_start, expected):
    # 21 training objects, 4 new samples per selection; with select_at_start, the selection made from the model
    # the fit starts with is in epoch 0's loader (Lightning built that loader before on_train_start).
    if select_at_start:  # the default: the shared fit of the same arguments
        _, callback, _, sizes = request.getfixturevalue("pool_run")
        assert callback.select_at_start
    else:
        dm = make_datamodule(tiny_dataset, tmp_path)
        probe = TrainSetSizeProbe()
        callback = make_callback(selector="paper", fraction=0.2, select_at_start=select_at_start)
        make_trainer(tmp_path, 3, [callback, probe]).fit(EmptyPredictionModel(), datamodule=dm)
        sizes = probe.sizes
    assert sizes == expected


def test_search_more_objects_than_get_views(tiny_dataset, tmp_path):
    dm = make_datamodule(tiny_dataset, tmp_path)
    callback = make_callback(
        selector="paper", fraction=0.1, search_fraction=0.5, generate_for="error", select_at_start=True
    )
    make_trainer(tmp_path, 1, [callback]).fit(EmptyPredictionModel(), datamodule=dm)
    record = json.loads((Path(tmp_path) / "vtr_selection" / "start.json").read_text())
    # round(0.5 * 21) = 10 objects searched, all in the pool; round(0.1 * 21) = 2 get new views
    assert record["searched"] == 10 and len(callback.pool) == 10
    assert len(dm.generated_samples) == 2
    # With an empty prediction an object's error is its occupancy: "error" picks the two fullest searched objects.
    occupancy = {key: dm.object_voxels(dm.record(*key.split("/"))).mean().item() for key in _pool_keys(callback)}
    fullest = sorted(occupancy, key=lambda key: -occupancy[key])[:2]
    assert sorted(f"{s['category']}/{s['object_id']}" for s in dm.generated_samples) == sorted(fullest)


def _pool_keys(callback) -> list[str]:
    return [f"{cat}/{oid}" for cat in callback.pool.categories() for oid in callback.pool.view_sets(cat)[0]]


def test_pool_refresh_keeps_only_the_latest_selection(tiny_dataset, tmp_path):
    dm = make_datamodule(tiny_dataset, tmp_path)
    callback = make_callback(selector="paper", fraction=0.2, pool={"refresh": True})
    make_trainer(tmp_path, 3, [callback]).fit(EmptyPredictionModel(), datamodule=dm)
    assert len(dm.generated_samples) == 12  # three selections of 4
    assert len(callback.pool) == 4  # only the last selection's sets
    last = {s["object_id"] for s in dm.generated_samples if s["epoch"] == 1}
    assert {key.split("/")[1] for key in _pool_keys(callback)} == last


def test_callback_rejects_a_search_fraction_below_fraction():
    with pytest.raises(ValueError, match=r"`search_fraction` must be >= `fraction` \(0.2\).*got 0.1"):
        ErrorGuidedViewAugmentation(fraction=0.2, search_fraction=0.1)
    with pytest.raises(ValueError, match="`generate_for` must be one of 'random', 'error', got 'worst'"):
        ErrorGuidedViewAugmentation(generate_for="worst")


# ---------------------------------------------------------------------------------------- logging, progress bar
def test_vtr_values_go_through_pl_module_log_and_images_to_the_logger(tiny_dataset, tmp_path, monkeypatch):
    import csv

    from lightning.pytorch.callbacks import ModelCheckpoint
    from lightning.pytorch.loggers import CSVLogger

    import lightning_vtr.augmentation.runner as runner_module

    bars = []
    real_tqdm = runner_module.tqdm
    monkeypatch.setattr(runner_module, "tqdm", lambda *a, **k: bars.append(k["disable"]) or real_tqdm(*a, **k))
    dm = make_datamodule(tiny_dataset, tmp_path)
    callback = make_callback(fraction=0.2, progress_bar=True)  # the Trainer's setting wins: no bar
    # a checkpoint monitoring a vtr/* value works only if it reaches trainer.callback_metrics
    best = ModelCheckpoint(dirpath=tmp_path / "ckpt", monitor="vtr/samples_total", mode="max", save_top_k=1)
    trainer = L.Trainer(
        max_epochs=2,
        accelerator="cpu",
        callbacks=[callback, best],
        default_root_dir=str(tmp_path),
        logger=CSVLogger(tmp_path, name="", version=""),
        enable_progress_bar=False,
        enable_model_summary=False,
        limit_train_batches=2,
        limit_val_batches=1,
        reload_dataloaders_every_n_epochs=1,
    )
    trainer.fit(EmptyPredictionModel(), datamodule=dm)

    assert bars and not any(b is False for b in bars)  # every synthesis bar disabled
    # 4 samples before epoch 0 and 4 after it: logged at epoch level through pl_module.log
    assert trainer.callback_metrics["vtr/samples_total"].item() == 8.0
    assert trainer.callback_metrics["vtr/samples_generated"].item() == 4.0
    rows = list(csv.DictReader((tmp_path / "metrics.csv").read_text().splitlines()))
    totals = [float(r["vtr/samples_total"]) for r in rows if r.get("vtr/samples_total")]
    assert totals == [8.0]  # epoch 0's row (epoch 1, the last, generates nothing)
    assert best.best_model_score.item() == 8.0
    # the pictures reach the CSV logger as PNG files: the grid of new views (4 samples x 3 views of 32 px) and the
    # error sheets of two of the objects given views
    grids = sorted((tmp_path / "images" / "vtr" / "new_views").glob("step_*.png"))
    assert len(grids) == 2 and np.asarray(Image.open(grids[0])).shape == (4 * 32, 3 * 32, 3)
    sheets = sorted((tmp_path / "images" / "vtr" / "error_sheets").glob("step_*.png"))
    assert len(sheets) == 2 and np.asarray(Image.open(sheets[0])).shape[0] > 2 * 5 * 96


@pytest.mark.parametrize("enabled", [True, False])
def test_the_synthesis_bar_follows_the_trainers_progress_bar(enabled):
    from lightning_vtr.callback import _trainer_shows_progress

    trainer = L.Trainer(enable_progress_bar=enabled, logger=False)
    assert _trainer_shows_progress(trainer) is enabled
