"""Procedural families modelled on everyday household categories.

| family | what | pieces |
|---|---|---|
| `spatula` | a thin flat tool lying on the table: a 2-4 mm blade, a neck and a thicker handle | 3 |
| `small` | items under 5 cm: dice, erasers, bottle caps | 1 |
| `bottle` | a bottle standing: body, shoulder, neck | 3 |
| `mug` | a cylindrical cup with a handle, hollow (open top, full-depth cavity) | 58 |
| `banana` | a curved, tapering fruit lying on its side | 12 |
| `lying` | cans and bottles lying on their side: they roll when pushed | 1 or 3 |

An object is the union of a few convex pieces, modelled upright on z = 0 in metres. The raw mesh
(`EVERYDAY_BUILDERS`) is the pieces side by side, each a closed convex hull overlapping its
neighbours without sharing a vertex: the object library takes them as the exact convex
decomposition (PyBullet's collision shape, no V-HACD) and fuses them into one watertight surface
(manifold3d). Sizes are measured on the pieces' vertices, so the designed footprint and height
are the mesh's.

Mass. Each object carries a designed mass (`params["mass_kg"]`) from the real category's range,
used instead of the library's uniform density (objects are hollow, filled, or made of ceramic):
see `model.load_object`. A mass is a density times the analytic volume of the design (or, for
containers, the liquid they hold plus the container); draws outside the family's mass range are
redrawn. Every figure below has its source, or says that it is chosen, not cited.

Why a hollow mug: a mug's mass sits in its walls, so its centre of mass is low and its inertia a
shell's; fingers can hook the rim or push inside it. Physics needs no compromise: the wall is 48
overlapping convex staves on a convex base, so the collision shape is exact and the mug rests and
slides like a real one (a closed cup would be a different object to push).

Why `lying` rests and rolls: a lying cylinder is a 48-sided prism resting on a face (not an edge),
so it is statically stable where it is put, and rolls when pushed across its axis (PyBullet's
collision margin rounds the prism's edges, so it rolls as a cylinder does). What stops it is the
simulation's rolling friction, not the object: set rolling at 0.1 m/s, 3 cans and 3 bottles rolled
on for 1.5-2.4 m in 10 s at the nominal 0, and stopped within 0.4-0.9 s at 0.002 (the execution
worlds' largest draw; tests/test_families.py checks one can both ways).
"""
from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import trimesh

Params = dict[str, float]
Dims = tuple[float, float, float]  # footprint a >= b and height H
Pieces = list[np.ndarray]  # the vertices of each convex piece

EVERYDAY_VERSION = 1  # bump when a generator here changes: these ids then map to new shapes (the primitives keep theirs)
EVERYDAY_FAMILIES = ("spatula", "small", "bottle", "mug", "banana", "lying")
EVERYDAY_FAMILY_CLASSES: dict[str, tuple[str, ...]] = {
    "spatula": ("flat",),
    # index % 6: die, eraser, cap, die, eraser, cap (the kind follows the index, so the held-out
    # proc-small-000..002 are one of each)
    "small": ("volumetric", "flat", "volumetric", "volumetric", "flat", "flat"),
    "bottle": ("tall",),
    "mug": ("volumetric",),
    "banana": ("flat",),
    "lying": ("volumetric",),
}
WATER_KG_M3 = 1000.0

