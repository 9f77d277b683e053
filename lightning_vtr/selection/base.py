"""The ``ViewSelector`` interface the augmentation callback calls."""

from __future__ import annotations

import abc
import dataclasses
import enum
import inspect
import os
from collections.abc import Callable, Mapping
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

__all__ = [
    "SelectionContext",
    "ViewSelector",
    "check_categories",
    "check_selection",
    "constructor_settings",
    "json_setting",
    "view_set_losses",
]


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


def json_setting(value: Any) -> Any:
    """``value`` as a plain JSON value, for a selector's :meth:`ViewSelector.settings`.

    ``None``, bools, ints, floats and strings are kept; tuples, lists and sets become lists, mappings dicts with
    string keys (each element converted alike); a NumPy or torch number or array becomes its Python value or
    nested list, an ``Enum`` its value, a path its string. A class or function becomes its import path
    ``module.Name``; an object with a ``settings()`` method (a selector, a score) becomes
    ``{"class_path": ..., "init_args": its settings}``; any other object its ``repr``, or its class path when
    its class has no ``repr`` of its own (the default one holds a memory address, which would differ between
    two runs of the same selector).

    Args:
        value: a constructor argument's value.

    Returns:
        A value :func:`json.dumps` writes as it is.

    Example:
        >>> json_setting((1, 2.5, "a")), json_setting({"lamp": torch.tensor(20.0)})
        ([1, 2.5, 'a'], {'lamp': 20.0})
        >>> json_setting(torch.nn.functional.relu), json_setting(object())
        ('torch.nn.functional.relu', 'builtins.object')
    """
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    if isinstance(value, enum.Enum):
        return json_setting(value.value)
    if isinstance(value, (Tensor, np.ndarray, np.generic)):
        return json_setting(value.tolist())
    if isinstance(value, Mapping):
        return {str(k): json_setting(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_setting(v) for v in value]
    if isinstance(value, (set, frozenset)):
        return sorted((json_setting(v) for v in value), key=repr)
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    if isinstance(value, type) or inspect.isroutine(value):
        return f"{value.__module__}.{value.__qualname__}"
    settings = getattr(value, "settings", None)
    if callable(settings):
        return {"class_path": f"{type(value).__module__}.{type(value).__qualname__}", "init_args": settings()}
    if type(value).__repr__ is object.__repr__:
        return f"{type(value).__module__}.{type(value).__qualname__}"
    return repr(value)


def constructor_settings(obj: object) -> dict[str, Any]:
    """The arguments of ``type(obj).__init__`` read back from ``obj``, as scikit-learn's ``get_params`` reads them.

    Each named argument (not ``*args`` / ``**kwargs``) is read from the attribute of its name, or else of
    ``_name``, and converted by :func:`json_setting`; an argument stored under neither name is left out (store it
    under its own name, or override :meth:`ViewSelector.settings`, to have it recorded).

    Args:
        obj: a selector (or any object built from its constructor's arguments).

    Returns:
        ``{argument: JSON value}``, in constructor order; empty for a class without an ``__init__`` of its own.

    Example:
        >>> class Above:
        ...     def __init__(self, pitch=60.0, yaws=(0, 90), *, jitter=None):
        ...         self.pitch, self._yaws, self.jitter = pitch, yaws, jitter
        >>> constructor_settings(Above(pitch=45.0))
        {'pitch': 45.0, 'yaws': [0, 90], 'jitter': None}
    """
    try:
        parameters = list(inspect.signature(type(obj).__init__).parameters.values())[1:]  # without `self`
    except (TypeError, ValueError):  # a constructor without a signature (a builtin's)
        return {}
    out: dict[str, Any] = {}
    for parameter in parameters:
        if parameter.kind in (parameter.VAR_POSITIONAL, parameter.VAR_KEYWORD):
            continue
        for attribute in (parameter.name, f"_{parameter.name}"):
            try:
                value = getattr(obj, attribute)
            except AttributeError:
                continue
            out[parameter.name] = json_setting(value)
            break
    return out


def check_selection(selector: ViewSelector, views: Any, batch: int) -> Tensor:
    """Check what ``selector.select`` returned for ``batch`` objects: the callback calls it right after each call.

    The contract of :meth:`ViewSelector.select`: a floating-point (or integer) tensor of shape
    ``(batch, selector.num_views, 2)`` holding finite (yaw, pitch) angles in degrees, every pitch in ``[-90, 90]``
    (a yaw may be any finite angle; it is wrapped).

    Args:
        selector: the selector that returned ``views``.
        views: its return value.
        batch: the number of objects it was asked about.

    Returns:
        ``views`` as a floating-point tensor (an integer one converted).

    Raises:
        ValueError: one line naming the selector's class, what the contract expects and what it returned: another
            type, shape or dtype, a NaN / infinite angle or a pitch outside ``[-90, 90]`` (with the first such
            object and view).

    Example:
        >>> class Front(ViewSelector):
        ...     num_views = 1
        ...     def select(self, predicted, target, categories, generator=None, context=None):
        ...         return torch.tensor([0.0, 30.0]).expand(predicted.shape[0], 2)
        >>> check_selection(Front(), Front().select(torch.rand(2, 4, 4, 4), None, ["a", "b"]), 2)
        Traceback (most recent call last):
        ...
        ValueError: Front.select must return viewpoints of shape (objects, num_views, 2) = (2, 1, 2), got (2, 2)
    """
    name = f"{type(selector).__name__}.select"
    expected = (batch, selector.num_views, 2)
    if not isinstance(views, Tensor):
        raise ValueError(
            f"{name} must return a torch.Tensor of shape (objects, num_views, 2) = {expected} (yaw, pitch in "
            f"degrees), got {type(views).__module__}.{type(views).__qualname__}"
        )
    if tuple(views.shape) != expected:
        raise ValueError(
            f"{name} must return viewpoints of shape (objects, num_views, 2) = {expected}, got {tuple(views.shape)}"
        )
    if views.dtype == torch.bool or views.is_complex():
        raise ValueError(f"{name} must return real (yaw, pitch) angles in degrees, got dtype {views.dtype}")
    views = views.detach()
    if not views.is_floating_point():
        views = views.to(torch.get_default_dtype())
    problems = (
        (~torch.isfinite(views).all(dim=-1), "finite (yaw, pitch) angles"),
        ((views[..., 1] < -90.0) | (views[..., 1] > 90.0), "pitches in [-90, 90] degrees"),
    )
    for bad, wanted in problems:
        if bad.any():
            obj, view = (int(i) for i in bad.nonzero()[0])
            values = [float(v) for v in views[obj, view].tolist()]
            raise ValueError(
                f"{name} must return {wanted}, got {values} for object {obj}, view {view} "
                f"({int(bad.sum())} of {bad.numel()} viewpoints)"
            )
    return views


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
            ``(B, num_views, 2)`` (yaw, pitch) in degrees, finite, every pitch in ``[-90, 90]`` (a yaw may be any
            angle; it is wrapped). The callback checks it (:func:`check_selection`) and stops with one line naming
            this class when it is not.
        """

    def settings(self) -> dict[str, Any]:
        """The effective settings of this selector, by constructor argument name.

        Every value is a plain JSON value (number, string, bool, ``None``, list, or a dict of them), with every
        default resolved, so that two selectors with equal settings (and the same class) select alike. The class
        name is not included. The callback records them (``settings.json``, its checkpointed rule, which a resume
        compares) and ``lightning-vtr report`` writes them to ``report.json``.

        This base derives them from the constructor, as scikit-learn's ``get_params`` does
        (:func:`constructor_settings`): each argument of ``__init__`` read back from the attribute of its name (or
        ``_name``), so a selector that stores its arguments under their own names needs no ``settings()`` of its
        own. A subclass overrides it when its arguments are not stored that way.

        Returns:
            ``{argument: value}``, in constructor order.

        Example:
            >>> from lightning_vtr.selection import RandomSelector
            >>> RandomSelector(num_views=2).settings()
            {'num_views': 2, 'mode': 'area', 'yaw_range': [-180.0, 180.0], 'pitch_range': [-90.0, 90.0]}
            >>> class Above(ViewSelector):  # no settings() of its own
            ...     def __init__(self, pitch: float = 60.0, num_views: int = 3):
            ...         self.pitch, self.num_views = pitch, num_views
            ...     def select(self, predicted, target, categories, generator=None, context=None):
            ...         return torch.tensor([0.0, self.pitch]).expand(predicted.shape[0], self.num_views, 2)
            >>> Above(pitch=45.0).settings()
            {'pitch': 45.0, 'num_views': 3}
        """
        return constructor_settings(self)

    def __repr__(self) -> str:
        """``ClassName(arg=value, ...)`` from :meth:`settings`."""
        items = ", ".join(f"{name}={value!r}" for name, value in self.settings().items())
        return f"{type(self).__name__}({items})"

    def state_dict(self) -> dict[str, Any]:
        """Learned state to checkpoint (empty for stateless selectors)."""
        return {}

    def load_state_dict(self, state: dict[str, Any]) -> None:  # noqa: B027 (optional: stateless selectors keep it)
        """Restore what :meth:`state_dict` returned."""
