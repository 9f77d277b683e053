"""The ``ViewSelector`` interface the augmentation callback calls."""

from __future__ import annotations

import abc
from typing import Any

import torch
from torch import Tensor

__all__ = ["ViewSelector"]


class ViewSelector(abc.ABC):
    """Chooses new input viewpoints for a batch of objects.

    ``select`` sees the model's predictions and the ground truth (selectors that ignore them, such as
    Random and Nature, still take them so the callback treats every strategy alike).
    """

    #: Number of viewpoints returned per object.
    num_views: int = 3

    @abc.abstractmethod
    def select(
        self,
        predicted: Tensor,
        target: Tensor,
        categories: list[str],
        generator: torch.Generator | None = None,
    ) -> Tensor:
        """Viewpoints ``(B, num_views, 2)`` in degrees for predictions / targets ``(B, R, R, R)``."""

    def state_dict(self) -> dict[str, Any]:
        """Learned state to checkpoint (empty for stateless selectors)."""
        return {}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore what :meth:`state_dict` returned."""
