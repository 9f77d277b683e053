"""An on-disk cache of synthesized views, so a re-run or a resumed run does not regenerate them.

Images are keyed by ``(synthesizer config_key, object_id, target viewpoint)``; the viewpoint is normalised
(yaw wrapped into ``[-180, 180)``, pitch clamped) and rounded to ``1e-3`` degree. Layout::

    <root>/<sha256(config_key)[:16]>/config_key.txt
    <root>/<sha256(config_key)[:16]>/<quoted object_id>/<yaw_mdeg>_<pitch_mdeg>.png

Writes go through :func:`lightning_vtr.utils.io.atomic_open` (a uniquely named temporary file in the same
directory, flushed to disk, then renamed over the destination), so a reader (or another DDP rank writing the
same key) never sees a half-written PNG, and a leftover temporary file from a killed run is never mistaken
for a hit. The source images of an object are assumed fixed for a dataset: point
different datasets at different cache roots.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path
from typing import cast
from urllib.parse import quote

import numpy as np
import torch
from PIL import Image
from torch import Tensor

from lightning_vtr.geometry import check_viewpoints
from lightning_vtr.synthesis.base import SynthesisRequest, Synthesizer
from lightning_vtr.utils.io import atomic_open
from lightning_vtr.utils.paths import join_under
from lightning_vtr.utils.validation import check_type

__all__ = ["CachedSynthesizer", "SynthesisCache", "viewpoint_key"]

#: Viewpoints are rounded to this many thousandths of a degree before keying.
_MILLIDEGREES = 1000


def viewpoint_key(viewpoint: Tensor | np.ndarray | tuple[float, float]) -> str:
    """A file-name-safe key ``"<yaw>_<pitch>"`` of one viewpoint, in integer thousandths of a degree.

    The viewpoint (degrees) is normalised (yaw wrapped into ``[-180, 180)``, pitch clamped to ``[-90, 90]``)
    and rounded to ``1e-3`` degree, so equal views key equally: ``(180, 0)`` and ``(-180, 0)`` both give
    ``"-180000_0"``. The cache names its files by it and the Zero-1-to-3 synthesizer derives each view's
    noise seed from it, so a cached view and a regenerated one agree.

    Raises:
        ValueError: ``viewpoint`` is not one finite (yaw, pitch) pair.
    """
    vp = check_viewpoints(torch.as_tensor(np.asarray(viewpoint, dtype=np.float64)), "viewpoint")
    if vp.shape != (2,):
        raise ValueError(f"`viewpoint` must be one (yaw, pitch) pair in degrees, got shape {tuple(vp.shape)}")
    yaw, pitch = (round(float(a) * _MILLIDEGREES) for a in vp)
    # integer arithmetic so 180.0 and -180.0 (and -0.0 and 0.0) land on the same file
    yaw = (yaw + 180 * _MILLIDEGREES) % (360 * _MILLIDEGREES) - 180 * _MILLIDEGREES
    pitch = max(-90 * _MILLIDEGREES, min(90 * _MILLIDEGREES, pitch))
    return f"{yaw}_{pitch}"


class SynthesisCache:
    """PNG files of generated RGBA views under ``root``.

    Args:
        root: cache directory (created on first write).

    Example::

        cache = SynthesisCache("cache/views")
        cache.put("chair_0001", (30.0, 15.0), synthesizer.config_key(), image)  # image: (256, 256, 4) uint8
        cache.get("chair_0001", (30.0, 15.0), synthesizer.config_key()).shape  # (256, 256, 4)
    """

    def __init__(self, root: str | os.PathLike) -> None:
        from lightning_vtr.utils.io import remove_stale_temporaries

        self.root = Path(root)
        remove_stale_temporaries(self.root)  # what a killed run's writes left (files untouched for a minute)

    def config_dir(self, config_key: str) -> Path:
        """The directory holding every image made under ``config_key``.

        Raises:
            TypeError: ``config_key`` is not a string.
            ValueError: ``config_key`` is empty.
        """
        check_type("config_key", config_key, str)
        if not config_key:
            raise ValueError(f"`config_key` must be a non-empty string, got {config_key!r}")
        return self.root / hashlib.sha256(config_key.encode("utf-8")).hexdigest()[:16]

    def path(self, object_id: str, viewpoint: Tensor | tuple[float, float], config_key: str) -> Path:
        """Where the image of ``object_id`` at ``viewpoint`` (yaw, pitch degrees) under ``config_key`` lives.

        Raises:
            TypeError: ``object_id`` or ``config_key`` is not a string.
            ValueError: either is empty, or ``viewpoint`` is not one (yaw, pitch) pair.
        """
        check_type("object_id", object_id, str)
        if not object_id:
            raise ValueError(f"`object_id` must be a non-empty string, got {object_id!r}")
        # quote() makes any id with slashes a single component; join_under refuses "." and ".." (not quoted)
        return join_under(self.config_dir(config_key), quote(object_id, safe=""), f"{viewpoint_key(viewpoint)}.png")

    def get(self, object_id: str, viewpoint: Tensor | tuple[float, float], config_key: str) -> np.ndarray | None:
        """The cached ``(H, W, 4)`` uint8 RGBA image, or ``None`` on a miss (a missing or unreadable file)."""
        path = self.path(object_id, viewpoint, config_key)
        try:
            with Image.open(path) as im:
                return np.asarray(im.convert("RGBA"), dtype=np.uint8).copy()
        except FileNotFoundError:
            return None
        except OSError:
            # a file we cannot decode (disk trouble, manual edits) is regenerated rather than trusted
            return None

    def put(self, object_id: str, viewpoint: Tensor | tuple[float, float], config_key: str, image: np.ndarray) -> Path:
        """Store an ``(H, W, 4)`` uint8 RGBA image atomically; returns its path.

        Raises:
            ValueError: ``image`` is not an ``(H, W, 4)`` uint8 array (or a key argument is bad, see :meth:`path`).
        """
        image = np.asarray(image)
        if image.dtype != np.uint8 or image.ndim != 3 or image.shape[-1] != 4:
            raise ValueError(
                f"`image` must be an (H, W, 4) uint8 RGBA array, got shape {image.shape} and dtype {image.dtype}"
            )
        path = self.path(object_id, viewpoint, config_key)
        key_file = path.parent.parent / "config_key.txt"
        # fsync: a cache entry must survive a crash whole, since a later run trusts every file it finds
        if not key_file.exists():
            with atomic_open(key_file, "wb", fsync=True) as f:
                f.write(config_key.encode("utf-8"))
        with atomic_open(path, "wb", fsync=True) as f:
            Image.fromarray(image, mode="RGBA").save(f, format="PNG")
        return path


class CachedSynthesizer(Synthesizer):
    """Wraps a :class:`Synthesizer` so only views missing from a :class:`SynthesisCache` are generated.

    Every requested target is looked up under the wrapped synthesizer's ``config_key()``; the misses of all
    requests go to the wrapped synthesizer in a single :meth:`~Synthesizer.synthesize` call (each request
    keeping its source views), and its outputs are stored before being returned.

    Args:
        synthesizer: the synthesizer to wrap.
        cache_dir: the cache root (see :class:`SynthesisCache`).

    Example::

        synth = CachedSynthesizer(Zero123Synthesizer.from_pretrained(weights_dir), "cache/zero123")
        images = synth.synthesize(requests)  # generated once; later calls read the cached PNGs
    """

    def __init__(self, synthesizer: Synthesizer, cache_dir: str | os.PathLike) -> None:
        self.synthesizer = check_type("synthesizer", synthesizer, Synthesizer)
        self.cache = SynthesisCache(cache_dir)

    @property
    def image_size(self) -> int:  # type: ignore[override]  # read-only: the wrapped synthesizer's
        return self.synthesizer.image_size

    @property
    def needs_source_images(self) -> bool:  # type: ignore[override]  # read-only: the wrapped synthesizer's
        return self.synthesizer.needs_source_images

    def config_key(self) -> str:
        return self.synthesizer.config_key()

    def synthesize(self, requests: list[SynthesisRequest]) -> list[np.ndarray]:
        """Return cached views where present and generate the rest; one ``(T_i, H, W, 4)`` array per request."""
        key = self.config_key()
        found: list[list[np.ndarray | None]] = []
        misses: list[tuple[int, list[int]]] = []  # (request index, missing target indices)
        for r, req in enumerate(requests):
            targets = check_viewpoints(req.target_viewpoints, "target_viewpoints").reshape(-1, 2)
            hits = [self.cache.get(req.object_id, targets[t], key) for t in range(targets.shape[0])]
            found.append(hits)
            missing = [t for t, h in enumerate(hits) if h is None]
            if missing:
                misses.append((r, missing))

        if misses:
            sub_requests = [
                SynthesisRequest(
                    object_id=requests[r].object_id,
                    category=requests[r].category,
                    source_images=requests[r].source_images,
                    source_viewpoints=requests[r].source_viewpoints,
                    target_viewpoints=torch.as_tensor(requests[r].target_viewpoints).reshape(-1, 2)[missing],
                    mesh_path=requests[r].mesh_path,
                    extra=requests[r].extra,
                )
                for r, missing in misses
            ]
            generated = self.synthesizer.synthesize(sub_requests)
            if len(generated) != len(sub_requests):
                raise RuntimeError(
                    f"{type(self.synthesizer).__name__}.synthesize returned {len(generated)} results "
                    f"for {len(sub_requests)} requests"
                )
            for (r, missing), sub, images in zip(misses, sub_requests, generated):
                if len(images) != len(missing):
                    raise RuntimeError(
                        f"{type(self.synthesizer).__name__}.synthesize returned {len(images)} images for object "
                        f"{sub.object_id!r}, expected {len(missing)}"
                    )
                for j, (t, image) in enumerate(zip(missing, images)):
                    self.cache.put(sub.object_id, sub.target_viewpoints[j], key, np.asarray(image))
                    found[r][t] = np.asarray(image)

        out = []
        for hits in found:
            if hits:
                out.append(np.stack(cast("list[np.ndarray]", hits), axis=0))  # every miss was filled above
            else:
                size = self.image_size
                out.append(np.zeros((0, size, size, 4), dtype=np.uint8))
        return out
