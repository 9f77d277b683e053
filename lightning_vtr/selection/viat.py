"""VIAT: adversarial viewpoint distributions learned by natural evolution strategies (comparison method).

Ruan et al. (ICCV 2023), building on ViewFool (Dong et al., NeurIPS 2022), treat a viewpoint change
as an attack: they learn a distribution of viewpoints that maximises the model's loss plus an entropy
bonus that keeps the adversarial viewpoints diverse, then train on views drawn from it. The paper
adapts it to multi-view reconstruction with roll fixed: a Gaussian mixture over (yaw, pitch) gives
one adversarial viewpoint and the other two input views sit 120 and 240 degrees of yaw further.
"""

from __future__ import annotations

import math
from typing import Any

import torch
from torch import Tensor

from lightning_vtr.geometry import wrap_yaw
from lightning_vtr.selection.base import SelectionContext, ViewSelector, check_categories, view_set_losses
from lightning_vtr.utils.validation import check_float, check_int

__all__ = ["VIATSelector"]

#: (yaw, pitch) bounds in degrees of the tanh reparameterisation ``v = bound * tanh(z)``.
_BOUNDS = (180.0, 90.0)
#: Clamp on the per-component log standard deviations (pre-tanh units), so that NES can neither
#: collapse a component to a point nor spread it into two piles at the tanh bounds.
_LOG_STD_RANGE = (math.log(0.02), math.log(2.0))
#: Pre-tanh standard deviation of every component at initialisation (about 90 degrees of yaw near 0).
_INIT_STD = 0.5


def _nes_utilities(fitness: Tensor) -> Tensor:
    """Rank-based fitness shaping of NES (Wierstra et al., 2014): ``(P,)`` fitness -> ``(P,)`` utilities.

    The best candidate gets the largest weight, the bottom half none before centring; utilities sum to
    zero, which acts as the baseline, and are invariant to any monotone rescaling of the fitness.
    """
    pop = fitness.numel()
    ranks = torch.empty(pop, dtype=torch.long)
    ranks[torch.argsort(fitness.detach().cpu(), descending=True, stable=True)] = torch.arange(pop)
    raw = (math.log(pop / 2.0 + 1.0) - torch.log(ranks.to(torch.float64) + 1.0)).clamp_min(0.0)
    return (raw / raw.sum() - 1.0 / pop).to(fitness.dtype)


