"""Pix3D: the reader's checks, the crop, the voxel down-sampling, the frame derivation (on a fixture rendered by
Pix3D's documented camera), the package-frame voxels and viewpoints, and per-category evaluation."""

from __future__ import annotations

import functools
import json
import math

import numpy as np
import pytest
import scipy.io
import torch
from helpers import one_thread
from PIL import Image
from scipy import ndimage

from lightning_vtr.data.format import DatasetFormatError
from lightning_vtr.data.pix3d import (
    VOXEL_TO_MODEL,
    Pix3DDataset,
    camera_rotation,
    crop_to_bbox,
    downsample_voxels,
    load_voxel_mat,
    pix3d_viewpoint,
    read_pix3d,
    rotate_grid,
    yaw_rotation,
)
from lightning_vtr.data.transforms import ImageTransform
from lightning_vtr.evaluation.pix3d import evaluate_pix3d, frame_check
from lightning_vtr.geometry import camera_basis, orthographic_pixel_coords

_one_thread = pytest.fixture(autouse=True)(one_thread)


# ---------------------------------------------------------------------------------------------- the fixture
# Everything below writes a Pix3D copy from Pix3D's documentation alone (README + demo.py), independently of
# the module's matrices: an asymmetric chair in the *model* frame (x left, y up, z inward, front facing -z),
# voxel.mat in the *voxel* frame (x left, y outward, z up: (x_v, y_v, z_v) = (x_m, -z_m, y_m)), and the
# photograph rendered as demo.py does (world = R p + t, camera at the origin looking along +Z, up +Y, right -X,
# focal length in mm on a 32 mm wide sensor).
def chair(p: np.ndarray) -> np.ndarray:
    """Occupancy of model-frame points ``(N, 3)``: a chaise longue, not mirror-symmetric in any plane.

    A seat whose +x half extends forward (-z, toward the canonical camera), a back rest behind (+z), a side
    panel on the -x side only, and legs under the seat's corners."""
    x, y, z = p[:, 0], p[:, 1], p[:, 2]

    def box(x0, x1, y0, y1, z0, z1):
        return (x >= x0) & (x <= x1) & (y >= y0) & (y <= y1) & (z >= z0) & (z <= z1)

    seat = box(-0.35, 0.35, -0.05, 0.05, -0.1, 0.3)
    chaise = box(0.05, 0.35, -0.05, 0.05, -0.45, -0.1)
    back = box(-0.35, 0.35, 0.05, 0.48, 0.2, 0.3)
    panel = box(-0.35, -0.27, 0.05, 0.3, -0.1, 0.2)
    legs = np.zeros(len(p), bool)
    for lx, lz in ((-0.34, -0.09), (-0.34, 0.23), (0.28, 0.23), (0.06, -0.44), (0.28, -0.44)):
        legs |= box(lx, lx + 0.06, -0.45, -0.05, lz, lz + 0.06)
    return seat | chaise | back | panel | legs


def voxel_mat_grid(n: int) -> np.ndarray:
    c = (np.arange(n) + 0.5) / n - 0.5
    xv, yv, zv = np.meshgrid(c, c, c, indexing="ij")
    model = np.stack([xv, zv, -yv], -1).reshape(-1, 3)  # x_m = x_v, y_m = z_v, z_m = -y_v
    return chair(model).reshape(n, n, n).astype(np.uint8)


@functools.cache
def chair_points() -> np.ndarray:
    """Model-frame points filling the chair, 0.006 apart (finer than a pixel of the fixture's photographs)."""
    c = np.arange(-0.5, 0.5, 0.006)
    grid = np.stack(np.meshgrid(c, c, c, indexing="ij"), -1).reshape(-1, 3)
    return grid[chair(grid)]


