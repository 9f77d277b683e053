"""Voxel pictures: a grid drawn with the package's renderer, a prediction coloured by its error against the
ground truth, and the per-object sheet (input views | prediction | ground truth | error | error projections).

Grids follow the package's layout (``V[i, j, k]`` centred at ``((i + .5) / R - .5, ...)``, +Z up) and
viewpoints are ``(yaw, pitch)`` in **degrees**, so a voxel picture at a viewpoint shows the object as the
dataset's image at that viewpoint does. Pictures are ``uint8`` RGB arrays ``(..., H, W, 3)``; the sheet is
composed with Pillow (no matplotlib state is touched).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from types import MappingProxyType
from typing import TYPE_CHECKING, Any, Literal, cast, overload

import numpy as np
import torch
import trimesh
from PIL import Image, ImageDraw, ImageFont
from torch import Tensor

from lightning_vtr.geometry import check_viewpoints
from lightning_vtr.protocol import DEFAULT_THRESHOLD
from lightning_vtr.utils.validation import check_float, check_int, check_type

if TYPE_CHECKING:
    import lightning as L

    from lightning_vtr.selection.base import ViewSelector

__all__ = [
    "CORRECT",
    "DISPLAY_VIEWPOINTS",
    "EMPTY",
    "ERROR_COLORS",
    "FALSE_NEGATIVE",
    "FALSE_POSITIVE",
    "VOXEL_COLOR",
    "as_voxel_grid",
    "compose_sheet",
    "display_images",
    "error_labels",
    "error_projection_images",
    "log_validation_sheets",
    "object_sheet",
    "render_error",
    "render_voxels",
    "stack_sheets",
    "voxel_mesh",
]

EMPTY = 0
"""Label of :func:`error_labels` for a voxel in neither grid."""
CORRECT = 1
"""Label of :func:`error_labels` for a voxel in both grids."""
FALSE_POSITIVE = 2
"""Label of :func:`error_labels` for a voxel in the prediction only."""
FALSE_NEGATIVE = 3
"""Label of :func:`error_labels` for a voxel in the ground truth only."""
ERROR_COLORS: Mapping[int, tuple[int, int, int]] = MappingProxyType(
    {CORRECT: (185, 185, 185), FALSE_POSITIVE: (213, 94, 0), FALSE_NEGATIVE: (0, 114, 178)}
)
"""RGB (0-255) of each error label; vermillion and blue stay apart for the common colour-vision deficiencies."""
VOXEL_COLOR = (150, 172, 204)
"""RGB of an occupied voxel in plain pictures (prediction and ground truth alike, so they compare)."""
DISPLAY_VIEWPOINTS: tuple[tuple[float, float], ...] = ((-45.0, 30.0), (135.0, 30.0))
"""Viewpoints ``(yaw, pitch)`` in degrees of the prediction / ground truth / error pictures of a sheet:
two three-quarter views from opposite sides, 30 degrees up (the Aligned elevation)."""

_SILHOUETTE = (228, 228, 228)  # projection pixels that see the object but no error
_ERROR_LEGEND = (
    (ERROR_COLORS[CORRECT], "correct"),
    (ERROR_COLORS[FALSE_POSITIVE], "extra (FP)"),
    (ERROR_COLORS[FALSE_NEGATIVE], "missed (FN)"),
)
_PROJECTION_LEGEND = (
    (_SILHOUETTE, "no error on ray"),
    (ERROR_COLORS[FALSE_POSITIVE], "first: extra"),
    (ERROR_COLORS[FALSE_NEGATIVE], "first: missed"),
)
_WHITE = (255, 255, 255)


# --------------------------------------------------------------------------------------------- inputs
def as_voxel_grid(voxels: Any, name: str = "voxels") -> np.ndarray:
    """``(R, R, R)`` float or bool ndarray from a tensor or array; ``TypeError``/``ValueError`` naming ``name``.

    Args:
        voxels: ``(R, R, R)`` grid, a :class:`torch.Tensor` (any device) or a :class:`numpy.ndarray`.
        name: the argument's name in error messages.

    Returns:
        ``(R, R, R)`` ndarray on the CPU: bool for a bool tensor, float32 for another tensor, an ndarray as given.

    Raises:
        TypeError: ``voxels`` is neither a tensor nor an ndarray.
        ValueError: ``voxels`` is not ``(R, R, R)`` with ``R >= 1``.

    Example:
        >>> as_voxel_grid(torch.ones(2, 2, 2, dtype=torch.bool)).dtype
        dtype('bool')
        >>> as_voxel_grid(torch.zeros(2, 2, 2, dtype=torch.float64)).dtype
        dtype('float32')
    """
    if isinstance(voxels, Tensor):
        voxels = voxels.detach().cpu()
        voxels = voxels.numpy() if voxels.dtype == torch.bool else voxels.float().numpy()
    check_type(name, voxels, np.ndarray, "torch.Tensor or numpy.ndarray of shape (R, R, R)")
    if voxels.ndim != 3 or len(set(voxels.shape)) != 1 or voxels.shape[0] == 0:
        raise ValueError(f"`{name}` must have shape (R, R, R) with R >= 1, got {voxels.shape}")
    return voxels


def _occupancy(voxels: Any, threshold: float, name: str) -> np.ndarray:
    """Bool ``(R, R, R)``: a bool grid as is, a float one as ``voxels >= threshold`` (the IoU convention)."""
    grid = as_voxel_grid(voxels, name)
    return grid if grid.dtype == np.bool_ else grid >= threshold


def _viewpoints(viewpoints: Any) -> np.ndarray:
    vp = check_viewpoints(torch.as_tensor(np.asarray(viewpoints, dtype=np.float64)))
    if vp.ndim != 2 or vp.shape[0] == 0:
        raise ValueError(
            f"`viewpoints` must have shape (V, 2) with V >= 1 (yaw, pitch in degrees), got {tuple(vp.shape)}"
        )
    return vp.numpy()


# --------------------------------------------------------------------------------------------- meshes
def voxel_mesh(occupancy: Any, colors: np.ndarray | None = None) -> trimesh.Trimesh:
    """The exposed faces of the occupied cells of a grid, as a mesh in world coordinates.

    Cell ``(i, j, k)`` of an ``R^3`` grid is the cube ``[i / R - .5, (i + 1) / R - .5] x ...``,
    so the mesh of a full grid is the cube ``[-0.5, 0.5]^3``. Faces between two occupied cells are left out;
    every face is wound counter-clockwise seen from outside (outward normals, for the renderer's lighting).

    Args:
        occupancy: ``(R, R, R)`` bool (or 0/1) grid.
        colors: ``(R, R, R, 3)`` uint8 RGB per cell (each face takes its cell's colour), or ``None``.

    Returns:
        a :class:`trimesh.Trimesh` with 2 triangles (4 own vertices) per exposed face; no faces for an empty grid.

    Raises:
        TypeError: ``occupancy`` is neither a tensor nor an ndarray.
        ValueError: ``occupancy`` is not ``(R, R, R)`` with ``R >= 1``, or ``colors`` is not ``(R, R, R, 3)``.

    Example:
        >>> mesh = voxel_mesh(np.ones((2, 2, 2), bool))  # a full grid: the cube [-0.5, 0.5]^3
        >>> len(mesh.faces), mesh.bounds.tolist()  # 4 exposed cell faces per side, 2 triangles each
        (48, [[-0.5, -0.5, -0.5], [0.5, 0.5, 0.5]])
    """
    occ = as_voxel_grid(occupancy, "occupancy") != 0
    r = occ.shape[0]
    if colors is not None:
        colors = np.asarray(colors)
        if colors.shape != (r, r, r, 3):
            raise ValueError(f"`colors` must have shape {(r, r, r, 3)} (RGB per cell), got {colors.shape}")
    padded = np.pad(occ, 1)
    quads, face_colors = [], []
    corners = np.array([[0, 0], [1, 0], [1, 1], [0, 1]])  # counter-clockwise in (u, v): normal +axis
    for axis in range(3):
        u, v = (axis + 1) % 3, (axis + 2) % 3  # e_u x e_v = e_axis
        for sign in (1, -1):
            neighbour = np.roll(padded, -sign, axis=axis)[1:-1, 1:-1, 1:-1]
            cells = np.argwhere(occ & ~neighbour)  # (F, 3)
            if len(cells) == 0:
                continue
            order = corners if sign > 0 else corners[::-1]
            quad = np.repeat(cells[:, None, :], 4, axis=1).astype(np.float64)  # (F, 4, 3)
            quad[:, :, axis] += 1.0 if sign > 0 else 0.0
            quad[:, :, u] += order[:, 0]
            quad[:, :, v] += order[:, 1]
            quads.append(quad)
            if colors is not None:
                face_colors.append(colors[cells[:, 0], cells[:, 1], cells[:, 2]])
    if not quads:
        return trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), np.int64), process=False)
    quad = np.concatenate(quads)
    vertices = quad.reshape(-1, 3) / r - 0.5
    base = np.arange(len(quad))[:, None] * 4
    faces = np.concatenate([base + np.array([0, 1, 2]), base + np.array([0, 2, 3])], axis=1).reshape(-1, 3)
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    if colors is not None:
        rgb = np.repeat(np.concatenate(face_colors), 2, axis=0).astype(np.uint8)  # two triangles per quad
        visual = cast(trimesh.visual.ColorVisuals, mesh.visual)  # a mesh made from arrays has colour visuals
        visual.face_colors = np.concatenate([rgb, np.full((len(rgb), 1), 255, np.uint8)], axis=1)
    return mesh


def _render_mesh(
    mesh: trimesh.Trimesh, viewpoints: np.ndarray, image_size: int, background: Sequence[int]
) -> np.ndarray:
    if len(mesh.faces) == 0:
        return np.tile(np.asarray(background, np.uint8), (len(viewpoints), image_size, image_size, 1))
    from lightning_vtr.renderer import composite, get_renderer  # imports pyrender / OpenGL on first use only

    return composite(get_renderer(image_size).render(mesh, viewpoints), cast("tuple[int, int, int]", tuple(background)))


# --------------------------------------------------------------------------------------------- pictures
def render_voxels(
    voxels: Any,
    viewpoints: Any = DISPLAY_VIEWPOINTS,
    *,
    threshold: float = DEFAULT_THRESHOLD,
    colors: np.ndarray | None = None,
    image_size: int = 128,
    background: Sequence[int] = _WHITE,
) -> np.ndarray:
    """Render a voxel grid as cubes with the package's renderer (perspective camera, camera-attached light).

    Args:
        voxels: ``(R, R, R)`` occupancy probabilities (occupied where ``>= threshold``) or a bool grid.
        viewpoints: ``(V, 2)`` (yaw, pitch) in **degrees**.
        threshold: binarisation threshold of a float grid (:data:`~lightning_vtr.protocol.DEFAULT_THRESHOLD`).
        colors: ``(R, R, R, 3)`` uint8 RGB per cell; ``None`` paints every cell :data:`VOXEL_COLOR`.
        image_size: side ``S`` of each picture in pixels.
        background: RGB (0-255) behind the object.

    Returns:
        ``(V, S, S, 3)`` uint8; an empty grid gives pictures of the background alone.

    Raises:
        TypeError: ``voxels`` is not a tensor or ndarray, ``threshold`` not a number or ``image_size`` not an int.
        ValueError: ``voxels`` is not ``(R, R, R)``, ``colors`` not ``(R, R, R, 3)``, ``viewpoints`` not a
            non-empty ``(V, 2)`` of finite angles, ``threshold`` outside ``[0, 1]`` or ``image_size < 1``.

    Example::

        pictures = render_voxels(predicted[0], [[-45.0, 30.0], [135.0, 30.0]], image_size=128)  # (2, 128, 128, 3)
        Image.fromarray(pictures[0]).save("prediction.png")
    """
    threshold = check_float("threshold", threshold, minimum=0.0, maximum=1.0)
    image_size = check_int("image_size", image_size, minimum=1)
    occ = _occupancy(voxels, threshold, "voxels")
    if colors is None:
        colors = np.broadcast_to(np.asarray(VOXEL_COLOR, np.uint8), (*occ.shape, 3))
    return _render_mesh(voxel_mesh(occ, colors), _viewpoints(viewpoints), image_size, background)


def error_labels(predicted: Any, target: Any, *, threshold: float = DEFAULT_THRESHOLD) -> np.ndarray:
    """Per-voxel error class of a prediction against the ground truth.

    Args:
        predicted: ``(R, R, R)`` probabilities (occupied where ``>= threshold``) or a bool grid.
        target: ``(R, R, R)`` ground truth (occupied where ``>= 0.5``) or a bool grid.
        threshold: binarisation threshold of ``predicted``.

    Returns:
        ``(R, R, R)`` uint8: :data:`EMPTY`, :data:`CORRECT` (in both), :data:`FALSE_POSITIVE` (predicted only) or
        :data:`FALSE_NEGATIVE` (ground truth only).

    Raises:
        TypeError: a grid is neither a tensor nor an ndarray, or ``threshold`` is not a number.
        ValueError: a grid is not ``(R, R, R)``, the two shapes differ, or ``threshold`` is outside ``[0, 1]``.

    Example:
        >>> predicted = torch.zeros(2, 2, 2)
        >>> predicted[0] = 0.9  # four voxels predicted
        >>> target = torch.zeros(2, 2, 2)
        >>> target[0, 0, 0] = target[1, 1, 1] = 1.0  # two voxels in the ground truth
        >>> np.bincount(error_labels(predicted, target).ravel())  # EMPTY, CORRECT, FALSE_POSITIVE, FALSE_NEGATIVE
        array([3, 1, 3, 1])
    """
    threshold = check_float("threshold", threshold, minimum=0.0, maximum=1.0)
    pred = _occupancy(predicted, threshold, "predicted")
    gt = _occupancy(target, 0.5, "target")
    if pred.shape != gt.shape:
        raise ValueError(f"`predicted` and `target` must have the same shape, got {pred.shape} and {gt.shape}")
    labels = np.zeros(pred.shape, np.uint8)
    labels[pred & gt] = CORRECT
    labels[pred & ~gt] = FALSE_POSITIVE
    labels[~pred & gt] = FALSE_NEGATIVE
    return labels


def _label_colors(labels: np.ndarray) -> np.ndarray:
    lut = np.zeros((4, 3), np.uint8)
    for label, rgb in ERROR_COLORS.items():
        lut[label] = rgb
    return lut[labels]


def render_error(
    predicted: Any,
    target: Any,
    viewpoints: Any = DISPLAY_VIEWPOINTS,
    *,
    threshold: float = DEFAULT_THRESHOLD,
    image_size: int = 128,
    background: Sequence[int] = _WHITE,
) -> np.ndarray:
    """Render the union of prediction and ground truth, each cell coloured by :func:`error_labels`.

    Correct cells are grey, false positives (predicted, not there) vermillion, false negatives (missed) blue
    (:data:`ERROR_COLORS`).

    Args:
        predicted: ``(R, R, R)`` occupancy probabilities (occupied where ``>= threshold``) or a bool grid.
        target: ``(R, R, R)`` ground truth (occupied where ``>= 0.5``) or a bool grid.
        viewpoints: ``(V, 2)`` (yaw, pitch) in **degrees**.
        threshold: binarisation threshold of ``predicted``.
        image_size: side ``S`` of each picture in pixels.
        background: RGB (0-255) behind the object.

    Returns:
        ``(V, S, S, 3)`` uint8; two empty grids give pictures of the background alone.

    Raises:
        TypeError: a grid is not a tensor or ndarray, ``threshold`` not a number or ``image_size`` not an int.
        ValueError: a grid is not ``(R, R, R)``, the shapes differ, ``viewpoints`` is not a non-empty ``(V, 2)``
            of finite angles, ``threshold`` is outside ``[0, 1]`` or ``image_size < 1``.

    Example::

        pictures = render_error(predicted[0], target[0], image_size=128)  # (2, 128, 128, 3) at DISPLAY_VIEWPOINTS
        Image.fromarray(pictures[0]).save("error.png")
    """
    labels = error_labels(predicted, target, threshold=threshold)
    image_size = check_int("image_size", image_size, minimum=1)
    mesh = voxel_mesh(labels != EMPTY, _label_colors(labels))
    return _render_mesh(mesh, _viewpoints(viewpoints), image_size, background)


def error_projection_images(
    predicted: Any,
    target: Any,
    viewpoints: Any,
    *,
    threshold: float = DEFAULT_THRESHOLD,
    image_size: int | None = None,
) -> np.ndarray:
    """The paper's error projection (first hit of the binary error volume along each ray, orthographic),
    coloured by which error the ray meets first.

    Computed with :func:`lightning_vtr.selection.projection.error_projection` on a volume holding 1 at false
    positives and 2 at false negatives, so a pixel shows the class of the first error voxel from the camera
    side (vermillion / blue as in :data:`ERROR_COLORS`), light grey where the ray meets the object (either
    grid) but no error, white elsewhere. A view's error score in the paper is the count of coloured pixels.

    Args:
        predicted: as in :func:`error_labels`.
        target: as in :func:`error_labels`.
        threshold: as in :func:`error_labels`.
        viewpoints: ``(V, 2)`` (yaw, pitch) in degrees, e.g. the views a selector chose.
        image_size: output side ``S``; the projection is computed at ``R`` pixels (as the selection does) and
            enlarged by pixel repetition. ``None``: ``R``.

    Returns:
        ``(V, S, S, 3)`` uint8.

    Raises:
        TypeError: a grid is not a tensor or ndarray, ``threshold`` not a number or ``image_size`` not an int.
        ValueError: a grid is not ``(R, R, R)``, the shapes differ, ``viewpoints`` is not a non-empty ``(V, 2)``
            of finite angles, ``threshold`` is outside ``[0, 1]`` or ``image_size < 1``.

    Example:
        A prediction that misses the top filled layer, seen from above and from the side:

        >>> predicted = torch.zeros(4, 4, 4)
        >>> predicted[:, :, :2] = 0.9
        >>> target = torch.zeros(4, 4, 4)
        >>> target[:, :, :3] = 1.0
        >>> images = error_projection_images(predicted, target, [[0.0, 90.0], [0.0, 0.0]])
        >>> images.shape
        (2, 4, 4, 3)
        >>> (images == ERROR_COLORS[FALSE_NEGATIVE]).all(-1).sum(axis=(1, 2))  # blue (missed) pixels per view
        array([4, 2])
    """
    from lightning_vtr.selection.projection import error_projection

    labels = error_labels(predicted, target, threshold=threshold)
    vp = torch.as_tensor(_viewpoints(viewpoints), dtype=torch.float32)
    r = labels.shape[0]
    size = r if image_size is None else check_int("image_size", image_size, minimum=1)
    kind = np.zeros(labels.shape, np.float32)
    kind[labels == FALSE_POSITIVE] = 1.0
    kind[labels == FALSE_NEGATIVE] = 2.0
    volumes = torch.from_numpy(np.stack([kind, (labels != EMPTY).astype(np.float32)]))
    maps = error_projection(volumes, vp).numpy()  # (2, V, R, R): first-hit error class, object silhouette
    out = np.full((*maps.shape[1:], 3), _WHITE, np.uint8)
    out[maps[1] > 0] = _SILHOUETTE
    out[maps[0] == 1.0] = ERROR_COLORS[FALSE_POSITIVE]
    out[maps[0] == 2.0] = ERROR_COLORS[FALSE_NEGATIVE]
    if size != r:
        out = np.stack([np.asarray(Image.fromarray(m).resize((size, size), Image.NEAREST)) for m in out])  # type: ignore[attr-defined]  # PIL sets the alias at runtime
    return out


def display_images(images: Any, normalize: str | None = "auto") -> np.ndarray:
    """Model input images back to displayable RGB.

    Args:
        images: ``(V, 3, H, W)`` float tensor of model input, or ``(V, H, W, 3|4)`` uint8 pictures (returned as
            RGB; RGBA is composited on white).
        normalize: the normalisation the input was made with (``"imagenet"``, ``"pm1"`` or ``None``, as in
            :data:`lightning_vtr.data.transforms.NORMALIZATIONS`), or ``"auto"``: each image stretched to
            ``[0, 1]`` by its own minimum and maximum.

    Returns:
        ``(V, H, W, 3)`` uint8.

    Raises:
        ValueError: ``images`` has another shape, or ``normalize`` is not one of the values above.

    Example:
        >>> pictures = display_images(torch.zeros(2, 3, 4, 4), normalize="pm1")  # 0 in [-1, 1] is mid-grey
        >>> pictures.shape, pictures[0, 0, 0]
        ((2, 4, 4, 3), array([128, 128, 128], dtype=uint8))
    """
    if isinstance(images, np.ndarray) and images.dtype == np.uint8:
        if images.ndim != 4 or images.shape[-1] not in (3, 4):
            raise ValueError(f"`images` must have shape (V, H, W, 3 or 4) as uint8, got {images.shape}")
        if images.shape[-1] == 4:
            from lightning_vtr.renderer import composite

            return composite(images)
        return images
    x = torch.as_tensor(images).detach().cpu().float()
    if x.ndim != 4 or x.shape[1] != 3:
        raise ValueError(f"`images` must have shape (V, 3, H, W), got {tuple(x.shape)}")
    if normalize == "auto":
        low = x.amin(dim=(1, 2, 3), keepdim=True)
        high = x.amax(dim=(1, 2, 3), keepdim=True)
        x = (x - low) / (high - low).clamp_min(1e-8)
    elif normalize == "imagenet":
        from lightning_vtr.data.transforms import IMAGENET_MEAN, IMAGENET_STD

        x = x * torch.tensor(IMAGENET_STD).view(1, 3, 1, 1) + torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1)
    elif normalize == "pm1":
        x = (x + 1.0) / 2.0
    elif normalize is not None:
        raise ValueError(f"`normalize` must be one of 'auto', 'imagenet', 'pm1', None, got {normalize!r}")
    return (x.clamp(0.0, 1.0) * 255.0).round().to(torch.uint8).permute(0, 2, 3, 1).numpy()


# --------------------------------------------------------------------------------------------- the sheet
def _font(size: int) -> ImageFont.ImageFont | ImageFont.FreeTypeFont:
    try:
        return ImageFont.load_default(size=size)
    except TypeError:  # Pillow < 10.1: a fixed bitmap font
        return ImageFont.load_default()


def _caption(viewpoint: Sequence[float]) -> str:
    return f"yaw {viewpoint[0]:.0f}, pitch {viewpoint[1]:.0f}"


def compose_sheet(
    rows: Sequence[tuple[str, Sequence[np.ndarray], Sequence[str]]],
    *,
    title: str | None = None,
    panel_size: int = 128,
    legends: Mapping[str, Sequence[tuple[Sequence[int], str]]] | None = None,
) -> tuple[np.ndarray, dict[str, list[tuple[int, int, int, int]]]]:
    """Lay pictures out in labelled rows: a title line, then per row a label on the left and the panels.

    Args:
        rows: ``(label, panels, captions)``: panels ``(H, W, 3)`` uint8 (resized to ``panel_size`` when they
            differ), one caption per panel (``""`` for none).
        title: the line on top (``None``: no title line).
        panel_size: side of each panel in pixels.
        legends: per row label, ``(rgb, text)`` entries of a colour legend drawn under the label.

    Returns:
        ``(sheet (H, W, 3) uint8, boxes)``: ``boxes[label]`` lists each panel's ``(top, left, bottom, right)``.
        ``H = title + rows x (caption + panel_size + gap)``, ``W = label + max panels x (panel_size + gap)``.

    Raises:
        TypeError: ``panel_size`` is not an int.
        ValueError: ``panel_size < 8``.

    Example:
        >>> panels = [np.zeros((8, 8, 3), np.uint8)] * 2
        >>> sheet, boxes = compose_sheet([("prediction", panels, ["view 0", "view 1"])], panel_size=16)
        >>> sheet.shape
        (38, 156, 3)
        >>> boxes["prediction"]  # (top, left, bottom, right) of each panel
        [(18, 116, 34, 132), (18, 136, 34, 152)]
    """
    panel_size = check_int("panel_size", panel_size, minimum=8)
    gap, label_w, caption_h = 4, 112, 14
    title_h = 22 if title else 0
    cols = max((len(panels) for _, panels, _ in rows), default=1)
    width = label_w + cols * (panel_size + gap) + gap
    height = title_h + len(rows) * (caption_h + panel_size + gap) + gap
    sheet = Image.new("RGB", (width, height), _WHITE)
    draw = ImageDraw.Draw(sheet)
    small, big = _font(11), _font(14)
    if title:
        draw.text((gap, 4), title, fill=(0, 0, 0), font=big)
    boxes: dict[str, list[tuple[int, int, int, int]]] = {}
    for r, (label, panels, captions) in enumerate(rows):
        top = title_h + r * (caption_h + panel_size + gap) + gap
        draw.text((gap, top + caption_h + panel_size // 2 - 20), label, fill=(0, 0, 0), font=big)
        for n, (rgb, text) in enumerate((legends or {}).get(label, ())):
            y = top + caption_h + panel_size // 2 + n * 14
            draw.rectangle((gap, y, gap + 9, y + 9), fill=tuple(int(c) for c in rgb))
            draw.text((gap + 14, y - 1), text, fill=(60, 60, 60), font=small)
        boxes[label] = []
        for c, panel in enumerate(panels):
            left = label_w + c * (panel_size + gap) + gap
            picture = Image.fromarray(np.ascontiguousarray(panel[..., :3]).astype(np.uint8))
            if picture.size != (panel_size, panel_size):
                picture = picture.resize((panel_size, panel_size), Image.BILINEAR)  # type: ignore[attr-defined]  # PIL sets the alias at runtime
            sheet.paste(picture, (left, top + caption_h))
            draw.rectangle(
                (left - 1, top + caption_h - 1, left + panel_size, top + caption_h + panel_size),
                outline=(210, 210, 210),
            )
            caption = captions[c] if c < len(captions) else ""
            if caption:
                draw.text((left, top), caption, fill=(60, 60, 60), font=small)
            boxes[label].append((top + caption_h, left, top + caption_h + panel_size, left + panel_size))
    return np.asarray(sheet), boxes


@overload
def object_sheet(
    predicted: Any,
    target: Any | None = ...,
    images: Any | None = ...,
    *,
    input_viewpoints: Any | None = ...,
    input_captions: Sequence[str] | None = ...,
    selected_viewpoints: Any | None = ...,
    display_viewpoints: Any = ...,
    threshold: float = ...,
    panel_size: int = ...,
    normalize: str | None = ...,
    title: str | None = ...,
    return_boxes: Literal[False] = ...,
) -> np.ndarray: ...
@overload
def object_sheet(
    predicted: Any,
    target: Any | None = ...,
    images: Any | None = ...,
    *,
    input_viewpoints: Any | None = ...,
    input_captions: Sequence[str] | None = ...,
    selected_viewpoints: Any | None = ...,
    display_viewpoints: Any = ...,
    threshold: float = ...,
    panel_size: int = ...,
    normalize: str | None = ...,
    title: str | None = ...,
    return_boxes: Literal[True],
) -> tuple[np.ndarray, dict[str, list[tuple[int, int, int, int]]]]: ...
@overload
def object_sheet(
    predicted: Any,
    target: Any | None = ...,
    images: Any | None = ...,
    *,
    input_viewpoints: Any | None = ...,
    input_captions: Sequence[str] | None = ...,
    selected_viewpoints: Any | None = ...,
    display_viewpoints: Any = ...,
    threshold: float = ...,
    panel_size: int = ...,
    normalize: str | None = ...,
    title: str | None = ...,
    return_boxes: bool = ...,
) -> np.ndarray | tuple[np.ndarray, dict[str, list[tuple[int, int, int, int]]]]: ...
def object_sheet(
    predicted: Any,
    target: Any | None = None,
    images: Any | None = None,
    *,
    input_viewpoints: Any | None = None,
    input_captions: Sequence[str] | None = None,
    selected_viewpoints: Any | None = None,
    display_viewpoints: Any = DISPLAY_VIEWPOINTS,
    threshold: float = DEFAULT_THRESHOLD,
    panel_size: int = 128,
    normalize: str | None = "auto",
    title: str | None = None,
    return_boxes: bool = False,
) -> np.ndarray | tuple[np.ndarray, dict[str, list[tuple[int, int, int, int]]]]:
    """One object's sheet: what the model saw, what it predicted and where it is wrong.

    Rows, top to bottom: ``input views`` (the ``V`` images, captioned with their viewpoints when given);
    ``prediction`` and, with a ``target``, ``ground truth`` and ``error`` (:func:`render_error`) at the
    ``display_viewpoints``; then ``error projection`` (:func:`error_projection_images`) at the
    ``selected_viewpoints`` (e.g. the views a selector chose for the object; default the display viewpoints).

    Args:
        predicted: ``(R, R, R)`` occupancy probabilities.
        target: ``(R, R, R)`` ground truth, or ``None`` (then only the first two rows).
        images: the input views, ``(V, 3, H, W)`` model input or ``(V, H, W, 3|4)`` uint8 (see
            :func:`display_images`), or ``None`` (no input row).
        input_viewpoints: ``(V, 2)`` viewpoints of ``images`` in degrees, for the captions.
        input_captions: captions of ``images`` when there are no viewpoints (e.g. file names).
        selected_viewpoints: ``(n, 2)`` viewpoints in degrees of the error projection row.
        display_viewpoints: ``(D, 2)`` viewpoints in degrees of the rendered rows.
        threshold: binarisation threshold of ``predicted``.
        panel_size: side of every panel in pixels.
        normalize: how ``images`` were normalised (see :func:`display_images`).
        title: the sheet's title line (e.g. ``"chair/0003, spherical: IoU 0.41"``).
        return_boxes: also return the panel boxes of :func:`compose_sheet`.

    Returns:
        ``(H, W, 3)`` uint8 (and the boxes when ``return_boxes``).

    Raises:
        TypeError: a grid is not a tensor or ndarray, or ``threshold`` / ``panel_size`` has the wrong type.
        ValueError: a grid or ``images`` has the wrong shape, a set of viewpoints is not a non-empty ``(V, 2)``
            of finite angles, ``input_viewpoints`` does not give one viewpoint per image, or ``threshold``,
            ``panel_size`` or ``normalize`` is out of range.

    Example::

        sheet = object_sheet(
            predicted[0],  # (R, R, R) probabilities
            target[0],
            batch["images"][0],  # (V, 3, H, W) model input
            input_viewpoints=batch["viewpoints"][0],
            selected_viewpoints=ErrorGuidedSelector.paper().select(predicted[:1], target[:1], ["chair"])[0],
            title="chair/0003",
        )
        Image.fromarray(sheet).save("chair_0003.png")
    """
    display = _viewpoints(display_viewpoints)
    captions = [_caption(v) for v in display]
    rows: list[tuple[str, Sequence[np.ndarray], Sequence[str]]] = []
    if images is not None:
        pictures = display_images(images, normalize)
        if input_viewpoints is not None:
            view_captions = [_caption(v) for v in _viewpoints(input_viewpoints)]
            if len(view_captions) != len(pictures):
                raise ValueError(
                    f"`input_viewpoints` must give one viewpoint per image ({len(pictures)}), got {len(view_captions)}"
                )
        elif input_captions is not None:
            view_captions = [str(c) for c in input_captions]
        else:
            view_captions = [f"view {i}" for i in range(len(pictures))]
        rows.append(("input views", list(pictures), view_captions))
    rows.append(
        ("prediction", list(render_voxels(predicted, display, threshold=threshold, image_size=panel_size)), captions)
    )
    legends: dict[str, Sequence[tuple[Sequence[int], str]]] = {}
    if target is not None:
        rows.append(
            ("ground truth", list(render_voxels(target, display, threshold=0.5, image_size=panel_size)), captions)
        )
        rows.append(
            (
                "error",
                list(render_error(predicted, target, display, threshold=threshold, image_size=panel_size)),
                captions,
            )
        )
        selected = display if selected_viewpoints is None else _viewpoints(selected_viewpoints)
        maps = error_projection_images(predicted, target, selected, threshold=threshold, image_size=panel_size)
        rows.append(("error projection", list(maps), [_caption(v) for v in selected]))
        legends = {"error": _ERROR_LEGEND, "error projection": _PROJECTION_LEGEND}
    sheet, boxes = compose_sheet(rows, title=title, panel_size=panel_size, legends=legends)
    return (sheet, boxes) if return_boxes else sheet


def stack_sheets(sheets: Sequence[np.ndarray], gap: int = 6) -> np.ndarray:
    """Sheets ``(H_i, W_i, 3)`` one under the other on white, ``(sum H_i + gaps, max W_i, 3)`` uint8.

    Args:
        sheets: ``(H_i, W_i, 3)`` uint8 pictures, e.g. from :func:`object_sheet`; each is placed at the left edge.
        gap: white rows between two sheets, in pixels.

    Returns:
        ``(sum H_i + gap * (n - 1), max W_i, 3)`` uint8 for ``n`` sheets.

    Raises:
        ValueError: ``sheets`` is empty.

    Example:
        >>> stack_sheets([np.zeros((10, 20, 3), np.uint8), np.zeros((5, 30, 3), np.uint8)]).shape
        (21, 30, 3)
    """
    if not sheets:
        raise ValueError("`sheets` must hold at least one sheet, got none")
    width = max(s.shape[1] for s in sheets)
    out = np.full((sum(s.shape[0] for s in sheets) + gap * (len(sheets) - 1), width, 3), 255, np.uint8)
    top = 0
    for s in sheets:
        out[top : top + s.shape[0], : s.shape[1]] = s
        top += s.shape[0] + gap
    return out


# --------------------------------------------------------------------------------------------- logging
def _normalization_of(trainer: L.Trainer | None) -> str | None:
    transform = getattr(getattr(trainer, "datamodule", None), "transform", None) if trainer is not None else None
    return getattr(transform, "normalize", "auto") if transform is not None else "auto"


def log_validation_sheets(
    pl_module: L.LightningModule,
    batch: Mapping[str, Any],
    predicted: Tensor,
    *,
    max_objects: int = 4,
    selector: ViewSelector | None = None,
    threshold: float = DEFAULT_THRESHOLD,
    panel_size: int = 96,
    tag: str = "val/sheets",
) -> np.ndarray | None:
    """Log the sheets (:func:`object_sheet`) of the first few objects of a validation batch to the trainer's
    loggers, one picture with a sheet per object, through :func:`lightning_vtr.utils.image_logging.log_image`.

    Meant for a model's ``on_validation_epoch_end``, with the first validation batch and its predictions kept
    by ``validation_step``. Only global rank 0 draws and logs; nothing is drawn in the sanity check. The error
    projection row shows the views ``selector`` (default: the paper's ``ErrorGuidedSelector.paper()``) picks for each
    object, seeded by the epoch: what the augmentation would synthesize for it next.

    Args:
        pl_module: the LightningModule, attached to a Trainer.
        batch: the validation batch: ``"images"`` ``(B, V, 3, H, W)`` model input (the datamodule's
            normalisation is undone for display), ``"voxels"`` ``(B, R, R, R)`` ground truth and, optionally,
            ``"viewpoints"`` ``(B, V, 2)`` in degrees (the captions).
        predicted: ``(B, R, R, R)`` occupancy probabilities for the batch.
        max_objects: objects drawn (the first ones of the batch).
        selector: a :class:`~lightning_vtr.selection.base.ViewSelector` for the error projection row.
        threshold: binarisation threshold of ``predicted``.
        panel_size: side of each panel in pixels.
        tag: the image's name in the loggers.

    Returns:
        the logged ``(H, W, 3)`` uint8 picture, or ``None`` where nothing was drawn (another rank, the sanity
        check, no trainer).

    Raises:
        TypeError: ``max_objects`` is not an int.
        ValueError: ``max_objects < 1``, ``batch`` lacks ``images`` or ``voxels``, or the shapes do not fit
            together.

    Example::

        class Model(L.LightningModule):
            def validation_step(self, batch, batch_idx):
                if batch_idx == 0:  # keep the first batch and its predictions
                    self._sheet_batch = (batch, self.predict_voxels(batch["images"]).detach())

            def on_validation_epoch_end(self):
                log_validation_sheets(self, *self._sheet_batch, max_objects=4)
    """
    max_objects = check_int("max_objects", max_objects, minimum=1)
    try:
        trainer = pl_module.trainer
    except RuntimeError:  # not attached to a Trainer
        return None
    if trainer is None or trainer.sanity_checking or not trainer.is_global_zero:
        return None
    missing = [key for key in ("images", "voxels") if key not in batch]
    if missing:
        raise ValueError(f"`batch` must hold 'images' and 'voxels', got keys {sorted(batch)} (missing {missing})")
    images, target, viewpoints = batch["images"], batch["voxels"], batch.get("viewpoints")
    if images.ndim != 5 or predicted.ndim != 4 or target.shape != predicted.shape or len(images) != len(predicted):
        raise ValueError(
            "`batch['images']`, `predicted` and `batch['voxels']` must have shapes (B, V, 3, H, W), (B, R, R, R) "
            f"and (B, R, R, R), got {tuple(images.shape)}, {tuple(predicted.shape)} and {tuple(target.shape)}"
        )
    from lightning_vtr.metrics.functional import voxel_iou
    from lightning_vtr.utils.image_logging import log_image

    n = min(max_objects, len(images))
    predicted = predicted[:n].detach().float().cpu()
    target = target[:n].detach().float().cpu()
    if selector is None:
        from lightning_vtr.selection.error_guided import ErrorGuidedSelector

        selector = ErrorGuidedSelector.paper()
    generator = torch.Generator().manual_seed(int(trainer.current_epoch))
    selected = selector.select(predicted, target, ["object"] * n, generator=generator)
    normalize = _normalization_of(trainer)
    ious = voxel_iou(predicted, target, thresholds=(threshold,))[:, 0].tolist()
    sheets = []
    for i in range(n):
        sheets.append(
            object_sheet(
                predicted[i],
                target[i],
                images[i],
                input_viewpoints=None if viewpoints is None else viewpoints[i].detach().cpu(),
                selected_viewpoints=selected[i],
                threshold=threshold,
                panel_size=panel_size,
                normalize=normalize,
                title=f"epoch {trainer.current_epoch}, object {i}: IoU@{threshold:g} {ious[i]:.3f}",
            )
        )
    picture = stack_sheets(sheets)
    log_image(trainer, tag, picture, step=trainer.global_step)
    return picture
