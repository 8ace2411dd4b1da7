"""Physical geometry of an object: mass properties, its body frame O, resting poses, shape class.

Object frame O: origin at the centre of mass; axes along the principal axes of inertia (kept
equal to the source's axes when those already are principal, e.g. procedural shapes). With this
choice the URDF inertial frame *is* the link frame, so PyBullet's base pose (which is the
centre-of-mass frame) equals O's pose, and the inertia tensor PyBullet keeps (only its diagonal)
is the full tensor.

Resting pose: a rotation R (O -> table frame, up to yaw) and the height h of the centre of mass
when the lowest point touches z = 0. Placing O at T_D_O = [Rz(yaw) R | (0, 0, h)] puts the object
on the table with its centre of mass above D's origin, as docs/architecture.md §Frames requires.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import trimesh
from scipy.spatial import ConvexHull, QhullError

from .errors import ObjectLoadError
from .sdf import inside_mask, node_axes

SHAPE_CLASSES = ("flat", "volumetric", "tall")
# Shape class from height H over footprint width w = sqrt(a·b) (a, b: sides of the smallest
# rectangle around the footprint): flat if H < 0.4 w (books, plates, jenga block), tall if
# H > 1.5 w (bottles, cans, cereal boxes), volumetric otherwise (mugs, boxes, toys).
FLAT_MAX_RATIO = 0.4
TALL_MIN_RATIO = 1.5
# An object whose resting pose must tilt less than this before it tips over an edge of its support rolls
# (tipping_angle_deg): a tessellated ball or lying can's facet gives a few degrees, the flattest-based things
# that stand (a box on end, a jenga block upright) over 10.
ROLLS_BELOW_DEG = 6.0
# Below this revolution_deviation a surface is a body of revolution about the axis, as a camera or the table sees
# it (the library's bodies of revolution 0.006-0.036; its curved bananas 0.045 or more, every other shape more).
REVOLUTION_MAX = 0.1
# A true body of revolution about a horizontal axis (below TRUE_REVOLUTION_MAX: a ball, a lying fruit or can)
# resting on a small flat of its own still rolls: the flat holds it where it is put, a push tips it off the flat's
# edge and it rolls on. A ball on a 1 mm flat must tilt about 10 degrees first, a lemon lying on a 2 mm flat about
# 20, a banana (no true body of revolution) 14-24 and then rocks back; such a body rolls below
# ROLLS_ON_FLAT_BELOW_DEG.
TRUE_REVOLUTION_MAX = 0.04
ROLLS_ON_FLAT_BELOW_DEG = 25.0
# What makes it a flat of its own, not a facet: it stands on under this share of its footprint (support_share: a
# ball's flat about 0.03, a fruit's about 0.1), where a tessellated capsule lying on one of its facets stands on
# 0.16 or more and stays where it is put (every library capsule, in each of its resting poses).
FLAT_SUPPORT_MAX_SHARE = 0.15
MIN_POSE_PROBABILITY = 0.01  # quasi-static drop probability below which a pose is ignored
MAX_RESTING_POSES = 8
NATIVE_MATCH_DEG = 2.0
SUPPORT_TOLERANCE_M = 2e-4
STABLE_POSE_HULL_FACES = 1500
VOXEL_MASS_RESOLUTION = 64


@dataclass(frozen=True, eq=False)
class RestingPose:
    """A stable way for the object to lie on the table."""

    rotation: np.ndarray  # 3x3, O -> table-aligned frame (yaw 0)
    height: float  # centre-of-mass height above the table (m)
    probability: float  # quasi-static probability of landing in this pose (trimesh)
    native: bool = False  # the source's own upright orientation (as modelled / as designed)

    def transform(self, yaw_rad: float = 0.0) -> np.ndarray:
        """T_D_O: the object resting in this pose, rotated by `yaw_rad` about D's z axis."""
        c, s = math.cos(yaw_rad), math.sin(yaw_rad)
        yaw = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        out = np.eye(4)
        out[:3, :3] = yaw @ self.rotation
        out[2, 3] = self.height
        return out


