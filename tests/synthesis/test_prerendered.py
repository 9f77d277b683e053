"""Views rendered once into the dataset (``build-dataset --prerender-views``) and served by
``PrerenderedSynthesizer``, which needs no OpenGL: the snap to the nearest rendered viewpoint, pixel equality with
``RenderSynthesizer``, the missing-views error, verification, resuming, and a fit with pyrender blocked."""

from __future__ import annotations

import json
import shutil
import sys

import numpy as np
import pytest
import torch
from PIL import Image

from lightning_vtr.cli import main
from lightning_vtr.data.format import scan_dataset
from lightning_vtr.errors import DataError
from lightning_vtr.geometry import angular_distance, candidate_viewpoints
from lightning_vtr.synthesis import PrerenderedSynthesizer, RenderSynthesizer
from lightning_vtr.synthesis.base import SynthesisRequest
from lightning_vtr.synthesis.prerendered import prerendered_image_name

#: K = 90: 8 views per training object keeps the fixture fast; the default K = 30 renders 72.
K = 90


@pytest.fixture(scope="module")
def prerendered_dataset(tmp_path_factory):
    """2 categories x 3 procedural objects at 64 px (1 / 1 / 1 split each), built and prerendered in one command."""
    root = tmp_path_factory.mktemp("prerendered") / "data"
    argv = ["build-dataset", str(root), "--categories", "chair,table", "--objects-per-category", "3"]
    argv += ["--image-size", "64", "--views-per-set", "3", "--prerender-views", "--prerender-interval", str(K)]
    assert main([*argv, "--no-progress"]) == 0
    return root


def _train(root):
    return [r for r in scan_dataset(root) if r.split == "train"]


def _copy(root, tmp_path):
    shutil.copytree(root, tmp_path / "copy")
    return tmp_path / "copy"


def _request(record, targets):
    return SynthesisRequest(
        record.object_id, record.category, np.zeros((0, 0, 0, 4), np.uint8), torch.zeros(0, 2),
        torch.as_tensor(targets, dtype=torch.float32), mesh_path=record.mesh_path,
    )  # fmt: skip


def _png(path):
    with Image.open(path) as im:
        return np.asarray(im.convert("RGBA"))


def test_the_build_renders_the_grid_of_every_training_object_only(prerendered_dataset):
    grid = candidate_viewpoints(K).double().numpy()
    config = json.loads((prerendered_dataset / "prerendered.json").read_text())
    assert (config["interval"], config["image_size"]) == (K, 64)
    for record in scan_dataset(prerendered_dataset):
        folder = record.voxel_path.parent / "prerendered"
        assert folder.is_dir() == (record.split == "train"), record.key
        if record.split == "train":
            index = json.loads((folder / "index.json").read_text())
            np.testing.assert_allclose(index["viewpoints"], grid)
            assert sorted(p.name for p in folder.glob("*.png")) == sorted(prerendered_image_name(v) for v in grid)


def test_a_request_gets_the_nearest_grid_image_and_its_snap_angle(prerendered_dataset):
    record = _train(prerendered_dataset)[0]
    targets = torch.tensor([[10.0, 20.0], [-100.0, -50.0], [170.0, 80.0], [-44.0, 46.0]])
    grid = candidate_viewpoints(K).double()
    distances = angular_distance(targets.double()[:, None], grid[None])  # (4, 8)
    nearest = distances.argmin(1)
    synthesizer = PrerenderedSynthesizer()
    images = synthesizer.synthesize([_request(record, targets)])[0]
    folder = record.voxel_path.parent / "prerendered"
    assert images.shape == (4, 64, 64, 4) and synthesizer.image_size == 64
    for t, i in enumerate(nearest.tolist()):
        assert np.array_equal(images[t], _png(folder / prerendered_image_name(grid[i])))
    expected = distances.min(1).values.numpy()
    np.testing.assert_allclose(synthesizer.last_snap_angles[0], expected, atol=1e-6)
    assert expected[3] == pytest.approx(
        float(angular_distance(targets[3].double(), torch.tensor([-45.0, 45.0]).double())), abs=1e-6
    )
    assert expected.min() > 0.5  # none of these targets is a grid point: every one snapped
    np.testing.assert_allclose(synthesizer.pop_snap_angles(), expected, atol=1e-6)
    assert synthesizer.pop_snap_angles().shape == (0,)  # popped


def test_a_grid_view_equals_what_the_render_synthesizer_makes(prerendered_dataset):
    record = _train(prerendered_dataset)[1]
    viewpoint = candidate_viewpoints(K)[5:6]  # (45, 45)
    rendered = RenderSynthesizer(image_size=64).synthesize([_request(record, viewpoint)])[0]
    synthesizer = PrerenderedSynthesizer(prerendered_dataset)
    served = synthesizer.synthesize([_request(record, viewpoint)])[0]
    assert served.shape == rendered.shape == (1, 64, 64, 4)
    assert np.array_equal(served, rendered)
    assert (rendered[..., 3] > 0).any()  # the object is in the picture
    assert synthesizer.last_snap_angles[0].tolist() == [pytest.approx(0.0, abs=1e-3)]


def test_an_object_without_prerendered_views_is_named_with_the_fix(prerendered_dataset, tmp_path):
    root = _copy(prerendered_dataset, tmp_path)
    records = _train(root)
    shutil.rmtree(records[0].voxel_path.parent / "prerendered")
    synthesizer = PrerenderedSynthesizer()
    with pytest.raises(DataError) as error:
        synthesizer.check_serves(records)
    message = str(error.value)
    assert "\n" not in message
    assert (
        f"1 of 2 training objects have no prerendered views (first: object {records[0].key} of dataset {root})"
        in message
    )
    assert f"lightning-vtr build-dataset {root} --prerender-views" in message
    with pytest.raises(DataError, match=f"object {records[0].key} of dataset {root} has no prerendered views"):
        synthesizer.synthesize([_request(records[0], [[0.0, 0.0]])])
    synthesizer.check_serves(records[1:])  # the other object is served


