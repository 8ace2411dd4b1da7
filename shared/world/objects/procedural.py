"""Procedural objects with exact meshes: primitives (boxes, cylinders, cones, ellipsoids, capsules,
convex hulls) and families modelled on everyday household categories (everyday.py: spatulas, small
items, bottles, mugs, bananas, cans and bottles lying on their side).

Ids are `proc-<family>-<NNN>` (NNN = 000..PER_FAMILY-1). Everything about an object follows from
its id: the target shape class cycles with the index (flat / volumetric / tall, as the family
allows) and the dimensions are drawn from a generator seeded by the id's hash, rejecting draws
whose height-to-footprint ratio is within 15% of a class boundary, so the class measured on the
mesh (geometry.shape_class) is the designed one. Sizes are pushable by a robot hand: footprint
sides 4–25 cm, heights 2–25 cm.

Every primitive is modelled upright (its base on z = const, +z up) and is convex, so it is its own
convex decomposition. Round shapes that would roll (ellipsoids, capsules lying down) have 8% of
their height cut off at the bottom, giving a small flat base as a real object standing still has.
The everyday families are unions of convex pieces with sizes and a designed mass drawn from the
ranges of real objects (everyday.py says where each range comes from); they have their own
generator version (EVERYDAY_VERSION) and seeds, so the primitives' objects, meshes and cache keys
are those they always were.
"""
from __future__ import annotations

import functools
import hashlib
import math
import re
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import trimesh

from .errors import UnknownObjectError
from .everyday import EVERYDAY_BUILDERS, EVERYDAY_FAMILIES, EVERYDAY_FAMILY_CLASSES, EVERYDAY_SAMPLERS, EVERYDAY_VERSION
from .geometry import FLAT_MAX_RATIO, SHAPE_CLASSES, TALL_MIN_RATIO, shape_class

PRIMITIVE_FAMILIES = ("box", "cylinder", "cone", "ellipsoid", "capsule", "hull")
# New families go at the end: ids, listings and every selection by count keep their order.
FAMILIES = PRIMITIVE_FAMILIES + EVERYDAY_FAMILIES
FAMILY_CLASSES: dict[str, tuple[str, ...]] = {
    "box": SHAPE_CLASSES,
    "cylinder": SHAPE_CLASSES,
    "cone": SHAPE_CLASSES,
    "ellipsoid": ("flat", "volumetric"),  # a standing egg on a cut base is not a resting pose people use
    "capsule": ("flat", "volumetric"),  # lying pills and rods
    "hull": SHAPE_CLASSES,
    **EVERYDAY_FAMILY_CLASSES,
}
PER_FAMILY = 100
PROCEDURAL_VERSION = 1  # bump when a primitive's generator changes: ids then map to new shapes
_ID_PATTERN = re.compile(r"^proc-([a-z]+)-(\d{3})$")
_CLASS_MARGIN = 0.15
_ROUND_SECTIONS = 48
_BASE_CUT = 0.08  # fraction of an ellipsoid's / capsule's height cut off to make a base

Params = dict[str, float]
Dims = tuple[float, float, float]  # footprint a >= b and height H


@dataclass(frozen=True)
class ProceduralSpec:
    object_id: str
    family: str
    index: int
    shape_class: str
    params: dict[str, float]
    dims: tuple[float, float, float]  # designed footprint a >= b and height H (metres), upright

    @property
    def mass_kg(self) -> float | None:
        """The designed mass of an everyday-family object (None: the library's uniform density decides)."""
        return self.params.get("mass_kg")


def procedural_ids() -> list[str]:
    return [f"proc-{family}-{index:03d}" for family in FAMILIES for index in range(PER_FAMILY)]


def is_procedural_id(object_id: str) -> bool:
    return object_id.startswith("proc-")


def parse_procedural_id(object_id: str) -> tuple[str, int]:
    """(family, index) of a procedural id, without generating it; UnknownObjectError otherwise."""
    match = _ID_PATTERN.match(object_id)
    if not match or match.group(1) not in FAMILIES or int(match.group(2)) >= PER_FAMILY:
        raise UnknownObjectError(
            f"{object_id!r}: not a procedural object id (expected proc-<family>-<000..{PER_FAMILY - 1:03d}>, "
            f"family one of {', '.join(FAMILIES)})"
        )
    return match.group(1), int(match.group(2))


def is_everyday_id(object_id: str) -> bool:
    """True for an id of an everyday family (added after the primitives; see everyday.py)."""
    match = _ID_PATTERN.match(object_id)
    return match is not None and match.group(1) in EVERYDAY_FAMILIES


