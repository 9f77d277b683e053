"""MVTN: a network that regresses view offsets, trained through a differentiable projection (comparison method).

Hamdi et al. (ICCV 2021) learn per-shape camera viewpoints by back-propagating a downstream loss
through a differentiable renderer. The paper adapts it to reconstruction with voxels instead of point
clouds and 3 views; here the network reads the object's error volume (or its predicted volume) and
moves 3 base views within bounds so that they see as much reconstruction error as possible, measured
by :func:`~lightning_vtr.selection.differentiable_projection.soft_error_projection`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any, Literal

import torch
from torch import Tensor, nn

from lightning_vtr.geometry import wrap_yaw
from lightning_vtr.protocol import DEFAULT_THRESHOLD
from lightning_vtr.selection.base import SelectionContext, ViewSelector, check_categories
from lightning_vtr.selection.differentiable_projection import soft_error_projection
from lightning_vtr.selection.projection import check_volume_pair, error_volume
from lightning_vtr.utils.validation import check_choice, check_float, check_int

__all__ = ["MVTNSelector"]


class _ViewRegressor(nn.Module):
    """``(B, 1, R, R, R)`` volume -> ``(B, V, 2)`` unbounded view parameters (any ``R >= 4``).

    Two strided 3D convolutions and an adaptive pool make the encoder independent of ``R``; the last
    layer starts at zero so an untrained network returns the base views exactly.
    """

    def __init__(self, num_views: int, width: int, hidden: int) -> None:
        super().__init__()
        self.num_views = num_views
        self.encoder = nn.Sequential(
            nn.Conv3d(1, width, kernel_size=3, stride=2, padding=1),
            nn.ReLU(),
            nn.Conv3d(width, 2 * width, kernel_size=3, stride=2, padding=1),
            nn.ReLU(),
            nn.AdaptiveAvgPool3d(4),
            nn.Flatten(),
        )
        self.head = nn.Sequential(nn.Linear(2 * width * 64, hidden), nn.ReLU(), nn.Linear(hidden, 2 * num_views))
        last = self.head[-1]
        assert isinstance(last, nn.Linear)
        nn.init.zeros_(last.weight)
        nn.init.zeros_(last.bias)

    def forward(self, volumes: Tensor) -> Tensor:
        return self.head(self.encoder(volumes)).view(-1, self.num_views, 2)


class MVTNSelector(ViewSelector):
    """Regress bounded offsets of 3 base views from the error volume, maximising the error they cover.

    Views are ``yaw_i = base_yaw_i + max_yaw_offset * tanh(a_i)`` and
    ``pitch_i = 90 tanh(atanh(base_pitch / 90) + b_i)`` (degrees), where ``(a_i, b_i)`` come from a
    small 3D-conv network. The yaw offset is bounded as in MVTN's circular setup (``180 / num_views``
    by default, so the views keep their sectors); the pitch reparameterisation starts at the base
    pitch and reaches any elevation in ``(-90, 90)``. Each :meth:`select` call

    1. computes the error volume ``E`` (:func:`~lightning_vtr.selection.projection.error_volume`),
    2. trains the network for ``steps`` Adam steps on the batch, maximising the mean over objects of
       the summed coverage ``sum_views mean_pixels P(E, view)`` of the soft first-hit projection,
    3. returns the network's views for the batch.

    The network and its optimizer persist across calls (:meth:`state_dict`); their initialisation is
    seeded, so two selectors built with the same ``seed`` behave identically and ``generator`` is not
    used. With DDP each rank trains on its own objects unless the caller merges states.

    Args:
        base_yaw: ``(0.0, 120.0, 240.0)`` (default): the views' base yaws in degrees, one per view;
            :meth:`evenly_spaced` builds them for another number of views.
        base_pitch: ``30.0`` (default): base elevation in degrees, in ``(-90, 90)``.
        max_yaw_offset: ``60.0`` (default: half the spacing of the default base yaws, so the views keep
            their sectors): bound of the yaw offset in degrees.
        steps: ``10`` (default): Adam steps per ``select`` call.
        lr: ``0.01`` (default): Adam learning rate.
        input: ``"error"`` (default: the error volume) or ``"predicted"`` (the prediction): what the
            network reads.
        threshold: ``0.4`` (default, :data:`~lightning_vtr.protocol.DEFAULT_THRESHOLD`): binarisation
            threshold of the prediction for the error volume.
        density: ``5.0`` (default): sharpness of the soft projection, opacity per voxel of error crossed.
        image_size: ``None`` (default: the side ``R`` of the volumes given to :meth:`select`): side of the
            projected maps in pixels.
        width: ``8`` (default): channels of the first convolution (the second has ``2 * width``).
        hidden: ``64`` (default): width of the hidden layer of the MLP head.
        seed: ``0`` (default): seed of the network's initialisation.

    Raises:
        TypeError: an argument of the wrong type (named in the message, with its value).
        ValueError: for a bad count, bound, pitch, learning rate, threshold, density or ``input``.

    Example:
        >>> selector = MVTNSelector(steps=1)
        >>> selector.base_views()  # what the untrained network returns
        tensor([[   0.,   30.],
                [ 120.,   30.],
                [-120.,   30.]])
        >>> predicted = torch.rand(2, 8, 8, 8, generator=torch.Generator().manual_seed(0))
        >>> target = (predicted > 0.5).float()
        >>> selector.select(predicted, target, ["chair", "chair"]).shape  # (B, num_views, 2) degrees
        torch.Size([2, 3, 2])
    """

    uses_pool = False
    #: MVTN learns from the predictions and targets alone; it needs no model or synthesizer.
    needs_context = False
    batched = True

    def __init__(
        self,
        base_yaw: Sequence[float] = (0.0, 120.0, 240.0),
        base_pitch: float = 30.0,
        max_yaw_offset: float = 60.0,
        steps: int = 10,
        lr: float = 1e-2,
        input: Literal["error", "predicted"] = "error",
        threshold: float = DEFAULT_THRESHOLD,
        density: float = 5.0,
        image_size: int | None = None,
        width: int = 8,
        hidden: int = 64,
        seed: int = 0,
    ) -> None:
        steps = check_int("steps", steps, minimum=0)
        width = check_int("width", width, minimum=1)
        hidden = check_int("hidden", hidden, minimum=1)
        values = base_yaw.tolist() if isinstance(base_yaw, Tensor) else list(base_yaw)
        base_yaw = [check_float(f"base_yaw[{i}]", yaw) for i, yaw in enumerate(values)]
        if not base_yaw:
            raise ValueError("`base_yaw` must hold one angle (degrees) per view, got none")
        num_views = len(base_yaw)
        # open interval: the pitch is reparameterised through atanh(base_pitch / 90)
        base_pitch = check_float("base_pitch", base_pitch, minimum=-90.0, maximum=90.0, min_open=True, max_open=True)
        max_yaw_offset = check_float("max_yaw_offset", max_yaw_offset, minimum=0.0, maximum=180.0)
        self.num_views = num_views
        self.base_yaw = torch.tensor(base_yaw, dtype=torch.float32)
        self.base_pitch = base_pitch
        self.max_yaw_offset = max_yaw_offset
        self.steps = steps
        self.lr = check_float("lr", lr, minimum=0.0, min_open=True)
        self.input = check_choice("input", input, ("error", "predicted"))
        self.threshold = check_float("threshold", threshold, minimum=0.0, maximum=1.0)
        self.density = check_float("density", density, minimum=0.0, min_open=True)
        self.image_size = None if image_size is None else check_int("image_size", image_size, minimum=1)
        seed = check_int("seed", seed)
        self.width, self.hidden, self.seed = width, hidden, seed
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)
            self.network = _ViewRegressor(num_views, width, hidden)
        self.optimizer = torch.optim.Adam(self.network.parameters(), lr=lr)

    @classmethod
    def evenly_spaced(cls, num_views: int, **kwargs: Any) -> MVTNSelector:
        """``num_views`` base yaws evenly spaced from 0 degrees, each free to move half the spacing.

        Args:
            num_views: views per object.
            **kwargs: the other constructor arguments.

        Example:
            >>> MVTNSelector.evenly_spaced(4).settings()["base_yaw"], MVTNSelector.evenly_spaced(4).max_yaw_offset
            ([0.0, 90.0, 180.0, 270.0], 45.0)
        """
        num_views = check_int("num_views", num_views, minimum=1)
        spacing = 360.0 / num_views
        return cls(base_yaw=[i * spacing for i in range(num_views)], max_yaw_offset=spacing / 2, **kwargs)

    def select(
        self,
        predicted: Tensor,
        target: Tensor,
        categories: list[str],
        generator: torch.Generator | None = None,
        context: SelectionContext | None = None,
    ) -> Tensor:
        """Train on the batch, then return its views ``(B, num_views, 2)`` in degrees.

        Args:
            predicted: ``(B, R, R, R)`` occupancy probabilities.
            target: ``(B, R, R, R)`` ground truth.
            categories: ``B`` category names (unused; one network serves every category).
            generator: unused (training is deterministic given the seed and the data).
            context: unused.

        Returns:
            ``(B, num_views, 2)`` (yaw, pitch) in degrees, yaw wrapped into ``[-180, 180)``, in the dtype of
            ``predicted``.

        Raises:
            TypeError: ``predicted`` / ``target`` are not float or bool tensors, or ``categories`` is a string.
            ValueError: the grids' shapes differ or are not ``(B, R, R, R)``, ``categories`` does not hold ``B``
                names, or the network predicts non-finite views (training diverged; lower ``lr``).
        """
        # 1. check inputs and build the volumes the network reads and the projection scores
        predicted, target = check_volume_pair(predicted, target)
        check_categories(categories, predicted.shape[0])
        # The callback may call us under no_grad / inference mode; training needs autograd and
        # ordinary (non-inference) tensors.
        with torch.inference_mode(False), torch.enable_grad():
            error = error_volume(predicted.detach().clone(), target.detach().clone(), threshold=self.threshold)
            error = error.float()
            features = (error if self.input == "error" else predicted.detach().clone().float())[:, None]
            self._to_device(error.device)

            # 2. train the network to maximise the error its views cover
            self.network.train()
            for _ in range(self.steps):
                self.optimizer.zero_grad()
                loss = -self.coverage(error, self.views(features)).sum(1).mean()
                loss.backward()
                self.optimizer.step()

            # 3. the trained network's views for this batch
            self.network.eval()
            with torch.no_grad():
                views = self.views(features)
        if not torch.isfinite(views).all():  # the network diverged (e.g. a too large lr): say so, not NaN views
            bad = int((~torch.isfinite(views)).any(-1).sum())
            raise ValueError(
                f"MVTN's network must predict finite views, got {bad} of {views.shape[0] * views.shape[1]} "
                f"non-finite (yaw, pitch) pairs after {self.steps} training steps; lower `lr` (now {self.lr:g})"
            )
        yaw = wrap_yaw(views[..., 0])
        out = torch.stack([yaw, views[..., 1].clamp(-90.0, 90.0)], dim=-1)
        return out.to(predicted.dtype if predicted.is_floating_point() else torch.float32)

    def views(self, volumes: Tensor) -> Tensor:
        """Network views ``(B, V, 2)`` in degrees (yaw not wrapped) for inputs ``(B, 1, R, R, R)``; differentiable."""
        raw = self.network(volumes)
        base_yaw = self.base_yaw.to(raw)
        yaw = base_yaw + self.max_yaw_offset * torch.tanh(raw[..., 0])
        pitch = 90.0 * torch.tanh(math.atanh(self.base_pitch / 90.0) + raw[..., 1])
        return torch.stack([yaw, pitch], dim=-1)

    def coverage(self, error: Tensor, views: Tensor) -> Tensor:
        """Fraction ``(B, V)`` of each view's image covered by projected error, for ``error (B, R, R, R)``."""
        maps = soft_error_projection(error, views, image_size=self.image_size, density=self.density)
        return maps.mean(dim=(-2, -1))

    def base_views(self) -> Tensor:
        """The untrained views ``(num_views, 2)`` in degrees (yaw wrapped)."""
        return torch.stack([wrap_yaw(self.base_yaw), torch.full_like(self.base_yaw, self.base_pitch)], dim=-1)

    def _to_device(self, device: torch.device) -> None:
        # Module.to moves parameters in place but leaves Adam's moment buffers where they were.
        self.network.to(device)
        for state in self.optimizer.state.values():
            for key, value in state.items():
                if isinstance(value, Tensor) and key != "step":
                    state[key] = value.to(device)

    def state_dict(self) -> dict[str, Any]:
        """Network weights and Adam state."""
        return {
            "network": {k: v.detach().cpu().clone() for k, v in self.network.state_dict().items()},
            "optimizer": self.optimizer.state_dict(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict`; an empty dict (an older checkpoint) keeps the seeded initialisation."""
        if not state:
            return
        try:
            self.network.load_state_dict(state["network"])
        except RuntimeError as err:
            raise ValueError(
                "MVTNSelector state does not fit this network (was it saved with another number of base yaws, width or hidden?): "
                f"{err}"
            ) from err
        if "optimizer" in state:
            self.optimizer.load_state_dict(state["optimizer"])
