"""The ``ViewSelector`` interface the augmentation callback calls."""

from __future__ import annotations

import abc
import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor

from lightning_vtr.protocol import DEFAULT_THRESHOLD
from lightning_vtr.utils.validation import check_probabilities

#: The hint of a model whose predictions (queried by VIAT and the input score) are not probabilities.
_PROBABILITIES_HINT = (
    "at the selector's candidate views; did predict_voxels return logits? apply torch.sigmoid to them; "
    "non-finite values mean the model diverged"
)

__all__ = ["SelectionContext", "ViewSelector", "check_categories", "view_set_losses"]


def check_categories(categories: list[str], batch: int) -> list[str]:
    """Check that ``categories`` names one category per object of a batch of ``batch``; returns it.

    Every selector's :meth:`ViewSelector.select` takes the names alongside ``(B, R, R, R)`` grids.

    Args:
        categories: one category name per object.
        batch: the number of objects ``B``.

    Returns:
        ``categories`` itself, unchanged.

    Raises:
        TypeError: ``categories`` is a single string (a common slip) or has no length.
        ValueError: its length is not ``batch``.

    Example:
        >>> check_categories(["chair", "table"], 2)
        ['chair', 'table']
    """
    if isinstance(categories, str) or not hasattr(categories, "__len__"):
        raise TypeError(
            f"`categories` must be a sequence of names, one per object, got {type(categories).__name__} {categories!r}"
        )
    if len(categories) != batch:
        raise ValueError(f"`categories` must have one entry per object, got {len(categories)} for a batch of {batch}")
    return categories


@dataclass
class SelectionContext:
    """What the callback can offer a selector beyond predictions and targets.

    Selectors that search viewpoints by querying the model (VIAT) or learn from it (MVTN) use it;
    the error-guided, Random and Nature selectors ignore it.

    Attributes:
        model: the reconstruction model (a :class:`~lightning_vtr.protocol.ReconstructionModel`), in eval mode.
        synthesizer: a :class:`~lightning_vtr.synthesis.base.Synthesizer` able to render candidate views.
        requests: one :class:`~lightning_vtr.synthesis.base.SynthesisRequest` per object (targets empty).
        transform: turns ``(T, H, W, 4)`` uint8 RGBA images into model input ``(T, 3, h, w)`` float.
        loss_fn: per-object reconstruction loss ``(pred (B, R, R, R), target (B, R, R, R)) -> (B,)``.
        device: where the model lives.

    Example::

        # what ErrorGuidedViewAugmentation builds for a selector with ``needs_context``
        context = SelectionContext(
            model=pl_module,
            synthesizer=synthesizer,
            requests=requests,  # one SynthesisRequest per object of the batch
            transform=datamodule.transform,
            loss_fn=lambda pred, target: F.binary_cross_entropy(pred, target, reduction="none").flatten(1).mean(1),
            device=pl_module.device,
        )
        views = VIATSelector().select(predicted, target, categories, context=context)  # (B, 3, 2) degrees
    """

    model: Any
    synthesizer: Any
    requests: list
    transform: Callable[[np.ndarray], Tensor]
    loss_fn: Callable[[Tensor, Tensor], Tensor]
    device: torch.device


@torch.no_grad()
def view_set_losses(sets: Tensor, target: Tensor, context: SelectionContext, batch_size: int | None = None) -> Tensor:
    """Loss ``(B, P)`` of the model given each object's images from each of its view sets ``(B, P, V, 2)`` (degrees).

    One synthesizer call renders every view of every object (``context.requests``, one per object); the model
    predicts from ``(N, V, 3, h, w)`` batches of at most ``batch_size`` sets (``None``: all at once), and
    ``context.loss_fn`` compares each prediction with its object's ``target (B, R, R, R)``. VIAT scores its
    candidate distributions with it, ``ErrorGuidedSelector(score="input")`` its single-view bins.

    Raises:
        ValueError: a request count other than ``B``, or a synthesizer that returns another number of objects
            or of images per object.
    """
    batch, pop, views = sets.shape[:3]
    if len(context.requests) != batch:
        raise ValueError(
            f"`context.requests` must hold one SynthesisRequest per object: expected {batch}, got {len(context.requests)}"
        )
    requests = [
        dataclasses.replace(req, target_viewpoints=sets[b].reshape(pop * views, 2).to(torch.float32))
        for b, req in enumerate(context.requests)
    ]
    images = context.synthesizer.synthesize(requests)
    if len(images) != batch or any(len(img) != pop * views for img in images):
        raise ValueError(
            f"The synthesizer returned {[len(img) for img in images]} images for {batch} objects of "
            f"{pop * views} views each"
        )
    inputs = torch.stack([torch.as_tensor(context.transform(np.asarray(img))) for img in images])
    inputs = inputs.reshape(batch * pop, views, *inputs.shape[2:]).to(context.device)
    reference = target.to(context.device).repeat_interleave(pop, dim=0)
    chunk = batch_size or inputs.shape[0]
    losses = []
    for start in range(0, inputs.shape[0], chunk):
        pred = context.model.predict_voxels(inputs[start : start + chunk])
        check_probabilities("predict_voxels", pred.detach(), _PROBABILITIES_HINT)  # like the callback's own check
        losses.append(torch.as_tensor(context.loss_fn(pred, reference[start : start + chunk])).reshape(-1))
    return torch.cat(losses).reshape(batch, pop).detach().cpu()


