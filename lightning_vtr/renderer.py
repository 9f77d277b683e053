"""Headless pyrender renderer: RGBA images of a mesh at a batch of viewpoints.

Camera poses come from :func:`lightning_vtr.geometry.camera_pose`, so a rendered view, the error
projection and the Zero-1-to-3 pose all share one definition of a viewpoint ``(yaw, pitch)`` in
degrees. Creating an OpenGL context is slow and contexts leak, so every :class:`Renderer` in a process
draws through one shared :class:`pyrender.OffscreenRenderer`, resized on demand.

Caveat (pyrender with EGL): ``OffscreenRenderer.delete()`` terminates the process's EGL display, which
invalidates every other live context. Do not create and delete private OffscreenRenderers next to this
module's; closing the last :class:`Renderer` deletes the shared one, and the next render makes a new one.
"""

from __future__ import annotations

import os

# pyrender picks its GL platform when OpenGL is first imported; EGL works headless without X.
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import math
import threading
from typing import Any, Literal

import numpy as np
import pyrender
import torch
import trimesh

from lightning_vtr.geometry import DEFAULT_HALF_EXTENT, camera_pose, check_viewpoints
from lightning_vtr.utils.compositing import alpha_composite
from lightning_vtr.utils.validation import check_choice, check_float, check_int

__all__ = [
    "DEFAULT_DISTANCE",
    "DEFAULT_HALF_EXTENT",
    "DEFAULT_YFOV_DEG",
    "Renderer",
    "composite",
    "get_renderer",
]

DEFAULT_YFOV_DEG = math.degrees(2.0 * math.atan(16.0 / 35.0))  # ~49.13
"""Vertical field of view (degrees) of Zero-1-to-3's Objaverse renders (35 mm lens, 32 mm sensor),
so rendered views resemble what the Zero-1-to-3 synthesizer was trained on."""
DEFAULT_DISTANCE = 2.2
"""Camera distance (world units): the top of Zero-1-to-3's range [1.5, 2.2]. At this distance the
bounding sphere of ``[-0.5, 0.5]^3`` (radius sqrt(3)/2) subtends 23.2 degrees of the 24.6-degree
half field of view, so a normalised object is in frame from every viewpoint."""
# DEFAULT_HALF_EXTENT (re-exported): half the side (world units) of the square an orthographic view covers,
# the radius of the bounding sphere of ``[-0.5, 0.5]^3``; defined once in lightning_vtr.geometry so the
# renderer and the error projection cannot drift apart.
_ZNEAR = 0.05

# Key light direction in camera coordinates (x right, y up, looking along -z): from the upper left,
# slightly off the viewing axis, so faces at equal angles left and right of the view get different
# shades; no face visible to the camera is ever lit from behind.
_KEY_LIGHT_DIR = np.array([0.35, -0.45, -1.0]) / np.linalg.norm([0.35, -0.45, -1.0])


class _SharedContext:
    """The process's one OffscreenRenderer (one GL context), recreated after a fork."""

    def __init__(self) -> None:
        self.lock = threading.RLock()
        self.renderer: pyrender.OffscreenRenderer | None = None
        self.pid: int | None = None
        self.users = 0

    def get(self, width: int, height: int) -> pyrender.OffscreenRenderer:
        if self.renderer is None or self.pid != os.getpid():
            # A context inherited through fork() is not usable in the child; drop it without deleting.
            self.renderer = pyrender.OffscreenRenderer(width, height)
            self.pid = os.getpid()
        elif (self.renderer.viewport_width, self.renderer.viewport_height) != (width, height):
            # pyrender reallocates its framebuffers on the next render; the context stays.
            self.renderer.viewport_width = width
            self.renderer.viewport_height = height
        return self.renderer

    def release(self) -> None:
        if self.renderer is not None and self.pid == os.getpid():
            self.renderer.delete()
        self.renderer, self.pid = None, None


_CONTEXT = _SharedContext()
_CACHE: dict[tuple, Renderer] = {}


