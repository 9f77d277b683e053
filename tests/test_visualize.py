"""Voxel pictures: cube meshes of grids, renders, error classes and colours, error projections, sheets and the
validation-sheet logging a model calls."""

from __future__ import annotations

import re

import lightning as L
import numpy as np
import pytest
import torch
from helpers import one_thread
from lightning.pytorch.loggers import CSVLogger
from PIL import Image
from torch import nn

from lightning_vtr.visualize import (
    CORRECT,
    DISPLAY_VIEWPOINTS,
    EMPTY,
    ERROR_COLORS,
    FALSE_NEGATIVE,
    FALSE_POSITIVE,
    compose_sheet,
    display_images,
    error_labels,
    error_projection_images,
    log_validation_sheets,
    object_sheet,
    render_error,
    render_voxels,
    stack_sheets,
    voxel_mesh,
)

_one_thread = pytest.fixture(autouse=True)(one_thread)
WHITE = np.array([255, 255, 255], np.uint8)


def _block(r=8, lo=2, hi=6):
    grid = np.zeros((r, r, r), bool)
    grid[lo:hi, lo:hi, lo:hi] = True
    return grid


# ----------------------------------------------------------------------------------------------- meshes
def test_one_voxel_is_a_closed_cube_of_its_cell_with_outward_faces():
    grid = np.zeros((4, 4, 4), bool)
    grid[3, 0, 1] = True  # x in [0.25, 0.5], y in [-0.5, -0.25], z in [-0.25, 0]
    mesh = voxel_mesh(grid)
    assert len(mesh.faces) == 12  # 6 faces, 2 triangles each
    np.testing.assert_allclose(mesh.bounds, [[0.25, -0.5, -0.25], [0.5, -0.25, 0.0]])
    mesh.merge_vertices()
    assert mesh.is_watertight and mesh.volume == pytest.approx(0.25**3)  # positive: normals point outward


def test_faces_between_occupied_cells_are_left_out():
    grid = np.zeros((4, 4, 4), bool)
    grid[1, 1, 1] = grid[2, 1, 1] = True
    assert len(voxel_mesh(grid).faces) == 2 * 10  # 12 faces of two cubes minus the shared pair
    assert len(voxel_mesh(np.zeros((4, 4, 4), bool)).faces) == 0


def test_each_face_takes_its_cells_colour():
    grid = np.zeros((4, 4, 4), bool)
    grid[0, 0, 0] = grid[3, 3, 3] = True
    colors = np.zeros((4, 4, 4, 3), np.uint8)
    colors[0, 0, 0] = (255, 0, 0)
    colors[3, 3, 3] = (0, 0, 255)
    mesh = voxel_mesh(grid, colors)
    low = mesh.triangles_center[:, 0] < 0
    assert (mesh.visual.face_colors[low, :3] == (255, 0, 0)).all()
    assert (mesh.visual.face_colors[~low, :3] == (0, 0, 255)).all()
    with pytest.raises(
        ValueError, match=re.escape("`colors` must have shape (4, 4, 4, 3) (RGB per cell), got (4, 4, 3)")
    ):
        voxel_mesh(grid, colors[0])


# ----------------------------------------------------------------------------------------------- renders
def test_render_voxels_shapes_background_and_threshold():
    probs = _block().astype(np.float32) * 0.45
    pictures = render_voxels(probs, [[30.0, 20.0], [0.0, 90.0], [-120.0, -45.0]], image_size=48, threshold=0.4)
    assert pictures.shape == (3, 48, 48, 3) and pictures.dtype == np.uint8
    assert (pictures[:, 0, 0] == WHITE).all()  # corners are background
    assert not (pictures[:, 24, 24] == WHITE).all(axis=-1).any()  # the block covers the centre from every side
    # 0.45 < 0.5: nothing to draw at a higher threshold
    assert (render_voxels(probs, image_size=16, threshold=0.5) == WHITE).all()


def test_cells_appear_where_their_world_position_says():
    # From yaw 0, pitch 0 the camera sits on +X looking at the origin, +Z up, so its right vector is
    # forward x up = (-1, 0, 0) x (0, 0, 1) = +Y: cells at high j (+Y) show on the right, high k (+Z) at the top.
    grid = np.zeros((8, 8, 8), bool)
    grid[3:5, 6:8, 6:8] = True  # +Y, +Z corner
    picture = render_voxels(grid, [[0.0, 0.0]], image_size=64)[0]
    rows, cols = np.nonzero((picture != WHITE).any(axis=-1))
    assert cols.min() > 32 and rows.max() < 32


