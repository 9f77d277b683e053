"""The paper's "Nature" comparison strategy: views from an object's natural viewing band."""

from __future__ import annotations

from collections.abc import Mapping

import torch
from torch import Tensor

from lightning_vtr.geometry import clamp_pitch, sample_uniform_viewpoints
from lightning_vtr.selection.base import SelectionContext, ViewSelector, check_categories
from lightning_vtr.selection.projection import check_volume_pair
from lightning_vtr.utils.validation import check_float, check_int, check_range

__all__ = ["NatureSelector"]


class NatureSelector(ViewSelector):
    """Viewpoints "from training objects' natural states" (e.g. cars seen from the side).

    Objects in this package stand upright in a canonical pose, so their natural viewing band is the
    horizon: pitch ``pitch`` (0 by default), yaw uniform in ``yaw_range``. ``pitch`` may be a mapping from
    category to pitch for categories usually seen from above or below; categories missing from the
    mapping use 0. ``pitch_jitter`` spreads the pitch uniformly over ``[pitch - jitter, pitch + jitter]``
    (clamped to [-90, 90]). All angles in degrees; selections are trained on directly
    (``uses_pool = False``).

    Args:
        num_views: ``3`` (default): viewpoints per object.
        pitch: ``0.0`` (default): natural pitch in degrees, or ``{category: pitch}`` (missing categories: 0).
        pitch_jitter: ``0.0`` (default): half-width of the uniform pitch spread, ``>= 0``.
        yaw_range: ``(-180.0, 180.0)`` (default): ``(low, high)`` yaw in degrees, within [-180, 180].

    Raises:
        TypeError: an argument of the wrong type (e.g. a pitch that is not a number).
        ValueError: naming the argument and the bad value.

    Example:
        >>> predicted, target = torch.rand(2, 4, 4, 4), torch.zeros(2, 4, 4, 4)
        >>> views = NatureSelector(pitch={"lamp": 20.0}).select(predicted, target, ["lamp", "car"])
        >>> views.shape
        torch.Size([2, 3, 2])
        >>> views[..., 1]  # pitch in degrees: the lamp's from the mapping, the car's the default 0
        tensor([[20., 20., 20.],
                [ 0.,  0.,  0.]])
    """

    uses_pool = False

    def __init__(
        self,
        num_views: int = 3,
        pitch: float | Mapping[str, float] = 0.0,
        pitch_jitter: float = 0.0,
        yaw_range: tuple[float, float] = (-180.0, 180.0),
    ) -> None:
        self.num_views = check_int("num_views", num_views, minimum=1)
        if isinstance(pitch, Mapping):
            self.pitch: float | dict[str, float] = {
                str(cat): check_float(f"pitch[{cat!r}]", p, minimum=-90.0, maximum=90.0) for cat, p in pitch.items()
            }
        else:
            self.pitch = check_float("pitch", pitch, minimum=-90.0, maximum=90.0)
        self.pitch_jitter = check_float("pitch_jitter", pitch_jitter, minimum=0.0, maximum=180.0)
        self.yaw_range = check_range("yaw_range", yaw_range, -180.0, 180.0, "degrees")

    def pitch_for(self, category: str) -> float:
        """The natural pitch (degrees) of ``category``."""
        if isinstance(self.pitch, dict):
            return self.pitch.get(category, 0.0)
        return self.pitch

    def select(
        self,
        predicted: Tensor,
        target: Tensor,
        categories: list[str],
        generator: torch.Generator | None = None,
        context: SelectionContext | None = None,
    ) -> Tensor:
        """Viewpoints ``(B, num_views, 2)`` in degrees; ``B = 0`` gives an empty result.

        Random draws: all yaws and pitch jitters at once, ``(B * num_views, 2)`` uniforms from ``generator``.
        """
        predicted, _ = check_volume_pair(predicted, target)
        batch = predicted.shape[0]
        check_categories(categories, batch)
        # yaw uniform in the range; the pitch column of this draw is reused as the jitter's uniform
        draw = sample_uniform_viewpoints(
            batch * self.num_views,
            mode="angle",
            yaw_range=self.yaw_range,
            pitch_range=(-90.0, 90.0),
            generator=generator,
        ).view(batch, self.num_views, 2)
        centre = torch.tensor([self.pitch_for(c) for c in categories], dtype=draw.dtype).view(batch, 1)
        pitch = clamp_pitch(centre + self.pitch_jitter * draw[..., 1] / 90.0)
        return torch.stack([draw[..., 0], pitch], dim=-1).to(predicted.device)