def render_mask(rotation, translation, focal, width, height) -> np.ndarray:
    points = chair_points()
    world = points @ np.asarray(rotation).T + np.asarray(translation)
    f_px = focal / 32.0 * width
    col = width / 2.0 + f_px * (-world[:, 0] / world[:, 2])
    row = height / 2.0 - f_px * (world[:, 1] / world[:, 2])
    mask = np.zeros((height, width), np.uint8)
    inside = (col >= 0) & (col < width) & (row >= 0) & (row < height)
    mask[row[inside].astype(int), col[inside].astype(int)] = 255
    return mask


def euler(rx, ry, rz) -> np.ndarray:
    ax, ay, az = np.radians([rx, ry, rz])
    rx_ = np.array([[1, 0, 0], [0, np.cos(ax), -np.sin(ax)], [0, np.sin(ax), np.cos(ax)]])
    ry_ = np.array([[np.cos(ay), 0, np.sin(ay)], [0, 1, 0], [-np.sin(ay), 0, np.cos(ay)]])
    rz_ = np.array([[np.cos(az), -np.sin(az), 0], [np.sin(az), np.cos(az), 0], [0, 0, 1]])
    return rz_ @ ry_ @ rx_


def write_pix3d(
    root, shots, *, n=64, width=160, height=128, focal=35.0, category="chair", model="TEST_CHAIR", voxels=None
):
    """Write ``shots`` (``(stem, rotation, translation, extra keys)``) of one chaise model; return the records.

    ``voxels`` replaces the model's voxel.mat grid (the photographs still show the chaise)."""
    (root / "model" / category / model).mkdir(parents=True, exist_ok=True)
    grid = voxel_mat_grid(n) if voxels is None else voxels
    scipy.io.savemat(root / "model" / category / model / "voxel.mat", {"voxel": grid})
    (root / "img" / category).mkdir(parents=True, exist_ok=True)
    (root / "mask" / category).mkdir(parents=True, exist_ok=True)
    entries = []
    for stem, rotation, translation, extra in shots:
        mask = render_mask(rotation, translation, focal, width, height)
        rows, cols = np.nonzero(mask)
        rng = np.random.default_rng(len(entries))
        image = rng.integers(0, 120, (height, width, 3), dtype=np.uint8)
        image[mask > 0] = (200, 40, 30)
        Image.fromarray(image).save(root / "img" / category / f"{stem}.png")
        Image.fromarray(mask).save(root / "mask" / category / f"{stem}.png")
        entry = {
            "img": f"img/{category}/{stem}.png",
            "mask": f"mask/{category}/{stem}.png",
            "voxel": f"model/{category}/{model}/voxel.mat",
            "model": f"model/{category}/{model}/model.obj",
            "category": category,
            "img_size": [width, height],
            "bbox": [int(cols.min()), int(rows.min()), int(cols.max()), int(rows.max())],
            "rot_mat": np.asarray(rotation).tolist(),
            "trans_mat": list(map(float, translation)),
            "focal_length": focal,
            "inplane_rotation": 0.0,
            "truncated": False,
            "occluded": False,
            "slightly_occluded": False,
        }
        entry.update(extra)
        entries.append(entry)
    previous = json.loads((root / "pix3d.json").read_text()) if (root / "pix3d.json").exists() else []
    (root / "pix3d.json").write_text(json.dumps(previous + entries))
    return entries


SHOTS = [
    ("0001", euler(20, 35, 5), (0.08, -0.04, 3.2), {}),
    ("0002", euler(-15, 140, -8), (-0.1, 0.05, 3.5), {}),
    ("0003", euler(35, -70, 12), (0.0, 0.1, 3.0), {}),
]


@pytest.fixture(scope="module")
def pix3d_root(tmp_path_factory):
    root = tmp_path_factory.mktemp("pix3d")
    write_pix3d(root, SHOTS)
    return root