def _light_pose() -> np.ndarray:
    """Pose (in the camera's frame) of a directional light shining along ``_KEY_LIGHT_DIR``."""
    z = -_KEY_LIGHT_DIR  # pyrender's directional lights shine along their node's -z
    x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    pose = np.eye(4)
    pose[:3, :3] = np.stack([x, np.cross(z, x), z], axis=1)
    return pose


class Renderer:
    """Render a mesh at a batch of viewpoints with a fixed camera model and lighting.

    Args:
        image_size: output height = width, in pixels.
        camera: ``"perspective"`` (default; field of view ``yfov_deg`` at ``distance``) or
            ``"orthographic"`` (covers ``[-half_extent, half_extent]^2`` of the image plane).
        yfov_deg: perspective vertical (= horizontal) field of view, **degrees**.
        distance: camera distance from the origin, world units.
        half_extent: orthographic half-width, world units.
        ambient: ambient light intensity (0..1) so faces away from the key light stay visible.
        light_intensity: intensity of the directional key light attached to the camera.
        base_color: RGB (0..1) of the material given to meshes that have no colours or material.
        smooth: interpolate vertex normals (``False`` suits the flat faces of CAD models).

    The lighting moves with the camera (a key light from the camera's upper left plus ambient), so
    every view is lit the same way relative to what it sees and no view leaves the object in shadow.

    Raises:
        TypeError: an argument of the wrong type (e.g. a non-integral ``image_size``).
        ValueError: an argument out of range (named in the message, with its value).

    Example:
        >>> import trimesh
        >>> r = get_renderer(64)
        >>> r.render(trimesh.creation.box(extents=(0.5, 0.4, 0.3)), [[30.0, 20.0], [0.0, 90.0]]).shape
        (2, 64, 64, 4)
    """

    def __init__(
        self,
        image_size: int = 256,
        *,
        camera: Literal["perspective", "orthographic"] = "perspective",
        yfov_deg: float = DEFAULT_YFOV_DEG,
        distance: float = DEFAULT_DISTANCE,
        half_extent: float = DEFAULT_HALF_EXTENT,
        ambient: float = 0.3,
        light_intensity: float = 2.0,
        base_color: tuple[float, float, float] = (0.72, 0.72, 0.72),
        smooth: bool = False,
    ) -> None:
        # an integral float (64.0) is accepted as a size, as it always was; anything else that is not a
        # positive integer is refused with the shared message form
        if isinstance(image_size, (float, np.floating)) and float(image_size).is_integer():
            image_size = int(image_size)
        self.image_size = check_int("image_size", image_size, minimum=1)
        self.camera = check_choice("camera", camera, ("perspective", "orthographic"))
        self.yfov_deg = check_float("yfov_deg", yfov_deg, minimum=0.0, maximum=180.0, min_open=True, max_open=True)
        # the camera must stand outside the near plane
        self.distance = check_float("distance", distance, minimum=_ZNEAR, min_open=True)
        self.half_extent = check_float("half_extent", half_extent, minimum=0.0, min_open=True)
        self.ambient = float(ambient)
        self.light_intensity = float(light_intensity)
        if not isinstance(base_color, (tuple, list, np.ndarray)):
            kind = type(base_color).__name__
            raise TypeError(f"`base_color` must be three numbers in [0, 1], got {kind} {base_color!r}")
        if len(base_color) != 3:
            raise ValueError(f"`base_color` must be three numbers in [0, 1], got {base_color!r}")
        self.base_color = tuple(
            check_float(f"base_color[{i}]", c, minimum=0.0, maximum=1.0) for i, c in enumerate(base_color)
        )
        self.smooth = smooth
        self._closed = False
        with _CONTEXT.lock:
            _CONTEXT.users += 1

    # ------------------------------------------------------------------ scene
    def _make_camera(self) -> pyrender.Camera:
        # behind the far side of the object's bounding sphere (radius DEFAULT_HALF_EXTENT), with a margin
        zfar = self.distance + 2.0 * DEFAULT_HALF_EXTENT + 1.0
        if self.camera == "perspective":
            return pyrender.PerspectiveCamera(
                yfov=math.radians(self.yfov_deg), aspectRatio=1.0, znear=_ZNEAR, zfar=zfar
            )
        return pyrender.OrthographicCamera(xmag=self.half_extent, ymag=self.half_extent, znear=_ZNEAR, zfar=zfar)

    def _make_scene(self, mesh: trimesh.Trimesh) -> tuple[pyrender.Scene, pyrender.Node]:
        if not isinstance(mesh, trimesh.Trimesh):
            raise TypeError(f"`mesh` must be a trimesh.Trimesh, got {type(mesh).__name__}")
        if len(mesh.faces) == 0:
            raise ValueError("`mesh` has no triangles; nothing to render")
        material = None
        if (
            mesh.visual is None or not mesh.visual.defined
        ):  # keep vertex/face colours and textures when the mesh has them
            material = pyrender.MetallicRoughnessMaterial(
                baseColorFactor=(*self.base_color, 1.0), metallicFactor=0.0, roughnessFactor=0.8, alphaMode="OPAQUE"
            )
        scene = pyrender.Scene(bg_color=(0.0, 0.0, 0.0, 0.0), ambient_light=(self.ambient,) * 3)
        scene.add(pyrender.Mesh.from_trimesh(mesh, material=material, smooth=self.smooth))
        camera_node = scene.add(self._make_camera(), pose=np.eye(4))
        light = pyrender.DirectionalLight(color=np.ones(3), intensity=self.light_intensity)
        scene.add(light, pose=_light_pose(), parent_node=camera_node)
        return scene, camera_node

    def _poses(self, viewpoints: Any) -> np.ndarray:
        vp = check_viewpoints(torch.as_tensor(np.asarray(viewpoints, dtype=np.float64)))
        if vp.ndim != 2:
            raise ValueError(f"`viewpoints` must have shape (V, 2) (yaw, pitch in degrees), got {tuple(vp.shape)}")
        return camera_pose(vp.double(), self.distance).numpy()

    def _render(self, mesh: trimesh.Trimesh, viewpoints: Any, want_color: bool) -> np.ndarray:
        if self._closed:
            raise RuntimeError("This Renderer was closed; create a new one or call get_renderer()")
        poses = self._poses(viewpoints)
        size = self.image_size
        out = (
            np.zeros((len(poses), size, size, 4), np.uint8)
            if want_color
            else np.zeros((len(poses), size, size), np.float32)
        )
        if len(poses) == 0:
            return out
        scene, camera_node = self._make_scene(mesh)
        # No back-face culling: ShapeNet meshes have flipped and one-sided faces.
        flags = pyrender.RenderFlags.RGBA | pyrender.RenderFlags.SKIP_CULL_FACES
        if not want_color:
            flags = pyrender.RenderFlags.DEPTH_ONLY | pyrender.RenderFlags.SKIP_CULL_FACES
        with _CONTEXT.lock:
            offscreen = _CONTEXT.get(size, size)
            for v, pose in enumerate(poses):
                scene.set_pose(camera_node, pose)  # move the camera; the scene is built once per mesh
                result = offscreen.render(scene, flags=flags)
                if want_color:
                    out[v] = result[0]
                else:
                    out[v] = result
        if want_color:
            out = _unpremultiply(out)
        return out

    # ------------------------------------------------------------------ public API
    def render(self, mesh: trimesh.Trimesh, viewpoints: Any) -> np.ndarray:
        """Render ``mesh`` from each viewpoint.

        Args:
            mesh: a mesh in world coordinates (+Z up, normally inside ``[-0.5, 0.5]^3``).
            viewpoints: ``(V, 2)`` (yaw, pitch) in **degrees** (tensor, array or nested list).

        Returns:
            ``(V, H, W, 4)`` uint8 RGBA with straight (not premultiplied) alpha; alpha is 0 on the
            background and 255 inside the object, intermediate on anti-aliased edges.
        """
        return self._render(mesh, viewpoints, want_color=True)

    def render_depth(self, mesh: trimesh.Trimesh, viewpoints: Any) -> np.ndarray:
        """``(V, H, W)`` float32 depth: distance along the viewing axis from the camera, 0 on the background."""
        return self._render(mesh, viewpoints, want_color=False)

    def close(self) -> None:
        """Stop using the shared GL context; it is deleted when no open Renderer is left."""
        if self._closed:
            return
        self._closed = True
        with _CONTEXT.lock:
            for key, cached in list(_CACHE.items()):
                if cached is self:
                    del _CACHE[key]
            _CONTEXT.users -= 1
            if _CONTEXT.users <= 0:
                _CONTEXT.users = 0
                _CONTEXT.release()

    def __enter__(self) -> Renderer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        cam = f"yfov_deg={self.yfov_deg:.2f}" if self.camera == "perspective" else f"half_extent={self.half_extent:.4f}"
        return f"Renderer(image_size={self.image_size}, camera={self.camera!r}, {cam}, distance={self.distance})"


