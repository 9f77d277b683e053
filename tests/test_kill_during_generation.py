"""A training process killed (SIGKILL) while ErrorGuidedViewAugmentation writes generated samples loses nothing:
no half-written file is ever listed or read, every sample reported written is in the registry after the resume,
and the resumed run ends with the weights of an uninterrupted one."""

from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from helpers import assert_same_training_state, fit_pix2vox, generated_index, one_thread
from PIL import Image

_one_thread = pytest.fixture(autouse=True)(one_thread)

# The child trains like `fit_pix2vox(..., epochs=4)`, the session's uninterrupted run. It reports every generated sample once its files are written
# (done.jsonl); in the generation after epoch 1 (3 samples), once one sample is done, it writes half of the next
# sample's first PNG into the atomic writer's temporary file, says so (killable) and waits to be killed. The last
# checkpoint then is epoch 0's (ModelCheckpoint saves at the train epoch's end, after the callback's generation).
_CHILD = r"""
import hashlib, io, json, os, sys, time
from pathlib import Path

root, run_dir, report, tests_dir = sys.argv[1:5]
sys.path.insert(0, tests_dir)
import torch

torch.set_num_threads(1)
from PIL import Image

import lightning_vtr.data.datamodule as datamodule_module
import lightning_vtr.data.dataset as dataset_module
from helpers import fit_pix2vox

report = Path(report)
state = {"epoch": None, "done": 0}
real_write, real_save = datamodule_module.write_generated_sample, dataset_module._atomic_save_png


def write(sample, directory):
    state["epoch"] = sample.epoch
    entry = real_write(sample, directory)
    entry["sha1"] = [hashlib.sha1((directory / n).read_bytes()).hexdigest() for n in entry["images"]]
    with open(report / "done.jsonl", "a") as f:
        f.write(json.dumps(entry) + "\n")
        f.flush()
        os.fsync(f.fileno())
    state["done"] += sample.epoch == 1
    return entry


def save(image, path):
    if state["epoch"] == 1 and state["done"] == 1:
        buffer = io.BytesIO()
        Image.fromarray(image).save(buffer, format="PNG")
        with dataset_module.atomic_open(path, "wb") as f:
            f.write(buffer.getvalue()[: len(buffer.getvalue()) // 2])
            f.flush()
            os.fsync(f.fileno())
            (report / "killable").write_text(str(path))
            time.sleep(600)
    real_save(image, path)


datamodule_module.write_generated_sample = write
dataset_module._atomic_save_png = save
fit_pix2vox(root, Path(run_dir), epochs=4)
"""


def _decodes(path: Path) -> bool:
    try:
        with Image.open(path) as image:
            image.load()
        return True
    except OSError:
        return False


@pytest.mark.slow
def test_a_kill_while_writing_samples_loses_nothing(tiny_dataset, pix2vox_run_4_epochs, tmp_path):
    run, report = tmp_path / "run", tmp_path / "report"
    report.mkdir()
    (tmp_path / "child.py").write_text(_CHILD)
    tests_dir = str(Path(__file__).parent)
    log = open(tmp_path / "child.log", "w")  # noqa: SIM115 (the child writes it until killed)
    child = subprocess.Popen(
        [sys.executable, str(tmp_path / "child.py"), str(tiny_dataset), str(run), str(report), tests_dir],
        stdout=log,
        stderr=subprocess.STDOUT,
        env=os.environ | {"OMP_NUM_THREADS": "1"},
    )
    deadline = time.monotonic() + 300  # about 20 s on 2 idle cores
    while not (report / "killable").exists():
        if child.poll() is not None or time.monotonic() > deadline:
            child.kill()
            child.wait()
            log.close()
            pytest.fail("the child never reached the kill point:\n" + (tmp_path / "child.log").read_text()[-3000:])
        time.sleep(0.05)
    os.kill(child.pid, signal.SIGKILL)
    assert child.wait() == -signal.SIGKILL
    log.close()

    # 1. at the kill: 3 samples before epoch 0, 3 after it and 1 after epoch 1 were reported written; the 2nd after
    # epoch 1 was half-written, into a temporary file only
    done = [json.loads(line) for line in (report / "done.jsonl").read_text().splitlines()]
    assert [d["epoch"] for d in done] == [-1] * 3 + [0] * 3 + [1]
    half = Path((report / "killable").read_text())
    assert not half.exists()
    (partial,) = half.parent.glob(f".{half.name}.*.tmp")
    assert partial.stat().st_size > 0 and not _decodes(partial)
    # the index on disk lists the generation the kill did not interrupt, and every file it names is whole
    on_disk = json.loads((run / "gen" / "index.json").read_text())
    assert [e["dir"] for e in on_disk] == [d["dir"] for d in done[:6]]
    assert all(_decodes(run / "gen" / e["dir"] / n) for e in on_disk for n in e["images"])

    # 2. resume from the last checkpoint (epoch 0's end): epoch 1 trains again and its generation is redone
    resumed = fit_pix2vox(tiny_dataset, run, epochs=4, ckpt_path=str(run / "ckpt" / "last.ckpt"))
    registry = resumed.datamodule.generated_samples
    assert [s["epoch"] for s in registry] == [-1] * 3 + [0] * 3 + [1] * 3 + [2] * 3
    # every sample reported written is in the registry, under its directory, with the same files
    for reported in done:
        (entry,) = [e for e in registry if e["dir"] == reported["dir"]]
        assert {k: entry[k] for k in ("epoch", "category", "object_id", "images", "viewpoints")} == {
            k: reported[k] for k in ("epoch", "category", "object_id", "images", "viewpoints")
        }
        sha1 = [hashlib.sha1((run / "gen" / entry["dir"] / n).read_bytes()).hexdigest() for n in entry["images"]]
        assert sha1 == reported["sha1"]
    # the half-written sample was written again, whole; the index on disk is the registry
    assert _decodes(half)
    assert json.loads((run / "gen" / "index.json").read_text()) == registry
    assert not any(n.startswith(".") for e in registry for n in e["images"])

    # 3. the same samples, weights and optimizer state as a run nobody killed
    full, full_dir = pix2vox_run_4_epochs
    assert generated_index(run / "gen") == generated_index(full_dir / "gen")
    assert_same_training_state(resumed, full)
