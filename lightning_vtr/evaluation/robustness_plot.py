"""Pictures of :class:`~lightning_vtr.evaluation.robustness.RobustnessMap` s: the sphere, equal-area.

Each bin is drawn as a rectangle at its yaw span (x, degrees) and the span of ``sin(pitch)`` (y) of its pitch
band, so every rectangle's area is proportional to the solid angle of its bin (a Lambert cylindrical
equal-area projection): a region that looks large covers a large share of the viewing directions. The
Aligned elevation (the pitch of the training views) is drawn as a dashed line and the two poles are marked.
Matplotlib runs with the Agg backend; nothing is shown on screen.
"""

from __future__ import annotations

import html
import math
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from lightning_vtr.evaluation.robustness import RobustnessMap
from lightning_vtr.utils.io import atomic_write, save_figure
from lightning_vtr.utils.paths import join_under
from lightning_vtr.utils.validation import check_int

__all__ = ["map_file_stem", "plot_difference", "plot_map", "write_index_html"]

_DPI = 100


def _figure(width_px: int, height_px: int):
    import matplotlib

    matplotlib.use("Agg", force=False)
    from matplotlib.figure import Figure

    width_px = check_int("width_px", width_px, minimum=64)
    height_px = check_int("height_px", height_px, minimum=64)
    # a Figure not registered with pyplot: no global state, nothing to close
    return Figure(figsize=(width_px / _DPI, height_px / _DPI), dpi=_DPI)


def _draw(ax, rmap: RobustnessMap, values: np.ndarray, cmap: str, vmin: float, vmax: float, label: str, fig) -> None:
    from matplotlib.cm import ScalarMappable
    from matplotlib.collections import PatchCollection
    from matplotlib.colors import Normalize
    from matplotlib.patches import Rectangle

    half = rmap.k / 2.0
    patches = []
    for yaw, pitch in rmap.centres:
        low, high = math.sin(math.radians(pitch - half)), math.sin(math.radians(pitch + half))
        patches.append(Rectangle((yaw - half, low), rmap.k, high - low))
    norm = Normalize(vmin=vmin, vmax=vmax)
    collection = PatchCollection(patches, cmap=cmap, norm=norm, edgecolor="white", linewidth=0.4)
    collection.set_array(np.ma.masked_invalid(values))
    ax.add_collection(collection)
    ax.set_xlim(-180, 180)
    ax.set_ylim(-1.08, 1.08)
    ax.set_xticks(range(-180, 181, 90))
    ticks = [-90, -60, -30, 0, 30, 60, 90]
    ax.set_yticks([math.sin(math.radians(p)) for p in ticks], [f"{p}°" for p in ticks])
    ax.set_xlabel("yaw (degrees)")
    ax.set_ylabel("pitch (equal-area: sin pitch)")
    if rmap.aligned_pitch is not None:
        y = math.sin(math.radians(rmap.aligned_pitch))
        ax.axhline(y, color="black", linestyle="--", linewidth=1.0)
        ax.text(178, y + 0.02, f"Aligned ({rmap.aligned_pitch:g}°)", ha="right", va="bottom", fontsize=7)
    for y, name in ((1.0, "north pole"), (-1.0, "south pole")):
        ax.plot([-180, 180], [y, y], color="black", linewidth=1.5)
        ax.plot([0], [y], marker="^" if y > 0 else "v", color="black", markersize=5, clip_on=False)
        ax.text(-178, y + (0.02 if y > 0 else -0.02), name, va="bottom" if y > 0 else "top", fontsize=7)
    bar = fig.colorbar(ScalarMappable(norm=norm, cmap=cmap), ax=ax, fraction=0.04, pad=0.02)
    bar.set_label(label)


def _save(fig, path: str | Path) -> Path:
    return save_figure(fig, path, dpi=_DPI, format="png")


def plot_map(
    rmap: RobustnessMap,
    path: str | Path,
    *,
    category: str | None = None,
    title: str | None = None,
    vmin: float = 0.0,
    vmax: float = 1.0,
    width_px: int = 800,
    height_px: int = 450,
) -> Path:
    """Write an equal-area picture of one map's per-bin mean IoU as a PNG.

    Args:
        rmap: the map.
        path: the PNG file to write (parent folders are created).
        category: only the objects of this category (``None``: all).
        title: the figure title (``None``: the mean IoU over the sphere and the object count).
        vmin: IoU at the bottom of the colour scale; pass the same ``vmin``/``vmax`` to every map of a
            comparison so that one colour means one IoU in all of them.
        vmax: IoU at the top of the colour scale.
        width_px: image width in pixels.
        height_px: image height in pixels.

    Returns:
        ``path``, a ``width_px x height_px`` PNG.

    Raises:
        KeyError: no object of ``category``.
        ValueError: an image side below 64 pixels.

    Example::

        plot_map(robustness_map(model, dm), "runs/robustness/ours.png", title="Ours")
    """
    values = rmap.mean(category)
    n = rmap.num_objects if category is None else len(rmap.subset(category).object_ids)
    fig = _figure(width_px, height_px)
    ax = fig.add_subplot()
    _draw(ax, rmap, values, "viridis", vmin, vmax, f"mean IoU@{rmap.threshold:g}", fig)
    suffix = f" ({category})" if category else ""
    ax.set_title(
        title if title is not None else f"IoU over the sphere {rmap.overall(category):.3f}{suffix}, {n} objects",
        fontsize=9,
    )
    fig.tight_layout()
    return _save(fig, path)


