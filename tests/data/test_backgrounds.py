"""Folder backgrounds: training views composited over random crops of a folder's images."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from helpers import write_rendering_layout
from PIL import Image

from lightning_vtr.data.datamodule import VTRDataModule
from lightning_vtr.data.transforms import IMAGE_RECIPES, BackgroundFolder, ImageRecipe, ImageTransform

SIDE = 4


def _view() -> np.ndarray:
    """A 4x4 RGBA view: opaque object (200, 10, 50) in column 0, transparent columns 1-2, alpha 128 in column 3."""
    view = np.zeros((SIDE, SIDE, 4), dtype=np.uint8)
    view[:, 0] = (200, 10, 50, 255)
    view[:, 1:3] = (7, 7, 7, 0)  # the colour of a transparent pixel must not show
    view[:, 3] = (100, 100, 100, 128)
    return view


def _coded(height: int, width: int, tag: int) -> np.ndarray:
    """An RGB image whose pixel (r, c) is (10 r + c, tag, 255 - 10 r - c): every window is recognisable."""
    r, c = np.meshgrid(np.arange(height), np.arange(width), indexing="ij")
    return np.stack([10 * r + c, np.full_like(r, tag), 255 - 10 * r - c], axis=-1).astype(np.uint8)


def _save(image: np.ndarray, path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(image).save(path)


def _composite(view: np.ndarray, background: np.ndarray) -> np.ndarray:
    """The expected composite in [0, 1], computed by hand: rgb * a + bg * (1 - a)."""
    a = view[..., 3:].astype(np.float64) / 255
    return view[..., :3] / 255 * a + background / 255 * (1 - a)


def _transform(folder, **kw) -> ImageTransform:
    return ImageTransform(SIDE, normalize=None, background_folder=str(folder), **kw)


# ------------------------------------------------------------------------------------------ compositing


def test_composite_over_a_background_of_the_views_size_is_exact(tmp_path):
    # One image exactly the view's size: one possible crop, so the composite is known for any key.
    background = _coded(SIDE, SIDE, tag=77)
    _save(background, tmp_path / "bg" / "only.png")
    out = _transform(tmp_path / "bg")(_view(), key=(0, 3, 5))
    assert out.shape == (3, SIDE, SIDE)
    got = out.permute(1, 2, 0).double().numpy()
    np.testing.assert_allclose(got, _composite(_view(), background), atol=1e-6)
    # Spot values by hand: opaque object pixel; transparent pixel (row 2, col 1) = background (21, 77, 234);
    # alpha 128 at (1, 3): 100 * 128/255 + bg (13, 77, 242) * 127/255.
    np.testing.assert_allclose(got[0, 0] * 255, [200, 10, 50], atol=1e-4)
    np.testing.assert_allclose(got[2, 1] * 255, [21, 77, 234], atol=1e-4)
    expected = (100 * 128 + np.array([13, 77, 242]) * 127) / 255
    np.testing.assert_allclose(got[1, 3] * 255, expected, atol=1e-4)


def test_composite_over_a_folder_image_is_the_float32_formula_bit_for_bit(tmp_path):
    # Random views, one background image of their size: rgb * a + bg * (1 - a) in float32, as the transform always did.
    rng = np.random.default_rng(4)
    background = rng.integers(0, 256, (SIDE, SIDE, 3), dtype=np.uint8)
    _save(background, tmp_path / "bg" / "only.png")
    views = rng.integers(0, 256, (3, SIDE, SIDE, 4), dtype=np.uint8)
    out = _transform(tmp_path / "bg")(views, key=(0, 1, 2))
    x = torch.from_numpy(views).float() / 255.0
    bg = torch.from_numpy(background).float() / 255.0
    expected = (x[..., :3] * x[..., 3:] + bg * (1.0 - x[..., 3:])).permute(0, 3, 1, 2)
    assert torch.equal(out, expected)


def test_crop_of_a_larger_background_is_the_window_at_the_drawn_position(tmp_path):
    # A 6 x 7 image: (6 - 4 + 1) x (7 - 4 + 1) = 12 possible windows.
    background = _coded(6, 7, tag=5)
    _save(background, tmp_path / "bg" / "big.png")
    transform = _transform(tmp_path / "bg")
    views = np.stack([_view(), _view()])  # two views: each gets its own crop
    seen = set()
    for index in range(60):
        key = (0, 1, index)
        out = transform(views, key=key).permute(0, 2, 3, 1).double().numpy()
        scenes = transform.draw(key, 2).scenes
        assert len(scenes) == 2
        for t, (image, u, v) in enumerate(scenes):
            assert image == 0 and 0 <= u < 1 and 0 <= v < 1
            top, left = int(u * 3), int(v * 4)  # floor(u * (6 - 4 + 1)), floor(v * (7 - 4 + 1))
            window = background[top : top + SIDE, left : left + SIDE]
            np.testing.assert_allclose(out[t], _composite(_view(), window), atol=1e-6)
            seen.add((top, left))
    assert seen == {(r, c) for r in range(3) for c in range(4)}  # every window position occurs


def test_smaller_background_is_scaled_up_to_cover_the_view(tmp_path):
    # 2 x 3 and one colour: scaled up (aspect kept) to 4 x 6, any crop is that colour.
    _save(np.full((2, 3, 3), (30, 60, 90), dtype=np.uint8), tmp_path / "bg" / "small.png")
    out = _transform(tmp_path / "bg")(_view(), key=(1, 0, 0)).permute(1, 2, 0).double().numpy()
    np.testing.assert_allclose(out, _composite(_view(), np.full((SIDE, SIDE, 3), (30, 60, 90))), atol=1e-6)
    folder = BackgroundFolder(tmp_path / "bg")
    assert folder.crop(0, (0.99, 0.99), 5, 9).shape == (5, 9, 3)  # 2x3 -> 6x9 (scale 3), crop 5x9


def test_folder_is_scanned_recursively_sorted_and_filtered(tmp_path):
    root = tmp_path / "sun"
    _save(np.zeros((4, 4, 3), np.uint8), root / "b.png")
    _save(np.zeros((4, 4, 3), np.uint8), root / "a" / "z.JPG")
    _save(np.zeros((4, 4, 3), np.uint8), root / "a" / "y.jpeg")
    _save(np.zeros((4, 4, 3), np.uint8), root / "c.gif")
    (root / "notes.txt").write_text("not an image")
    folder = BackgroundFolder(root)
    assert [p.relative_to(root).as_posix() for p in folder.paths] == ["a/y.jpeg", "a/z.JPG", "b.png"]
    assert len(folder) == 3


def test_every_image_is_drawn_and_each_view_draws_its_own(tmp_path):
    for tag in range(3):
        _save(np.full((SIDE, SIDE, 3), 40 * (tag + 1), dtype=np.uint8), tmp_path / "bg" / f"{tag}.png")
    transform = _transform(tmp_path / "bg")
    picks = [transform.draw((0, 0, i), 3).scenes for i in range(40)]
    assert {image for scenes in picks for image, _, _ in scenes} == {0, 1, 2}
    assert any(len({image for image, _, _ in scenes}) > 1 for scenes in picks)  # views of one sample differ
    # A view's draw does not depend on how many views follow it.
    assert transform.draw((0, 0, 7), 1).scenes == transform.draw((0, 0, 7), 3).scenes[:1]
    # Transparent pixels show exactly the drawn image's colour.
    out = transform(np.stack([_view()] * 3), key=(0, 0, 7))
    for t, (image, _, _) in enumerate(transform.draw((0, 0, 7), 3).scenes):
        assert torch.allclose(out[t, :, 0, 1], torch.full((3,), 40 * (image + 1) / 255))


# ------------------------------------------------------------------------------------------ determinism


def test_same_key_same_composite_other_epoch_differs(tmp_path):
    _save(np.random.default_rng(0).integers(0, 256, (40, 50, 3), dtype=np.uint8), tmp_path / "bg" / "a.png")
    _save(np.random.default_rng(1).integers(0, 256, (30, 30, 3), dtype=np.uint8), tmp_path / "bg" / "b.png")
    views = np.stack([_view()] * 3)
    first, second = _transform(tmp_path / "bg"), _transform(tmp_path / "bg")  # two processes' transforms
    torch.manual_seed(0)
    a = first(views, key=(0, 2, 9))
    torch.manual_seed(1)  # the global RNG plays no part
    np.random.seed(1)
    assert torch.equal(a, second(views, key=(0, 2, 9)))
    assert not torch.equal(a, second(views, key=(0, 3, 9)))  # next epoch: other crops
    assert not torch.equal(a, second(views, key=(0, 2, 10)))  # other sample
    assert first.draw((0, 2, 9), 3).scenes != first.draw((0, 3, 9), 3).scenes


def test_the_folder_leaves_the_recipes_other_draws_unchanged(tmp_path):
    _save(_coded(8, 8, 1), tmp_path / "bg" / "a.png")
    plain = ImageTransform(SIDE, brightness=0.4, contrast=0.4, lighting_std=0.1, hflip=True, permute_rgb=True)
    folder = _transform(tmp_path / "bg", brightness=0.4, contrast=0.4, lighting_std=0.1, hflip=True, permute_rgb=True)
    for key in [(0, 0, 0), (3, 1, 4)]:
        a, b = plain.draw(key, 2), folder.draw(key, 2)
        assert (a.factors, a.order, a.lighting, a.channels, a.flips) == (
            b.factors,
            b.order,
            b.lighting,
            b.channels,
            b.flips,
        )
        assert a.scenes == () and len(b.scenes) == 2


def test_folder_background_needs_a_key_and_eval_transform_drops_it(tmp_path):
    _save(_coded(8, 8, 1), tmp_path / "bg" / "a.png")
    recipe = ImageRecipe(background=(240, 240, 240), background_folder=str(tmp_path / "bg"), normalize=None)
    assert recipe.is_random
    with pytest.raises(ValueError, match="`key` must be given"):
        recipe.train_transform(SIDE)(_view())
    evaluation = recipe.eval_transform(SIDE)
    assert evaluation.backgrounds is None and not evaluation.is_random
    got = evaluation(_view()).permute(1, 2, 0).double().numpy()
    np.testing.assert_allclose(got, _composite(_view(), np.full((SIDE, SIDE, 3), 240.0)), atol=1e-6)


# ------------------------------------------------------------------------------------------ errors


def test_empty_or_missing_folder_is_refused_naming_it(tmp_path):
    empty = tmp_path / "empty"
    (empty / "sub").mkdir(parents=True)
    (empty / "sub" / "readme.txt").write_text("no images here")
    with pytest.raises(ValueError, match=r"folder '.*empty' has no images: expected files ending in \.png, \.jpg"):
        ImageTransform(SIDE, background_folder=str(empty))
    with pytest.raises(FileNotFoundError, match="nope' is not a directory"):
        BackgroundFolder(tmp_path / "nope")
    with pytest.raises(ValueError, match="has no images"):
        VTRDataModule(str(tmp_path), background=f"folder:{empty}")
    with pytest.raises(ValueError, match=r"`background` must be three ints \(R, G, B\) or 'folder:PATH', got 'sun'"):
        VTRDataModule(str(tmp_path), background="sun")
    with pytest.raises(ValueError, match="`background_range` must be None with `background='folder:"):
        VTRDataModule(str(tmp_path), background=f"folder:{tmp_path}", background_range=(0, 10))
    with pytest.raises(TypeError, match="`background_folder` must be None or a folder path, got int 3"):
        ImageRecipe(background_folder=3)


# ------------------------------------------------------------------------------------------ through the datamodule

OBJECT_COLOUR = (200, 10, 50)


@pytest.fixture
def rendering_layout(tmp_path):
    """A ShapeNetRendering-layout dataset of 8x8 RGBA renders (left half opaque, right half transparent):
    one train, one val and one test chair with 4 views each."""
    image = np.zeros((8, 8, 4), dtype=np.uint8)
    image[:, :4] = (*OBJECT_COLOUR, 255)
    splits = {"chairT": "train", "chairV": "val", "chairX": "test"}
    return write_rendering_layout(tmp_path, splits, image, np.ones((32, 32, 32), dtype=bool))


def test_datamodule_composites_training_views_and_keeps_eval_background(tmp_path, rendering_layout):
    colours = [(0, 128, 255), (90, 45, 0)]
    for i, colour in enumerate(colours):
        _save(np.full((12, 10, 3), colour, dtype=np.uint8), tmp_path / "sun" / f"{i}.png")
    dm = VTRDataModule(
        shapenet_rendering=rendering_layout,
        background=f"folder:{tmp_path / 'sun'}",
        normalize=None,
        image_size=8,
        num_views=4,
        batch_size=1,
        test_view_sets=["aligned"],  # the layout's only view set
    )
    dm.setup("fit")
    assert dm.recipe.background_folder == str(tmp_path / "sun") and dm.recipe.background == (255, 255, 255)
    images = next(iter(dm.train_dataloader()))["images"][0]  # (4 views, 3, 8, 8)
    expected = torch.tensor(OBJECT_COLOUR) / 255
    assert torch.allclose(images[:, :, :, :4], expected[None, :, None, None].expand(4, 3, 8, 4))
    shown = {tuple(round(float(c) * 255) for c in images[t, :, 0, 6]) for t in range(4)}
    assert shown <= set(colours) and len(shown) == 2  # each view over one of the folder's images
    for t in range(4):  # one image per view: the whole transparent half is that colour
        assert torch.equal(images[t, :, :, 4:], images[t, :, :1, 6:7].expand(3, 8, 4))
    for loader in (dm.val_dataloader(), *dm.test_dataloader()):
        evaluation = next(iter(loader))["images"][0]
        assert torch.equal(evaluation[:, :, :, 4:], torch.ones(4, 3, 8, 4))  # the plain recipe's white
        assert torch.allclose(evaluation[:, :, :, :4], expected[None, :, None, None].expand(4, 3, 8, 4))
    # With a named recipe the folder replaces its colour range in training; evaluation keeps its 240.
    lrgt = VTRDataModule(shapenet_rendering=rendering_layout, background=f"folder:{tmp_path / 'sun'}", recipe="lrgt")
    assert lrgt.recipe == dataclasses.replace(IMAGE_RECIPES["lrgt"], background_folder=str(tmp_path / "sun"))
    assert lrgt.transform.background == (240, 240, 240) and lrgt.transform.backgrounds is None
    assert len(lrgt.train_transform.backgrounds) == 2
    assert lrgt.hparams["background"] == f"folder:{tmp_path / 'sun'}"


def test_backgrounds_do_not_depend_on_the_process_or_worker(tmp_path, rendering_layout):
    rng = np.random.default_rng(3)
    for i in range(3):
        _save(rng.integers(0, 256, (20 + i, 30, 3), dtype=np.uint8), tmp_path / "sun" / f"{i}.png")

    def batches(num_workers: int, epoch: int) -> torch.Tensor:
        dm = VTRDataModule(
            shapenet_rendering=rendering_layout,
            background=f"folder:{tmp_path / 'sun'}",
            image_size=8,
            num_views=4,
            batch_size=1,
            num_workers=num_workers,
            test_view_sets=["aligned"],
        )
        dataset = dm.train_dataset()
        dataset.set_epoch(epoch)  # what a resumed run's loader does for its epoch
        loader = torch.utils.data.DataLoader(dataset, batch_size=1, num_workers=num_workers)
        return torch.cat([b["images"] for b in loader])

    torch.manual_seed(0)
    main_process = batches(0, epoch=2)
    torch.manual_seed(1)
    assert torch.equal(main_process, batches(2, epoch=2))  # two worker processes, another global seed
    assert not torch.equal(main_process, batches(0, epoch=3))