@dataclass(frozen=True, eq=False)
class MassProperties:
    """Volume, centre of mass and inertia at unit density, in the frame they were computed in."""

    volume: float
    center_of_mass: np.ndarray
    unit_inertia: np.ndarray  # 3x3 about the centre of mass, for density 1 kg/m^3
    from_voxels: bool


def mass_properties(mesh: trimesh.Trimesh, source: str) -> MassProperties:
    """Exact (divergence theorem) for closed meshes; from the ray-vote voxel fill for open ones."""
    if mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0:
        props = mesh.mass_properties  # density defaults to 1
        return MassProperties(float(props["volume"]), np.asarray(props["center_mass"]), np.asarray(props["inertia"]), False)
    return _voxel_mass_properties(mesh, source)


def _voxel_mass_properties(mesh: trimesh.Trimesh, source: str, resolution: int = VOXEL_MASS_RESOLUTION) -> MassProperties:
    lower, upper = mesh.bounds
    cell = (upper - lower) / (resolution - 2)
    lower, upper = lower - 0.5 * cell, upper + 0.5 * cell  # node-centred voxels covering the mesh
    axes = node_axes(lower, upper, resolution)
    filled = inside_mask(mesh, axes)
    if not filled.any():
        raise ObjectLoadError(f"{source}: the surface encloses no volume (an open sheet, or holes on most sides)")
    centres = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)[filled]
    cell = (upper - lower) / (resolution - 1)
    voxel_volume = float(np.prod(cell))
    com = centres.mean(axis=0)
    r = centres - com
    inertia = (np.eye(3) * (r * r).sum() - r.T @ r) * voxel_volume
    inertia += np.diag([cell[1] ** 2 + cell[2] ** 2, cell[0] ** 2 + cell[2] ** 2, cell[0] ** 2 + cell[1] ** 2]) * voxel_volume * len(r) / 12.0
    return MassProperties(voxel_volume * len(r), com, inertia, True)


def principal_frame(props: MassProperties) -> np.ndarray:
    """T_source_O: centre of mass + principal axes (source axes kept when already principal)."""
    inertia = props.unit_inertia
    off_diagonal = np.abs(inertia - np.diag(np.diag(inertia))).max()
    if off_diagonal <= 1e-6 * np.abs(np.diag(inertia)).max():
        rotation = np.eye(3)
    else:
        _, vectors = np.linalg.eigh(inertia)  # ascending moments
        # one deterministic sign per axis: its largest component positive; then right-handed
        signs = np.sign(vectors[np.abs(vectors).argmax(axis=0), np.arange(3)])
        rotation = vectors * signs
        if np.linalg.det(rotation) < 0:
            rotation[:, 2] *= -1
    transform = np.eye(4)
    transform[:3, :3] = rotation
    transform[:3, 3] = props.center_of_mass
    return transform


def resting_poses(mesh_o: trimesh.Trimesh, native_rotation: np.ndarray | None) -> tuple[list[RestingPose], int]:
    """Stable poses of a mesh given in O (centre of mass at the origin), most probable first.

    Poses less probable than MIN_POSE_PROBABILITY are dropped, except the native orientation:
    when it is given and statically stable it is kept whatever its drop probability (a capsule
    lying on its small flat base is still a way people put it down) and it is the default.
    Returns the poses and the index of the default (the native pose, else the most probable).
    """
    with np.errstate(invalid="ignore", divide="ignore"):  # trimesh's spherical areas of sliver triangles
        transforms, probabilities = trimesh.poses.compute_stable_poses(_coarse_hull(mesh_o), center_mass=np.zeros(3), sigma=0.0, n_samples=1)
    order = np.argsort(-np.asarray(probabilities), kind="stable")
    candidates = [
        RestingPose(transforms[i][:3, :3].copy(), _rest_height(mesh_o, transforms[i][:3, :3]), float(probabilities[i])) for i in order
    ]
    poses = [pose for pose in candidates if pose.probability >= MIN_POSE_PROBABILITY][:MAX_RESTING_POSES] or candidates[:1]
    if native_rotation is None:
        return poses, 0
    # trimesh can miss a facet whose sliver triangles give NaN areas: then the static check decides
    match = _matching_pose(candidates, native_rotation)
    if match is None and not is_statically_stable(mesh_o, native_rotation):
        return poses, 0
    probability = candidates[match].probability if match is not None else 0.0
    native = RestingPose(native_rotation.copy(), _rest_height(mesh_o, native_rotation), probability, native=True)
    poses = [pose for pose in poses if match is None or pose is not candidates[match]]
    poses.append(native)
    poses.sort(key=lambda pose: -pose.probability)
    return poses, poses.index(native)