# ---------------------------------------------------------------------------------------------- frame check
def test_the_derived_frame_matches_the_masks_and_wrong_frames_do_not(pix3d_root):
    records = read_pix3d(pix3d_root)
    assert [r.object_id for r in records] == ["0001", "0002", "0003"]
    right = [frame_check(r) for r in records]
    assert min(right) > 0.8, right
    swapped = np.eye(3, dtype=int)  # voxel.mat read as if it were the model frame (no y/z swap)
    mirrored = VOXEL_TO_MODEL * np.array([[-1], [1], [1]])  # x flipped
    upside_down = VOXEL_TO_MODEL * np.array([[1], [-1], [-1]])  # a half turn about x
    for wrong in (swapped, mirrored, upside_down):
        ious = [frame_check(r, voxel_to_model=wrong) for r in records]
        assert max(ious) < 0.7 and np.mean(ious) < np.mean(right) - 0.25, (wrong.tolist(), ious, right)


def test_a_transposed_rotation_fails_the_check(pix3d_root, tmp_path):
    records = read_pix3d(pix3d_root)
    entries = json.loads((pix3d_root / "pix3d.json").read_text())
    for entry in entries:
        entry["rot_mat"] = np.asarray(entry["rot_mat"]).T.tolist()
    (tmp_path / "pix3d.json").write_text(json.dumps(entries))
    transposed = read_pix3d(pix3d_root, annotations=tmp_path / "pix3d.json")
    right = [frame_check(r) for r in records]
    wrong = [frame_check(r) for r in transposed]
    assert max(wrong) < 0.7 < min(right), (wrong, right)


# ---------------------------------------------------------------------------------------------- package frame
def shot_from_viewpoint(yaw, pitch, distance=3.0):
    """``rot_mat`` and ``trans_mat`` of a photograph taken from the package viewpoint ``(yaw, pitch)`` (no roll)."""
    model_to_package = np.array([[0, 0, -1], [-1, 0, 0], [0, 1, 0]])  # (X, Y, Z) = (-z_m, -x_m, y_m)
    world_to_camera = camera_basis(torch.tensor([[yaw, pitch]], dtype=torch.float64))[0].numpy()
    rotation = np.diag([-1, 1, -1]) @ world_to_camera @ model_to_package
    return rotation, (0.0, 0.0, distance)


def silhouette_iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / (a | b).sum())


def package_projection(voxels: np.ndarray, viewpoint, size: int) -> np.ndarray:
    """The package's own orthographic projection of a package-frame grid, cropped to its bounding box."""
    from lightning_vtr.evaluation.pix3d import _square_raster

    r = voxels.shape[0]
    c = (torch.arange(r, dtype=torch.float64) + 0.5) / r - 0.5
    centres = torch.stack(torch.meshgrid(c, c, c, indexing="ij"), -1)[torch.from_numpy(voxels)]
    offsets = torch.stack(torch.meshgrid(*[torch.tensor([-1.0, 0.0, 1.0]) / 3 / r] * 3, indexing="ij"), -1)
    points = (centres[:, None] + offsets.reshape(1, -1, 3)).reshape(-1, 3)
    pix = orthographic_pixel_coords(points, torch.tensor([viewpoint], dtype=torch.float64), 256, 1.0)[0].numpy()
    return _square_raster(pix[:, 0], pix[:, 1], size)


