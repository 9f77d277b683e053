"""Tests of the view-selection plots: PNG files written, the chosen bins marked, pool points drawn."""

from __future__ import annotations

import subprocess
import sys

import torch
from matplotlib.figure import Figure

from lightning_vtr.selection import ViewpointPool
from research.plots import plot_error_projections, plot_pool_distribution

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _red_framed(fig) -> int:
    count = 0
    for ax in fig.axes:
        colors = {tuple(spine.get_edgecolor()) for spine in ax.spines.values()}
        count += colors == {(1.0, 0.0, 0.0, 1.0)}
    return count


def test_error_projection_grid_marks_chosen_bins(tmp_path):
    err = torch.zeros(8, 8, 8)
    err[6:, 2:6, 2:6] = 1.0
    chosen = torch.tensor([[10.0, 10.0], [20.0, 5.0], [-100.0, -80.0]])  # first two share bin (15, 15)
    info = plot_error_projections(err, 30, chosen, tmp_path / "sub" / "maps.png")
    assert info["path"].read_bytes()[:8] == PNG_MAGIC
    assert info["grid"] == (6, 12) and len(info["figure"].axes) == 72
    assert info["marked_bins"] == [2, 42]  # bin centres (-105, -75) -> index 2 and (15, 15) -> 3 * 12 + 6
    assert _red_framed(info["figure"]) == 2
    # panel scores are the sums of the maps: the slab is seen from +-X with the same area
    assert info["scores"].shape == (72,) and float(info["scores"].sum()) > 0


def test_pool_distribution_plot(tmp_path):
    pool = ViewpointPool(num_views=3)
    pool.add("chair", "a", torch.zeros(3, 2))
    pool.add("chair", "b", torch.ones(3, 2))
    pool.add("lamp", "c", torch.ones(3, 2))
    info = plot_pool_distribution(pool, tmp_path / "pool.png")
    assert info["path"].read_bytes()[:8] == PNG_MAGIC
    assert info["categories"] == ["chair", "lamp"] and info["points"] == {"chair": 6, "lamp": 3}
    visible = [ax for ax in info["figure"].axes if ax.get_visible()]
    assert len(visible) == 2
    assert [len(ax.collections[0].get_offsets()) for ax in visible] == [6, 3]
    empty = plot_pool_distribution(ViewpointPool(), tmp_path / "empty.png")
    assert empty["points"] == {} and empty["path"].read_bytes()[:8] == PNG_MAGIC


def test_figures_bypass_pyplot(tmp_path):
    import matplotlib.pyplot as plt

    before = plt.get_fignums()
    info = plot_pool_distribution(ViewpointPool(), tmp_path / "pool.png")
    assert type(info["figure"]) is Figure
    assert plt.get_fignums() == before  # never registered with pyplot: nothing to close, nothing leaks


def test_importing_the_plugin_keeps_the_users_matplotlib_backend():
    # (pyplot itself may get imported, by torchmetrics through Lightning; only a `matplotlib.use` would switch)
    code = (
        "import matplotlib; matplotlib.use('svg'); "
        "import lightning_vtr.callback, lightning_vtr.selection; print(matplotlib.get_backend())"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.split() == ["svg"]