def is_statically_stable(mesh_o: trimesh.Trimesh, rotation: np.ndarray, margin: float = 1e-4) -> bool:
    """True if, resting in `rotation`, the centre of mass (O's origin) is over the support polygon.

    The support polygon is made of the hull vertices within SUPPORT_TOLERANCE_M of the lowest
    one: modelled flat bottoms are flat only to tenths of a millimetre.
    """
    polygon = _support_polygon(mesh_o, rotation)
    return polygon is not None and bool(np.all(polygon.equations[:, 2] <= -margin))  # origin inside by `margin`


def tipping_angle_deg(mesh_o: trimesh.Trimesh, rotation: np.ndarray) -> float:
    """How far (degrees) the object, resting in `rotation` (O -> a table-aligned frame; any yaw), must be tilted
    about the nearest edge of its support before its centre of mass passes over that edge: atan(the centre's
    horizontal distance to the edge / its height). 0 when it touches the table at a point or along a line
    (a ball, a can on its side), or does not rest at all.

    What rolls has no edge to tip over: a tessellated body of revolution lies on one facet (360/sections/2
    degrees: 3.75 for the library's 48 sections), a box or a standing can needs tens of degrees."""
    polygon = _support_polygon(mesh_o, rotation)
    if polygon is None:
        return 0.0
    height = -float((np.asarray(mesh_o.convex_hull.vertices) @ np.asarray(rotation)[2]).min())
    margin = max(0.0, float(np.min(-polygon.equations[:, 2])))  # the origin's distance to the nearest edge
    return math.degrees(math.atan2(margin, max(height, 1e-9)))


def rolls(mesh_o: trimesh.Trimesh, rotation: np.ndarray) -> bool:
    """Whether the object, resting in `rotation` (O -> table-aligned frame), rolls when pushed rather than
    sliding or tipping: a ball, a fruit or a can on its side. It has no edge to tip over (tipping_angle_deg below
    ROLLS_BELOW_DEG) and is a body of revolution about a horizontal axis (revolution_deviation below
    REVOLUTION_MAX), the axis it rolls about; an irregular lump balanced near an edge of its support only tips.
    The axes tried: the table's x and y (for a ball any horizontal axis is one) and O's principal axes lying
    within 20 degrees of the table (a can on its side rolls about its own). A true body of revolution resting on a
    small flat (a ball or a fruit that stands where it is put) rolls too: see ROLLS_ON_FLAT_BELOW_DEG."""
    rotation = np.asarray(rotation, dtype=np.float64)
    tipping = tipping_angle_deg(mesh_o, rotation)
    if tipping >= max(ROLLS_BELOW_DEG, ROLLS_ON_FLAT_BELOW_DEG):
        return False
    axes = [rotation[0], rotation[1]] + [np.eye(3)[i] for i in range(3) if abs(rotation[2, i]) < math.sin(math.radians(20))]
    deviation = min(revolution_deviation(mesh_o, axis) for axis in axes)
    if tipping < ROLLS_BELOW_DEG:
        return deviation < REVOLUTION_MAX
    return deviation < TRUE_REVOLUTION_MAX and support_share(mesh_o, rotation) < FLAT_SUPPORT_MAX_SHARE


def support_share(mesh_o: trimesh.Trimesh, rotation: np.ndarray) -> float:
    """The area the object, resting in `rotation`, stands on as a share of its footprint's (0: a point or a line)."""
    polygon = _support_polygon(mesh_o, rotation)
    if polygon is None:
        return 0.0
    footprint = ConvexHull((np.asarray(mesh_o.convex_hull.vertices) @ np.asarray(rotation).T)[:, :2])
    return float(polygon.volume / footprint.volume)  # a 2-D hull's volume is its area


