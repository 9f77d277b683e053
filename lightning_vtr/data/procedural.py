"""The embedded procedural dataset: furniture, vehicles and objects built from primitives.

Every object is a union (a concatenation, not a boolean union) of trimesh primitives, so it
needs no downloads and is generated deterministically from ``(category, index, seed)``.
Each category has several structural variants (a chair with or without arms, on four legs
or a pedestal, with a solid or slatted back, ...) and random proportions, which gives the
reconstruction models a ShapeNet-like intra-category variety to learn from.

Canonical pose, shared by all categories (it mirrors ShapeNet's aligned pose after the
+Y-up -> +Z-up conversion of :mod:`lightning_vtr.data.mesh`):

* +Z is up; every object stands on (or, for airplanes, is centred above) the ground.
* The object's front faces +X: the side a person sits on (chair, bench, sofa), the foot of a
  bed, the screen of a monitor, the open side of a shelf, the nose of an airplane or car.
  A camera at yaw 0 therefore sees the front.
* Long seating / storage objects (bench, sofa, shelf, table) extend along Y; vehicles and
  beds along X.

Objects are normalised into ``[-0.5, 0.5]^3`` (bounding box centred, longest side 1) by
:func:`lightning_vtr.data.mesh.normalize_mesh`.
"""

from __future__ import annotations

import zlib
from collections.abc import Callable, Sequence
from typing import cast

import numpy as np
import trimesh

from lightning_vtr.data.mesh import normalize_mesh
from lightning_vtr.utils.validation import check_choice, check_int

__all__ = ["CATEGORIES", "make_object", "object_id", "object_variant"]

_SECTIONS = 16  # cylinder facets: enough for a 32^3 grid and 256 px renders, cheap to render


# --------------------------------------------------------------------------------------------
# Primitives. All sizes are in metre-like units before normalisation; centres are (x, y, z).
# --------------------------------------------------------------------------------------------


def _box(extents: Sequence[float], center: Sequence[float]) -> trimesh.Trimesh:
    mesh = trimesh.creation.box(extents=np.asarray(extents, dtype=float))
    mesh.apply_translation(np.asarray(center, dtype=float))
    return mesh


def _rod(p0: Sequence[float], p1: Sequence[float], radius: float) -> trimesh.Trimesh:
    """A cylinder of ``radius`` whose axis runs from ``p0`` to ``p1``."""
    return trimesh.creation.cylinder(radius=radius, segment=np.array([p0, p1], dtype=float), sections=_SECTIONS)


def _vcyl(radius: float, z0: float, z1: float, x: float = 0.0, y: float = 0.0) -> trimesh.Trimesh:
    """A vertical cylinder from height ``z0`` to ``z1``."""
    return _rod((x, y, z0), (x, y, z1), radius)


def _sphere(radius: float, center: Sequence[float]) -> trimesh.Trimesh:
    mesh = trimesh.creation.icosphere(subdivisions=2, radius=radius)
    mesh.apply_translation(np.asarray(center, dtype=float))
    return mesh


def _frustum(r0: float, r1: float, z0: float, z1: float, x: float = 0.0, y: float = 0.0) -> trimesh.Trimesh:
    """A closed solid of revolution about a vertical axis: radius ``r0`` at ``z0``, ``r1`` at ``z1``."""
    profile = np.array([[0.0, z0], [max(r0, 1e-4), z0], [max(r1, 1e-4), z1], [0.0, z1]])
    mesh = trimesh.creation.revolve(profile, sections=_SECTIONS)
    if mesh.volume < 0:  # revolve's winding depends on the profile direction
        mesh.invert()
    mesh.apply_translation((x, y, 0.0))
    return mesh


def _rotated_z(mesh: trimesh.Trimesh, degrees: float, about: Sequence[float]) -> trimesh.Trimesh:
    mesh.apply_transform(trimesh.transformations.rotation_matrix(np.radians(degrees), (0, 0, 1), about))
    return mesh


