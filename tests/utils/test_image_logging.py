"""One picture to every logger: TensorBoard, W&B (offline), MLflow (a recording stand-in), Comet-less fallbacks."""

from __future__ import annotations

import re
import warnings

import lightning as L
import numpy as np
import pytest
import torch
from lightning.pytorch.loggers import CSVLogger, Logger, MLFlowLogger
from PIL import Image

from lightning_vtr.utils import image_logging
from lightning_vtr.utils.image_logging import image_to_uint8, log_image, png_path


def _picture(h=6, w=10):
    rng = np.random.default_rng(0)
    return rng.integers(0, 256, (h, w, 3), dtype=np.uint8)


def test_image_to_uint8_takes_the_usual_layouts():
    picture = _picture()
    np.testing.assert_array_equal(image_to_uint8(torch.from_numpy(picture).permute(2, 0, 1)), picture)  # CHW tensor
    np.testing.assert_array_equal(image_to_uint8(picture.astype(np.float32) / 255.0), picture)  # float in [0, 1]
    np.testing.assert_array_equal(image_to_uint8(Image.fromarray(picture)), picture)
    assert image_to_uint8(np.zeros((2, 3), np.uint8)).shape == (2, 3, 3)  # grey
    transparent = np.zeros((2, 2, 4), np.uint8)
    assert (image_to_uint8(transparent) == 255).all()  # alpha composited on white
    with pytest.raises(
        ValueError, match=re.escape("`image` must have shape (H, W, 3), (H, W, 4), (3, H, W) or (H, W), got (2, 2, 5)")
    ):
        image_to_uint8(np.zeros((2, 2, 5)))
    with pytest.raises(TypeError, match="`image` must be a numpy array, torch tensor or PIL image, got list"):
        image_to_uint8([[0]])


def test_rgba_is_composited_on_white_as_the_float32_formula_rounded():
    rgba = np.random.default_rng(1).integers(0, 256, (6, 5, 4), dtype=np.uint8)
    alpha = rgba[..., 3:].astype(np.float32) / 255.0
    expected = (rgba[..., :3].astype(np.float32) * alpha + 255.0 * (1.0 - alpha)).round().astype(np.uint8)
    np.testing.assert_array_equal(image_to_uint8(rgba), expected)
    np.testing.assert_array_equal(image_to_uint8(torch.from_numpy(rgba).permute(2, 0, 1)), expected)


def test_png_path_keeps_tags_inside_the_images_folder(tmp_path):
    assert png_path(tmp_path, "vtr/new_views", 12) == tmp_path / "images" / "vtr" / "new_views" / "step_000012.png"
    assert png_path(tmp_path, "../../etc/x y", 1) == tmp_path / "images" / "etc" / "x_y" / "step_000001.png"


def test_csv_logger_gets_png_files_without_a_warning(tmp_path):
    trainer = L.Trainer(logger=CSVLogger(tmp_path, name="run", version=0), enable_progress_bar=False)
    picture = _picture()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        written = log_image(trainer, "vtr/new_views", picture, step=7)
    assert written == [tmp_path / "run" / "version_0" / "images" / "vtr" / "new_views" / "step_000007.png"]
    np.testing.assert_array_equal(np.asarray(Image.open(written[0])), picture)


class _Unknown(Logger):
    """A logger that takes no images and that the helper does not know."""

    def __init__(self, root):
        super().__init__()
        self._root = root

    @property
    def name(self):
        return "unknown"

    @property
    def version(self):
        return 0

    @property
    def save_dir(self):
        return str(self._root)

    def log_metrics(self, metrics, step=None):
        pass

    def log_hyperparams(self, params, *args, **kwargs):
        pass


def test_an_unknown_logger_gets_png_files_and_one_warning_per_type(tmp_path, monkeypatch):
    monkeypatch.setattr(image_logging, "_WARNED", set())
    logger = _Unknown(tmp_path)
    with pytest.warns(UserWarning, match="cannot send images to a _Unknown logger; writing them as PNG files under"):
        first = log_image(logger, "a", _picture(), step=1)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the second picture: no second warning
        second = log_image([logger], "a", _picture(), step=2)
    assert [p.name for p in first + second] == ["step_000001.png", "step_000002.png"]
    assert first[0].parent == tmp_path / "images" / "a"


def test_no_logger_or_another_rank_logs_nothing(tmp_path):
    assert log_image(L.Trainer(logger=False, default_root_dir=tmp_path), "a", _picture()) == []
    assert not any(tmp_path.rglob("*.png"))
    with pytest.raises(TypeError, match="`target` must be a Trainer, a Logger or an iterable of Loggers, got int"):
        log_image(3, "a", _picture())


def test_tensorboard_gets_add_image(tmp_path):
    pytest.importorskip("tensorboard")
    from lightning.pytorch.loggers import TensorBoardLogger
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    logger = TensorBoardLogger(tmp_path, name="tb", version=0)
    picture = _picture(6, 10)
    assert log_image(logger, "vtr/new_views", picture, step=3) == []  # nothing written by the fallback
    logger.experiment.flush()
    events = EventAccumulator(logger.log_dir, size_guidance={"images": 0})
    events.Reload()
    (image,) = events.Images("vtr/new_views")
    assert (image.step, image.width, image.height) == (3, 10, 6)
    import io

    np.testing.assert_array_equal(
        np.asarray(Image.open(io.BytesIO(image.encoded_image_string)).convert("RGB")), picture
    )


def test_wandb_offline_gets_log_image(tmp_path, monkeypatch):
    pytest.importorskip("wandb")
    from lightning.pytorch.loggers import WandbLogger

    monkeypatch.setenv("WANDB_MODE", "offline")
    monkeypatch.setenv("WANDB_DIR", str(tmp_path))
    monkeypatch.setenv("WANDB_SILENT", "true")
    logger = WandbLogger(save_dir=str(tmp_path), offline=True, project="lightning_vtr_test")
    try:
        assert log_image(logger, "vtr/new_views", _picture(6, 10), step=2) == []
    finally:
        logger.experiment.finish()
    media = list(tmp_path.rglob("media/images/vtr/new_views_*.png"))  # named by W&B's own step counter
    assert len(media) == 1
    np.testing.assert_array_equal(np.asarray(Image.open(media[0]).convert("RGB")), _picture(6, 10))


def test_mlflow_gets_log_image_as_an_artifact(monkeypatch):
    # MLflow is not installed here: a stand-in client records the call the helper makes (the MlflowClient API).
    calls = []

    class Client:
        def log_image(self, run_id, image, artifact_file=None):
            calls.append((run_id, image, artifact_file))

    logger = MLFlowLogger.__new__(MLFlowLogger)
    Logger.__init__(logger)
    logger._run_id = "run-1"
    monkeypatch.setattr(MLFlowLogger, "experiment", property(lambda self: Client()))
    monkeypatch.setattr(MLFlowLogger, "run_id", property(lambda self: self._run_id))
    picture = _picture()
    assert log_image(logger, "vtr/new_views", picture, step=5) == []
    ((run_id, image, artifact),) = calls
    assert run_id == "run-1" and artifact == "images/vtr/new_views/step_000005.png"
    np.testing.assert_array_equal(image, picture)