def revolution_deviation(mesh: trimesh.Trimesh, axis: np.ndarray) -> float:
    """How far `mesh` is from a body of revolution about `axis` (in the mesh's frame) through its surface's
    centre: the RMS over the surface of ((p - c) x n) . axis / radius, 0 for a body of revolution, ~0.2-0.3 for
    a box. Turning such a body about that axis changes nothing a camera sees or the table touches."""
    points, faces = trimesh.sample.sample_surface(mesh, 2000, seed=0)
    normals = np.asarray(mesh.face_normals, dtype=np.float64)[faces]
    points = np.asarray(points, dtype=np.float64)
    centre = points.mean(axis=0)
    radius = max(float(np.max(np.linalg.norm(points - centre, axis=1))), 1e-6)
    unit = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    lever = np.cross(points - centre, normals) @ unit / radius
    return float(np.sqrt(np.mean(lever**2)))


def _support_polygon(mesh_o: trimesh.Trimesh, rotation: np.ndarray) -> ConvexHull | None:
    """The convex hull (in the table plane) of the hull vertices within SUPPORT_TOLERANCE_M of the lowest, the
    object resting in `rotation`; None when they touch at a point or along a line."""
    vertices = np.asarray(mesh_o.convex_hull.vertices) @ np.asarray(rotation).T
    lowest = vertices[:, 2].min()
    support = vertices[vertices[:, 2] < lowest + SUPPORT_TOLERANCE_M][:, :2]
    if len(support) < 3:
        return None
    try:
        return ConvexHull(support)
    except QhullError:  # collinear contact: an edge, not a face
        return None


def _coarse_hull(mesh: trimesh.Trimesh, max_faces: int = STABLE_POSE_HULL_FACES) -> trimesh.Trimesh:
    """The convex hull, thinned to about `max_faces` faces for trimesh's per-face Python loop.

    A smooth 10k-vertex scan has a ~12k-face hull (seconds in compute_stable_poses); keeping the
    outermost hull vertex per cell of a grid only moves the hull by a fraction of a cell, and
    flat bottoms stay flat (their kept vertices are still coplanar).
    """
    hull: trimesh.Trimesh = mesh.convex_hull
    if len(hull.faces) <= max_faces:
        return hull
    vertices = hull.vertices
    cell = float(np.max(hull.extents)) / math.sqrt(max_faces / 2.0)
    keys = np.floor((vertices - vertices.min(axis=0)) / cell).astype(np.int64)
    order = np.argsort(-np.linalg.norm(vertices, axis=1), kind="stable")  # outermost first
    _, first = np.unique(keys[order], axis=0, return_index=True)
    thinned: trimesh.Trimesh = trimesh.convex.convex_hull(vertices[order[first]])
    return thinned


def _rest_height(mesh_o: trimesh.Trimesh, rotation: np.ndarray) -> float:
    return float(-(mesh_o.vertices @ rotation[2]).min())


def _matching_pose(poses: list[RestingPose], rotation: np.ndarray) -> int | None:
    """The pose with the same up direction (in O) as `rotation`, if any."""
    up = rotation[2]  # world z expressed in O
    cos_limit = math.cos(math.radians(NATIVE_MATCH_DEG))
    for index, pose in enumerate(poses):
        if float(np.dot(pose.rotation[2], up)) >= cos_limit:
            return index
    return None


def footprint_and_height(mesh_o: trimesh.Trimesh, pose: RestingPose) -> tuple[float, float, float]:
    """(a, b, H): sides of the smallest footprint rectangle (a >= b) and the height, in metres."""
    hull = mesh_o.convex_hull.vertices @ pose.rotation.T
    _, extents = trimesh.bounds.oriented_bounds_2D(hull[:, :2])
    a, b = sorted((float(extents[0]), float(extents[1])), reverse=True)
    height = float(hull[:, 2].max() - hull[:, 2].min())
    return a, b, height


def shape_class(a: float, b: float, height: float) -> str:
    """flat / volumetric / tall from the footprint sides and the height (see the thresholds)."""
    ratio = height / math.sqrt(a * b)
    if ratio < FLAT_MAX_RATIO:
        return "flat"
    if ratio > TALL_MIN_RATIO:
        return "tall"
    return "volumetric"