# ----------------------------------------------------------------------------- sizes and masses, with sources
# Spatula (kitchen turner): "a spatula is usually short and about 8 inches long" (20 cm;
# https://www.cookipedia.co.uk/wiki/index.php?title=Spatula); a "3 x 6 inch" turner blade
# (7.6 x 15.2 cm; https://aromacucina.com/explore/tools-of-the-trade-the-spatula/). Chosen, not cited:
# the upper length 32 cm, blade widths 5-9 cm and lengths 6-15 cm, blade 2-4 mm and handle 8-15 mm
# thick, handle 1.5-3 cm wide, plastic densities 900-1400 kg/m^3 and the mass range.
SPATULA_LENGTH_M = (0.20, 0.32)
SPATULA_BLADE_WIDTH_M = (0.05, 0.09)
SPATULA_BLADE_LENGTH_M = (0.06, 0.15)
SPATULA_BLADE_THICKNESS_M = (0.002, 0.004)
SPATULA_HANDLE_THICKNESS_M = (0.008, 0.015)
SPATULA_MASS_KG = (0.02, 0.15)
# Small items, all under 5 cm. Dice: "standard sizes for casino dice or board game dice range from
# 12mm to 19mm" (https://adsy.me/home_questions/what-is-the-smallest-and-largest-size-of-dice-available/).
# Caps: bottle neck calibres of 25, 28 and 35 mm (http://www.marutoys.com/article-drink-bottle-common-
# caliber-specification-1018.html), so caps 26-40 mm across. Chosen, not cited: eraser sizes (3-5 x
# 1.5-2.5 x 0.8-1.2 cm), cap heights (1-2 cm), densities (dice 1150-1350, erasers 1100-1700 kg/m^3;
# a cap, hollow, modelled closed with an effective 200-500 kg/m^3) and so the masses.
SMALL_MAX_EXTENT_M = 0.05
DIE_SIDE_M = (0.012, 0.019)
CAP_DIAMETER_M = (0.026, 0.040)
SMALL_MASS_KG = (0.001, 0.05)
# Bottles standing. 500 ml bottles average 23.5 cm x 7.0 cm (PET), 26.4 x 7.6 (glass), 22.6 x 8.4
# (HDPE) (https://www.glasscraftbottle.com/glass-insights/sizeguides/1683.html); a 4 oz bottle is
# 100 mm x 46 mm (https://harrisspice.com/collections/packaging/products/bottle-4-oz-round); neck
# calibres 25-35 mm (marutoys, above). Water 1 kg/L. Chosen, not cited: a plastic bottle (10-30 g)
# filled from a quarter to full, its capacity 0.85 of its outer volume (a can's share, below), the body
# 0.5-0.7 and the shoulder 0.1-0.2 of the height.
BOTTLE_DIAMETER_M = (0.045, 0.085)
BOTTLE_HEIGHT_M = (0.10, 0.265)
BOTTLE_NECK_DIAMETER_M = (0.025, 0.035)
BOTTLE_MASS_KG = (0.03, 1.3)
# Mugs: 8 fl oz mugs 2.75 x 3.15 inches (7.0 x 8.0 cm) and ceramic mugs of 250-400 g
# (https://www.measuringknowhow.com/how-much-does-a-coffee-mug-weigh/); mugs "approximately 3 to 4
# inches in height by 3 1/2 inches across" (http://www.theteahorsecaravan.com/2013/03/teacups-saucers-but-mugs.html).
# Chosen, not cited: diameters 7-9.5 cm and heights 7.5-11 cm around those, walls 4-7 mm, bottoms
# 6-10 mm, porcelain / stoneware 2000-2500 kg/m^3 (mass = that times the designed volume, kept when
# in the cited 250-400 g) and the handle's size.
MUG_DIAMETER_M = (0.07, 0.095)
MUG_HEIGHT_M = (0.075, 0.11)
MUG_MASS_KG = (0.25, 0.40)
# Bananas: USDA size classes from under 6 inches to 9 inches and longer, 81-152 g without the peel
# (https://visualfoodie.com/banana-calorie-content-by-weight-and-size); a whole Cavendish fruit 180.56 g
# against 114.54 g of pulp (https://ntro.it.com/how-much-is-1-banana-in-grams), so whole fruits of about
# 81/0.634 = 128 g to 152/0.634 = 240 g (the range below rounds these outward). Chosen, not cited: the upper length 25 cm, diameters 3.4-4.4 cm,
# the bend (50-100 degrees of arc), density 900-1050 kg/m^3.
BANANA_LENGTH_M = (0.15, 0.25)  # along the centre line
BANANA_MASS_KG = (0.125, 0.245)
# Lying cans and bottles. Cans: 500 ml cans are 66.1 mm x 168 mm (https://www.yorkshire-escapes.com/post/24502),
# a 12 oz (355 ml) can 4.83 inches (123 mm) tall (https://thefoodiesite.com/?p=32740) and 15 g empty
# (https://www.cgcreativeshop.com/chi-sono/digital-graphics/2462-drink-aluminum-cans-3d-objects-download.html):
# 500 ml in 66.1 x 168 mm, and 355 ml in 123 mm of the same diameter (assumed: the page gives the lid's),
# are 0.87 and 0.85 of the outer volume. Bottles as above. Chosen, not cited: cans and jars 5-8.5 cm across, 1.2-3.5 diameters and at most 24 cm long,
# filled from a quarter to full.
CAN_DIAMETER_M = (0.05, 0.085)
CAN_LENGTH_MAX_M = 0.24
CAN_CAPACITY_SHARE = 0.85
CAN_EMPTY_KG = 0.015
LYING_MASS_KG = (0.03, 1.3)

