"""The callback's settings (repr, the fit-start log line, the settings record), the selection round as a pure
function, and where each run writes: two runs resumed from one checkpoint at the same time."""

from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers import TinyUserModel, make_callback, make_trainer

from lightning_vtr.augmentation.selection_round import Selection, plan_round, search_indices
from lightning_vtr.callback import ErrorGuidedViewAugmentation
from lightning_vtr.data.datamodule import VTRDataModule
from lightning_vtr.selection.pool import ViewpointPool


def _selection(index: int, category: str, yaw: float, error: float = 0.1) -> Selection:
    return Selection(index, category, f"o{index}", np.array([[yaw, 0.0], [yaw - 90, 10.0], [yaw - 150, -10.0]]), error)


def test_a_round_is_a_pure_function_of_seed_epoch_and_pool():
    searched = [_selection(i, "chair" if i % 2 else "table", 10.0 * i, error=i / 10) for i in range(6)]
    kw = {"fraction": 2 / 12, "min_objects": 1, "seed": 0}
    # the two objects with the largest error get views, in train order
    plan = plan_round(searched, 12, 0, generate_for="error", pool=None, **kw)
    assert [s.index for s in plan.targets] == [4, 5]
    assert [v.tolist() for v in plan.view_sets] == [searched[4].viewpoints.tolist(), searched[5].viewpoints.tolist()]
    # with a pool each target draws a set found on another object of its category
    pool = ViewpointPool(refresh=True)
    pooled = plan_round(searched, 12, 0, generate_for="error", pool=pool, **kw)
    for target, views in zip(pooled.targets, pooled.view_sets):
        sources = [s for s in searched if s.category == target.category and s.index != target.index]
        assert any(np.allclose(views, s.viewpoints) for s in sources)
    assert len(pool) == 6
    # a refreshing pool keeps only this round's sets; one that keeps them holds both rounds'
    plan_round(searched[:2], 12, 1, generate_for="random", pool=pool, **kw)
    assert len(pool) == 2
    keeping = ViewpointPool()
    plan_round(searched, 12, 0, generate_for="random", pool=keeping, **kw)
    plan_round(searched[:2], 12, 1, generate_for="random", pool=keeping, **kw)
    assert len(keeping) == 8
    # the same inputs give the same round; another epoch draws other objects
    again = plan_round(searched, 12, 0, generate_for="random", pool=ViewpointPool(refresh=True), **kw)
    twice = plan_round(searched, 12, 0, generate_for="random", pool=ViewpointPool(refresh=True), **kw)
    assert [s.index for s in again.targets] == [s.index for s in twice.targets]
    assert all(np.array_equal(a, b) for a, b in zip(again.view_sets, twice.view_sets))
    assert search_indices(40, 0, search_fraction=0.25, min_objects=1, seed=0) != search_indices(
        40, 1, search_fraction=0.25, min_objects=1, seed=0
    )


def test_repr_names_every_effective_setting():
    text = repr(ErrorGuidedViewAugmentation.paper(fraction=0.1))
    assert text.startswith("ErrorGuidedViewAugmentation(selector=ErrorGuidedSelector(")
    assert "min_separation=None" in text and "temperature=None" in text
    assert "fraction=0.1, search_fraction=0.1" in text
    assert "pool=ViewpointPool(capacity=None, num_views=3, fallback='area', prefer_others=True, refresh=False)" in text
    assert "pool=None" in repr(ErrorGuidedViewAugmentation("random", pool=None))
    default = repr(ErrorGuidedViewAugmentation())
    assert "min_separation=30.0, temperature=10.0" in default and "search_fraction=0.35" in default
    assert "refresh=True" in default