@functools.lru_cache(maxsize=4096)
def procedural_spec(object_id: str) -> ProceduralSpec:
    """The family, designed class and dimensions (metres) of a procedural id (cached: specs are immutable)."""
    family, index = parse_procedural_id(object_id)
    everyday = family in EVERYDAY_FAMILIES
    return draw_spec(object_id, family, index, _everyday_seed(object_id) if everyday else _seed(object_id))


def draw_spec(object_id: str, family: str, index: int, seed: int) -> ProceduralSpec:
    """An object of `family` drawn from `seed`: the shape class follows `index` (as the library's ids), the
    dimensions the seeded generator. The library's ids draw from their id's hash; the final split
    (final_split.py) draws the same families from seeds of its own."""
    classes = FAMILY_CLASSES[family]
    target = classes[index % len(classes)]
    everyday = family in EVERYDAY_FAMILIES
    rng = np.random.default_rng(seed)
    for _ in range(100_000):
        params, (a, b, height) = EVERYDAY_SAMPLERS[family](rng, index) if everyday else _SAMPLERS[family](rng)
        if _clearly_in_class(a, b, height, target):
            return ProceduralSpec(object_id, family, index, target, params, (a, b, height))
    raise RuntimeError(f"{object_id}: no {target} dimensions found for family {family}")  # cannot happen with these ranges


def procedural_mesh(spec: ProceduralSpec) -> trimesh.Trimesh:
    """The exact mesh of a procedural object, upright, in metres: one closed convex body for a
    primitive, the closed convex pieces side by side for an everyday family."""
    return _BUILDERS[spec.family](spec.params)


def generator_version(family: str) -> dict[str, int]:
    """What identifies the generator of a family's objects (part of their cache key)."""
    if family in EVERYDAY_FAMILIES:
        return {"everyday": EVERYDAY_VERSION}
    return {"procedural": PROCEDURAL_VERSION}


def _seed(object_id: str) -> int:
    digest = hashlib.sha256(f"gd2p-procedural-v{PROCEDURAL_VERSION}:{object_id}".encode()).digest()
    return int.from_bytes(digest[:8], "little")


def _everyday_seed(object_id: str) -> int:
    digest = hashlib.sha256(f"gd2p-everyday-v{EVERYDAY_VERSION}:{object_id}".encode()).digest()
    return int.from_bytes(digest[:8], "little")


def _clearly_in_class(a: float, b: float, height: float, target: str) -> bool:
    low, high = 1.0 - _CLASS_MARGIN, 1.0 + _CLASS_MARGIN
    if shape_class(a, b, height * low) != target or shape_class(a, b, height * high) != target:
        return False
    ratio = height / math.sqrt(a * b)
    return not (FLAT_MAX_RATIO * low < ratio < FLAT_MAX_RATIO * high or TALL_MIN_RATIO * low < ratio < TALL_MIN_RATIO * high)


def _log_uniform(rng: np.random.Generator, low: float, high: float) -> float:
    return float(math.exp(rng.uniform(math.log(low), math.log(high))))


# ----------------------------------------------------------------------------- samplers: params, (a, b, H)
def _sample_box(rng: np.random.Generator) -> tuple[Params, Dims]:
    a, b = sorted((_log_uniform(rng, 0.04, 0.25), _log_uniform(rng, 0.04, 0.25)), reverse=True)
    height = _log_uniform(rng, 0.02, 0.25)
    return {"a": a, "b": b, "height": height}, (a, b, height)


def _sample_cylinder(rng: np.random.Generator) -> tuple[Params, Dims]:
    diameter, height = _log_uniform(rng, 0.04, 0.20), _log_uniform(rng, 0.02, 0.25)
    return {"diameter": diameter, "height": height}, (diameter, diameter, height)


def _sample_cone(rng: np.random.Generator) -> tuple[Params, Dims]:
    diameter, height = _log_uniform(rng, 0.05, 0.22), _log_uniform(rng, 0.03, 0.25)
    top_ratio = float(rng.uniform(0.0, 0.7))  # 0 = a pointed cone, else a frustum (cup, lampshade)
    return {"diameter": diameter, "top_ratio": top_ratio, "height": height}, (diameter, diameter, height)


def _sample_ellipsoid(rng: np.random.Generator) -> tuple[Params, Dims]:
    a = _log_uniform(rng, 0.05, 0.22)
    b = _log_uniform(rng, 0.04, a)
    c = _log_uniform(rng, 0.025, 0.16)
    return {"a": a, "b": b, "c": c}, (a, b, c * (1.0 - _BASE_CUT))


def _sample_capsule(rng: np.random.Generator) -> tuple[Params, Dims]:
    radius = _log_uniform(rng, 0.01, 0.04)
    length = _log_uniform(rng, max(0.05, 5.0 * radius), 0.25)  # overall, caps included
    return {"radius": radius, "length": length}, (length, 2 * radius, 2 * radius * (1.0 - _BASE_CUT))