MASS_RANGES_KG: dict[str, tuple[float, float]] = {
    "spatula": SPATULA_MASS_KG, "small": SMALL_MASS_KG, "bottle": BOTTLE_MASS_KG, "mug": MUG_MASS_KG,
    "banana": BANANA_MASS_KG, "lying": LYING_MASS_KG,
}

_SECTIONS = 48  # round cross-sections (as the primitive families)
_OVERLAP_M = 3e-4  # pieces reach this far into their neighbours (no shared vertices, no gaps)
_DRAWS = 10_000


def _uniform(rng: np.random.Generator, bounds: tuple[float, float]) -> float:
    return float(rng.uniform(*bounds))


def _ring(radius: float, z: float, count: int = _SECTIONS, phase: float = 0.0) -> np.ndarray:
    """`count` points on a circle about the z axis at height z."""
    angles = phase + np.linspace(0.0, 2 * math.pi, count, endpoint=False)
    return np.stack([radius * np.cos(angles), radius * np.sin(angles), np.full(count, z)], axis=1)


def _prism(outline: np.ndarray, z0: float, z1: float) -> np.ndarray:
    """A 2-D convex outline [n, 2] extruded from z0 to z1 (vertices)."""
    n = len(outline)
    return np.vstack([np.column_stack([outline, np.full(n, z0)]), np.column_stack([outline, np.full(n, z1)])])


def _chamfered_box(a: float, b: float, h: float, chamfer: float) -> np.ndarray:
    """A box (centred in x, y; base on z = 0) with its edges and corners cut by `chamfer`."""
    boxes = [(a, b - 2 * chamfer, h - 2 * chamfer), (a - 2 * chamfer, b, h - 2 * chamfer), (a - 2 * chamfer, b - 2 * chamfer, h)]
    corners = np.array([[sx, sy, sz] for sx in (-0.5, 0.5) for sy in (-0.5, 0.5) for sz in (-0.5, 0.5)])
    points = np.vstack([corners * np.array(extents) for extents in boxes])
    points[:, 2] += h / 2
    return points


def _volume_frustum(r0: float, r1: float, height: float) -> float:
    return math.pi * height * (r0 * r0 + r0 * r1 + r1 * r1) / 3.0


def footprint_dims(pieces: Pieces) -> Dims:
    """(a, b, H) of the pieces standing as modelled: the smallest footprint rectangle (as the library
    measures a mesh, `geometry.footprint_and_height`) and the height."""
    points = np.vstack(pieces)
    _, extents = trimesh.bounds.oriented_bounds_2D(points[:, :2])
    a, b = sorted((float(extents[0]), float(extents[1])), reverse=True)
    return a, b, float(points[:, 2].max() - points[:, 2].min())


def pieces_mesh(pieces: Pieces) -> trimesh.Trimesh:
    """The convex hull of every piece, side by side in one mesh (fused later by the library)."""
    hulls = [trimesh.convex.convex_hull(points) for points in pieces]
    mesh = trimesh.util.concatenate(hulls)
    assert isinstance(mesh, trimesh.Trimesh)
    return mesh