def _rotated_y(mesh: trimesh.Trimesh, degrees: float, about: Sequence[float]) -> trimesh.Trimesh:
    mesh.apply_transform(trimesh.transformations.rotation_matrix(np.radians(degrees), (0, 1, 0), about))
    return mesh


def _legs(rng: np.random.Generator, half_x: float, half_y: float, z_top: float, inset: float) -> list[trimesh.Trimesh]:
    """Four legs from the floor to ``z_top`` at the corners of a rectangle, square or round."""
    thick = rng.uniform(0.025, 0.05)
    round_legs = rng.random() < 0.5
    parts = []
    for sx in (-1, 1):
        for sy in (-1, 1):
            x, y = sx * (half_x - inset), sy * (half_y - inset)
            if round_legs:
                parts.append(_vcyl(thick * 0.6, 0.0, z_top, x, y))
            else:
                parts.append(_box((thick, thick, z_top), (x, y, z_top / 2)))
    return parts


# --------------------------------------------------------------------------------------------
# Categories. Each builder returns (variant name, parts).
# --------------------------------------------------------------------------------------------

_Builder = Callable[[np.random.Generator], tuple[str, list[trimesh.Trimesh]]]


def _chair(rng: np.random.Generator) -> tuple[str, list[trimesh.Trimesh]]:
    depth, width = rng.uniform(0.4, 0.55), rng.uniform(0.4, 0.55)
    seat_h, seat_t = rng.uniform(0.4, 0.5), rng.uniform(0.03, 0.07)
    back_h = rng.uniform(0.35, 0.6)
    base = rng.choice(["legs", "pedestal"], p=[0.7, 0.3])
    back = rng.choice(["panel", "slats"])
    arms = bool(rng.random() < 0.4)
    parts = [_box((depth, width, seat_t), (0, 0, seat_h - seat_t / 2))]
    if base == "legs":
        parts += _legs(rng, depth / 2, width / 2, seat_h - seat_t, 0.03)
    else:
        parts.append(_vcyl(rng.uniform(0.025, 0.04), 0.05, seat_h - seat_t))
        spoke = rng.uniform(0.22, 0.3)
        for k in range(5):  # a five-star office-chair base
            leg = _box((spoke, 0.04, 0.04), (spoke / 2, 0, 0.03))
            parts.append(_rotated_z(leg, 72.0 * k, (0, 0, 0)))
    back_t = rng.uniform(0.03, 0.06)
    back_x = -depth / 2 + back_t / 2
    tilt = rng.uniform(0.0, 12.0)  # degrees the backrest leans back (toward -X)
    pivot = (back_x, 0.0, seat_h)
    if back == "panel":
        panel = _box((back_t, width, back_h), (back_x, 0, seat_h + back_h / 2))
        parts.append(_rotated_y(panel, -tilt, pivot))
    else:
        n_slats = int(rng.integers(3, 6))
        rail_h = rng.uniform(0.05, 0.1)
        parts.append(_rotated_y(_box((back_t, width, rail_h), (back_x, 0, seat_h + back_h - rail_h / 2)), -tilt, pivot))
        for y in np.linspace(-width / 2 + 0.02, width / 2 - 0.02, n_slats):
            slat = _box((back_t * 0.8, 0.03, back_h), (back_x, y, seat_h + back_h / 2))
            parts.append(_rotated_y(slat, -tilt, pivot))
    if arms:
        arm_h = rng.uniform(0.18, 0.25)
        for sy in (-1, 1):
            y = sy * (width / 2 - 0.02)
            parts.append(_box((depth * 0.85, 0.05, 0.04), (-depth * 0.075, y, seat_h + arm_h)))
            parts.append(_box((0.04, 0.04, arm_h), (depth * 0.3, y, seat_h + arm_h / 2)))
    return f"{base}-{back}{'-arms' if arms else ''}", parts


