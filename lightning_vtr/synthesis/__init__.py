"""View synthesis: images of an object at requested viewpoints (mesh rendering, Zero-1-to-3, views rendered
once into the dataset), with caching."""

from __future__ import annotations

from typing import TYPE_CHECKING

from lightning_vtr.utils.exports import lazy_exports

if TYPE_CHECKING:  # what type checkers, IDEs and the API reference read
    from lightning_vtr.synthesis.base import SynthesisRequest, Synthesizer
    from lightning_vtr.synthesis.cache import CachedSynthesizer, SynthesisCache
    from lightning_vtr.synthesis.pose import nearest_source_view, relative_pose
    from lightning_vtr.synthesis.prerendered import PrerenderedSynthesizer, prerender_views
    from lightning_vtr.synthesis.render import RenderSynthesizer
    from lightning_vtr.synthesis.zero123 import Zero123CheckpointError, Zero123Synthesizer
else:  # at run time each name is imported from its module on first use
    __getattr__, __dir__ = lazy_exports(
        __name__,
        {
            "lightning_vtr.synthesis.base": ["SynthesisRequest", "Synthesizer"],
            "lightning_vtr.synthesis.cache": ["CachedSynthesizer", "SynthesisCache"],
            "lightning_vtr.synthesis.pose": ["nearest_source_view", "relative_pose"],
            "lightning_vtr.synthesis.prerendered": ["PrerenderedSynthesizer", "prerender_views"],
            "lightning_vtr.synthesis.render": ["RenderSynthesizer"],
            "lightning_vtr.synthesis.zero123": ["Zero123CheckpointError", "Zero123Synthesizer"],
        },
    )

__all__ = [
    "CachedSynthesizer",
    "PrerenderedSynthesizer",
    "RenderSynthesizer",
    "SynthesisCache",
    "SynthesisRequest",
    "Synthesizer",
    "Zero123CheckpointError",
    "Zero123Synthesizer",
    "nearest_source_view",
    "prerender_views",
    "relative_pose",
]