def test_error_labels_classify_every_cell():
    predicted = torch.tensor([0.9, 0.9, 0.1, 0.1, 0.4, 0.39]).view(1, 1, 6).expand(6, 6, 6)
    target = torch.tensor([1.0, 0.0, 1.0, 0.0, 1.0, 1.0]).view(1, 1, 6).expand(6, 6, 6)
    labels = error_labels(predicted, target, threshold=0.4)
    assert labels[0, 0].tolist() == [CORRECT, FALSE_POSITIVE, FALSE_NEGATIVE, EMPTY, CORRECT, FALSE_NEGATIVE]
    with pytest.raises(ValueError, match=re.escape("must have the same shape, got (6, 6, 6) and (4, 4, 4)")):
        error_labels(predicted, torch.zeros(4, 4, 4))
    with pytest.raises(ValueError, match=re.escape("`predicted` must have shape (R, R, R) with R >= 1, got (6, 6)")):
        error_labels(np.zeros((6, 6)), target)


def test_render_error_paints_each_class_in_its_colour():
    target = _block()
    predicted = target.astype(np.float32)
    predicted[2:6, 2:6, 5] = 0.0  # the top layer missed
    pictures = render_error(predicted, target, [[0.0, 90.0], [0.0, 0.0]], image_size=64)
    top, side = pictures
    # From above only the missed top layer shows; from the side, correct cells below it too. Lighting shades the
    # colours, so compare hues: blue dominates where FN shows, grey (equal channels) where correct cells show.
    centre = top[28:36, 28:36].reshape(-1, 3).astype(int)
    assert (centre[:, 2] > centre[:, 0] + 60).all()
    column = side[:, 32].astype(int)
    drawn = np.nonzero((side[:, 32] != WHITE).any(axis=-1))[0]
    assert np.abs(column[drawn[-1] - 2, 0] - column[drawn[-1] - 2, 2]) < 12  # bottom rows: grey (correct)
    assert column[drawn[0] + 1, 2] > column[drawn[0] + 1, 0] + 60  # top rows: blue (missed)


def test_error_projection_shows_the_first_error_from_the_camera_side():
    r = 8
    predicted = np.zeros((r, r, r), np.float32)
    target = np.zeros((r, r, r), np.float32)
    predicted[2:6, 2:6, 6] = 1.0  # an extra layer on top (false positives) ...
    target[2:6, 2:6, 1] = 1.0  # ... above a missed layer at the bottom (false negatives)
    from_top, from_below, from_side = error_projection_images(
        predicted, target, [[0.0, 90.0], [0.0, -90.0], [0.0, 0.0]]
    )
    colours = lambda m: {tuple(c) for c in m.reshape(-1, 3).tolist()}  # noqa: E731
    assert colours(from_top) == {tuple(ERROR_COLORS[FALSE_POSITIVE]), (255, 255, 255)}
    assert colours(from_below) == {tuple(ERROR_COLORS[FALSE_NEGATIVE]), (255, 255, 255)}
    assert {tuple(ERROR_COLORS[FALSE_POSITIVE]), tuple(ERROR_COLORS[FALSE_NEGATIVE])} <= colours(from_side)
    # The same pixels as the selection's own projection of the binary error: the paper's score is their count.
    from lightning_vtr.selection.projection import error_projection, error_volume

    maps = error_projection(
        error_volume(torch.from_numpy(predicted)[None], torch.from_numpy(target)[None]), torch.tensor([[0.0, 90.0]])
    )
    assert int((from_top != WHITE).any(-1).sum()) == int(maps.sum())
    assert error_projection_images(predicted, target, [[0.0, 90.0]], image_size=4 * r).shape == (1, 32, 32, 3)


def test_display_images_undo_each_normalisation():
    pixels = torch.randint(0, 256, (2, 3, 5, 5)).float() / 255.0
    expected = (pixels * 255).round().to(torch.uint8).permute(0, 2, 3, 1).numpy()
    np.testing.assert_array_equal(display_images(pixels * 2 - 1, "pm1"), expected)
    mean, std = (
        torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1),
        torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1),
    )
    np.testing.assert_array_equal(display_images((pixels - mean) / std, "imagenet"), expected)
    stretched = display_images(pixels * 0.5 + 0.2, "auto")
    assert stretched.min() == 0 and stretched.max() == 255
    rgba = np.zeros((1, 2, 2, 4), np.uint8)
    assert (display_images(rgba) == 255).all()  # transparent on white
    with pytest.raises(
        ValueError, match=re.escape("`normalize` must be one of 'auto', 'imagenet', 'pm1', None, got 'z'")
    ):
        display_images(pixels, "z")


# ----------------------------------------------------------------------------------------------- sheets
def test_compose_sheet_size_and_boxes():
    panel = np.zeros((10, 10, 3), np.uint8)
    sheet, boxes = compose_sheet([("a", [panel] * 3, ["x", "y", "z"]), ("b", [panel], [""])], title="t", panel_size=20)
    # width: label 112 + 3 x (20 + 4) + 4; height: title 22 + 2 x (caption 14 + 20 + 4) + 4
    assert sheet.shape == (22 + 2 * 38 + 4, 112 + 3 * 24 + 4, 3)
    top, left, bottom, right = boxes["b"][0]
    assert (bottom - top, right - left) == (20, 20)
    assert (sheet[top:bottom, left:right] == 0).all()  # the (resized) black panel sits in its box