def shared_limits(maps: Mapping[str, RobustnessMap] | list[RobustnessMap]) -> tuple[float, float]:
    """``(vmin, vmax)``: the range of the per-bin mean IoU over all ``maps``, one colour scale for them all."""
    values = [m.mean() for m in (maps.values() if isinstance(maps, Mapping) else maps)]
    joined = np.concatenate(values)
    low, high = float(np.nanmin(joined)), float(np.nanmax(joined))
    return (low, high) if high > low else (low - 0.05, high + 0.05)


def plot_difference(
    first: RobustnessMap,
    second: RobustnessMap,
    path: str | Path,
    *,
    category: str | None = None,
    title: str | None = None,
    limit: float | None = None,
    width_px: int = 800,
    height_px: int = 450,
) -> Path:
    """Write the per-bin difference ``first - second`` of the mean IoU as a PNG, on a symmetric colour scale.

    Blue bins are where ``first`` is better, red where ``second`` is; white is no difference. The scale runs
    from ``-limit`` to ``+limit``, by default the largest absolute difference, so 0 sits in the middle.

    Args:
        first: a map.
        second: a map on the same grid (same ``k``).
        path: the PNG file to write.
        category: compare only this category's objects.
        title: the figure title (``None``: the difference over the sphere).
        limit: half the range of the colour scale (``None``: the largest absolute difference).
        width_px: image width in pixels.
        height_px: image height in pixels.

    Returns:
        ``path``.

    Raises:
        ValueError: maps on different grids, or an image side below 64 pixels.
        KeyError: no object of ``category`` in one of the maps.

    Example::

        ours = RobustnessMap.from_csv("runs/robustness/ours")
        baseline = RobustnessMap.from_csv("runs/robustness/baseline")
        plot_difference(ours, baseline, "runs/robustness/ours-minus-baseline.png", category="chair")
    """
    if first.k != second.k:
        raise ValueError(f"The maps must share their grid to be compared, got K = {first.k} and K = {second.k}")
    diff = first.mean(category) - second.mean(category)
    if limit is None:
        largest = float(np.nanmax(np.abs(diff))) if np.isfinite(diff).any() else 0.0
        limit = largest if largest > 0 else 0.01
    fig = _figure(width_px, height_px)
    ax = fig.add_subplot()
    _draw(ax, first, diff, "RdBu", -limit, limit, "difference of mean IoU", fig)
    overall = first.overall(category) - second.overall(category)
    ax.set_title(title if title is not None else f"difference over the sphere {overall:+.3f}", fontsize=9)
    fig.tight_layout()
    return _save(fig, path)


def map_file_stem(name: str) -> str:
    """The file name stem :func:`write_index_html` gives the pictures of the map called ``name``.

    Every character but letters, digits, ``-``, ``_`` and ``.`` becomes ``_``; leading and trailing dots and
    underscores are dropped; an empty result is ``"map"``. Two names with one stem would write the same files.

    Args:
        name: the map's name (a checkpoint's label, say).

    Returns:
        A stem safe as a file name on every platform.

    Example:
        >>> map_file_stem("VTR (default rule)"), map_file_stem("a/b"), map_file_stem("..")
        ('VTR__default_rule', 'a_b', 'map')
    """
    stem = "".join(c if c.isalnum() or c in "-_." else "_" for c in name).strip("._")
    return stem or "map"


