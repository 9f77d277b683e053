"""Renderer speed: views per second at 128 and 256 pixels, cached GL context vs a fresh one per call.

Run: ``python benchmarks/render_speed.py`` (options: ``--views``, ``--faces``, ``--fresh-calls``).
The mesh is a procedural union of spheres and boxes of a few thousand faces, the size of a procedural
dataset object. The reference in the same run is what a naive port does: create a new
``pyrender.OffscreenRenderer`` (a new GL context) for every call and delete it afterwards.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import pyrender
import torch
import trimesh

from lightning_vtr.data.mesh import normalize_mesh
from lightning_vtr.geometry import camera_pose, sample_uniform_viewpoints
from lightning_vtr.renderer import DEFAULT_DISTANCE, Renderer, get_renderer


def make_mesh(target_faces: int) -> trimesh.Trimesh:
    """A chair-like union of boxes plus icospheres adding up to about ``target_faces`` triangles."""
    parts = [trimesh.creation.box(extents=(0.8, 0.8, 0.1)).apply_translation((0, 0, 0.0))]
    parts += [
        trimesh.creation.box(extents=(0.08, 0.08, 0.6)).apply_translation((x, y, -0.35))
        for x in (-0.35, 0.35)
        for y in (-0.35, 0.35)
    ]
    parts.append(trimesh.creation.box(extents=(0.1, 0.8, 0.8)).apply_translation((-0.35, 0, 0.45)))
    spheres = max(1, (target_faces - 72) // 1280)  # an icosphere of subdivision 3 has 1280 faces
    rng = np.random.default_rng(0)
    parts += [
        trimesh.creation.icosphere(3, radius=0.1).apply_translation(rng.uniform(-0.4, 0.4, 3)) for _ in range(spheres)
    ]
    return normalize_mesh(trimesh.util.concatenate(parts))


def cached_views_per_second(mesh: trimesh.Trimesh, size: int, viewpoints: torch.Tensor) -> float:
    renderer = get_renderer(size)
    renderer.render(mesh, viewpoints[:2])  # warm-up: context creation, shader compilation
    start = time.perf_counter()
    renderer.render(mesh, viewpoints)
    return len(viewpoints) / (time.perf_counter() - start)


def fresh_context_views_per_second(mesh: trimesh.Trimesh, size: int, viewpoints: torch.Tensor) -> float:
    """One new OffscreenRenderer per call (one view per call), as in a naive per-image loop."""
    scene_builder = Renderer(size)
    scene, camera_node = scene_builder._make_scene(mesh)
    poses = camera_pose(viewpoints.double(), DEFAULT_DISTANCE).numpy()
    start = time.perf_counter()
    for pose in poses:
        offscreen = pyrender.OffscreenRenderer(size, size)
        scene.set_pose(camera_node, pose)
        offscreen.render(scene, flags=pyrender.RenderFlags.RGBA)
        offscreen.delete()
    elapsed = time.perf_counter() - start
    scene_builder.close()
    return len(poses) / elapsed


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--views", type=int, default=48, help="views per timed batch")
    parser.add_argument("--faces", type=int, default=4000, help="approximate triangle count of the mesh")
    parser.add_argument("--fresh-calls", type=int, default=8, help="calls timed for the fresh-context reference")
    args = parser.parse_args()

    mesh = make_mesh(args.faces)
    viewpoints = sample_uniform_viewpoints(args.views, generator=torch.Generator().manual_seed(0))
    print(f"mesh: {len(mesh.faces)} faces; perspective camera; {args.views} views per batch")
    # The fresh-context reference runs first: pyrender's OffscreenRenderer.delete() terminates the EGL
    # display, which would invalidate the cached context if it already existed.
    fresh_rates = {
        size: fresh_context_views_per_second(mesh, size, viewpoints[: args.fresh_calls]) for size in (128, 256)
    }
    for size in (128, 256):
        cached = cached_views_per_second(mesh, size, viewpoints)
        fresh = fresh_rates[size]
        print(
            f"{size:>4} px: cached renderer {cached:7.1f} views/s ({1000 / cached:6.1f} ms/view) | "
            f"fresh GL context per call {fresh:6.1f} views/s ({1000 / fresh:6.1f} ms/view) | speed-up x{cached / fresh:.1f}"
        )


if __name__ == "__main__":
    main()