def _table(rng: np.random.Generator) -> tuple[str, list[trimesh.Trimesh]]:
    length, depth = rng.uniform(0.8, 1.8), rng.uniform(0.5, 0.9)
    height, top_t = rng.uniform(0.45, 0.8), rng.uniform(0.03, 0.07)
    top = rng.choice(["rect", "round"], p=[0.7, 0.3])
    base = rng.choice(["legs", "pedestal", "trestle"])
    z_under = height - top_t
    if top == "round":
        radius = depth * rng.uniform(0.6, 0.9)
        parts = [_vcyl(radius, z_under, height)]
        half_x = half_y = radius * 0.7
    else:
        parts = [_box((depth, length, top_t), (0, 0, height - top_t / 2))]
        half_x, half_y = depth / 2, length / 2
    if base == "legs":
        parts += _legs(rng, half_x, half_y, z_under, 0.05)
        if rng.random() < 0.4:  # a lower shelf between the legs
            parts.append(_box((2 * half_x - 0.08, 2 * half_y - 0.08, 0.025), (0, 0, z_under * rng.uniform(0.2, 0.4))))
    elif base == "pedestal":
        parts.append(_vcyl(rng.uniform(0.04, 0.08), 0.03, z_under))
        parts.append(_frustum(min(half_x, half_y) * rng.uniform(0.6, 1.0), 0.06, 0.0, 0.06))
    else:
        panel_t = rng.uniform(0.04, 0.07)
        for sy in (-1, 1):
            parts.append(_box((2 * half_x * 0.7, panel_t, z_under), (0, sy * (half_y * 0.8), z_under / 2)))
        parts.append(_box((0.05, 2 * half_y * 0.8, 0.06), (0, 0, z_under * 0.3)))
    return f"{top}-{base}", parts


def _lamp(rng: np.random.Generator) -> tuple[str, list[trimesh.Trimesh]]:
    kind = rng.choice(["floor", "table", "desk"])
    base_r = rng.uniform(0.1, 0.18)
    base_h = rng.uniform(0.02, 0.05)
    parts = [
        _vcyl(base_r, 0.0, base_h) if rng.random() < 0.6 else _box((2 * base_r, 2 * base_r, base_h), (0, 0, base_h / 2))
    ]
    stem_r = rng.uniform(0.01, 0.02)
    if kind == "floor":
        stem_top = rng.uniform(1.2, 1.7)
        parts.append(_vcyl(stem_r, base_h, stem_top))
        shade_h = rng.uniform(0.2, 0.35)
        parts.append(
            _frustum(
                rng.uniform(0.15, 0.25), rng.uniform(0.06, 0.12), stem_top - shade_h * 0.5, stem_top + shade_h * 0.5
            )
        )
    elif kind == "table":
        body_h = rng.uniform(0.2, 0.35)
        parts.append(
            _frustum(base_r * 0.6, base_r * rng.uniform(0.3, 0.8), base_h, base_h + body_h)
        )  # a vase-like body
        stem_top = base_h + body_h + rng.uniform(0.1, 0.2)
        parts.append(_vcyl(stem_r, base_h + body_h, stem_top))
        shade_h = rng.uniform(0.15, 0.3)
        r_low = rng.uniform(0.15, 0.25)
        parts.append(_frustum(r_low, r_low * rng.uniform(0.5, 1.0), stem_top - shade_h * 0.6, stem_top + shade_h * 0.4))
    else:  # a desk lamp: a vertical post, an arm reaching forward (+X) and a conical head
        post_top = rng.uniform(0.3, 0.5)
        parts.append(_vcyl(stem_r, base_h, post_top))
        reach = rng.uniform(0.25, 0.45)
        head_z = post_top + rng.uniform(-0.05, 0.15)
        tip = (reach, 0.0, head_z)
        parts.append(_rod((0.0, 0.0, post_top), tip, stem_r))
        parts.append(_sphere(stem_r * 2, (0.0, 0.0, post_top)))
        head_h = rng.uniform(0.1, 0.16)
        parts.append(_frustum(rng.uniform(0.07, 0.11), 0.025, head_z - head_h, head_z, x=reach))
    return str(kind), parts