class ViewSelector(abc.ABC):
    """Chooses new input viewpoints for a batch of objects.

    ``select`` sees the model's predictions and the ground truth (selectors that ignore them, such as
    Random and Nature, still take them so the callback treats every strategy alike). A subclass implements
    :meth:`select` and sets the class attributes below; selectors that learn across calls also override
    :meth:`state_dict` and :meth:`load_state_dict` so their state is checkpointed.

    Example:
        A selector that always looks at the object from the front, 30 degrees up:

        >>> class FrontViews(ViewSelector):
        ...     num_views = 1
        ...     def select(self, predicted, target, categories, generator=None, context=None):
        ...         check_categories(categories, predicted.shape[0])
        ...         return torch.tensor([0.0, 30.0]).expand(predicted.shape[0], 1, 2)
        >>> FrontViews().select(torch.rand(2, 4, 4, 4), torch.zeros(2, 4, 4, 4), ["chair", "table"]).shape
        torch.Size([2, 1, 2])
    """

    #: Number of viewpoints returned per object.
    num_views: int = 3
    #: Occupancy threshold of the predictions: selectors that binarise them (error-guided, MVTN) set it, and
    #: the callback measures each object's voxel error (``mean_error``, ``generate_for="error"``) at it.
    threshold: float = DEFAULT_THRESHOLD
    #: Whether the callback should store selections in a per-category viewpoint pool and train on
    #: view sets drawn from it (the paper's error-guided method), rather than on the selections directly.
    uses_pool: bool = False
    #: Whether ``select`` needs a :class:`SelectionContext` (the model and synthesizer).
    needs_context: bool = False
    #: Whether the selector learns across objects (VIAT's mixtures, MVTN's network) or compares them
    #: (``ErrorGuidedSelector(relative=True)``): the callback then calls
    #: ``select`` once per epoch with all searched objects, on global rank 0, and broadcasts the result and
    #: the selector's state so every rank stays identical. Stateless selectors are called per object, sharded.
    batched: bool = False

    @abc.abstractmethod
    def select(
        self,
        predicted: Tensor,
        target: Tensor,
        categories: list[str],
        generator: torch.Generator | None = None,
        context: SelectionContext | None = None,
    ) -> Tensor:
        """Viewpoints ``(B, num_views, 2)`` in degrees for predictions / targets ``(B, R, R, R)``.

        Args:
            predicted: ``(B, R, R, R)`` occupancy probabilities in ``[0, 1]``.
            target: ``(B, R, R, R)`` ground-truth occupancy in ``{0, 1}``.
            categories: ``B`` category names, one per object.
            generator: the random source of a stochastic selector (``None``: torch's global one).
            context: the model and synthesizer, for a selector with :attr:`needs_context`; else ``None``.

        Returns:
            ``(B, num_views, 2)`` (yaw, pitch) in degrees.
        """

    def settings(self) -> dict[str, Any]:
        """The effective settings of this selector, by constructor argument name.

        Every value is a plain JSON value (number, string, bool, ``None``, list, or a dict of them), with every
        default resolved, so that two selectors with equal settings (and the same class) select alike. The class
        name is not included. A subclass returns all of its constructor arguments; this base returns none.

        Returns:
            ``{argument: value}``, in constructor order.

        Example:
            >>> from lightning_vtr.selection import RandomSelector
            >>> RandomSelector(num_views=2).settings()
            {'num_views': 2, 'mode': 'area', 'yaw_range': [-180.0, 180.0], 'pitch_range': [-90.0, 90.0]}
        """
        return {}

    def __repr__(self) -> str:
        """``ClassName(arg=value, ...)`` from :meth:`settings`."""
        items = ", ".join(f"{name}={value!r}" for name, value in self.settings().items())
        return f"{type(self).__name__}({items})"

    def state_dict(self) -> dict[str, Any]:
        """Learned state to checkpoint (empty for stateless selectors)."""
        return {}

    def load_state_dict(self, state: dict[str, Any]) -> None:  # noqa: B027 (optional: stateless selectors keep it)
        """Restore what :meth:`state_dict` returned."""