def test_package_frame_voxels_seen_from_the_viewpoint_match_the_mask(tmp_path):
    from lightning_vtr.evaluation.pix3d import _mask_silhouette

    views = [(30.0, 20.0), (-120.0, 35.0), (75.0, -10.0)]
    # Far away with a long lens: nearly orthographic, as the package's projection is.
    shots = [(f"{i:04d}", *shot_from_viewpoint(*v, distance=10.0), {}) for i, v in enumerate(views)]
    write_pix3d(tmp_path, shots, n=64, focal=110.0)
    records = read_pix3d(tmp_path)
    for record, view in zip(records, views):
        np.testing.assert_allclose(pix3d_viewpoint(record), view, atol=1e-6)
        expected = camera_basis(torch.tensor([view], dtype=torch.float64))[0].numpy()
        np.testing.assert_allclose(camera_rotation(record), expected, atol=1e-9)
    mask_iou, wrong_iou = [], []
    for offset in (0, 90):
        dataset = Pix3DDataset(records, resolution=32, image_size=16, yaw_offset=offset)
        for i, record in enumerate(records):
            item = dataset[i]
            voxels = item["voxels"].numpy() > 0.5
            viewpoint = item["viewpoints"][0].tolist()
            np.testing.assert_allclose(viewpoint, [((views[i][0] + offset + 180) % 360) - 180, views[i][1]], atol=1e-4)
            mask = np.asarray(Image.open(record.mask_path))
            silhouette = _mask_silhouette(mask, 48)
            mask_iou.append(silhouette_iou(package_projection(voxels, viewpoint, 48), silhouette))
            # The voxels turned without the viewpoint (or the other way round) no longer match.
            wrong_iou.append(
                silhouette_iou(
                    package_projection(voxels, views[i] if offset else [viewpoint[0] + 90, viewpoint[1]], 48),
                    silhouette,
                )
            )
    assert min(mask_iou) > 0.8, mask_iou
    assert max(wrong_iou) < 0.7, wrong_iou


def test_package_frame_puts_the_front_at_plus_x_and_up_at_plus_z(pix3d_root):
    voxels = Pix3DDataset(read_pix3d(pix3d_root), resolution=32, image_size=16)[0]["voxels"].numpy() > 0.5
    # Package frame (X, Y, Z) = (-z_m, -x_m, y_m), the chaise fitted to the grid (its height, 0.93, is the cube):
    # back rest X cells 3..6, seat Z 14..17, legs below; chaise X 17..29 at Y 4..14; side panel Y 25..28.
    assert voxels[:, :, 27:].any() and not voxels[8:, :, 27:].any(), "only the back rest is that high, at -X"
    # Legs (x_m, z_m) -> (X, Y) = (-z_m, -x_m) cells: (-.31, -.06) -> (15, 26), (-.31, .26) -> (4, 26),
    # (.31, .26) -> (4, 5), (.09, -.41) -> (27, 12), (.31, -.41) -> (27, 5).
    labels, count = ndimage.label(voxels[:, :, 2])
    centres = {tuple(round(c) for c in ndimage.center_of_mass(voxels[:, :, 2], labels, i)) for i in range(1, count + 1)}
    assert centres == {(15, 26), (4, 26), (4, 5), (27, 12), (27, 5)}
    chaise = voxels[19:, :, 14:18]
    assert chaise.any() and not chaise[:, 16:].any(), "the chaise (model +x, forward) is at +X and -Y"
    panel = voxels[9:16, :, 19:25]
    assert panel.any() and not panel[:, :24].any(), "the side panel (model -x) is at +Y"


def test_rotate_grid_matches_the_rotation_of_cell_centres():
    rng = np.random.default_rng(0)
    grid = rng.random((6, 6, 6)) > 0.7
    centres = (np.argwhere(grid) + 0.5) / 6 - 0.5
    for rotation in (
        yaw_rotation(90),
        yaw_rotation(-90),
        yaw_rotation(180),
        np.array([[0, 1, 0], [-1, 0, 0], [0, 0, 1]]),
    ):
        rotated = rotate_grid(grid, rotation)
        moved = centres @ rotation.T
        assert sorted(map(tuple, np.rint((moved + 0.5) * 6 - 0.5).astype(int))) == sorted(
            map(tuple, np.argwhere(rotated))
        )
    with pytest.raises(ValueError, match="multiple of 90"):
        yaw_rotation(45)
    with pytest.raises(ValueError, match="signed permutation"):
        rotate_grid(grid, np.eye(3) * 2)