def test_object_sheet_rows_with_and_without_ground_truth():
    target = _block()
    predicted = target.astype(np.float32) * 0.9
    predicted[:, :, 6] = 0.8  # a plate of false positives
    images = np.full((3, 20, 20, 3), 7, np.uint8)
    sheet, boxes = object_sheet(
        predicted, target, images, selected_viewpoints=[[0.0, 90.0]], panel_size=40, title="o", return_boxes=True
    )
    assert list(boxes) == ["input views", "prediction", "ground truth", "error", "error projection"]
    assert [len(b) for b in boxes.values()] == [3, len(DISPLAY_VIEWPOINTS), 2, 2, 1]
    assert sheet.shape == (22 + 5 * 58 + 4, 112 + 3 * 44 + 4, 3)
    top, left, bottom, right = boxes["input views"][0]
    assert (sheet[top:bottom, left:right] == 7).all()
    top, left, bottom, right = boxes["error projection"][0]
    seen = {tuple(c) for c in sheet[top:bottom, left:right].reshape(-1, 3).tolist()}
    assert tuple(ERROR_COLORS[FALSE_POSITIVE]) in seen and tuple(ERROR_COLORS[FALSE_NEGATIVE]) not in seen
    alone, boxes = object_sheet(predicted, panel_size=40, return_boxes=True)
    assert list(boxes) == ["prediction"] and alone.shape == (58 + 4, 112 + 2 * 44 + 4, 3)
    with pytest.raises(ValueError, match=re.escape("`input_viewpoints` must give one viewpoint per image (3), got 2")):
        object_sheet(predicted, target, images, input_viewpoints=[[0, 0], [1, 1]], panel_size=40)


def test_stack_sheets():
    out = stack_sheets([np.zeros((3, 4, 3), np.uint8), np.zeros((2, 6, 3), np.uint8)], gap=1)
    assert out.shape == (6, 6, 3) and (out[3] == 255).all() and (out[:3, 4:] == 255).all()


# ----------------------------------------------------------------------------------------------- logging
class _SheetModel(L.LightningModule):
    """Predicts a fixed block and logs the validation sheets the way the lead's hook in models/base.py would."""

    image_size, num_views, voxel_resolution = 16, 2, 8

    def __init__(self):
        super().__init__()
        self.scale = nn.Parameter(torch.ones(()))
        self.logged = []

    def predict_voxels(self, images):
        return (torch.from_numpy(_block()).float() * 0.9 * self.scale).expand(len(images), 8, 8, 8)

    def training_step(self, batch, batch_idx):
        return (self.predict_voxels(batch["images"]) - batch["voxels"]).pow(2).mean()

    def validation_step(self, batch, batch_idx):
        if batch_idx == 0:  # the hook models/base.py gets: keep the first batch and its predictions
            self._sheet_batch = (batch, self.predict_voxels(batch["images"]).detach())

    def on_validation_epoch_end(self):
        self.logged.append(log_validation_sheets(self, *self._sheet_batch, max_objects=2, panel_size=32))
        self._sheet_batch = None

    def configure_optimizers(self):
        return torch.optim.SGD(self.parameters(), lr=0.0)


def _loader():
    items = [
        {"images": torch.rand(2, 3, 16, 16), "voxels": torch.from_numpy(_block(lo=2 + i % 2)).float()} for i in range(3)
    ]
    return torch.utils.data.DataLoader(items, batch_size=3)


def test_log_validation_sheets_writes_one_picture_per_validation_epoch(tmp_path):
    model = _SheetModel()
    logger = CSVLogger(tmp_path, name="", version="")
    trainer = L.Trainer(
        max_epochs=2,
        logger=logger,
        enable_progress_bar=False,
        enable_model_summary=False,
        enable_checkpointing=False,
        num_sanity_val_steps=1,
    )
    trainer.fit(model, _loader(), _loader())
    # sanity check: nothing; then one picture per epoch: two sheets of 5 rows (views, prediction, truth, error, projection)
    assert model.logged[0] is None and len(model.logged) == 3
    sheet_height = 22 + 5 * (14 + 32 + 4) + 4
    assert model.logged[1].shape[0] == 2 * sheet_height + 6
    files = sorted((tmp_path / "images" / "val" / "sheets").glob("step_*.png"))
    assert [f.name for f in files] == ["step_000001.png", "step_000002.png"]
    np.testing.assert_array_equal(np.asarray(Image.open(files[-1])), model.logged[-1])
    with pytest.raises(ValueError, match=re.escape("`batch` must hold 'images' and 'voxels', got keys ['images']")):
        log_validation_sheets(model, {"images": torch.rand(1, 2, 3, 16, 16)}, torch.rand(1, 8, 8, 8))