def _text_html(text: str) -> str:
    """HTML for ``text``: each run of Markdown pipe-table lines (``| a | b |``, its ``|---|`` rule dropped) a
    ``<table>`` whose first row is the header, each other paragraph a ``<p>``; every cell and line escaped."""
    blocks: list[str] = []
    table: list[list[str]] = []
    paragraph: list[str] = []

    def flush() -> None:
        if table:
            head, *body = table
            rows = ["<tr>" + "".join(f"<th>{html.escape(cell)}</th>" for cell in head) + "</tr>"]
            rows += ["<tr>" + "".join(f"<td>{html.escape(cell)}</td>" for cell in row) + "</tr>" for row in body]
            blocks.append("<table>\n" + "\n".join(rows) + "\n</table>")
            table.clear()
        if paragraph:
            blocks.append(f"<p>{html.escape(' '.join(paragraph))}</p>")
            paragraph.clear()

    for line in text.splitlines():
        stripped = line.strip()
        if stripped.startswith("|") and stripped.endswith("|") and len(stripped) > 1:
            if paragraph:
                flush()
            cells = [cell.strip() for cell in stripped[1:-1].split("|")]
            if not all(set(cell) <= set(":-") and cell for cell in cells):  # not the |---| rule
                table.append(cells)
        elif stripped:
            if table:
                flush()
            paragraph.append(stripped)
        else:
            flush()
    flush()
    return "\n".join(blocks)


def write_index_html(
    out: str | Path,
    maps: Mapping[str, RobustnessMap],
    *,
    reference: str | None = None,
    title: str = "Robustness maps",
    sections: Mapping[str, str] | None = None,
) -> Path:
    """Write one PNG per map (one shared colour scale) and an ``index.html`` showing them with a small table.

    The table lists, per map, the mean IoU over the sphere (area-weighted), its worst and best bin, and the
    number of objects. With ``reference``, a difference map of every other map against it is drawn too.

    Args:
        out: the output directory (created).
        maps: name -> map; the names title the pictures and name the files (``<name>.png``).
        reference: the name of the map the others are compared with (``None``: no difference maps).
        title: the page title.
        sections: heading -> text shown below the pictures, in order: its Markdown pipe tables become HTML
            tables, its other paragraphs HTML paragraphs (every cell and line escaped).

    Returns:
        The path of ``index.html``, written last and atomically (a page that is there is whole).

    Raises:
        ValueError: no maps.
        KeyError: a ``reference`` not among ``maps``.

    Example::

        write_index_html("runs/robustness", {"baseline": base_map, "ours": our_map}, reference="baseline")
    """
    if not maps:
        raise ValueError("`maps` must hold at least one map to show, got none")
    if reference is not None and reference not in maps:
        raise KeyError(f"`reference` {reference!r} is not among the maps {sorted(maps)}")
    directory = Path(out)
    directory.mkdir(parents=True, exist_ok=True)
    vmin, vmax = shared_limits(maps)
    rows, figures = [], []
    for name, rmap in maps.items():
        png = plot_map(
            rmap,
            join_under(directory, f"{map_file_stem(name)}.png", replace_link=True),
            title=name,
            vmin=vmin,
            vmax=vmax,
        )
        means = rmap.mean()
        worst, best = int(np.nanargmin(means)), int(np.nanargmax(means))
        rows.append(
            "<tr>"
            f"<td>{html.escape(name)}</td><td>{rmap.overall():.3f}</td>"
            f"<td>{means[worst]:.3f} at ({rmap.centres[worst, 0]:g}°, {rmap.centres[worst, 1]:g}°)</td>"
            f"<td>{means[best]:.3f} at ({rmap.centres[best, 0]:g}°, {rmap.centres[best, 1]:g}°)</td>"
            f"<td>{rmap.num_objects}</td></tr>"
        )
        figures.append(f'<figure><img src="{html.escape(png.name)}" alt="{html.escape(name)}"></figure>')
        if reference is not None and name != reference:
            diff = plot_difference(
                rmap,
                maps[reference],
                join_under(directory, f"{map_file_stem(name)}_minus_{map_file_stem(reference)}.png", replace_link=True),
                title=f"{name} - {reference}",
            )
            figures.append(f'<figure><img src="{html.escape(diff.name)}" alt="{html.escape(diff.stem)}"></figure>')
    extra = [f"<h2>{html.escape(heading)}</h2>\n{_text_html(text)}" for heading, text in (sections or {}).items()]
    first = next(iter(maps.values()))
    page = f"""<!DOCTYPE html>
<html><head><meta charset="utf-8"><title>{html.escape(title)}</title>
<style>body{{font-family:sans-serif}} table{{border-collapse:collapse}} td,th{{border:1px solid #ccc;padding:2px 8px}}
figure{{display:inline-block;margin:4px}}</style></head>
<body><h1>{html.escape(title)}</h1>
<p>IoU at {first.threshold:g} on view sets drawn around each bin of the K = {first.k}° grid; the pictures are
equal-area (yaw against sin pitch); the dashed line is the Aligned elevation. All maps share one colour scale
({vmin:.3f} to {vmax:.3f}).</p>
<table><tr><th>map</th><th>IoU over the sphere</th><th>worst bin</th><th>best bin</th><th>objects</th></tr>
{chr(10).join(rows)}
</table>
{chr(10).join(figures)}
{chr(10).join(extra)}
</body></html>
"""
    index = directory / "index.html"
    atomic_write(index, page)
    return index
