"""Reading object meshes (user files and pybullet_data assets) and making them usable.

Everything returned is a `trimesh.Trimesh` in metres. Cleaning merges duplicated vertices
(OBJ files split them along texture seams, which makes a closed surface look open), drops
degenerate and duplicate faces, fuses overlapping closed parts into one surface (manifold3d),
and tries trimesh's repairs on open meshes. Real scans often stay open after that: callers then
use ray-vote inside/outside (see `sdf.py`) instead of the mesh's own volume.
"""
from __future__ import annotations

import logging
import math
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from .errors import ObjectLoadError

log = logging.getLogger(__name__)

SUPPORTED_SUFFIXES = (".obj", ".stl", ".ply", ".glb")
# A pushable object is centimetres to tens of centimetres; outside this the file is almost
# certainly in the wrong unit (millimetres) or not an object at all.
MIN_EXTENT_M = 0.005
MAX_EXTENT_M = 1.0
# glTF is +Y up by specification; the world here is +Z up.
_GLTF_Y_UP_TO_Z_UP = trimesh.transformations.rotation_matrix(math.pi / 2, [1.0, 0.0, 0.0])


def read_mesh_file(path: Path) -> trimesh.Trimesh:
    """Parse a user mesh file (OBJ/STL/PLY/GLB, metres) into one triangle mesh.

    Raises ObjectLoadError naming the file for an unsupported type, a parse failure, a file with
    no triangles (e.g. a point cloud) or non-finite coordinates.
    """
    suffix = check_suffix(path)
    if not path.is_file():
        raise ObjectLoadError(f"{path}: no such file")
    if path.stat().st_size == 0:
        raise ObjectLoadError(f"{path}: file is empty")
    try:
        loaded = trimesh.load(str(path), file_type=suffix[1:], force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types for corrupt input; report them all alike
        raise ObjectLoadError(f"{path}: cannot parse as {suffix[1:].upper()}: {type(exc).__name__}: {exc}") from exc
    mesh = _as_triangle_mesh(loaded, path)
    if suffix == ".glb":
        mesh.apply_transform(_GLTF_Y_UP_TO_Z_UP)
    return mesh


def check_suffix(path: Path) -> str:
    """The lower-case suffix of a supported mesh file; ObjectLoadError naming the file otherwise."""
    suffix = path.suffix.lower()
    if suffix not in SUPPORTED_SUFFIXES:
        raise ObjectLoadError(f"{path}: unsupported mesh type {suffix or '(no extension)'!r}; supported: {', '.join(SUPPORTED_SUFFIXES)}")
    return suffix


def _as_triangle_mesh(loaded: object, source: Path | str) -> trimesh.Trimesh:
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        kind = type(loaded).__name__
        raise ObjectLoadError(f"{source}: contains no triangles (loaded as {kind}; a point cloud or an empty scene?)")
    if not np.all(np.isfinite(loaded.vertices)):
        raise ObjectLoadError(f"{source}: has non-finite (NaN/inf) vertex coordinates")
    return loaded


@dataclass(frozen=True)
class UrdfVisual:
    """The mesh a URDF link shows, with the scale and origin the URDF applies to it."""

    mesh_path: Path
    scale: tuple[float, float, float]
    origin: np.ndarray  # 4x4, link frame <- mesh frame


def read_urdf_visual(urdf_path: Path) -> UrdfVisual:
    """The first visual mesh of a single-link URDF (how pybullet_data objects declare their shape)."""
    try:
        root = ET.parse(urdf_path).getroot()
    except (OSError, ET.ParseError) as exc:
        raise ObjectLoadError(f"{urdf_path}: cannot read URDF: {exc}") from exc
    visual = root.find(".//visual")
    mesh = visual.find("geometry/mesh") if visual is not None else None
    filename = mesh.get("filename") if mesh is not None else None
    if visual is None or mesh is None or not filename:
        raise ObjectLoadError(f"{urdf_path}: no visual mesh")
    scale = [float(v) for v in (mesh.get("scale") or "1 1 1").split()]
    origin = visual.find("origin")
    xyz = [float(v) for v in (origin.get("xyz", "0 0 0") if origin is not None else "0 0 0").split()]
    rpy = [float(v) for v in (origin.get("rpy", "0 0 0") if origin is not None else "0 0 0").split()]
    roll, pitch, yaw = rpy
    transform = trimesh.transformations.euler_matrix(roll, pitch, yaw, axes="sxyz")
    transform[:3, 3] = xyz
    return UrdfVisual(urdf_path.parent / filename, (scale[0], scale[1], scale[2]), transform)


def read_asset_mesh(mesh_path: Path, scale: Sequence[float] = (1.0, 1.0, 1.0),
                    transform: np.ndarray | None = None) -> trimesh.Trimesh:
    """A bundled asset mesh with a URDF-style per-axis scale, then a rigid transform."""
    try:
        loaded = trimesh.load(str(mesh_path), force="mesh", process=False)
    except Exception as exc:
        raise ObjectLoadError(f"{mesh_path}: cannot parse: {type(exc).__name__}: {exc}") from exc
    mesh = _as_triangle_mesh(loaded, mesh_path)
    mesh.apply_transform(np.diag([*scale, 1.0]))
    if transform is not None:
        mesh.apply_transform(transform)
    return mesh


def check_extent(mesh: trimesh.Trimesh, source: str) -> None:
    """Reject meshes whose size cannot be a pushable object in metres."""
    extent = float(np.max(mesh.extents))
    if extent > MAX_EXTENT_M:
        raise ObjectLoadError(
            f"{source}: largest extent is {extent:.3g} m, over {MAX_EXTENT_M} m — meshes must be in metres "
            "(is this file in millimetres? scale it by 0.001)"
        )
    if extent < MIN_EXTENT_M:
        raise ObjectLoadError(f"{source}: largest extent is {extent:.3g} m, under {MIN_EXTENT_M} m — too small to push (or not in metres)")


def clean_mesh(mesh: trimesh.Trimesh, source: str) -> trimesh.Trimesh:
    """Merge texture / normal seams, drop degenerate and duplicate faces, check the size."""
    mesh = trimesh.Trimesh(vertices=np.asarray(mesh.vertices, dtype=np.float64), faces=np.asarray(mesh.faces), process=False)
    mesh.merge_vertices(merge_tex=True, merge_norm=True)
    mesh.update_faces(mesh.nondegenerate_faces())
    mesh.update_faces(mesh.unique_faces())
    mesh.remove_unreferenced_vertices()
    if len(mesh.faces) == 0:
        raise ObjectLoadError(f"{source}: no non-degenerate triangles left after cleaning")
    check_extent(mesh, source)
    return mesh


def make_solid(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """Fuse overlapping closed parts and repair what trimesh can; the result may still be open."""
    mesh = fuse_closed_parts(mesh)
    if not mesh.is_watertight:
        trimesh.repair.fill_holes(mesh)  # closes triangle / quad holes only: fans over larger holes can be wrong
    trimesh.repair.fix_normals(mesh, multibody=True)  # consistent winding, outward for closed parts
    return mesh


def split_bodies(mesh: trimesh.Trimesh) -> list[trimesh.Trimesh]:
    return list(mesh.split(only_watertight=False))


def fuse_closed_parts(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """Union overlapping closed parts (e.g. a set of convex hulls) so no face lies inside the solid."""
    bodies = split_bodies(mesh)
    if len(bodies) < 2 or not all(body.is_watertight for body in bodies):
        return mesh
    try:
        fused: trimesh.Trimesh = trimesh.boolean.union(bodies, engine="manifold")
    except Exception as exc:  # manifold3d refuses some inputs; the parts still work without fusing
        log.debug("union of %d parts failed (%s); keeping them separate", len(bodies), exc)
        return mesh
    if not fused.is_watertight or fused.volume <= 0:
        return mesh
    return fused


def convex_bodies(mesh: trimesh.Trimesh) -> list[trimesh.Trimesh] | None:
    """The mesh's parts when every part is a closed convex solid (then they are its decomposition)."""
    bodies = split_bodies(mesh)
    if all(body.is_watertight and body.is_convex for body in bodies):
        return bodies
    return None