# ----------------------------------------------------------------------------- spatula
def _sample_spatula(rng: np.random.Generator, index: int) -> Params:
    length = _uniform(rng, SPATULA_LENGTH_M)
    blade_length = min(_uniform(rng, SPATULA_BLADE_LENGTH_M), 0.5 * length)
    p = {
        "length": length,
        "blade_width": _uniform(rng, SPATULA_BLADE_WIDTH_M),
        "blade_length": blade_length,
        "blade_thickness": _uniform(rng, SPATULA_BLADE_THICKNESS_M),
        "neck_length": float(rng.uniform(0.01, 0.03)),
        "handle_width": float(rng.uniform(0.015, 0.03)),
        "handle_thickness": _uniform(rng, SPATULA_HANDLE_THICKNESS_M),
        "corner_radius": float(rng.uniform(0.1, 0.3)),  # of the blade width: rounded front corners
    }
    p["density"] = float(rng.uniform(900.0, 1400.0))
    return p


def _spatula_pieces(p: Params) -> Pieces:
    """Blade (front at x = 0), neck and handle, all lying on the table."""
    width, blade_length, blade_t = p["blade_width"], p["blade_length"], p["blade_thickness"]
    handle_w, handle_t, length = p["handle_width"], p["handle_thickness"], p["length"]
    neck_end = blade_length + p["neck_length"]
    radius = p["corner_radius"] * width
    arc = np.linspace(math.pi, math.pi / 2, 7)  # front-left corner, then mirrored
    corner = np.stack([radius + radius * np.cos(arc), width / 2 - radius + radius * np.sin(arc)], axis=1)
    blade_outline = np.vstack([corner, corner[::-1] * [1.0, -1.0], [[blade_length, -width / 2], [blade_length, width / 2]]])
    blade = _prism(blade_outline, 0.0, blade_t)
    neck = np.array([[blade_length - 2 * _OVERLAP_M, y, z] for y in (-0.45 * width, 0.45 * width) for z in (0.0, 0.9 * blade_t)]
                    + [[neck_end, y, z] for y in (-0.45 * handle_w, 0.45 * handle_w) for z in (0.0, 0.95 * handle_t)])
    end = np.linspace(-math.pi / 2, math.pi / 2, 9)  # a round handle end
    handle_outline = np.vstack([[[neck_end - _OVERLAP_M, -handle_w / 2]],
                                np.stack([length - handle_w / 2 + handle_w / 2 * np.cos(end), handle_w / 2 * np.sin(end)], axis=1),
                                [[neck_end - _OVERLAP_M, handle_w / 2]]])
    handle = _prism(handle_outline, 0.0, handle_t)
    return [blade, neck, handle]


def _spatula_volume(p: Params) -> float:
    handle_length = p["length"] - p["blade_length"] - p["neck_length"]
    neck = p["neck_length"] * 0.5 * (p["blade_width"] + p["handle_width"]) * 0.5 * (p["blade_thickness"] + p["handle_thickness"])
    return p["blade_width"] * p["blade_length"] * p["blade_thickness"] + neck + p["handle_width"] * handle_length * p["handle_thickness"]


# ----------------------------------------------------------------------------- small items
_SMALL_KINDS = ("die", "eraser", "cap")


def _sample_small(rng: np.random.Generator, index: int) -> Params:
    kind = index % len(_SMALL_KINDS)
    if _SMALL_KINDS[kind] == "die":
        side = _uniform(rng, DIE_SIDE_M)
        p = {"a": side, "b": side, "height": side, "chamfer": float(rng.uniform(0.05, 0.15)) * side}
        density, volume = float(rng.uniform(1150.0, 1350.0)), side**3
    elif _SMALL_KINDS[kind] == "eraser":
        a, b, height = float(rng.uniform(0.03, 0.05)), float(rng.uniform(0.015, 0.025)), float(rng.uniform(0.008, 0.012))
        p = {"a": a, "b": b, "height": height, "chamfer": float(rng.uniform(0.1, 0.25)) * height}
        density, volume = float(rng.uniform(1100.0, 1700.0)), a * b * height
    else:
        diameter, height = _uniform(rng, CAP_DIAMETER_M), float(rng.uniform(0.01, 0.02))
        p = {"a": diameter, "b": diameter, "height": height, "chamfer": 0.0}
        density, volume = float(rng.uniform(200.0, 500.0)), math.pi * diameter * diameter / 4 * height
    p["kind"] = float(kind)
    p["density"] = density
    p["mass_kg"] = density * volume
    return p


