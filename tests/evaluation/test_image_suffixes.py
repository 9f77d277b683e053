"""One list of picture suffixes (``lightning_vtr.data.format.IMAGE_SUFFIXES``) for every reader, and PIL reads
a picture of each kind: image folders of ``predict``, folder test sets and background folders."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from lightning_vtr.data import folder_test_set, transforms
from lightning_vtr.data.format import IMAGE_SUFFIXES
from lightning_vtr.data.transforms import BackgroundFolder
from lightning_vtr.evaluation import predict
from lightning_vtr.evaluation.predict import read_view_folder

COLOUR = (200, 40, 90)


def test_every_reader_uses_the_one_list():
    assert IMAGE_SUFFIXES == (".png", ".jpg", ".jpeg", ".webp", ".bmp")
    assert transforms.BACKGROUND_EXTENSIONS is IMAGE_SUFFIXES
    assert folder_test_set.IMAGE_SUFFIXES is IMAGE_SUFFIXES
    assert predict.IMAGE_SUFFIXES is IMAGE_SUFFIXES


@pytest.mark.parametrize("suffix", IMAGE_SUFFIXES)
def test_pil_reads_a_picture_of_each_suffix_in_every_reader(tmp_path, suffix):
    picture = np.zeros((6, 4, 3), np.uint8)
    picture[:] = COLOUR
    path = tmp_path / "views" / f"a{suffix.upper()}"  # suffixes compare case-insensitively
    path.parent.mkdir()
    Image.fromarray(picture).save(path, quality=100, lossless=True)

    pictures, names, truth = read_view_folder(path.parent)
    assert names == [path.name] and truth is None
    assert pictures[0].shape == (6, 6, 4)  # padded to a square
    np.testing.assert_allclose(pictures[0][:, 1:5, :3].reshape(-1, 3).mean(0), COLOUR, atol=3)

    folder = BackgroundFolder(path.parent)
    assert folder.paths == [path]
    np.testing.assert_allclose(folder.load(0).reshape(-1, 3).mean(0), COLOUR, atol=3)


def test_a_large_picture_is_read_at_the_working_size_with_its_mask(tmp_path):
    """A picture of thousands of pixels a side is scaled down as it is read (a 17 KB PNG of 8192 x 8192 took 4 GB
    through the pipeline at full size); its mask follows it."""
    folder = tmp_path / "views"
    folder.mkdir()
    side = predict.WORKING_SIDE * 3
    picture = Image.new("RGB", (side, side // 2), COLOUR)
    picture.save(folder / "big.png")
    mask = Image.new("L", (side, side // 2), 0)
    mask.paste(255, (0, 0, side // 2, side // 2))  # the left half is the object
    mask.save(folder / "big_mask.png")
    pictures, names, _ = read_view_folder(folder)
    assert names == ["big.png"]
    (square,) = pictures
    assert square.shape == (predict.WORKING_SIDE, predict.WORKING_SIDE, 4)  # 1024 x 512, padded to a square
    rows = square[predict.WORKING_SIDE // 4 : 3 * predict.WORKING_SIDE // 4]  # the picture's band
    assert (rows[:, : predict.WORKING_SIDE // 2 - 2, 3] == 255).all()
    assert (rows[:, predict.WORKING_SIDE // 2 + 2 :, 3] == 0).all()
    assert tuple(rows[0, 0, :3]) == COLOUR