# ---------------------------------------------------------------------------------------------- voxels
def test_downsample_max_and_mean_on_a_known_grid():
    grid = np.zeros((8, 8, 8), bool)
    grid[0:2, 0:2, 0:2] = True  # a full 2x2x2 block: cell (0, 0, 0)
    grid[2, 2, 2] = True  # one voxel of cell (1, 1, 1)
    grid[4:6, 4:6, 4] = True  # half of cell (2, 2, 2)
    maxed = downsample_voxels(grid, 4, fit=False, pooling="max")
    meaned = downsample_voxels(grid, 4, fit=False, pooling="mean")
    assert sorted(map(tuple, np.argwhere(maxed))) == [(0, 0, 0), (1, 1, 1), (2, 2, 2)]
    assert sorted(map(tuple, np.argwhere(meaned))) == [(0, 0, 0), (2, 2, 2)]  # 8/8 and 4/8 >= 0.5; 1/8 is not
    assert not downsample_voxels(np.zeros((8, 8, 8)), 4).any()


def test_downsample_fit_centres_the_box_in_a_cube():
    grid = np.zeros((16, 16, 16), bool)
    grid[2:6, 4:12, 6:8] = True  # extents 4, 8, 2: the cube has side 8
    fitted = downsample_voxels(grid, 8, fit=True)
    expected = np.zeros((8, 8, 8), bool)
    expected[2:6, 0:8, 3:5] = True  # centred along x (2 + 4 + 2) and z (3 + 2 + 3)
    np.testing.assert_array_equal(fitted, expected)
    up = downsample_voxels(grid, 16, fit=True)  # up-sampling by 2: nearest
    np.testing.assert_array_equal(up, np.repeat(np.repeat(np.repeat(expected, 2, 0), 2, 1), 2, 2))


def test_load_voxel_mat_names_the_file_and_the_variable(tmp_path):
    scipy.io.savemat(tmp_path / "a.mat", {"Volume": np.ones((4, 4, 4), np.uint8)})
    with pytest.raises(DatasetFormatError, match=r"a\.mat has no variable 'voxel'; it holds \['Volume'\]"):
        load_voxel_mat(tmp_path / "a.mat")
    scipy.io.savemat(tmp_path / "b.mat", {"voxel": np.ones((4, 4, 5), np.uint8)})
    with pytest.raises(DatasetFormatError, match=r"b\.mat: variable 'voxel' must be a cubic .* got shape \(4, 4, 5\)"):
        load_voxel_mat(tmp_path / "b.mat")


# ---------------------------------------------------------------------------------------------- images
def test_crop_to_bbox_on_known_pixels():
    image = np.arange(6 * 10 * 3, dtype=np.uint8).reshape(6, 10, 3)
    mask = np.zeros((6, 10), np.uint8)
    mask[1:3, 2:6] = 255
    crop = crop_to_bbox(image, mask, (2, 1, 5, 2), margin=0.0)  # 4 x 2 box -> 4 x 4 square, rows 0..3
    assert crop.shape == (4, 4, 4)
    np.testing.assert_array_equal(crop[..., :3], image[0:4, 2:6])
    np.testing.assert_array_equal(crop[..., 3], mask[0:4, 2:6])
    wide = crop_to_bbox(image, mask, (2, 1, 5, 2), margin=0.5, background=(240, 240, 240))
    assert wide.shape == (8, 8, 4)  # side 8: columns 0..7, rows -2..5 (two rows above the photograph)
    assert (wide[:2, :, :3] == 240).all() and (wide[..., 3] == 255).all()  # outside the photograph: background
    np.testing.assert_array_equal(wide[3:5, 2:6, :3], image[1:3, 2:6])  # the object, unchanged
    assert (wide[2, :, :3] == 240).all() and (wide[3:5, 0:2, :3] == 240).all()  # masked-out pixels
    whole = crop_to_bbox(image, None, (2, 1, 5, 2), margin=0.0)
    assert (whole[..., 3] == 255).all()