def _unpremultiply(rgba: np.ndarray) -> np.ndarray:
    """Turn the multisample-resolved colour (blended with a black background) into straight alpha, in place."""
    alpha = rgba[..., 3]
    edge = np.nonzero((alpha > 0) & (alpha < 255))  # only anti-aliased edge pixels need the division
    if edge[0].size:
        a = alpha[edge].astype(np.float32)[:, None]
        rgb = rgba[edge][:, :3].astype(np.float32)
        rgba[..., :3][edge] = np.rint(np.clip(rgb * 255.0 / a, 0.0, 255.0)).astype(np.uint8)
    return rgba


def get_renderer(image_size: int = 256, **kwargs: Any) -> Renderer:
    """The process's cached :class:`Renderer` for this configuration (created on first use).

    All renderers share one GL context, so asking for several sizes or cameras costs no new context.
    Keyword arguments are those of :class:`Renderer`.

    Args:
        image_size: output height = width, in pixels.
        **kwargs: the other (keyword) arguments of :class:`Renderer`, e.g. ``camera="orthographic"``.

    Returns:
        The cached :class:`Renderer` for ``image_size`` and ``kwargs``; a new one when there is none yet or the
        cached one was closed.

    Raises:
        TypeError: an argument of the wrong type, as :class:`Renderer` raises.
        ValueError: an argument out of range (named in the message, with its value), as :class:`Renderer` raises.

    Example:
        >>> get_renderer(64) is get_renderer(64)
        True
        >>> get_renderer(64, camera="orthographic")
        Renderer(image_size=64, camera='orthographic', half_extent=0.8660, distance=2.2)
    """
    # repr() so that list-valued options (e.g. base_color=[...]) can key the cache too.
    key = (int(image_size), tuple(sorted((name, repr(value)) for name, value in kwargs.items())))
    with _CONTEXT.lock:
        renderer = _CACHE.get(key)
        if renderer is None or renderer._closed:
            renderer = Renderer(image_size, **kwargs)
            _CACHE[key] = renderer
        return renderer