def _small_pieces(p: Params) -> Pieces:
    if _SMALL_KINDS[int(p["kind"])] == "cap":
        radius = p["a"] / 2
        return [np.vstack([_ring(radius, 0.0, 32), _ring(radius, p["height"], 32)])]
    return [_chamfered_box(p["a"], p["b"], p["height"], p["chamfer"])]


# ----------------------------------------------------------------------------- bottles (standing, and lying)
def _sample_bottle_shape(rng: np.random.Generator) -> Params:
    height = _uniform(rng, BOTTLE_HEIGHT_M)
    diameter = _uniform(rng, BOTTLE_DIAMETER_M)
    neck = min(_uniform(rng, BOTTLE_NECK_DIAMETER_M), 0.6 * diameter)
    body = float(rng.uniform(0.5, 0.7)) * height
    shoulder = float(rng.uniform(0.1, 0.2)) * height
    return {"diameter": diameter, "height": height, "neck_diameter": neck, "body_height": body, "shoulder_height": shoulder}


def _fill_bottle(rng: np.random.Generator, p: Params) -> Params:
    p["fill"] = float(rng.uniform(0.25, 1.0))
    p["container_kg"] = float(rng.uniform(0.01, 0.03))
    p["mass_kg"] = p["container_kg"] + p["fill"] * WATER_KG_M3 * CAN_CAPACITY_SHARE * _bottle_volume(p)
    return p


def _bottle_pieces(p: Params, phase: float = 0.0) -> Pieces:
    """Body, shoulder and neck about the z axis, base on z = 0. Each meets the next a hair inside it,
    with a small ledge (the shoulder starts at 98.5% of the body's radius, the neck stands in a
    ring 12% wider than itself), so no two pieces share a surface."""
    radius, neck_radius = p["diameter"] / 2, p["neck_diameter"] / 2
    body_top = p["body_height"]
    shoulder_top = body_top + p["shoulder_height"]
    body = np.vstack([_ring(radius, 0.0, phase=phase), _ring(radius, body_top, phase=phase)])
    shoulder = np.vstack([_ring(0.985 * radius, body_top - 1e-3, phase=phase), _ring(1.12 * neck_radius, shoulder_top, phase=phase)])
    neck = np.vstack([_ring(neck_radius, shoulder_top - 1e-3, phase=phase), _ring(neck_radius, p["height"], phase=phase)])
    return [body, shoulder, neck]


def _bottle_volume(p: Params) -> float:
    radius, neck_radius = p["diameter"] / 2, p["neck_diameter"] / 2
    neck_height = p["height"] - p["body_height"] - p["shoulder_height"]
    return (math.pi * radius * radius * p["body_height"] + _volume_frustum(0.985 * radius, 1.12 * neck_radius, p["shoulder_height"])
            + math.pi * neck_radius * neck_radius * neck_height)


def _sample_bottle(rng: np.random.Generator, index: int) -> Params:
    return _fill_bottle(rng, _sample_bottle_shape(rng))


# ----------------------------------------------------------------------------- mug
_MUG_STAVES = 48


