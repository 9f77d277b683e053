"""Renderer tests, including the cross-check that ties the renderer, the voxelizer and the error projection."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import trimesh

from lightning_vtr.data.mesh import normalize_mesh
from lightning_vtr.data.voxelize import voxelize
from lightning_vtr.geometry import sample_uniform_viewpoints
from lightning_vtr.renderer import (
    DEFAULT_DISTANCE,
    DEFAULT_HALF_EXTENT,
    DEFAULT_YFOV_DEG,
    Renderer,
    composite,
    get_renderer,
)
from lightning_vtr.selection.projection import error_projection


def _box(extents, centre=(0.0, 0.0, 0.0)) -> trimesh.Trimesh:
    return trimesh.creation.box(extents=extents).apply_translation(centre)


def _corner_shape(width: float = 0.36) -> trimesh.Trimesh:
    """Three arms of different lengths along +x, +y, +z from one corner: chiral, so no mirror image matches."""
    w = width
    arms = [((1.0, w, w), (0.5, w / 2, w / 2)), ((w, 0.6, w), (w / 2, 0.3, w / 2)), ((w, w, 0.8), (w / 2, w / 2, 0.4))]
    return normalize_mesh(trimesh.util.concatenate([_box(e, c) for e, c in arms]))


def _viewpoints_with_poles(n: int, seed: int = 0) -> torch.Tensor:
    poles = torch.tensor([[37.0, 90.0], [-120.0, -90.0]])
    return torch.cat([poles, sample_uniform_viewpoints(n - 2, generator=torch.Generator().manual_seed(seed))])


def _iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return (a & b).sum((-1, -2)) / np.maximum((a | b).sum((-1, -2)), 1)


# --------------------------------------------------------------------------- the cross-check
class TestSilhouetteMatchesErrorProjection:
    """Orthographic silhouette == first-hit projection of the voxelization, from any viewpoint."""

    RES, UP = 32, 4  # voxel grid / projection size, render supersampling

    @pytest.fixture(scope="class")
    def setup(self):
        mesh = _corner_shape()
        vox = torch.from_numpy(voxelize(mesh, self.RES)).float()[None]
        vp = _viewpoints_with_poles(20)
        rgba = Renderer(self.RES * self.UP, camera="orthographic").render(mesh, vp)
        # Resample the render to the projection's grid: the projection marks a pixel as soon as one voxel
        # centre falls in it, which happens when the object covers a part of it, so a pixel counts as
        # object when at least a quarter of its sub-pixels do.
        cover = (rgba[..., 3] > 0).reshape(len(vp), self.RES, self.UP, self.RES, self.UP).mean((2, 4))
        return vox, vp, cover >= 0.25

    def test_silhouettes_agree(self, setup):
        vox, vp, silhouette = setup
        projection = error_projection(vox, vp, half_extent=DEFAULT_HALF_EXTENT)[0].numpy() > 0
        iou = _iou(silhouette, projection)
        assert iou.min() >= 0.9, f"IoU per view {np.round(iou, 3)} for viewpoints {vp.tolist()}"

    def test_mirror_conventions_fail(self, setup):
        vox, vp, silhouette = setup
        right = _iou(silhouette, error_projection(vox, vp)[0].numpy() > 0)
        turned = vp.clone()
        turned[:, 0] += 180.0
        wrong = {
            "columns flipped": error_projection(vox, vp)[0].numpy()[..., ::-1] > 0,
            "rows flipped": error_projection(vox, vp)[0].numpy()[..., ::-1, :] > 0,
            "transposed": error_projection(vox, vp)[0].numpy().swapaxes(-1, -2) > 0,
            "yaw + 180": error_projection(vox, turned)[0].numpy() > 0,
        }
        for name, proj in wrong.items():
            iou = _iou(silhouette, proj)
            assert iou.mean() < 0.7, (
                f"{name}: mean IoU {iou.mean():.3f} should be far below the correct {right.mean():.3f}"
            )
            assert (iou < right - 0.05).mean() >= 0.75, (
                f"{name}: IoU {np.round(iou, 2)} vs correct {np.round(right, 2)}"
            )


# --------------------------------------------------------------------------- camera geometry
def test_orthographic_scale_and_orientation():
    # A 0.6 (y) x 0.3 (z) face seen from +X; a marker cube on the +Y end, above the middle.
    mesh = trimesh.util.concatenate([_box((0.2, 0.6, 0.3)), _box((0.1, 0.1, 0.1), (0.0, 0.25, 0.2))])
    size, half = 64, 0.5
    # Anti-aliased alpha is the covered fraction: >= 128 keeps the pixels more than half covered.
    alpha = Renderer(size, camera="orthographic", half_extent=half).render(mesh, [[0.0, 0.0]])[0, ..., 3] >= 128
    rows, cols = np.nonzero(alpha)
    px = size / (2 * half)  # pixels per world unit
    # Box: y in [-0.3, 0.3] -> cols [12.8, 51.2); z in [-0.15, 0.15] -> rows [22.4, 41.6); camera right = +Y.
    assert cols.min() == 13 and cols.max() == 50
    assert rows[cols < 40].min() == 22 and rows.max() == 41  # rows 22 and 41 are 60% covered
    assert abs(alpha[32].sum() - 0.6 * px) <= 1
    # The marker (z up to 0.25, y in [0.2, 0.3]) sticks out at the top, on the right.
    top = rows.min()
    assert top == round((half - 0.25) * px)
    assert cols[rows == top].min() == 45 and cols[rows == top].max() == 50  # y in [0.2, 0.3]: cols [44.8, 51.2)


def test_top_view_orientation():
    # From pitch +90 with yaw 0, image up is world -X and image right is world +Y; a marker tells them apart.
    mesh = trimesh.util.concatenate([_box((0.6, 0.2, 0.1)), _box((0.1, 0.1, 0.1), (-0.25, 0.15, 0.0))])
    alpha = Renderer(64, camera="orthographic", half_extent=0.5).render(mesh, [[0.0, 90.0]])[0, ..., 3] >= 128
    rows, cols = np.nonzero(alpha)
    # up = (-sin p cos y, -sin p sin y, cos p) = (-1, 0, 0); right = forward x up = (0,0,-1) x (-1,0,0) = (0, 1, 0).
    assert rows.max() - rows.min() + 1 == pytest.approx(0.6 * 64, abs=1)  # the long x side is vertical
    marker_rows = rows[cols > 32 + 0.1 * 64]
    assert marker_rows.size > 0 and marker_rows.max() < 32  # -X (marker side) is up, +Y is right


def test_perspective_pinhole_projection_and_depth():
    size = 96
    r = Renderer(size)
    small = _box((0.04, 0.04, 0.04), (0.0, 0.3, 0.2))
    alpha = r.render(small, [[0.0, 0.0]])[0, ..., 3] > 0
    rows, cols = np.nonzero(alpha)
    # Camera at (2.2, 0, 0) looking along -X; right = +Y, up = +Z; front face of the cube at x = 0.02.
    f = (size / 2) / math.tan(math.radians(DEFAULT_YFOV_DEG) / 2)
    depth = DEFAULT_DISTANCE - 0.0
    assert cols.mean() + 0.5 == pytest.approx(size / 2 + f * 0.3 / depth, abs=1.0)
    assert rows.mean() + 0.5 == pytest.approx(size / 2 - f * 0.2 / depth, abs=1.0)
    d = r.render_depth(_box((0.5, 0.5, 0.5)), [[0.0, 0.0]])[0]
    assert d[size // 2, size // 2] == pytest.approx(DEFAULT_DISTANCE - 0.25, abs=1e-3)
    assert d[0, 0] == 0.0


def test_normalized_object_stays_in_frame_from_every_viewpoint():
    # The unit cube's corners reach the bounding sphere: the worst case for a normalised object.
    cube = _box((1.0, 1.0, 1.0))
    vp = torch.cat([_viewpoints_with_poles(16, seed=1), torch.tensor([[45.0, 35.26], [-135.0, -35.26]])])
    alpha = get_renderer(64).render(cube, vp)[..., 3]
    border = np.concatenate([alpha[:, 0], alpha[:, -1], alpha[:, :, 0], alpha[:, :, -1]], axis=1)
    assert (border == 0).all()
    # ... and it is not tiny: the cube spans at least 35% of the image side in every view.
    spans = [(np.ptp(np.nonzero(a.any(0))[0]) + 1) / 64 for a in alpha > 0]
    assert min(spans) >= 0.35


# --------------------------------------------------------------------------- images
def test_background_alpha_and_batch_equals_single_views():
    mesh = _corner_shape()
    vp = [[30.0, 20.0], [-100.0, -60.0], [10.0, 90.0]]
    r = get_renderer(48)
    batch = r.render(mesh, vp)
    assert batch.shape == (3, 48, 48, 4) and batch.dtype == np.uint8
    for i, v in enumerate(vp):
        np.testing.assert_array_equal(batch[i], r.render(mesh, [v])[0])
    assert (batch[:, 0, 0] == 0).all()  # transparent, black corners
    assert (batch[..., 3] == 255).mean() > 0.05


def test_default_material_is_grey_and_colours_are_kept():
    box = _box((0.5, 0.5, 0.5))
    r = get_renderer(32)
    grey = r.render(box, [[30.0, 30.0]])[0]
    inside = grey[..., 3] == 255
    rgb = grey[inside][:, :3].astype(int)
    assert (np.abs(rgb[:, 0] - rgb[:, 1]) <= 2).all() and (np.abs(rgb[:, 1] - rgb[:, 2]) <= 2).all()
    red = box.copy()
    red.visual.vertex_colors = np.tile([255, 0, 0, 255], (len(red.vertices), 1))
    img = r.render(red, [[30.0, 30.0]])[0]
    rgb = img[img[..., 3] == 255][:, :3].astype(int)
    assert (rgb[:, 0] > 3 * rgb[:, 1] + 20).all()


def test_lighting_separates_the_visible_faces():
    # Seen from (30, 30) a cube shows three faces: they must get three distinct shades. From any view no
    # visible face may be left dark (the light moves with the camera, plus ambient).
    box = _box((0.6, 0.6, 0.6))
    view = get_renderer(64).render(box, [[30.0, 30.0]])[0]
    values = view[view[..., 3] == 255][:, 0]
    shades, counts = np.unique(values, return_counts=True)
    main = shades[counts > 0.1 * counts.sum()]
    assert len(main) == 3 and np.diff(np.sort(main)).min() >= 8
    images = get_renderer(64).render(box, _viewpoints_with_poles(12, seed=3))
    assert min(v[v[..., 3] == 255][:, 0].min() for v in images) >= 100


def test_composite_blends_over_background():
    rgba = np.array([[[[10, 20, 30, 0], [10, 20, 30, 255], [200, 100, 0, 128]]]], dtype=np.uint8)
    out = composite(rgba, background=(255, 255, 255))
    assert out.shape == (1, 1, 3, 3) and out.dtype == np.uint8
    np.testing.assert_array_equal(out[0, 0, 0], [255, 255, 255])
    np.testing.assert_array_equal(out[0, 0, 1], [10, 20, 30])
    a = 128 / 255
    np.testing.assert_array_equal(
        out[0, 0, 2], np.rint([200 * a + 255 * (1 - a), 100 * a + 255 * (1 - a), 255 * (1 - a)])
    )
    np.testing.assert_array_equal(composite(rgba, background=(0, 0, 0))[0, 0, 0], [0, 0, 0])
    with pytest.raises(ValueError, match="rgba"):
        composite(rgba[..., :3])
    with pytest.raises(ValueError, match="background"):
        composite(rgba, background=(0, 0, 300))


def test_composite_is_the_float32_formula_rounded_on_random_images():
    rgba = np.random.default_rng(2).integers(0, 256, (3, 6, 5, 4), dtype=np.uint8)
    for background in [(255, 255, 255), (0, 51, 240)]:
        alpha = rgba[..., 3:4].astype(np.float32) / 255.0
        bg = np.asarray(background, dtype=np.float32)
        expected = np.rint(rgba[..., :3].astype(np.float32) * alpha + bg * (1.0 - alpha)).astype(np.uint8)
        np.testing.assert_array_equal(composite(rgba, background=background), expected)


def test_renderers_share_one_cached_context():
    from lightning_vtr import renderer as render

    a, b = get_renderer(24), get_renderer(24)
    assert a is b
    c = get_renderer(24, camera="orthographic")
    assert c is not a
    a.render(_box((0.5, 0.5, 0.5)), [[0.0, 0.0]])
    ctx = render._CONTEXT.renderer
    c.render(_box((0.5, 0.5, 0.5)), [[0.0, 0.0]])
    assert render._CONTEXT.renderer is ctx  # the second configuration reused the GL context
    c.close()
    with pytest.raises(RuntimeError, match="closed"):
        c.render(_box((0.5, 0.5, 0.5)), [[0.0, 0.0]])
    assert get_renderer(24, camera="orthographic") is not c


def test_renderer_argument_types_and_messages():
    with Renderer(32.0) as renderer:
        assert renderer.image_size == 32  # an integral float size is still accepted
    with pytest.raises(TypeError, match="^`image_size` must be an int, got float 2.5$"):
        Renderer(2.5)
    with pytest.raises(ValueError, match=r"^`yfov_deg` must be a number in \(0, 180\), got 180.0$"):
        Renderer(32, yfov_deg=180.0)
    with pytest.raises(ValueError, match=r"^`base_color\[2\]` must be a number in \[0, 1\], got 2.0$"):
        Renderer(32, base_color=(0.5, 0.5, 2.0))
    with pytest.raises(ValueError, match=r"^`base_color` must be three numbers in \[0, 1\], got \[0.5, 0.5\]$"):
        Renderer(32, base_color=[0.5, 0.5])


def test_renderer_argument_errors():
    with pytest.raises(ValueError, match="image_size"):
        Renderer(0)
    with pytest.raises(ValueError, match="camera"):
        Renderer(32, camera="fisheye")
    with pytest.raises(ValueError, match="yfov_deg"):
        Renderer(32, yfov_deg=180.0)
    with pytest.raises(ValueError, match="viewpoints"):
        get_renderer(32).render(_box((0.5, 0.5, 0.5)), [0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="no triangles"):
        get_renderer(32).render(trimesh.Trimesh(), [[0.0, 0.0]])