def test_dataset_items_are_vtr_batches(pix3d_root):
    records = read_pix3d(pix3d_root)
    transform = ImageTransform(24, background=(240, 240, 240), normalize=None)
    item = Pix3DDataset(records, transform=transform, resolution=32)[0]
    assert set(item) == {"images", "voxels", "viewpoints", "category", "object_id", "view_set"}
    assert item["images"].shape == (1, 3, 24, 24) and item["voxels"].shape == (32, 32, 32)
    assert item["viewpoints"].shape == (1, 2) and item["view_set"] == "aligned"
    assert (item["category"], item["object_id"]) == ("chair", "0001")
    # The corners are outside the chair: the masked photograph shows the background there, not its noise.
    corner = item["images"][0, :, 0, 0]
    torch.testing.assert_close(corner, torch.full((3,), 240 / 255))
    centre = item["images"][0, :, 12, 12]  # the seat / back, red
    assert centre[0] > 0.6 and centre[1] < 0.3


# ---------------------------------------------------------------------------------------------- the reader
def test_read_pix3d_filters_and_names_bad_keys(tmp_path):
    write_pix3d(tmp_path, SHOTS[:2])
    write_pix3d(tmp_path, [SHOTS[2]], category="table", model="TEST_TABLE")
    entries = json.loads((tmp_path / "pix3d.json").read_text())
    entries[1]["occluded"] = True
    (tmp_path / "pix3d.json").write_text(json.dumps(entries))
    assert [r.key for r in read_pix3d(tmp_path)] == ["chair/0001", "table/0003"]
    assert [r.key for r in read_pix3d(tmp_path, include_hidden=True, categories=["chair"])] == [
        "chair/0001",
        "chair/0002",
    ]
    split = tmp_path / "Pix3D.json"
    split.write_text(json.dumps([{"taxonomy_id": "chair", "taxonomy_name": "chair", "test": ["0002"], "train": []}]))
    assert [r.key for r in read_pix3d(tmp_path, split_file=split, include_hidden=True)] == ["chair/0002"]
    with pytest.raises(ValueError, match=r"unknown \['sofa'\]"):
        read_pix3d(tmp_path, categories=["sofa"])
    bad = dict(entries[0], rot_mat=[[1, 0], [0, 1]])
    (tmp_path / "pix3d.json").write_text(json.dumps([bad]))
    with pytest.raises(
        DatasetFormatError, match=r"pix3d\.json, record 0 \(img/chair/0001\.png\): key 'rot_mat' must be 3x3"
    ):
        read_pix3d(tmp_path)
    mirror = dict(entries[0], rot_mat=(-np.eye(3)).tolist())
    (tmp_path / "pix3d.json").write_text(json.dumps([mirror]))
    with pytest.raises(DatasetFormatError, match=r"key 'rot_mat' must be a rotation .* det = -1"):
        read_pix3d(tmp_path)
    (tmp_path / "pix3d.json").write_text(json.dumps([{k: v for k, v in entries[0].items() if k != "bbox"}]))
    with pytest.raises(DatasetFormatError, match=r"record 0 \(img/chair/0001\.png\): missing key\(s\) \['bbox'\]"):
        read_pix3d(tmp_path)
    gone = dict(entries[0], voxel="model/chair/NOPE/voxel.mat")
    (tmp_path / "pix3d.json").write_text(json.dumps([gone, entries[2]]))
    with pytest.warns(UserWarning, match=r"Skipped 1 Pix3D record\(s\) .*NOPE/voxel\.mat"):
        assert [r.key for r in read_pix3d(tmp_path)] == ["table/0003"]
    with pytest.raises(FileNotFoundError, match=r"record 0 \(chair/0001\) names .*NOPE/voxel\.mat"):
        read_pix3d(tmp_path, missing="error")


# ---------------------------------------------------------------------------------------------- evaluation
class FixedModel:
    """Predicts the same grid for every input, and records the input shapes."""

    def __init__(self, grid: np.ndarray) -> None:
        self.grid = torch.from_numpy(grid.astype(np.float32))
        self.seen = []

    def predict_voxels(self, images):
        self.seen.append(tuple(images.shape))
        return self.grid.expand(images.shape[0], *self.grid.shape).clone()


