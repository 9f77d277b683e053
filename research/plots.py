"""Pictures of the view selection: error projection maps over all candidate views, and the viewpoint pool.

Figures are drawn on :class:`matplotlib.figure.Figure` objects, never through ``pyplot``: they need no
display, are not registered with pyplot's figure manager (nothing to close, no leak), and importing this
module leaves the user's matplotlib backend alone. Every function saves a PNG and returns what it drew so
callers (and tests) can check it without reading pixels.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from matplotlib.figure import Figure
from torch import Tensor

from lightning_vtr.geometry import angle_bins, candidate_viewpoints, check_bin_interval, check_viewpoints
from lightning_vtr.selection.pool import ViewpointPool
from lightning_vtr.selection.projection import error_projection, nearest_bins, view_scores

__all__ = ["plot_error_projections", "plot_pool_distribution"]


def plot_error_projections(
    volume_error: Tensor,
    k: int = 30,
    chosen: Tensor | None = None,
    path: str | Path = "error_projections.png",
    *,
    panel_size: float = 1.2,
) -> dict[str, Any]:
    """Grid of the first-hit error projection maps of one object over all candidate views.

    Rows are pitch bins (highest pitch on top), columns yaw bins (-180 on the left); each panel is titled
    with its bin centre (degrees) and score (sum of the map). Panels whose bin holds one of the ``chosen``
    viewpoints get a red frame.

    Args:
        volume_error: ``(R, R, R)`` error volume (e.g. one object's
            :func:`~lightning_vtr.selection.projection.error_volume`).
        k: bin interval ``K`` in degrees (must divide 180).
        chosen: ``(n, 2)`` selected viewpoints in degrees, or ``None``.
        path: PNG file to write (parent directories are created).
        panel_size: inches per panel.

    Returns:
        ``{"path", "figure", "scores" (V_c,), "marked_bins" (sorted flat bin indices), "grid" (rows, cols)}``;
        ``figure`` is a :class:`matplotlib.figure.Figure`.

    Raises:
        TypeError: ``volume_error`` is not a tensor, or ``k`` is not a number.
        ValueError: ``volume_error`` is not ``(R, R, R)``, a bad ``k`` or bad ``chosen`` viewpoints.

    Example::

        error = error_volume(predicted[:1], target[:1])[0]  # (R, R, R)
        chosen = ErrorGuidedSelector().select(predicted[:1], target[:1], ["chair"])[0]  # (3, 2) degrees
        drawn = plot_error_projections(error, k=30, chosen=chosen, path="figures/error_projections.png")
        drawn["grid"]  # (6, 12): pitch bins x yaw bins
    """
    k = check_bin_interval(k)
    if not isinstance(volume_error, Tensor):
        raise TypeError(f"`volume_error` must be a torch.Tensor of shape (R, R, R), got {type(volume_error).__name__}")
    if volume_error.ndim != 3:
        raise ValueError(f"`volume_error` must have shape (R, R, R), got {tuple(volume_error.shape)}")
    candidates = candidate_viewpoints(k)
    maps = error_projection(volume_error.detach().cpu().float(), candidates)  # (V_c, S, S)
    scores = view_scores(maps[None])[0]
    marked = set()
    if chosen is not None:
        marked = {int(i) for i in nearest_bins(check_viewpoints(chosen, "chosen").reshape(-1, 2).cpu(), k)}
    yaw_c, pitch_c = angle_bins(k)
    rows, cols = pitch_c.numel(), yaw_c.numel()
    vmax = max(float(maps.max()), 1e-12)

    fig = Figure(figsize=(cols * panel_size, rows * panel_size * 1.15))
    axes = fig.subplots(rows, cols, squeeze=False)
    for i_pitch in range(rows):
        for i_yaw in range(cols):
            index = i_pitch * cols + i_yaw
            ax = axes[rows - 1 - i_pitch, i_yaw]  # highest pitch in the top row
            ax.imshow(maps[index].numpy(), cmap="magma", vmin=0.0, vmax=vmax, interpolation="nearest")
            ax.set_xticks([])
            ax.set_yticks([])
            ax.set_title(f"{yaw_c[i_yaw]:.0f},{pitch_c[i_pitch]:.0f}\n{float(scores[index]):.0f}", fontsize=6)
            if index in marked:
                for spine in ax.spines.values():
                    spine.set_edgecolor("red")
                    spine.set_linewidth(2.5)
    fig.suptitle(f"First-hit error projections (yaw, pitch in degrees; score); K={k}, chosen bins in red", fontsize=8)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=80)
    return {"path": path, "figure": fig, "scores": scores, "marked_bins": sorted(marked), "grid": (rows, cols)}


def plot_pool_distribution(pool: ViewpointPool, path: str | Path = "viewpoint_pool.png") -> dict[str, Any]:
    """Per category, the pool's viewpoints as points on a yaw (x) / pitch (y) map in degrees.

    Args:
        pool: the :class:`ViewpointPool` to draw.
        path: PNG file to write (parent directories are created).

    Returns:
        ``{"path", "figure", "categories" (drawn order), "points" {category: number of viewpoints drawn}}``;
        ``figure`` is a :class:`matplotlib.figure.Figure`. An empty pool gives one empty panel titled accordingly.

    Example::

        pool = ViewpointPool(num_views=3)
        pool.add("chair", "c1", torch.tensor([[0.0, 30.0], [120.0, 30.0], [-120.0, 30.0]]))
        drawn = plot_pool_distribution(pool, path="figures/viewpoint_pool.png")
        drawn["points"]  # {"chair": 3}
    """
    categories = pool.categories()
    count = max(len(categories), 1)
    cols = min(count, 4)
    rows = (count + cols - 1) // cols
    fig = Figure(figsize=(3.6 * cols, 2.2 * rows))
    axes = fig.subplots(rows, cols, squeeze=False)
    points: dict[str, int] = {}
    for ax in axes.flat:
        ax.set_visible(False)
    if not categories:
        axes[0, 0].set_visible(True)
        axes[0, 0].set_title("viewpoint pool is empty", fontsize=8)
    for ax, category in zip(axes.flat, categories):
        _, views = pool.view_sets(category)
        flat = views.reshape(-1, 2)
        ax.set_visible(True)
        ax.scatter(flat[:, 0].numpy(), flat[:, 1].numpy(), s=6, alpha=0.6)
        ax.set_xlim(-180, 180)
        ax.set_ylim(-90, 90)
        ax.set_xticks(range(-180, 181, 90))
        ax.set_yticks(range(-90, 91, 45))
        ax.set_xlabel("yaw (deg)", fontsize=7)
        ax.set_ylabel("pitch (deg)", fontsize=7)
        ax.set_title(f"{category}: {views.shape[0]} sets", fontsize=8)
        ax.tick_params(labelsize=6)
        points[category] = int(flat.shape[0])
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=80)
    return {"path": path, "figure": fig, "categories": categories, "points": points}