class _Mixture:
    """One category's adversarial distribution: a Gaussian mixture over pre-tanh ``z = (z_yaw, z_pitch)``.

    Viewpoints are ``(yaw, pitch) = (180 tanh z_yaw, 90 tanh z_pitch)`` degrees.
    """

    def __init__(self, num_components: int, lr: float) -> None:
        yaw = -180.0 + (torch.arange(num_components, dtype=torch.float64) + 0.5) * 360.0 / num_components
        mean = torch.stack([torch.atanh(yaw / 180.0), torch.zeros(num_components, dtype=torch.float64)], -1)
        # Components start spread evenly in yaw at pitch 0, with equal weights: deterministic, so every
        # DDP rank starts from the same distribution.
        self.mean = mean.requires_grad_()
        self.log_std = torch.full((num_components, 2), math.log(_INIT_STD), dtype=torch.float64, requires_grad=True)
        self.logits = torch.zeros(num_components, dtype=torch.float64, requires_grad=True)
        self.optimizer = torch.optim.Adam([self.mean, self.log_std, self.logits], lr=lr)

    def sample(self, n: int, generator: torch.Generator | None) -> Tensor:
        """``(n, 2)`` pre-tanh samples (detached) via ``z = mu_k + sigma_k * eps``, ``k ~ softmax(logits)``."""
        with torch.no_grad():
            probs = torch.softmax(self.logits, 0)
            comp = torch.multinomial(probs, n, replacement=True, generator=generator)
            eps = torch.randn(n, 2, generator=generator, dtype=torch.float64)
            return self.mean[comp] + self.log_std[comp].exp() * eps

    def log_prob(self, z: Tensor) -> Tensor:
        """Log density ``(n,)`` of pre-tanh samples ``z (n, 2)`` under the mixture (differentiable)."""
        std = self.log_std.exp()
        normal = -0.5 * ((z[:, None, :] - self.mean) / std) ** 2 - self.log_std - 0.5 * math.log(2.0 * math.pi)
        return torch.logsumexp(torch.log_softmax(self.logits, 0) + normal.sum(-1), dim=1)

    def state_dict(self) -> dict[str, Any]:
        return {
            "mean": self.mean.detach().clone(),
            "log_std": self.log_std.detach().clone(),
            "logits": self.logits.detach().clone(),
            "optimizer": self.optimizer.state_dict(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        with torch.no_grad():
            for name in ("mean", "log_std", "logits"):
                value = torch.as_tensor(state[name], dtype=torch.float64)
                current = getattr(self, name)
                if value.shape != current.shape:
                    raise ValueError(
                        f"VIATSelector state: `{name}` has shape {tuple(value.shape)}, expected {tuple(current.shape)} "
                        "(was it saved with another num_components?)"
                    )
                current.copy_(value)
        if "optimizer" in state:
            self.optimizer.load_state_dict(state["optimizer"])


def _to_viewpoints(z: Tensor) -> Tensor:
    """Pre-tanh ``(..., 2)`` -> (yaw, pitch) in degrees, ``(180 tanh z_0, 90 tanh z_1)``."""
    return torch.tanh(z) * z.new_tensor(_BOUNDS)


class VIATSelector(ViewSelector):
    """Per-category adversarial viewpoint distributions, optimised by NES on the reconstruction loss.

    For each category in the batch, a Gaussian mixture over pre-tanh angles ``z`` defines viewpoints
    ``(yaw, pitch) = (180 tanh z_yaw, 90 tanh z_pitch)`` degrees. Each ``select`` call runs
    ``iterations`` NES steps per category present:

    1. draw ``population`` candidates ``z_i`` (reparameterised: component, then ``mu + sigma * eps``);
    2. fitness ``f_i = mean over the category's objects of loss(model(views at {v_i, v_i + 120, v_i + 240}))
       - entropy_weight * log p(u_i)``, where ``u = (yaw / 180, pitch / 90)`` is the viewpoint on the
       normalised square, so that ``E[-log p(u)]`` is the distribution's entropy in nats (ViewFool's
       regulariser) and does not depend on the angle unit;
    3. NES gradient ``sum_i utility(f_i) grad log p(z_i)`` with rank-based fitness shaping, one Adam
       ascent step on the means, log-stds and mixture logits.

    All candidates of a step, over all categories and objects, go to the synthesizer in one call and
    to the model in one call (or chunks of ``model_batch_size``). Then every object gets one viewpoint
    sampled from its category's distribution plus ``num_views - 1`` more spaced evenly in yaw
    (+120 and +240 degrees for 3 views, the paper's adaptation), at the same pitch.

    Cost per call: ``iterations * population * num_views`` synthesized images and
    ``iterations * population`` model predictions per object (with the defaults, 5 x 8 x 3 = 120 images
    per object). Distributions persist across calls (a warm start each epoch) and are checkpointed by
    :meth:`state_dict`. Categories are independent; with DDP each rank learns from its own objects
    unless the caller merges states.

    Args:
        num_components: ``3`` (default): Gaussian components per category.
        population: ``8`` (default): NES candidates per category and iteration.
        lr: ``0.1`` (default): Adam learning rate on the pre-tanh parameters (0.1 moves a mean up to ~18
            degrees of yaw).
        iterations: ``5`` (default): NES steps per ``select`` call.
        entropy_weight: ``0.1`` (default): ``lambda`` of the entropy bonus (nats on the normalised square).
        num_views: ``3`` (default): views returned per object.
        model_batch_size: ``None`` (default: all candidates at once), or the most view sets per model call.

    Raises:
        TypeError: an argument of the wrong type (named in the message, with its value).
        ValueError: for a non-positive count, a population below 2, or a non-positive rate or negative weight.

    Example::

        selector = VIATSelector(population=8, iterations=5)
        views = selector.select(pred, target, categories, generator=g, context=context)  # (B, 3, 2)
    """

    uses_pool = False
    #: Tells the callback to pass a :class:`SelectionContext` (model, synthesizer, requests).
    needs_context = True
    batched = True

    def __init__(
        self,
        num_components: int = 3,
        population: int = 8,
        lr: float = 0.1,
        iterations: int = 5,
        entropy_weight: float = 0.1,
        num_views: int = 3,
        model_batch_size: int | None = None,
    ) -> None:
        self.num_components = check_int("num_components", num_components, minimum=1)
        # rank-based NES utilities need at least a better and a worse candidate
        self.population = check_int("population", population, minimum=2)
        self.lr = check_float("lr", lr, minimum=0.0, min_open=True)
        self.iterations = check_int("iterations", iterations, minimum=0)
        self.entropy_weight = check_float("entropy_weight", entropy_weight, minimum=0.0)
        self.num_views = check_int("num_views", num_views, minimum=1)
        self.model_batch_size = (
            None if model_batch_size is None else check_int("model_batch_size", model_batch_size, minimum=1)
        )
        self._mixtures: dict[str, _Mixture] = {}

    def select(
        self,
        predicted: Tensor,
        target: Tensor,
        categories: list[str],
        generator: torch.Generator | None = None,
        context: SelectionContext | None = None,
    ) -> Tensor:
        """Optimise the categories' distributions, then sample view sets ``(B, num_views, 2)`` in degrees.

        Args:
            predicted: ``(B, R, R, R)`` (unused: VIAT queries the model itself at candidate views).
            target: ``(B, R, R, R)`` ground-truth voxels, the reference of the loss.
            categories: ``B`` category names.
            generator: CPU generator for every random draw (population and final samples).
            context: must provide ``model``, ``synthesizer``, ``requests`` (one per object),
                ``transform``, ``loss_fn`` and ``device``.

        Raises:
            ValueError: if ``context`` is missing or incomplete, or the sizes disagree.
            TypeError: if ``target`` is not a tensor or ``categories`` is a single string.
        """
        # 1. check inputs
        self._check_inputs(target, categories, context)
        assert context is not None, "_check_inputs refuses a missing context"
        # The callback may call us under no_grad / inference mode; the mixtures are trained with
        # autograd and must stay ordinary tensors.
        with torch.inference_mode(False), torch.enable_grad():
            order = list(dict.fromkeys(categories))  # first-appearance order: deterministic
            for name in order:
                if name not in self._mixtures:
                    self._mixtures[name] = _Mixture(self.num_components, self.lr)

            # 2. NES on every category present
            for _ in range(self.iterations):
                self._nes_step(target, categories, order, generator, context)

            # 3. sample one adversarial viewpoint per object and space the others in yaw
            z = torch.zeros(len(categories), 2, dtype=torch.float64)
            for name in order:
                idx = [b for b, c in enumerate(categories) if c == name]
                z[idx] = self._mixtures[name].sample(len(idx), generator)
            out = self._view_sets(_to_viewpoints(z))
        return out.to(device=target.device, dtype=target.dtype if target.is_floating_point() else torch.float32)

    def distribution(self, category: str) -> dict[str, Tensor]:
        """A category's mixture: ``weights (K,)``, ``means (K, 2)`` in degrees and pre-tanh ``std (K, 2)``."""
        if category not in self._mixtures:
            raise KeyError(
                f"VIATSelector has no distribution for category {category!r}; known: {sorted(self._mixtures)}"
            )
        mix = self._mixtures[category]
        with torch.no_grad():
            return {
                "weights": torch.softmax(mix.logits, 0).clone(),
                "means": _to_viewpoints(mix.mean).clone(),
                "std": mix.log_std.exp().clone(),
            }

    def sample_viewpoints(self, category: str, n: int, generator: torch.Generator | None = None) -> Tensor:
        """``(n, 2)`` adversarial viewpoints in degrees drawn from a category's current distribution."""
        if category not in self._mixtures:
            raise KeyError(
                f"VIATSelector has no distribution for category {category!r}; known: {sorted(self._mixtures)}"
            )
        return _to_viewpoints(self._mixtures[category].sample(n, generator))

    def state_dict(self) -> dict[str, Any]:
        """Per-category mixture parameters and Adam state, plus the settings that shape them."""
        return {
            "num_components": self.num_components,
            "categories": {name: mix.state_dict() for name, mix in self._mixtures.items()},
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict`; an empty dict (an older checkpoint) leaves fresh distributions."""
        if not state:
            return
        saved_k = state.get("num_components", self.num_components)
        if saved_k != self.num_components:
            raise ValueError(
                f"VIATSelector state was saved with num_components={saved_k}, this selector has {self.num_components}"
            )
        self._mixtures = {}
        for name, mix_state in state.get("categories", {}).items():
            mix = _Mixture(self.num_components, self.lr)
            mix.load_state_dict(mix_state)
            self._mixtures[name] = mix

    # ------------------------------------------------------------------------------------- internals
    def _check_inputs(self, target: Tensor, categories: list[str], context: SelectionContext | None) -> None:
        if context is None or context.model is None or context.synthesizer is None:
            raise ValueError(
                "VIATSelector needs a SelectionContext with a model and a synthesizer: it searches adversarial "
                "viewpoints by rendering candidate views and querying the model's loss. Got "
                f"context={'None' if context is None else 'a context without model/synthesizer'}."
            )
        if not isinstance(target, Tensor):
            raise TypeError(f"`target` must be a torch.Tensor of shape (B, R, R, R), got {type(target).__name__}")
        if target.ndim != 4:
            raise ValueError(f"`target` must have shape (B, R, R, R), got {tuple(target.shape)}")
        batch = target.shape[0]
        check_categories(categories, batch)
        if len(context.requests) != batch:
            raise ValueError(
                f"`context.requests` must hold one SynthesisRequest per object: expected {batch}, got {len(context.requests)}"
            )
        if context.transform is None or context.loss_fn is None:
            raise ValueError("VIATSelector needs `context.transform` and `context.loss_fn` to score candidate views")

    def _view_sets(self, first: Tensor) -> Tensor:
        """``(..., 2)`` adversarial viewpoints -> ``(..., num_views, 2)`` spaced by ``360 / num_views`` in yaw."""
        offsets = torch.arange(self.num_views, dtype=first.dtype) * (360.0 / self.num_views)
        yaw = wrap_yaw(first[..., None, 0] + offsets)
        pitch = first[..., None, 1].expand_as(yaw)
        return torch.stack([yaw, pitch], dim=-1)

    def _nes_step(
        self,
        target: Tensor,
        categories: list[str],
        order: list[str],
        generator: torch.Generator | None,
        context: SelectionContext,
    ) -> None:
        pop = self.population
        z = {name: self._mixtures[name].sample(pop, generator) for name in order}
        # Each object is scored at every candidate of its category: (B, P, num_views, 2) view sets.
        sets = torch.stack([self._view_sets(_to_viewpoints(z[c])) for c in categories])
        losses = view_set_losses(sets, target, context, self.model_batch_size)  # (B, P)

        for name in order:
            mix = self._mixtures[name]
            idx = torch.tensor([b for b, c in enumerate(categories) if c == name])
            loss = losses[idx].mean(0).to(torch.float64)  # (P,)
            zc = z[name]
            with torch.no_grad():
                # log p(u) on the normalised square u = tanh(z): change of variables from z.
                log_p_u = mix.log_prob(zc) - torch.log1p(-(torch.tanh(zc) ** 2)).sum(-1)
            fitness = loss - self.entropy_weight * log_p_u
            utilities = _nes_utilities(fitness)
            mix.optimizer.zero_grad()
            # The score-function estimate: its gradient is sum_i u_i grad log p(z_i); Adam minimises,
            # so the sign is flipped to ascend the fitness.
            surrogate = -(utilities * mix.log_prob(zc)).sum()
            surrogate.backward()
            mix.optimizer.step()
            with torch.no_grad():
                mix.log_std.clamp_(*_LOG_STD_RANGE)
