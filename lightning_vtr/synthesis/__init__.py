"""View synthesis: images of an object at requested viewpoints (mesh rendering, Zero-1-to-3), with caching."""

from __future__ import annotations

from lightning_vtr.synthesis.base import SynthesisRequest, Synthesizer
from lightning_vtr.synthesis.cache import CachedSynthesizer, SynthesisCache
from lightning_vtr.synthesis.pose import nearest_source_view, relative_pose
from lightning_vtr.synthesis.render import RenderSynthesizer
from lightning_vtr.synthesis.zero123 import Zero123CheckpointError, Zero123Synthesizer

__all__ = [
    "CachedSynthesizer",
    "RenderSynthesizer",
    "SynthesisCache",
    "SynthesisRequest",
    "Synthesizer",
    "Zero123CheckpointError",
    "Zero123Synthesizer",
    "nearest_source_view",
    "relative_pose",
]