def _airplane(rng: np.random.Generator) -> tuple[str, list[trimesh.Trimesh]]:
    length = rng.uniform(1.0, 1.4)
    fuse_r = length * rng.uniform(0.045, 0.07)
    span = length * rng.uniform(0.8, 1.2)
    wings = rng.choice(["straight", "swept", "delta"])
    wing_pos = rng.choice(["low", "high"])
    n_engines = int(rng.choice([0, 2, 4]))
    tail = rng.choice(["conventional", "t-tail"])
    z0 = 0.0
    half = length / 2
    nose_len = length * rng.uniform(0.1, 0.15)
    parts = [
        _rod((-half, 0, z0), (half - nose_len, 0, z0), fuse_r),
        _rotated_y(trimesh.creation.cone(fuse_r, nose_len, sections=_SECTIONS), 90.0, (0, 0, 0)),
    ]
    parts[-1].apply_translation((half - nose_len, 0, z0))
    wing_z = z0 + (fuse_r * 0.6 if wing_pos == "high" else -fuse_r * 0.6)
    chord = length * rng.uniform(0.12, 0.2)
    wing_t = fuse_r * 0.35
    wing_x = length * rng.uniform(-0.05, 0.1)
    if wings == "delta":
        # A triangle in plan view, made of a stack of boxes whose span shrinks toward the nose.
        root = length * rng.uniform(0.35, 0.5)
        for k in range(6):
            frac = (k + 0.5) / 6
            parts.append(_box((root / 6, span * (1 - frac), wing_t), (wing_x - root / 2 + root * frac, 0, wing_z)))
    else:
        sweep = 0.0 if wings == "straight" else rng.uniform(20.0, 35.0)
        for sy in (-1, 1):
            wing = _box((chord, span / 2, wing_t), (wing_x, sy * span / 4, wing_z))
            parts.append(_rotated_z(wing, sy * sweep, (wing_x + chord / 2, 0, wing_z)))
        for k in range(n_engines):
            y = (k // 2 + 1) * span * 0.14 * (1 if k % 2 == 0 else -1)
            ez = wing_z - fuse_r * 0.7
            ex = wing_x + chord * 0.4 - abs(y) * np.tan(np.radians(sweep))
            parts.append(_rod((ex - chord * 0.6, y, ez), (ex + chord * 0.3, y, ez), fuse_r * 0.45))
    fin_h = length * rng.uniform(0.12, 0.2)
    fin_c = length * rng.uniform(0.1, 0.15)
    tail_x = -half + fin_c / 2
    parts.append(_box((fin_c, wing_t, fin_h), (tail_x, 0, z0 + fin_h / 2)))
    stab_span = span * rng.uniform(0.3, 0.45)
    stab_z = z0 + fin_h if tail == "t-tail" else z0
    parts.append(_box((fin_c * 0.8, stab_span, wing_t), (tail_x, 0, stab_z)))
    return f"{wings}-{wing_pos}-{n_engines}eng-{tail}", parts


def _car(rng: np.random.Generator) -> tuple[str, list[trimesh.Trimesh]]:
    kind = rng.choice(["sedan", "hatchback", "suv", "pickup", "sports"])
    length, width = rng.uniform(3.8, 5.0), rng.uniform(1.6, 2.0)
    wheel_r = rng.uniform(0.3, 0.4) * (1.2 if kind in ("suv", "pickup") else 1.0)
    clearance = wheel_r * 0.5
    body_h = rng.uniform(0.5, 0.7) * (0.8 if kind == "sports" else 1.0)
    cabin_h = rng.uniform(0.4, 0.6) * {"sports": 0.7, "suv": 1.4}.get(kind, 1.0)
    body_top = clearance + body_h
    parts = [_box((length, width, body_h), (0, 0, clearance + body_h / 2))]
    if kind == "pickup":
        cab_len = length * 0.35
        cab_x = length * 0.05
        parts.append(_box((cab_len, width * 0.9, cabin_h), (cab_x, 0, body_top + cabin_h / 2)))
        bed_x0, bed_x1 = -length / 2, cab_x - cab_len / 2
        for sy in (-1, 1):  # the open bed's side walls
            parts.append(
                _box((bed_x1 - bed_x0, 0.08, 0.3), ((bed_x0 + bed_x1) / 2, sy * (width / 2 - 0.04), body_top + 0.15))
            )
        parts.append(_box((0.08, width, 0.3), (bed_x0 + 0.04, 0, body_top + 0.15)))
    else:
        cab_len = length * {"sedan": 0.45, "hatchback": 0.55, "suv": 0.65, "sports": 0.4}[str(kind)]
        # Hatchbacks and SUVs carry the cabin to the rear (-X); sedans and sports cars centre it.
        cab_x = {"sedan": -0.05, "hatchback": -0.18, "suv": -0.15, "sports": -0.1}[str(kind)] * length
        cab_x = max(cab_x, -length / 2 + cab_len / 2)
        parts.append(_box((cab_len, width * 0.88, cabin_h), (cab_x, 0, body_top + cabin_h / 2)))
    axle = length / 2 - wheel_r * rng.uniform(1.3, 1.8)
    for sx in (-1, 1):
        for sy in (-1, 1):
            y = sy * (width / 2 - 0.1)
            parts.append(_rod((sx * axle, y - 0.12, wheel_r), (sx * axle, y + 0.12, wheel_r), wheel_r))
    return str(kind), parts


def _bench(rng: np.random.Generator) -> tuple[str, list[trimesh.Trimesh]]:
    length, depth = rng.uniform(1.0, 2.0), rng.uniform(0.35, 0.5)
    seat_h, seat_t = rng.uniform(0.4, 0.5), rng.uniform(0.04, 0.08)
    support = rng.choice(["legs", "panels"])
    back = bool(rng.random() < 0.5)
    arms = back and bool(rng.random() < 0.5)
    z_under = seat_h - seat_t
    if rng.random() < 0.5:
        parts = [_box((depth, length, seat_t), (0, 0, seat_h - seat_t / 2))]
    else:  # a slatted seat
        n = int(rng.integers(3, 6))
        slat = depth / n * 0.8
        parts = [
            _box((slat, length, seat_t), (x, 0, seat_h - seat_t / 2))
            for x in np.linspace(-depth / 2 + slat / 2, depth / 2 - slat / 2, n)
        ]
        parts.append(_box((depth, 0.05, seat_t), (0, 0, seat_h - seat_t * 1.5)))  # a cross-beam holding the slats
    if support == "legs":
        parts += _legs(rng, depth / 2, length / 2, z_under, 0.05)
    else:
        for sy in (-1, 1):
            parts.append(_box((depth * 0.9, 0.06, z_under), (0, sy * (length / 2 - 0.1), z_under / 2)))
    if back:
        back_h = rng.uniform(0.3, 0.45)
        parts.append(_box((0.05, length, back_h), (-depth / 2 + 0.025, 0, seat_h + back_h / 2 + 0.05)))
        for y in (-length / 2 + 0.1, length / 2 - 0.1):
            parts.append(_box((0.04, 0.04, 0.1), (-depth / 2 + 0.025, y, seat_h + 0.03)))
    if arms:
        for sy in (-1, 1):
            parts.append(_box((depth, 0.05, 0.04), (0, sy * (length / 2 - 0.025), seat_h + 0.22)))
            parts.append(_box((0.04, 0.04, 0.22), (depth / 2 - 0.04, sy * (length / 2 - 0.025), seat_h + 0.11)))
    return f"{support}{'-back' if back else ''}{'-arms' if arms else ''}", parts


def _sofa(rng: np.random.Generator) -> tuple[str, list[trimesh.Trimesh]]:
    length, depth = rng.uniform(1.4, 2.4), rng.uniform(0.8, 1.0)
    leg_h = rng.uniform(0.0, 0.12)
    base_h = rng.uniform(0.25, 0.35)
    cushion_t = rng.uniform(0.1, 0.16)
    back_h, back_t = rng.uniform(0.35, 0.5), rng.uniform(0.15, 0.25)
    arms = bool(rng.random() < 0.75)
    chaise = bool(rng.random() < 0.25)
    arm_w = rng.uniform(0.12, 0.25) if arms else 0.0
    z_base = leg_h + base_h
    parts = [_box((depth, length, base_h), (0, 0, leg_h + base_h / 2))]
    parts.append(
        _box((back_t, length, back_h + cushion_t), (-depth / 2 + back_t / 2, 0, z_base + (back_h + cushion_t) / 2))
    )
    n_cushions = int(rng.integers(1, 4))
    inner = length - 2 * arm_w
    for k in range(n_cushions):
        w = inner / n_cushions
        y = -inner / 2 + w * (k + 0.5)
        parts.append(_box((depth - back_t, w * 0.97, cushion_t), (back_t / 2, y, z_base + cushion_t / 2)))
    if arms:
        arm_top = z_base + cushion_t + rng.uniform(0.1, 0.25)
        for sy in (-1, 1):
            parts.append(
                _box((depth, arm_w, arm_top - leg_h), (0, sy * (length / 2 - arm_w / 2), leg_h + (arm_top - leg_h) / 2))
            )
    if chaise:  # an L-shaped sofa: a lounge extension toward the front on the +Y side
        ext = rng.uniform(0.5, 0.8)
        wid = rng.uniform(0.6, 0.8)
        parts.append(
            _box(
                (ext, wid, base_h + cushion_t),
                (depth / 2 + ext / 2, length / 2 - wid / 2, leg_h + (base_h + cushion_t) / 2),
            )
        )
    if leg_h > 0.02:
        foot = _legs(rng, depth / 2, length / 2, leg_h, 0.06)
        parts += foot
    return f"{'arms' if arms else 'armless'}{'-chaise' if chaise else ''}{'-legs' if leg_h > 0.02 else ''}", parts


def _bed(rng: np.random.Generator) -> tuple[str, list[trimesh.Trimesh]]:
    length, width = rng.uniform(1.9, 2.2), rng.uniform(0.9, 1.9)
    frame_h = rng.uniform(0.15, 0.3)
    leg_h = rng.uniform(0.0, 0.2)
    mattress_h = rng.uniform(0.15, 0.3)
    footboard = bool(rng.random() < 0.5)
    head_h = rng.uniform(0.4, 0.9)
    parts = [_box((length, width, frame_h), (0, 0, leg_h + frame_h / 2))]
    z_top = leg_h + frame_h
    parts.append(_box((length * 0.97, width * 0.95, mattress_h), (0, 0, z_top + mattress_h / 2)))
    parts.append(_box((0.06, width, leg_h + frame_h + head_h), (-length / 2 - 0.03, 0, (leg_h + frame_h + head_h) / 2)))
    if footboard:
        foot_h = rng.uniform(0.1, 0.3)
        parts.append(_box((0.05, width, z_top + foot_h), (length / 2 + 0.025, 0, (z_top + foot_h) / 2)))
    n_pillows = 1 if width < 1.3 else 2
    pil_w = width * 0.9 / n_pillows
    for k in range(n_pillows):
        y = -width * 0.45 + pil_w * (k + 0.5)
        parts.append(_box((0.35, pil_w * 0.9, 0.1), (-length / 2 + 0.25, y, z_top + mattress_h + 0.05)))
    if leg_h > 0.03:
        parts += _legs(rng, length / 2, width / 2, leg_h, 0.05)
    return f"{'footboard' if footboard else 'open'}-{'legs' if leg_h > 0.03 else 'platform'}-{n_pillows}p", parts


def _shelf(rng: np.random.Generator) -> tuple[str, list[trimesh.Trimesh]]:
    width, depth = rng.uniform(0.6, 1.4), rng.uniform(0.25, 0.45)
    height = rng.uniform(0.8, 2.0)
    board = rng.uniform(0.02, 0.04)
    n_shelves = int(rng.integers(2, 6))
    back = bool(rng.random() < 0.6)
    dividers = int(rng.integers(0, 3))
    parts = []
    for sy in (-1, 1):
        parts.append(_box((depth, board, height), (0, sy * (width / 2 - board / 2), height / 2)))
    for z in np.linspace(board / 2 + 0.05, height - board / 2, n_shelves + 1):
        parts.append(_box((depth, width, board), (0, 0, z)))
    if back:
        parts.append(_box((board * 0.5, width, height), (-depth / 2 + board * 0.25, 0, height / 2)))
    for y in np.linspace(-width / 2, width / 2, dividers + 2)[1:-1]:
        parts.append(_box((depth, board, height), (0, y, height / 2)))
    return f"{n_shelves}-shelves{'-back' if back else ''}-{dividers}div", parts


def _monitor(rng: np.random.Generator) -> tuple[str, list[trimesh.Trimesh]]:
    width = rng.uniform(0.45, 0.8)
    height = width * rng.uniform(0.5, 0.7)
    kind = rng.choice(["flat", "crt"], p=[0.75, 0.25])
    stand = rng.choice(["neck", "legs"])
    # A CRT sits on its own box-shaped foot; a flat screen is raised on a stand.
    screen_z = 0.05 if kind == "crt" else rng.uniform(0.12, 0.25)
    z_mid = screen_z + height / 2
    if kind == "flat":
        thick = rng.uniform(0.02, 0.05)
        parts = [_box((thick, width, height), (0, 0, z_mid))]
    else:
        thick = width * rng.uniform(0.6, 0.9)
        parts = [
            _box((0.08, width, height), (0, 0, z_mid)),
            _box((thick, width * 0.7, height * 0.7), (-thick / 2, 0, z_mid)),
        ]
    if kind == "crt":
        parts.append(_box((thick * 0.6, width * 0.5, 0.05), (-thick * 0.3, 0, 0.025)))
    elif stand == "neck":
        base_d = rng.uniform(0.15, 0.25)
        neck_x = -thick / 2 - 0.02
        parts.append(_box((0.03, 0.06, z_mid), (neck_x, 0, z_mid / 2)))
        if rng.random() < 0.5:
            parts.append(_box((base_d, base_d * 1.3, 0.02), (neck_x + 0.02, 0, 0.01)))
        else:
            parts.append(_vcyl(base_d * 0.6, 0.0, 0.02, neck_x + 0.02))
    else:
        for sy in (-1, 1):
            y = sy * width * 0.35
            parts.append(_box((0.03, 0.03, screen_z + 0.02), (0, y, (screen_z + 0.02) / 2)))
            parts.append(_box((0.18, 0.04, 0.02), (0, y, 0.01)))
    return f"{kind}-{stand if kind == 'flat' else 'box'}", parts


def _vessel(rng: np.random.Generator) -> tuple[str, list[trimesh.Trimesh]]:
    length = rng.uniform(2.0, 4.0)
    beam = length * rng.uniform(0.25, 0.35)
    hull_h = beam * rng.uniform(0.35, 0.55)
    kind = rng.choice(["sailboat", "motorboat", "ship"])
    bow = length * rng.uniform(0.2, 0.3)
    # The hull: the convex hull of a flat transom (stern, -X), a full-beam midship section and
    # a raked stem (bow, +X); the keel is narrower than the deck.
    keel = rng.uniform(0.3, 0.7)
    x_stern, x_mid, x_bow = -length / 2, length / 2 - bow, length / 2
    hull_pts = []
    for x in (x_stern, x_mid):
        for y in (-beam / 2, beam / 2):
            hull_pts += [(x, y, hull_h), (x, y * keel, 0.0)]
    hull_pts += [(x_bow, 0.0, hull_h), (x_bow - bow * 0.4, 0.0, 0.0)]
    parts = [trimesh.Trimesh(vertices=np.array(hull_pts)).convex_hull]
    if kind == "sailboat":
        mast_h = length * rng.uniform(0.8, 1.2)
        mast_x = rng.uniform(-0.05, 0.15) * length
        parts.append(_vcyl(0.03 * beam, hull_h, hull_h + mast_h, mast_x))
        boom = length * rng.uniform(0.3, 0.45)
        # The sail: a thin triangle approximated by boxes narrowing upward behind the mast.
        for k in range(5):
            frac = (k + 0.5) / 5
            w = boom * (1 - frac)
            parts.append(
                _box((w, 0.01 * beam, mast_h * 0.18), (mast_x - w / 2, 0, hull_h + 0.1 * mast_h + frac * mast_h * 0.85))
            )
    elif kind == "motorboat":
        cab = length * rng.uniform(0.2, 0.35)
        parts.append(_box((cab, beam * 0.7, hull_h * 0.6), (-length * 0.05, 0, hull_h * 1.3)))
    else:
        deck_len = length * rng.uniform(0.3, 0.5)
        parts.append(_box((deck_len, beam * 0.8, hull_h * 0.8), (-length * 0.15, 0, hull_h * 1.4)))
        n_funnels = int(rng.integers(1, 4))
        for k in range(n_funnels):
            x = -length * 0.15 - deck_len / 2 + deck_len * (k + 0.5) / n_funnels
            parts.append(_vcyl(beam * 0.1, hull_h * 1.8, hull_h * 1.8 + beam * rng.uniform(0.3, 0.6), x))
    return str(kind), parts


_BUILDERS: dict[str, _Builder] = {
    "airplane": _airplane,
    "bed": _bed,
    "bench": _bench,
    "car": _car,
    "chair": _chair,
    "lamp": _lamp,
    "monitor": _monitor,
    "shelf": _shelf,
    "sofa": _sofa,
    "table": _table,
    "vessel": _vessel,
}

#: The procedural categories, sorted by name.
CATEGORIES: tuple[str, ...] = tuple(sorted(_BUILDERS))


def _check_args(category: str, index: int) -> int:
    """``index`` as an int, after checking both arguments."""
    check_choice("category", category, CATEGORIES)
    return check_int("index", index, minimum=0)


def object_id(category: str, index: int) -> str:
    """The id of the ``index``-th procedural object of ``category``, e.g. ``"chair_0007"``."""
    index = _check_args(category, index)
    return f"{category}_{index:04d}"


def _rng(category: str, index: int, seed: int) -> np.random.Generator:
    # crc32, not hash(): Python's str hash is salted per process, and workers must agree.
    return np.random.default_rng(np.random.SeedSequence([int(seed), zlib.crc32(category.encode()), int(index)]))


def _build(category: str, index: int, seed: int) -> tuple[str, trimesh.Trimesh]:
    index = _check_args(category, index)
    variant, parts = _BUILDERS[category](_rng(category, index, seed))
    return variant, normalize_mesh(cast(trimesh.Trimesh, trimesh.util.concatenate(parts)))  # meshes in, a mesh out


def make_object(category: str, index: int, seed: int = 0) -> trimesh.Trimesh:
    """Generate procedural object ``index`` of ``category``.

    The same ``(category, index, seed)`` always gives the same mesh, in any process.

    Args:
        category: one of :data:`CATEGORIES`.
        index: a non-negative integer; each index draws a new variant and proportions.
        seed: the dataset seed; changing it changes every object.

    Returns:
        A mesh, +Z up, front facing +X, normalised into ``[-0.5, 0.5]^3`` (longest side 1).
        It is a concatenation of closed primitives that may overlap (not a boolean union).

    Raises:
        ValueError: for an unknown ``category`` or a negative ``index``.
        TypeError: for an ``index`` that is not an int.
    """
    return _build(category, index, seed)[1]


def object_variant(category: str, index: int, seed: int = 0) -> str:
    """The structural variant (e.g. ``"legs-slats-arms"``) that :func:`make_object` draws."""
    return _build(category, index, seed)[0]