def _sample_mug(rng: np.random.Generator, index: int) -> Params:
    height = _uniform(rng, MUG_HEIGHT_M)
    p = {
        "diameter": _uniform(rng, MUG_DIAMETER_M),
        "height": height,
        "wall": float(rng.uniform(0.004, 0.007)),
        "bottom": float(rng.uniform(0.006, 0.010)),
        "reach": float(rng.uniform(0.022, 0.035)),  # how far the handle stands out of the wall
        "handle_thickness": float(rng.uniform(0.007, 0.011)),
        "handle_width": float(rng.uniform(0.010, 0.016)),
        "handle_top": float(rng.uniform(0.012, 0.02)),  # from the rim to the top of the handle
    }
    # between the handle's arms, centre to centre; its lower arm stays 1 cm above the table
    highest_arm = height - p["handle_top"] - p["handle_thickness"] / 2
    lowest_arm = 0.01 + p["handle_thickness"] / 2
    p["handle_span"] = min(float(rng.uniform(0.45, 0.7)) * height, highest_arm - lowest_arm)
    p["density"] = float(rng.uniform(2000.0, 2500.0))
    return p


def _tube_pieces(centre: np.ndarray, frames: np.ndarray, section: np.ndarray) -> Pieces:
    """Convex pieces of a tube: `section` [k, 2] placed in the plane of each frame [n, 2, 3] (its two
    in-plane axes) at `centre` [n, 3]; each piece joins two consecutive sections, each end pushed
    `_OVERLAP_M` beyond the joint so neighbours overlap."""
    pieces = []
    for i in range(len(centre) - 1):
        direction = centre[i + 1] - centre[i]
        direction /= np.linalg.norm(direction)
        ends = []
        for j, shift in ((i, -_OVERLAP_M), (i + 1, _OVERLAP_M)):
            ends.append(centre[j] + shift * direction + section[:, :1] * frames[j, 0] + section[:, 1:] * frames[j, 1])
        pieces.append(np.vstack(ends))
    return pieces


def _mug_handle(p: Params) -> Pieces:
    """A D-shaped handle in the xz-plane on the +x side, its ends buried in the wall."""
    radius, wall, thickness = p["diameter"] / 2, p["wall"], p["handle_thickness"]
    x_start, x_bar = radius - wall / 2, radius + p["reach"] - thickness / 2
    z_high = p["height"] - p["handle_top"] - thickness / 2
    z_low = z_high - p["handle_span"]
    corner = min(0.45 * (x_bar - radius), 0.3 * p["handle_span"])
    points = [[x_start, z_low], [x_bar - corner, z_low]]
    for angle in np.linspace(-math.pi / 2, 0.0, 4)[1:]:
        points.append([x_bar - corner + corner * math.cos(angle), z_low + corner + corner * math.sin(angle)])
    for angle in np.linspace(0.0, math.pi / 2, 4)[:-1]:
        points.append([x_bar - corner + corner * math.cos(angle), z_high - corner + corner * math.sin(angle)])
    points += [[x_bar - corner, z_high], [x_start, z_high]]
    path = np.array(points)
    centre = np.column_stack([path[:, 0], np.zeros(len(path)), path[:, 1]])
    tangents = np.gradient(centre, axis=0)
    tangents /= np.linalg.norm(tangents, axis=1, keepdims=True)
    side = np.array([0.0, 1.0, 0.0])
    normals = np.cross(side, tangents)  # in the xz-plane, across the handle
    frames = np.stack([normals, np.broadcast_to(side, normals.shape)], axis=1)
    angles = np.linspace(0.0, 2 * math.pi, 12, endpoint=False)
    section = np.stack([thickness / 2 * np.cos(angles), p["handle_width"] / 2 * np.sin(angles)], axis=1)
    return _tube_pieces(centre, frames, section)


def _mug_pieces(p: Params) -> Pieces:
    """A convex base and 48 overlapping convex staves (the wall: open top, full-depth cavity) and the
    handle. The base sits a hair inside the staves' outer faces, so the bottom has a 0.2 mm foot."""
    radius, inner, bottom = p["diameter"] / 2, p["diameter"] / 2 - p["wall"], p["bottom"]
    step = 2 * math.pi / _MUG_STAVES
    spread = 0.25 * step  # each stave reaches a quarter of its width into both neighbours
    starts = np.arange(_MUG_STAVES) * step
    edge_angles = np.sort(np.concatenate([starts - spread, starts + spread]))
    foot = radius * math.cos((step + 2 * spread) / 2)  # inside every stave's outer chord
    base_outline = np.stack([foot * np.cos(edge_angles), foot * np.sin(edge_angles)], axis=1)
    pieces = [_prism(base_outline, 0.0, bottom)]
    for start in starts:
        a0, a1 = start - spread, start + step + spread
        outline = np.array([[r * math.cos(a), r * math.sin(a)] for r in (radius, inner) for a in (a0, a1)])
        pieces.append(_prism(outline, bottom - 5e-4, p["height"]))
    return pieces + _mug_handle(p)


