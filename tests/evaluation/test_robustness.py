"""The viewpoint robustness map on a few tiny objects at K = 60 (18 bins), its CSV files and its plots."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from PIL import Image
from robustness_fixtures import N_BINS, ImageMeanModel, K, OracleModel

from lightning_vtr.data.dataset import load_voxels
from lightning_vtr.evaluation.robustness import (
    RobustnessMap,
    bin_area_fractions,
    read_bins_csv,
    robustness_map,
    view_sets_around_bins,
)
from lightning_vtr.geometry import angle_bins, candidate_viewpoints
from lightning_vtr.synthesis.base import Synthesizer
from lightning_vtr.synthesis.render import RenderSynthesizer


class PitchImages(Synthesizer):
    """Images whose red channel holds ``pitch + 90`` of their viewpoint (no mesh needed)."""

    image_size = 4
    needs_source_images = False

    def synthesize(self, requests):
        out = []
        for req in requests:
            pitch = np.asarray(req.target_viewpoints)[:, 1]
            images = np.zeros((len(pitch), 4, 4, 4), np.uint8)
            images[..., 0] = np.rint(pitch + 90.0).astype(np.uint8)[:, None, None]
            images[..., 3] = 255
            out.append(images)
        return out


def red_channel(images: np.ndarray) -> torch.Tensor:
    return torch.as_tensor(images[..., :3]).permute(0, 3, 1, 2).float()


class LooksFromAbove(OracleModel):
    """Predicts the object's ground truth when its views' mean pitch is above 0, else nothing."""

    image_size = 4

    def predict_voxels(self, images):
        above = images[:, :, 0].mean(dim=(1, 2, 3)) - 90.0 > 0
        return super().predict_voxels(images) * above[:, None, None, None].float()


def measure(model, objects, **kw):
    kw.setdefault("synthesizer", RenderSynthesizer(image_size=32))
    return robustness_map(model, objects, k=K, progress=False, **kw)


def test_bin_areas_are_the_sphere_fractions():
    areas = bin_area_fractions(K)
    assert areas.shape == (N_BINS,)
    assert areas.sum() == pytest.approx(1.0, abs=1e-12)
    # the top band, pitch [30, 90], covers (1 - sin 30) / 2 = 1/4 of the sphere, shared by its 6 bins; the
    # equatorial band [-30, 30] covers sin 30 = 1/2
    assert areas[-1] == pytest.approx(0.25 / 6, rel=1e-12)
    assert areas[6] == pytest.approx(0.5 / 6, rel=1e-12)


def test_view_sets_are_drawn_around_their_bin_centres():
    sets = view_sets_around_bins(30, 3, 4, torch.Generator().manual_seed(0))
    assert sets.shape == (72, 4, 3, 2)
    centres = candidate_viewpoints(30)
    # sigma = K / 6 = 5 degrees: away from the poles the pitch stays within 4 sigma of its centre
    equator = (centres[:, 1].abs() < 60).nonzero()[:, 0]
    offsets = (sets[equator, ..., 1] - centres[equator, None, None, 1]).abs()
    assert offsets.max() < 20.0
    assert 2.0 < float(offsets.mean()) < 6.0  # E|N(0, 5)| = 3.99


def test_map_shape_determinism_and_seed(objects):
    model = ImageMeanModel()
    first = measure(model, objects, seed=0)
    assert first.iou.shape == (3, N_BINS)
    assert first.centres.shape == (N_BINS, 2)
    np.testing.assert_array_equal(first.centres, candidate_viewpoints(K).double().numpy())
    assert first.areas.sum() == pytest.approx(1.0)
    assert first.object_ids == [r.object_id for r in objects]
    assert first.categories == [r.category for r in objects]
    assert first.aligned_pitch == pytest.approx(30.0)
    assert ((first.iou >= 0) & (first.iou <= 1)).all()
    again = measure(model, objects, seed=0, overlap=False, objects_per_call=1, batch_size=5)
    np.testing.assert_array_equal(first.iou, again.iou)  # the batching and the prediction thread change nothing
    other = measure(model, objects, seed=1)
    assert not np.array_equal(first.iou, other.iou)
    # an object's views depend on the seed and the object, not on the objects measured with it
    alone = measure(model, objects[1:2], seed=0)
    np.testing.assert_array_equal(alone.iou[0], first.iou[1])
    assert model.training  # its mode is restored


def test_a_model_that_predicts_the_truth_scores_one_everywhere(objects):
    targets = torch.stack([load_voxels(r) for r in objects])
    oracle = OracleModel(targets, per_object=N_BINS * 2)
    rmap = measure(oracle, objects, sets_per_bin=2, batch_size=7, objects_per_call=2)
    np.testing.assert_array_equal(rmap.iou, np.ones((3, N_BINS)))
    mean, low, _high = rmap.confidence_interval()
    np.testing.assert_array_equal(mean, np.ones(N_BINS))
    np.testing.assert_array_equal(low, np.ones(N_BINS))  # no spread, no width
    assert rmap.overall() == pytest.approx(1.0)


def test_bins_are_in_pitch_major_order_and_each_object_meets_its_own_target(objects):
    # The model is right exactly when it looks from above: IoU 1 in the top band, 0 in the bottom one.
    targets = torch.stack([load_voxels(r) for r in objects])
    model = LooksFromAbove(targets, per_object=N_BINS)
    rmap = robustness_map(
        model, objects, k=K, synthesizer=PitchImages(), transform=red_channel, batch_size=5, progress=False
    )
    n_yaw = 360 // K
    _, pitch = angle_bins(K)
    assert pitch.tolist() == [-60.0, 0.0, 60.0]
    np.testing.assert_array_equal(rmap.iou[:, :n_yaw], 0.0)
    np.testing.assert_array_equal(rmap.iou[:, 2 * n_yaw :], 1.0)
    middle = rmap.iou[:, n_yaw : 2 * n_yaw]
    assert set(np.unique(middle)) <= {0.0, 1.0} and 0 < middle.mean() < 1


def test_confidence_interval_is_student_t():
    iou = np.array([[0.2] * N_BINS, [0.4] * N_BINS, [0.9] * N_BINS])
    rmap = RobustnessMap.from_iou(iou, k=K, object_ids=["a", "b", "c"], categories=["x", "x", "y"])
    mean, low, high = rmap.confidence_interval()
    sd = np.std([0.2, 0.4, 0.9], ddof=1)
    half = 4.302652729911275 * sd / np.sqrt(3)  # t_{0.975, 2}
    np.testing.assert_allclose(mean, 0.5)
    np.testing.assert_allclose(high - mean, half)
    np.testing.assert_allclose(mean - low, half)
    np.testing.assert_allclose(rmap.mean("x"), 0.3)
    _, low_y, _ = rmap.confidence_interval("y")  # one object: no interval
    assert np.isnan(low_y).all()
    with pytest.raises(KeyError, match="'z'"):
        rmap.mean("z")


def test_csv_round_trips(tmp_path):
    rng = np.random.default_rng(0)
    iou = rng.uniform(size=(4, N_BINS))
    rmap = RobustnessMap.from_iou(
        iou, k=K, object_ids=list("abcd"), categories=["x", "x", "y", "y"], aligned_pitch=30.0, seed=3
    )
    assert len(read_bins_csv(rmap.to_csv(tmp_path / "plain"))) == N_BINS  # one row per bin
    bins = rmap.to_csv(tmp_path / "out", per_category=True)
    assert bins.name == "bins.csv"
    rows = read_bins_csv(bins)
    assert len(rows) == 3 * N_BINS  # all, x, y
    overall = [r for r in rows if r["category"] == "all"]
    np.testing.assert_array_equal([r["mean_iou"] for r in overall], iou.mean(0))
    np.testing.assert_array_equal([r["area"] for r in overall], bin_area_fractions(K))
    np.testing.assert_array_equal([[r["yaw"], r["pitch"]] for r in overall], candidate_viewpoints(K).numpy())
    assert {r["objects"] for r in overall} == {4}
    y_rows = [r for r in rows if r["category"] == "y"]
    np.testing.assert_array_equal([r["mean_iou"] for r in y_rows], iou[2:].mean(0))
    back = RobustnessMap.from_csv(tmp_path / "out")
    np.testing.assert_array_equal(back.iou, iou)
    assert (back.object_ids, back.categories, back.k) == (rmap.object_ids, rmap.categories, K)
    assert (back.aligned_pitch, back.seed) == (30.0, 3)


def test_plot_writes_a_png_of_the_expected_size(tmp_path):
    from lightning_vtr.evaluation.robustness_plot import plot_difference, plot_map, write_index_html

    rng = np.random.default_rng(0)
    a = RobustnessMap.from_iou(rng.uniform(size=(2, N_BINS)), k=K, object_ids="ab", categories="xx", aligned_pitch=30)
    b = RobustnessMap.from_iou(rng.uniform(size=(2, N_BINS)), k=K, object_ids="ab", categories="xx", aligned_pitch=30)
    path = plot_map(a, tmp_path / "a.png", title="A", width_px=640, height_px=400)
    with Image.open(path) as img:
        assert img.size == (640, 400)
    diff = plot_difference(a, b, tmp_path / "diff.png", width_px=500, height_px=300)
    with Image.open(diff) as img:
        assert img.size == (500, 300)
    index = write_index_html(tmp_path, {"A": a, "B": b})
    html = index.read_text()
    assert index.name == "index.html"
    for name in ("A", "B"):
        png = tmp_path / f"{name}.png"
        assert png.is_file() and f'src="{png.name}"' in html
    assert f"{a.overall():.3f}" in html
    compared = write_index_html(tmp_path / "ref", {"A": a, "B": b}, reference="A").read_text()
    assert (tmp_path / "ref" / "B_minus_A.png").is_file() and 'src="B_minus_A.png"' in compared


def test_index_html_renders_a_sections_markdown_table_as_an_html_table(tmp_path):
    from lightning_vtr.evaluation.robustness_plot import write_index_html

    a = RobustnessMap.from_iou(np.full((1, N_BINS), 0.5), k=K, object_ids="a", categories="x")
    table = "| score | Spearman <rho> |\n|---|---|\n| visible | 0.025 |\n| input | 0.171 |"
    page = write_index_html(tmp_path, {"A": a}, sections={"Score validity: A": table}).read_text()
    section = page.split("<h2>Score validity: A</h2>", 1)[1]
    assert "|" not in section.split("</body>")[0], "a Markdown pipe is left in the page"
    assert "<tr><th>score</th><th>Spearman &lt;rho&gt;</th></tr>" in section
    assert "<tr><td>visible</td><td>0.025</td></tr>" in section and "<tr><td>input</td><td>0.171</td></tr>" in section


def test_maps_of_a_pair_share_one_colour_scale():
    from lightning_vtr.evaluation.robustness_plot import shared_limits

    a = RobustnessMap.from_iou(np.full((1, N_BINS), 0.3), k=K, object_ids="a", categories="x")
    b = RobustnessMap.from_iou(np.linspace(0.5, 0.9, N_BINS)[None], k=K, object_ids="a", categories="x")
    assert shared_limits({"a": a, "b": b}) == pytest.approx((0.3, 0.9))


class CoarseModel(ImageMeanModel):
    """Predicts a 16^3 grid for 32^3 objects."""

    def predict_voxels(self, images):
        return super().predict_voxels(images)[:, ::2, ::2, ::2]


def test_a_model_output_of_the_wrong_grid_is_refused(objects):
    with pytest.raises(ValueError, match=r"got \(8, 16, 16, 16\)"):
        robustness_map(CoarseModel(), objects[:1], k=90, progress=False, synthesizer=RenderSynthesizer(image_size=32))


def test_a_datamodule_serves_its_split_and_transform(dataset_root, objects):
    from lightning_vtr.data.datamodule import VTRDataModule

    dm = VTRDataModule(str(dataset_root), image_size=32, num_views=3)
    model = ImageMeanModel()
    kw = dict(k=90, progress=False, synthesizer=RenderSynthesizer(image_size=32))
    from_dm = robustness_map(model, dm, split="train", **kw)
    records = dm.split_records("train")
    assert from_dm.object_ids == [r.object_id for r in records] and from_dm.num_objects == 4
    from_records = robustness_map(model, records, transform=dm.transform, **kw)
    np.testing.assert_array_equal(from_dm.iou, from_records.iou)
    with pytest.raises(ValueError, match="at least one object"):
        robustness_map(model, dm, split="test", **kw)  # the split is empty