def test_settings_are_logged_at_fit_start_and_recorded(tiny_dataset, tmp_path, caplog):
    callback = make_callback(fraction=0.15)
    dm = VTRDataModule(str(tiny_dataset), image_size=32, batch_size=8)
    with caplog.at_level(logging.INFO):
        make_trainer(tmp_path, 1, [callback]).fit(TinyUserModel(), datamodule=dm)
    assert sum(repr(callback) in r.getMessage() for r in caplog.records) == 1
    record = json.loads((tmp_path / "vtr_selection" / "settings.json").read_text())
    assert record == {"version": 1, "callback": repr(callback), "settings": callback.settings()}
    assert record["settings"]["search_fraction"] == 0.35 and record["settings"]["pool"]["refresh"] is True
    # the generated samples went under the run's own log directory, with an index of them
    index = json.loads((tmp_path / "vtr_generated" / "index.json").read_text())
    assert [e["dir"] for e in index] == [e["dir"] for e in dm.generated_samples] and len(index) == 3
    assert {e["root"] for e in index} == {str((tmp_path / "vtr_generated").absolute())}


_RESUME = textwrap.dedent(
    """
    import json, sys
    from pathlib import Path
    import torch
    torch.set_num_threads(1)
    from helpers import TinyUserModel, make_callback, make_trainer, generated_contents
    from lightning_vtr.data.datamodule import VTRDataModule
    root, run, ckpt = sys.argv[1:4]
    dm = VTRDataModule(root, image_size=32, batch_size=8)
    make_trainer(Path(run), 3, [make_callback(fraction=0.15)]).fit(TinyUserModel(), datamodule=dm, ckpt_path=ckpt)
    contents = [[c[0], c[1], c[2], c[3], c[4].hex()] for c in generated_contents(dm)]
    out = {"contents": contents, "roots": [e["root"] for e in dm.generated_samples]}
    Path(run, "result.json").write_text(json.dumps(out))
    """
)


@pytest.mark.slow
def test_two_runs_resumed_from_one_checkpoint_at_once_write_their_own_samples(tiny_dataset, tmp_path):
    first = tmp_path / "first"
    checkpoint = __import__("lightning").pytorch.callbacks.ModelCheckpoint(dirpath=first / "ckpt", save_last=True)
    dm = VTRDataModule(str(tiny_dataset), image_size=32, batch_size=8)
    make_trainer(first, 1, [make_callback(fraction=0.15), checkpoint]).fit(TinyUserModel(), datamodule=dm)
    first_index = (first / "vtr_generated" / "index.json").read_text()
    first_samples = sorted(p.name for p in (first / "vtr_generated").iterdir())
    script = tmp_path / "resume.py"
    script.write_text(_RESUME)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(Path(__file__).parent), os.environ.get("PYTHONPATH", "")])}
    runs = [tmp_path / "second", tmp_path / "third"]
    procs = [
        subprocess.Popen(
            [sys.executable, str(script), str(tiny_dataset), str(run), str(first / "ckpt" / "last.ckpt")],
            env=env,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
        )
        for run in runs
    ]
    for proc in procs:
        _, err = proc.communicate(timeout=600)
        assert proc.returncode == 0, err.decode()[-3000:]
    results = [json.loads((run / "result.json").read_text()) for run in runs]
    # both complete: the restored round before epoch 0 and the rounds after epochs 0 and 1, the same samples
    for result in results:
        assert [c[0] for c in result["contents"]] == [-1] * 3 + [0] * 3 + [1] * 3
    assert results[0]["contents"] == results[1]["contents"]
    # distinct: restored samples read from the first run, new ones written under each run's own log directory
    for run, result in zip(runs, results):
        own = str((run / "vtr_generated").absolute())
        assert result["roots"] == [str((first / "vtr_generated").absolute())] * 3 + [own] * 6
        index = json.loads((run / "vtr_generated" / "index.json").read_text())
        assert [e["root"] for e in index] == result["roots"]
        assert len([p for p in (run / "vtr_generated").iterdir() if p.is_dir()]) == 6
    # the first run's files are untouched
    assert (first / "vtr_generated" / "index.json").read_text() == first_index
    assert sorted(p.name for p in (first / "vtr_generated").iterdir()) == first_samples
    assert torch.load(first / "ckpt" / "last.ckpt", map_location="cpu", weights_only=False)["epoch"] == 0