def _mug_volume(p: Params) -> float:
    radius, inner = p["diameter"] / 2, p["diameter"] / 2 - p["wall"]
    wall = math.pi * (radius * radius - inner * inner) * (p["height"] - p["bottom"])
    handle_length = p["handle_span"] + 2 * (p["reach"] + p["wall"] / 2)
    handle = math.pi / 4 * p["handle_thickness"] * p["handle_width"] * handle_length
    return wall + math.pi * radius * radius * p["bottom"] + handle


# ----------------------------------------------------------------------------- banana
_BANANA_SEGMENTS = 12
_BANANA_BASE_CUT = 0.10  # of the thickest section's diameter: the flat it rests on


def _sample_banana(rng: np.random.Generator, index: int) -> Params:
    return {
        "length": _uniform(rng, BANANA_LENGTH_M),
        "bend": math.radians(float(rng.uniform(50.0, 100.0))),  # arc of the centre line
        "radius": float(rng.uniform(0.017, 0.022)),  # of the thickest section
        "tip": float(rng.uniform(0.25, 0.35)),  # the ends' radius, of the thickest
        "density": float(rng.uniform(900.0, 1050.0)),
    }


def _banana_radius(p: Params, s: np.ndarray) -> np.ndarray:
    return np.asarray(p["radius"] * np.maximum(np.sqrt(np.clip(np.sin(math.pi * s), 0.0, 1.0)), p["tip"]))


def _banana_pieces(p: Params) -> Pieces:
    """A tapering tube along a circular arc in the table plane (bulging to +x), its bottom cut flat."""
    s = np.linspace(0.0, 1.0, _BANANA_SEGMENTS + 1)
    bend_radius = p["length"] / p["bend"]
    theta = (s - 0.5) * p["bend"]
    centre = np.stack([bend_radius * np.cos(theta), bend_radius * np.sin(theta), np.zeros_like(s)], axis=1)
    outward = np.stack([np.cos(theta), np.sin(theta), np.zeros_like(s)], axis=1)
    up = np.broadcast_to(np.array([0.0, 0.0, 1.0]), outward.shape)
    frames = np.stack([outward, up], axis=1)
    angles = np.linspace(0.0, 2 * math.pi, 12, endpoint=False)
    unit = np.stack([np.cos(angles), np.sin(angles)], axis=1)
    radii = _banana_radius(p, s)
    pieces = []
    for i in range(_BANANA_SEGMENTS):
        direction = centre[i + 1] - centre[i]
        direction /= np.linalg.norm(direction)
        ends = [centre[j] + shift * direction + radii[j] * (unit[:, :1] * frames[j, 0] + unit[:, 1:] * frames[j, 1])
                for j, shift in ((i, -_OVERLAP_M), (i + 1, _OVERLAP_M))]
        pieces.append(np.vstack(ends))
    cut = -p["radius"] + _BANANA_BASE_CUT * 2 * p["radius"]
    for piece in pieces:
        piece[:, 2] = np.maximum(piece[:, 2], cut) - cut  # the flat base, on z = 0
    return pieces


def _banana_volume(p: Params) -> float:
    s = np.linspace(0.0, 1.0, 401)
    return float(np.trapezoid(math.pi * _banana_radius(p, s) ** 2, s) * p["length"])


# ----------------------------------------------------------------------------- lying cans and bottles
_LYING_KINDS = ("can", "bottle")
_LYING_PHASE = math.pi / _SECTIONS  # a face, not an edge, at the bottom once laid down


