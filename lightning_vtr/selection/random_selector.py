"""The paper's "Random" comparison strategy: viewpoints drawn uniformly, ignoring the reconstruction."""

from __future__ import annotations

from typing import Literal

import torch
from torch import Tensor

from lightning_vtr.geometry import sample_uniform_viewpoints
from lightning_vtr.selection.base import SelectionContext, ViewSelector
from lightning_vtr.selection.projection import check_volume_pair
from lightning_vtr.utils.validation import check_choice, check_int, check_range

__all__ = ["RandomSelector"]


class RandomSelector(ViewSelector):
    """Uniformly random viewpoints ("standard data augmentation with random viewpoints" in the paper).

    The paper's range is pitch in [-90, 90] and yaw in [-180, 180] (degrees). ``RandomSelector()`` is uniform
    over the covered patch of the sphere (``mode="area"``); the paper's Random, ``RandomSelector(mode="angle")``,
    draws yaw and pitch uniformly in their ranges (dense near the poles on the sphere). Predictions and
    targets are only checked, never used, and the selections are trained on directly (``uses_pool = False``).

    Args:
        num_views: ``3`` (default): viewpoints per object.
        mode: ``"area"`` (default: uniform on the sphere) or ``"angle"`` (uniform yaw and pitch).
        yaw_range: ``(-180.0, 180.0)`` (default): ``(low, high)`` yaw in degrees, within [-180, 180].
        pitch_range: ``(-90.0, 90.0)`` (default): ``(low, high)`` pitch in degrees, within [-90, 90].

    Raises:
        TypeError: an argument of the wrong type (e.g. a range that is not a pair of numbers).
        ValueError: naming the argument and the bad value.

    Example:
        >>> predicted, target = torch.rand(2, 4, 4, 4), torch.zeros(2, 4, 4, 4)
        >>> generator = torch.Generator().manual_seed(0)
        >>> RandomSelector(num_views=3).select(predicted, target, ["chair", "car"], generator=generator).shape
        torch.Size([2, 3, 2])
    """

    uses_pool = False

    def __init__(
        self,
        num_views: int = 3,
        mode: Literal["angle", "area"] = "area",
        yaw_range: tuple[float, float] = (-180.0, 180.0),
        pitch_range: tuple[float, float] = (-90.0, 90.0),
    ) -> None:
        self.num_views = check_int("num_views", num_views, minimum=1)
        self.mode = check_choice("mode", mode, ("angle", "area"))
        self.yaw_range = check_range("yaw_range", yaw_range, -180.0, 180.0, "degrees")
        self.pitch_range = check_range("pitch_range", pitch_range, -90.0, 90.0, "degrees")

    def select(
        self,
        predicted: Tensor,
        target: Tensor,
        categories: list[str],
        generator: torch.Generator | None = None,
        context: SelectionContext | None = None,
    ) -> Tensor:
        """Viewpoints ``(B, num_views, 2)`` in degrees; ``B = 0`` gives an empty result."""
        predicted, _ = check_volume_pair(predicted, target)
        batch = predicted.shape[0]
        views = sample_uniform_viewpoints(
            batch * self.num_views,
            mode=self.mode,
            yaw_range=self.yaw_range,
            pitch_range=self.pitch_range,
            generator=generator,
        )
        return views.view(batch, self.num_views, 2).to(predicted.device)