def _sample_hull(rng: np.random.Generator) -> tuple[Params, Dims]:
    a, b = sorted((_log_uniform(rng, 0.04, 0.24), _log_uniform(rng, 0.04, 0.24)), reverse=True)
    height = _log_uniform(rng, 0.02, 0.25)
    params = {"a": a, "b": b, "height": height, "top_scale": float(rng.uniform(0.3, 1.0)), "points_seed": float(rng.integers(2**31))}
    return params, (a, b, height)


_SAMPLERS: dict[str, Callable[[np.random.Generator], tuple[Params, Dims]]] = {
    "box": _sample_box,
    "cylinder": _sample_cylinder,
    "cone": _sample_cone,
    "ellipsoid": _sample_ellipsoid,
    "capsule": _sample_capsule,
    "hull": _sample_hull,
}


# ----------------------------------------------------------------------------- builders
def _build_box(p: Params) -> trimesh.Trimesh:
    box: trimesh.Trimesh = trimesh.creation.box(extents=(p["a"], p["b"], p["height"]))
    return box


def _build_cylinder(p: Params) -> trimesh.Trimesh:
    cylinder: trimesh.Trimesh = trimesh.creation.cylinder(radius=p["diameter"] / 2, height=p["height"],
                                                          sections=_ROUND_SECTIONS)
    return cylinder


def _ring(radius_x: float, radius_y: float, z: float, count: int, phase: float = 0.0) -> np.ndarray:
    angles = phase + np.linspace(0.0, 2 * math.pi, count, endpoint=False)
    return np.stack([radius_x * np.cos(angles), radius_y * np.sin(angles), np.full(count, z)], axis=1)


def _build_cone(p: Params) -> trimesh.Trimesh:
    radius = p["diameter"] / 2
    base = _ring(radius, radius, 0.0, _ROUND_SECTIONS)
    top_radius = radius * p["top_ratio"]
    top = _ring(top_radius, top_radius, p["height"], _ROUND_SECTIONS) if top_radius > 1e-3 else np.array([[0.0, 0.0, p["height"]]])
    cone: trimesh.Trimesh = trimesh.convex.convex_hull(np.vstack([base, top]))
    return cone


def _cut_base(mesh: trimesh.Trimesh, height: float) -> trimesh.Trimesh:
    """Remove the bottom `_BASE_CUT` of the mesh's height (exact boolean, manifold3d)."""
    lower, upper = mesh.bounds
    keep_lower = lower - 1.0
    keep_lower[2] = lower[2] + _BASE_CUT * height
    keep = trimesh.creation.box(bounds=[keep_lower, upper + 1.0])
    cut: trimesh.Trimesh = trimesh.boolean.intersection([mesh, keep], engine="manifold")
    return cut


def _build_ellipsoid(p: Params) -> trimesh.Trimesh:
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    sphere.apply_scale([p["a"] / 2, p["b"] / 2, p["c"] / 2])
    return _cut_base(sphere, p["c"])


def _build_capsule(p: Params) -> trimesh.Trimesh:
    radius = p["radius"]
    capsule = trimesh.creation.capsule(height=p["length"] - 2 * radius, radius=radius, count=[32, 16])
    capsule.apply_transform(trimesh.transformations.rotation_matrix(math.pi / 2, [0.0, 1.0, 0.0]))  # lie along x
    return _cut_base(capsule, 2 * radius)


def _build_hull(p: Params) -> trimesh.Trimesh:
    rng = np.random.default_rng(int(p["points_seed"]))
    rx, ry, height = p["a"] / 2, p["b"] / 2, p["height"]
    base = _ring(rx, ry, 0.0, 12, phase=float(rng.uniform(0, 2 * math.pi)))  # the footprint, so upright rests
    top = _ring(rx * p["top_scale"], ry * p["top_scale"], height, 5, phase=float(rng.uniform(0, 2 * math.pi)))
    radius = np.sqrt(rng.uniform(0.0, 1.0, 30))
    angle = rng.uniform(0.0, 2 * math.pi, 30)
    interior = np.stack([rx * radius * np.cos(angle), ry * radius * np.sin(angle), rng.uniform(0.0, height, 30)], axis=1)
    hull: trimesh.Trimesh = trimesh.convex.convex_hull(np.vstack([base, top, interior]))
    return hull


_BUILDERS: dict[str, Callable[[Params], trimesh.Trimesh]] = {
    "box": _build_box,
    "cylinder": _build_cylinder,
    "cone": _build_cone,
    "ellipsoid": _build_ellipsoid,
    "capsule": _build_capsule,
    "hull": _build_hull,
    **EVERYDAY_BUILDERS,
}