def _sample_lying(rng: np.random.Generator, index: int) -> Params:
    kind = index % len(_LYING_KINDS)  # cans and bottles alternate
    if _LYING_KINDS[kind] == "bottle":
        p = _fill_bottle(rng, _sample_bottle_shape(rng))
    else:
        diameter = _uniform(rng, CAN_DIAMETER_M)
        p = {"diameter": diameter, "height": min(float(rng.uniform(1.2, 3.5)) * diameter, CAN_LENGTH_MAX_M),
             "fill": float(rng.uniform(0.25, 1.0))}
        p["container_kg"] = CAN_EMPTY_KG
        p["mass_kg"] = CAN_EMPTY_KG + p["fill"] * WATER_KG_M3 * CAN_CAPACITY_SHARE * math.pi * diameter**2 / 4 * p["height"]
    p["kind"] = float(kind)
    return p


def _lying_pieces(p: Params) -> Pieces:
    """The can or bottle modelled along z, then laid along +x with a face of its 48-gon on z = 0."""
    if _LYING_KINDS[int(p["kind"])] == "bottle":
        upright = _bottle_pieces(p, phase=_LYING_PHASE)
    else:
        radius = p["diameter"] / 2
        upright = [np.vstack([_ring(radius, 0.0, phase=_LYING_PHASE), _ring(radius, p["height"], phase=_LYING_PHASE)])]
    laid = [np.column_stack([piece[:, 2], piece[:, 1], -piece[:, 0]]) for piece in upright]  # z -> x, x -> -z
    lowest = min(float(piece[:, 2].min()) for piece in laid)
    for piece in laid:
        piece[:, 2] -= lowest
    return laid


# ----------------------------------------------------------------------------- samplers and builders
_PIECES: dict[str, Callable[[Params], Pieces]] = {
    "spatula": _spatula_pieces, "small": _small_pieces, "bottle": _bottle_pieces, "mug": _mug_pieces,
    "banana": _banana_pieces, "lying": _lying_pieces,
}
_DRAW: dict[str, Callable[[np.random.Generator, int], Params]] = {  # (rng, index in the family)
    "spatula": _sample_spatula, "small": _sample_small, "bottle": _sample_bottle, "mug": _sample_mug,
    "banana": _sample_banana, "lying": _sample_lying,
}
_VOLUME: dict[str, Callable[[Params], float]] = {  # families whose mass is a density times this volume
    "spatula": _spatula_volume, "mug": _mug_volume, "banana": _banana_volume,
}


def _sampler(family: str) -> Callable[[np.random.Generator, int], tuple[Params, Dims]]:
    def sample(rng: np.random.Generator, index: int) -> tuple[Params, Dims]:
        low, high = MASS_RANGES_KG[family]
        for _ in range(_DRAWS):
            params = _DRAW[family](rng, index)
            if family in _VOLUME:
                params["mass_kg"] = params["density"] * _VOLUME[family](params)
            if not low <= params["mass_kg"] <= high:
                continue
            dims = footprint_dims(_PIECES[family](params))
            if family == "small" and max(dims) >= SMALL_MAX_EXTENT_M:
                continue
            return params, dims
        raise RuntimeError(f"no {family} within {low}-{high} kg")  # cannot happen with these ranges
    return sample


def _builder(family: str) -> Callable[[Params], trimesh.Trimesh]:
    def build(params: Params) -> trimesh.Trimesh:
        return pieces_mesh(_PIECES[family](params))
    return build


# sampler(rng, index in the family) -> (params, (a, b, H)); a draw of the right shape class is the caller's (procedural.py)
EVERYDAY_SAMPLERS: dict[str, Callable[[np.random.Generator, int], tuple[Params, Dims]]] = {f: _sampler(f) for f in EVERYDAY_FAMILIES}
EVERYDAY_BUILDERS: dict[str, Callable[[Params], trimesh.Trimesh]] = {f: _builder(f) for f in EVERYDAY_FAMILIES}
