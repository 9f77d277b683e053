"""The per-category viewpoint pool of the paper (Sec. "Viewpoint pool").

Selected view sets transfer between objects of one category, so training samples draw a view set found
on *another* object of the same category; the pool keeps every searched object's set for that.
"""

from __future__ import annotations

import json
from collections import OrderedDict
from pathlib import Path
from typing import Any, Literal

import torch
from torch import Tensor

from lightning_vtr.geometry import check_viewpoints, normalize_viewpoints, sample_uniform_viewpoints
from lightning_vtr.utils.limits import read_json
from lightning_vtr.utils.validation import check_choice, check_int, check_type

__all__ = ["ViewpointPool"]

_STATE_VERSION = 1


class ViewpointPool:
    """View sets ``(n, 2)`` (yaw, pitch in degrees) selected on each searched object, grouped by category.

    Every :meth:`add` appends a set (an object searched in several epochs contributes several sets).
    :meth:`sample` draws one set of the requested category uniformly among the sets found on *other*
    objects (the paper's transferability argument; with ``prefer_others=False``, among all the category's
    sets, the object's own included, as the released code does); if the category only holds sets of the
    requesting object, among those; if the category is
    empty or unknown, ``num_views`` uniform viewpoints (``fallback`` mode). With a ``capacity``, each
    category keeps its ``capacity`` most recent sets (first in, first out), so old selections made by an
    earlier model age out. With ``refresh``, the selection round of
    :class:`~lightning_vtr.callback.ErrorGuidedViewAugmentation` empties the pool before it adds the round's sets,
    so the pool holds only what the current model gets wrong.

    Everything is deterministic given a seeded ``torch.Generator``: one ``randint`` draw per sample from a
    non-empty category, ``sample_uniform_viewpoints`` otherwise. :meth:`state_dict` /
    :meth:`load_state_dict` restore the exact contents and order, hence the same samples.

    Args:
        capacity: most sets kept per category; ``None`` keeps all.
        num_views: ``n``, the size of every view set.
        fallback: uniform sampler for empty categories: ``"area"`` (uniform on the sphere) or ``"angle"``.
        prefer_others: draw from sets found on other objects of the category when there are any.
        refresh: empty the pool at the start of every selection round (:meth:`start_round`); ``False`` keeps every
            earlier round's sets (the paper's pool).

    Raises:
        TypeError: ``capacity`` or ``num_views`` is not an int.
        ValueError: naming the argument and the bad value.

    Example:
        >>> pool = ViewpointPool(num_views=3)
        >>> pool.add("chair", "c1", torch.tensor([[0.0, 30.0], [120.0, 30.0], [-120.0, 30.0]]))  # degrees
        >>> pool.sample("chair", object_id="c2", generator=torch.Generator().manual_seed(0))  # the set found on c1
        tensor([[   0.,   30.],
                [ 120.,   30.],
                [-120.,   30.]])
        >>> pool.sample("table", generator=torch.Generator().manual_seed(0)).shape  # empty: uniform viewpoints
        torch.Size([3, 2])
    """

    def __init__(
        self,
        capacity: int | None = None,
        num_views: int = 3,
        fallback: Literal["area", "angle"] = "area",
        prefer_others: bool = True,
        refresh: bool = False,
    ) -> None:
        self.capacity = None if capacity is None else check_int("capacity", capacity, minimum=1)
        self.num_views = check_int("num_views", num_views, minimum=1)
        self.fallback = check_choice("fallback", fallback, ("area", "angle"))
        self.prefer_others = check_type("prefer_others", prefer_others, bool)
        self.refresh = check_type("refresh", refresh, bool)
        # category -> list of (object id, (n, 2) float32 view set), oldest first
        self._entries: OrderedDict[str, list[tuple[str, Tensor]]] = OrderedDict()

    # ------------------------------------------------------------------------------------ contents
    def add(self, category: str, object_id: str, viewpoints: Tensor) -> None:
        """Store the view set ``viewpoints (num_views, 2)`` (degrees) selected on ``object_id``.

        Yaw is wrapped and pitch clamped; ids are stored as ``str``.
        """
        vp = check_viewpoints(viewpoints)
        if tuple(vp.shape) != (self.num_views, 2):
            raise ValueError(
                f"`viewpoints` of object {object_id!r} must have shape ({self.num_views}, 2), got {tuple(vp.shape)}"
            )
        sets = self._entries.setdefault(str(category), [])
        sets.append((str(object_id), normalize_viewpoints(vp.detach().cpu()).to(torch.float32)))
        if self.capacity is not None and len(sets) > self.capacity:
            del sets[: len(sets) - self.capacity]

    def clear(self) -> None:
        """Forget every stored set (a pool rebuilt each epoch from the current model starts here)."""
        self._entries.clear()

    def start_round(self) -> None:
        """Called before a selection round adds its sets: :meth:`clear` with ``refresh``, nothing otherwise."""
        if self.refresh:
            self.clear()

    def extend(self, categories: list[str], object_ids: list[str], viewpoints: Tensor) -> None:
        """:meth:`add` a batch: ``viewpoints (B, num_views, 2)`` with ``B`` categories and object ids."""
        vp = check_viewpoints(viewpoints)
        if vp.ndim != 3 or not (len(categories) == len(object_ids) == vp.shape[0]):
            raise ValueError(
                f"`viewpoints` must have shape (B, {self.num_views}, 2) with B = len(categories) = len(object_ids), "
                f"got {tuple(vp.shape)} with {len(categories)} categories and {len(object_ids)} object ids"
            )
        for category, object_id, views in zip(categories, object_ids, vp):
            self.add(category, object_id, views)

    def categories(self) -> list[str]:
        """Categories holding at least one set, in order of first insertion."""
        return [cat for cat, sets in self._entries.items() if sets]

    def view_sets(self, category: str) -> tuple[list[str], Tensor]:
        """Object ids and view sets ``(m, num_views, 2)`` of ``category``, oldest first."""
        sets = self._entries.get(str(category), [])
        if not sets:
            return [], torch.zeros(0, self.num_views, 2)
        return [oid for oid, _ in sets], torch.stack([vp for _, vp in sets])

    def __len__(self) -> int:
        """Total number of stored view sets."""
        return sum(len(sets) for sets in self._entries.values())

    def settings(self) -> dict[str, Any]:
        """The constructor arguments, JSON-serialisable: ``capacity``, ``num_views``, ``fallback``,
        ``prefer_others``, ``refresh``.

        Example:
            >>> ViewpointPool(refresh=True).settings()
            {'capacity': None, 'num_views': 3, 'fallback': 'area', 'prefer_others': True, 'refresh': True}
        """
        return {
            "capacity": self.capacity,
            "num_views": self.num_views,
            "fallback": self.fallback,
            "prefer_others": self.prefer_others,
            "refresh": self.refresh,
        }

    def __repr__(self) -> str:
        """``ViewpointPool(capacity=None, num_views=3, ...)``: the settings (the stored sets are not shown)."""
        return f"{type(self).__name__}({', '.join(f'{k}={v!r}' for k, v in self.settings().items())})"

    # ------------------------------------------------------------------------------------ sampling
    def sample(self, category: str, object_id: str | None = None, generator: torch.Generator | None = None) -> Tensor:
        """One view set ``(num_views, 2)`` in degrees for an object of ``category``.

        Prefers sets found on objects other than ``object_id`` (unless ``prefer_others`` is off); falls back
        to the object's own sets, then to uniform viewpoints when the category is empty.
        """
        sets = self._entries.get(str(category), [])
        if not sets:
            return sample_uniform_viewpoints(self.num_views, mode=self.fallback, generator=generator).to(torch.float32)
        mixed = object_id is None or not self.prefer_others
        others = sets if mixed else [s for s in sets if s[0] != str(object_id)]
        choices = others or sets
        index = int(torch.randint(len(choices), (1,), generator=generator))
        return choices[index][1].clone()

    def sample_batch(
        self, categories: list[str], object_ids: list[str] | None = None, generator: torch.Generator | None = None
    ) -> Tensor:
        """:meth:`sample` for each object, in order: ``(B, num_views, 2)``."""
        ids = [None] * len(categories) if object_ids is None else list(object_ids)
        if len(ids) != len(categories):
            raise ValueError(f"`object_ids` must match `categories` in length, got {len(ids)} and {len(categories)}")
        if not categories:
            return torch.zeros(0, self.num_views, 2)
        return torch.stack([self.sample(c, o, generator) for c, o in zip(categories, ids)])

    # --------------------------------------------------------------------------------- persistence
    def state_dict(self) -> dict[str, Any]:
        """Plain python types and tensors: ``{"version", "capacity", "num_views", "fallback", "entries"}``.

        ``entries`` maps each category (insertion order) to ``{"object_ids": [str], "viewpoints": (m, n, 2)}``.
        """
        entries = {}
        for category in self.categories():
            ids, views = self.view_sets(category)
            entries[category] = {"object_ids": ids, "viewpoints": views.clone()}
        return {
            "version": _STATE_VERSION,
            "capacity": self.capacity,
            "num_views": self.num_views,
            "fallback": self.fallback,
            "prefer_others": self.prefer_others,
            "entries": entries,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Replace the contents with those of :meth:`state_dict` (also accepts the JSON form's lists)."""
        for field in ("num_views", "entries"):
            if field not in state:
                raise KeyError(f"ViewpointPool state is missing {field!r}; got keys {sorted(state)}")
        if state["num_views"] != self.num_views:
            raise ValueError(
                f"ViewpointPool state holds view sets of {state['num_views']} views, this pool expects {self.num_views}"
            )
        self.capacity = state.get("capacity", self.capacity)
        self.fallback = state.get("fallback", self.fallback)
        self.prefer_others = bool(state.get("prefer_others", self.prefer_others))
        self._entries = OrderedDict()
        for category, entry in state["entries"].items():
            views = torch.as_tensor(entry["viewpoints"], dtype=torch.float32).reshape(-1, self.num_views, 2)
            ids = [str(i) for i in entry["object_ids"]]
            if len(ids) != views.shape[0]:
                raise ValueError(
                    f"ViewpointPool state for category {category!r}: {len(ids)} object ids but {views.shape[0]} view sets"
                )
            self._entries[str(category)] = [(oid, vp.clone()) for oid, vp in zip(ids, views)]

    def to_json(self, path: str | Path) -> None:
        """Write :meth:`state_dict` as human-readable JSON (viewpoints as nested lists of degrees)."""
        state = self.state_dict()
        state["entries"] = {
            cat: {"object_ids": e["object_ids"], "viewpoints": e["viewpoints"].tolist()}
            for cat, e in state["entries"].items()
        }
        from lightning_vtr.utils.io import atomic_write_json

        atomic_write_json(path, state)

    @classmethod
    def from_json(cls, path: str | Path) -> ViewpointPool:
        """Read a pool written by :meth:`to_json`."""
        try:
            state = read_json(path)
        except json.JSONDecodeError as err:
            raise ValueError(f"{path} is not a ViewpointPool JSON file: {err}") from None
        pool = cls(capacity=state.get("capacity"), num_views=state["num_views"], fallback=state.get("fallback", "area"))
        pool.load_state_dict(state)
        return pool