def composite(rgba: np.ndarray, background: tuple[int, int, int] = (255, 255, 255)) -> np.ndarray:
    """Alpha-composite straight-alpha RGBA images ``(..., H, W, 4)`` uint8 over a flat colour.

    The ``uint8`` form of :func:`~lightning_vtr.utils.compositing.alpha_composite`, with its inputs checked.

    Args:
        rgba: uint8 RGBA images, any leading dimensions.
        background: RGB in 0..255 (white by default, what Zero-1-to-3 and ShapeNetRendering users expect).

    Returns:
        ``(..., H, W, 3)`` uint8.

    Raises:
        ValueError: ``rgba`` is not ``(..., H, W, 4)`` uint8, or ``background`` not an RGB triple in 0..255.

    Example:
        >>> composite(np.array([[[200, 100, 0, 128]]], dtype=np.uint8), background=(0, 0, 0))[0, 0].tolist()
        [100, 50, 0]
    """
    rgba = np.asarray(rgba)
    if rgba.ndim < 3 or rgba.shape[-1] != 4:
        raise ValueError(f"`rgba` must have shape (..., H, W, 4), got {rgba.shape}")
    if rgba.dtype != np.uint8:
        raise ValueError(f"`rgba` must be uint8, got {rgba.dtype}")
    bg = np.asarray(background, dtype=np.float32)
    if bg.shape != (3,) or (bg < 0).any() or (bg > 255).any():
        raise ValueError(f"`background` must be an RGB triple in 0..255, got {background}")
    return alpha_composite(rgba, bg)