def test_verify_reports_a_deleted_prerendered_image(prerendered_dataset, tmp_path, capsys):
    from lightning_vtr.data.verify import verify_dataset

    root = _copy(prerendered_dataset, tmp_path)
    first, second = _train(root)
    deleted = first.voxel_path.parent / "prerendered" / prerendered_image_name((45.0, -45.0))
    deleted.unlink()
    shutil.rmtree(second.voxel_path.parent / "prerendered")
    report = verify_dataset(root, workers=1, progress=False)
    assert [(p.kind, p.path) for p in report.problems] == [
        ("prerendered", deleted),
        ("prerendered", second.voxel_path.parent / "prerendered"),
    ]
    assert "listed in index.json is missing" in report.problems[0].message
    assert main(["dataset-info", str(root), "--verify", "--workers", "1", "--no-progress"]) == 1
    assert f"PROBLEM [prerendered] {deleted}" in capsys.readouterr().out
    assert verify_dataset(prerendered_dataset, workers=1, progress=False).ok


def test_a_finished_build_gets_its_missing_views_and_keeps_the_others(prerendered_dataset, tmp_path, capsys):
    root = _copy(prerendered_dataset, tmp_path)
    first, second = _train(root)
    kept = (second.voxel_path.parent / "prerendered" / "index.json").stat().st_mtime_ns
    shutil.rmtree(first.voxel_path.parent / "prerendered")
    argv = ["build-dataset", str(root), "--prerender-views", "--prerender-interval", str(K), "--no-progress"]
    assert main(argv) == 0  # no build option given: only the prerendering runs
    assert "prerendered 1 objects (8 views each, K = 90), skipped 1" in capsys.readouterr().out
    assert (second.voxel_path.parent / "prerendered" / "index.json").stat().st_mtime_ns == kept
    original = prerendered_dataset / first.voxel_path.parent.relative_to(root) / "prerendered"
    for path in original.glob("*.png"):
        assert np.array_equal(_png(path), _png(first.voxel_path.parent / "prerendered" / path.name))
    assert main(["build-dataset", str(root), "--prerender-views", "--prerender-interval", "30", "--no-progress"]) == 2
    assert "records prerendered views of other options (interval: 90 on disk vs 30 now)" in capsys.readouterr().err


def test_a_fit_with_pyrender_blocked_trains_on_prerendered_views(prerendered_dataset, tmp_path, monkeypatch):
    from helpers import TinyUserModel, make_callback, make_datamodule, make_trainer

    # no renderer can be imported from here on: `import pyrender` raises ImportError
    monkeypatch.setitem(sys.modules, "pyrender", None)
    monkeypatch.setitem(sys.modules, "lightning_vtr.renderer", None)
    synthesizer = PrerenderedSynthesizer()
    callback = make_callback(synthesizer=synthesizer, selector="random", fraction=0.5)
    dm = make_datamodule(prerendered_dataset, tmp_path)
    trainer = make_trainer(tmp_path, 2, [callback], limit_train_batches=1, num_sanity_val_steps=0)
    trainer.fit(TinyUserModel(), datamodule=dm)
    samples = dm.generated_samples
    assert samples, "the round generated no sample"
    grid = candidate_viewpoints(K).double()
    for sample in samples:  # each view a file equal to the prerendered image nearest its viewpoint
        folder = prerendered_dataset / "objects" / sample["category"] / sample["object_id"] / "prerendered"
        nearest = angular_distance(torch.as_tensor(sample["viewpoints"])[:, None], grid[None]).argmin(1)
        assert len(sample["images"]) == len(nearest) == 3
        for name, i in zip(sample["images"], nearest.tolist()):
            written = _png(tmp_path / "gen" / sample["dir"] / name)
            assert np.array_equal(written, _png(folder / prerendered_image_name(grid[i])))
    assert 0.0 < float(trainer.callback_metrics["vtr/snap_angle_mean"]) <= 90.0


def test_a_strategies_row_names_its_synthesizer(prerendered_dataset, tmp_path):
    from lightning_vtr.experiments.config import ExperimentConfig
    from lightning_vtr.experiments.strategies import VARIANTS, StrategyFileError, load_variants
    from lightning_vtr.experiments.training import make_strategy, resolved_strategy

    callback = make_strategy("prerendered", ExperimentConfig(data=str(prerendered_dataset)), RenderSynthesizer())
    assert type(callback.synthesizer) is PrerenderedSynthesizer  # the row's own, over the report's
    assert type(make_strategy("error_guided", ExperimentConfig(), RenderSynthesizer()).synthesizer) is RenderSynthesizer
    resolved = resolved_strategy("prerendered")
    assert resolved["synthesizer"]["class_path"] == "lightning_vtr.synthesis.PrerenderedSynthesizer"
    assert {k: v for k, v in resolved.items() if k != "synthesizer"} == resolved_strategy("error_guided")
    assert VARIANTS["error_guided"].synthesizer is None
    bad = tmp_path / "rows.yaml"
    bad.write_text(
        "mine:\n  title: T\n  description: D\n  selector: random\n  synthesizer: {class_path: pathlib.Path}\n"
    )
    with pytest.raises(StrategyFileError, match="row 'mine', synthesizer: pathlib.Path is not a lightning_vtr"):
        load_variants(bad)