def test_per_category_evaluation_matches_hand_computed_iou(tmp_path):
    from lightning_vtr.metrics import voxel_fscore

    write_pix3d(tmp_path, SHOTS[:2])
    upside_down = voxel_mat_grid(64)[:, :, ::-1]  # the "table" is the chaise on its head
    write_pix3d(tmp_path, [SHOTS[2]], category="table", model="TEST_TABLE", voxels=upside_down)
    dataset = Pix3DDataset(read_pix3d(tmp_path), resolution=32, image_size=16)
    chair, table = dataset[0]["voxels"].numpy() > 0.5, dataset[2]["voxels"].numpy() > 0.5
    assert not np.array_equal(chair, table)
    predicted = np.zeros((32, 32, 32), np.float32)
    predicted[:, :, :16] = 0.45 * chair[:, :, :16]  # the chair's lower half at 0.45: occupied up to t = 0.4
    model = FixedModel(predicted)
    results = evaluate_pix3d(model, dataset, batch_size=2)
    assert model.seen == [(2, 1, 3, 16, 16), (1, 1, 3, 16, 16)]
    lower = predicted > 0.4
    chair_iou = (lower & chair).sum() / (lower | chair).sum()
    table_iou = (lower & table).sum() / (lower | table).sum()
    assert 0.1 < table_iou < chair_iou < 0.9
    f = voxel_fscore(torch.from_numpy(np.stack([predicted] * 2)), torch.from_numpy(np.stack([chair, table])).float())
    chair_f, table_f = float(f[0]), float(f[1])
    categories = results["categories"]
    assert (results["overall"]["count"], categories["chair"]["count"], categories["table"]["count"]) == (3, 2, 1)
    for key in ("iou@0.2", "iou@0.3", "iou@0.4"):
        assert math.isclose(categories["chair"][key], chair_iou, rel_tol=1e-6)
        assert math.isclose(categories["table"][key], table_iou, rel_tol=1e-6)
        assert math.isclose(results["overall"][key], (2 * chair_iou + table_iou) / 3, rel_tol=1e-6)  # per object
    assert results["overall"]["iou@0.5"] == categories["chair"]["iou@0.5"] == 0.0
    assert results["best_threshold"] == 0.2 and math.isclose(
        results["overall"]["iou_best"], (2 * chair_iou + table_iou) / 3, rel_tol=1e-6
    )
    # The F-score samples points afresh for each object, so compare with a tolerance of a few sampling errors.
    assert chair_f > 0.3 and abs(categories["chair"]["fscore"] - chair_f) < 0.05
    assert abs(categories["table"]["fscore"] - table_f) < 0.05 and table_f < chair_f - 0.1


def test_a_models_test_step_takes_the_items_and_agrees_with_evaluate_pix3d(pix3d_root):
    import lightning as L
    from torch.utils.data import DataLoader

    from lightning_vtr.models.pix2vox import Pix2VoxPlusPlus

    torch.manual_seed(0)
    model = Pix2VoxPlusPlus(preset="tiny", fscore_points=512)
    dataset = Pix3DDataset(read_pix3d(pix3d_root), image_size=64)
    trainer = L.Trainer(accelerator="cpu", logger=False, enable_progress_bar=False, enable_model_summary=False)
    (logged,) = trainer.test(model, DataLoader(dataset, batch_size=2), verbose=False)
    ours = evaluate_pix3d(model, dataset, batch_size=3, fscore_points=512)
    for t in ("0.2", "0.3", "0.4", "0.5"):
        assert math.isclose(logged[f"test/aligned/iou@{t}"], ours["overall"][f"iou@{t}"], rel_tol=1e-5)
        assert math.isclose(
            logged[f"test/aligned/chair/iou@{t}"], ours["categories"]["chair"][f"iou@{t}"], rel_tol=1e-5
        )
