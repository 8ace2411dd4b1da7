"""ObjectModel: everything the algorithms need about one object, loaded by id or mesh file.

`load_object("proc-box-017")`, `load_object("pb-mug")`, `load_object("scan.ply")`; ids that come
from elsewhere (a bus message) go through `load_library_object`, which never reads an id as a path.

The expensive parts are cached on disk by a content hash of the source (file bytes, scale,
procedural parameters) and the pipeline version: the cleaned mesh in the object frame O, mass
properties and resting poses (`geometry.npz`, computed at load), the SDF grid (`sdf-<res>.npz`,
computed on first use), the convex decomposition and URDF (physics.py, on first use).
"""
from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pybullet
import torch
import trimesh
from tqdm import tqdm

from shared.atomic import atomic_write_text

from . import meshio
from .cache import cache_root, load_npz, save_npz
from .catalog import (
    ObjectInfo,
    ObjectSource,
    is_user_mesh_id,
    list_object_ids,
    procedural_info,
    read_source_mesh,
    resolve_library_id,
    resolve_source,
    source_fingerprint,
    split_of,
)
from .errors import ObjectLoadError, UnknownObjectError
from .geometry import (
    RestingPose,
    footprint_and_height,
    mass_properties,
    principal_frame,
    resting_poses,
    shape_class,
)
from .procedural import is_procedural_id
from .sdf import DEFAULT_RESOLUTION, SdfGrid, compute_sdf_grid

PIPELINE_VERSION = 2  # bump when any cached artefact would change
DEFAULT_DENSITY = 500.0  # kg/m^3: wood / plastic-like household objects
MASS_LIMITS_KG = (0.05, 1.5)  # what a hand can push; hollow or huge meshes would say otherwise
# An object with a designed mass (the everyday procedural families: a real category's mass, e.g. a
# 3 g bottle cap or a 0.35 kg ceramic mug) keeps it: it is not a guess from a shape, so not clamped.


@dataclass(eq=False)
class _Geometry:
    """The cached result of the geometry pipeline (all in the object frame O)."""

    vertices: np.ndarray
    faces: np.ndarray
    T_source_O: np.ndarray
    volume: float
    unit_inertia: np.ndarray
    mass_from_voxels: bool
    watertight: bool
    poses: list[RestingPose]
    default_pose_index: int
    convex_parts: list[tuple[np.ndarray, np.ndarray]] | None

    def to_arrays(self) -> dict[str, np.ndarray]:
        parts = self.convex_parts or []
        return {
            "vertices": self.vertices,
            "faces": self.faces,
            "T_source_O": self.T_source_O,
            "volume": np.float64(self.volume),
            "unit_inertia": self.unit_inertia,
            "mass_from_voxels": np.bool_(self.mass_from_voxels),
            "watertight": np.bool_(self.watertight),
            "pose_rotations": np.stack([p.rotation for p in self.poses]),
            "pose_heights": np.array([p.height for p in self.poses]),
            "pose_probabilities": np.array([p.probability for p in self.poses]),
            "pose_native": np.array([p.native for p in self.poses]),
            "default_pose_index": np.int64(self.default_pose_index),
            "has_convex_parts": np.bool_(self.convex_parts is not None),
            "part_vertex_counts": np.array([len(v) for v, _ in parts], dtype=np.int64),
            "part_face_counts": np.array([len(f) for _, f in parts], dtype=np.int64),
            "part_vertices": np.concatenate([v for v, _ in parts]) if parts else np.zeros((0, 3)),
            "part_faces": np.concatenate([f for _, f in parts]) if parts else np.zeros((0, 3), dtype=np.int64),
        }

    @classmethod
    def from_arrays(cls, a: dict[str, np.ndarray]) -> _Geometry:
        poses = [
            RestingPose(r, float(h), float(p), bool(n))
            for r, h, p, n in zip(a["pose_rotations"], a["pose_heights"], a["pose_probabilities"], a["pose_native"],
                                  strict=True)
        ]
        parts = None
        if bool(a["has_convex_parts"]):
            vertex_splits = np.cumsum(a["part_vertex_counts"])[:-1]
            face_splits = np.cumsum(a["part_face_counts"])[:-1]
            parts = list(zip(np.split(a["part_vertices"], vertex_splits), np.split(a["part_faces"], face_splits),
                             strict=True))
        return cls(
            a["vertices"], a["faces"], a["T_source_O"], float(a["volume"]), a["unit_inertia"], bool(a["mass_from_voxels"]),
            bool(a["watertight"]), poses, int(a["default_pose_index"]), parts,
        )


def _compute_geometry(source: ObjectSource) -> _Geometry:
    raw = read_source_mesh(source)
    clean = meshio.clean_mesh(raw, source.label)
    parts = meshio.convex_bodies(clean)  # before fusing: touching convex parts are a decomposition
    solid = meshio.make_solid(clean)
    props = mass_properties(solid, source.label)
    if props.volume <= 0:
        raise ObjectLoadError(f"{source.label}: the surface encloses no volume")
    T_source_O = principal_frame(props)
    T_O_source = np.linalg.inv(T_source_O)
    solid.apply_transform(T_O_source)
    rotation = T_source_O[:3, :3]
    poses, default = resting_poses(solid, rotation if source.native_upright else None)
    convex_parts = None
    if parts is not None:
        convex_parts = [(trimesh.transform_points(p.vertices, T_O_source), np.asarray(p.faces, dtype=np.int64)) for p in parts]
    return _Geometry(
        np.asarray(solid.vertices, dtype=np.float64),
        np.asarray(solid.faces, dtype=np.int64),
        T_source_O,
        props.volume,
        rotation.T @ props.unit_inertia @ rotation,
        props.from_voxels,
        bool(solid.is_watertight),
        poses,
        default,
        convex_parts,
    )


class ObjectModel:
    """One object: mesh, mass, resting poses, SDF, surface samples; all in its frame O.

    Frame O: origin at the centre of mass, axes along the principal axes of inertia (so the
    URDF inertial frame is the link frame). `T_D_O(pose, yaw)` places the object resting on the
    table with its centre of mass above D's origin.
    """

    def __init__(
        self, source: ObjectSource, key: str, geometry: _Geometry, *, density: float | None, sdf_resolution: int,
        cache_dir: Path, provenance: dict[str, str | None],
    ) -> None:
        self.id = source.object_id
        self.source = source.source
        self.family = source.family
        self.source_path = source.path
        self.key = key
        self.cache_dir = cache_dir
        self.provenance = provenance
        self._geometry = geometry
        self.mesh = trimesh.Trimesh(geometry.vertices, geometry.faces, process=False)
        self.mesh_hash = hashlib.sha256(np.round(geometry.vertices * 1e9).astype(np.int64).tobytes() + geometry.faces.astype(np.int64).tobytes()).hexdigest()
        self.T_source_O = geometry.T_source_O
        self.watertight = geometry.watertight
        self.mass_from_voxels = geometry.mass_from_voxels
        self.volume = geometry.volume
        if density is None and source.mass_kg is not None:  # the designed mass, spread uniformly over the solid
            self.mass = float(source.mass_kg)
            self.density = self.mass / geometry.volume
        else:
            self.density = DEFAULT_DENSITY if density is None else density
            self.mass = float(np.clip(self.density * geometry.volume, *MASS_LIMITS_KG))
        self.inertia = geometry.unit_inertia * (self.mass / geometry.volume)
        self.resting_poses: list[RestingPose] = geometry.poses
        self.default_pose_index = geometry.default_pose_index
        self.sdf_resolution = sdf_resolution
        self._sdf: SdfGrid | None = None
        a, b, height = footprint_and_height(self.mesh, self.default_pose)
        self.info = ObjectInfo(self.id, shape_class(a, b, height), self.source, self.family, (a, b, height), split_of(self.id))

    def __repr__(self) -> str:
        a, b, h = self.info.size_m
        return f"ObjectModel({self.id}, {self.info.shape_class}, {a * 100:.1f}x{b * 100:.1f}x{h * 100:.1f} cm, {self.mass:.3f} kg)"

    # ------------------------------------------------------------------ poses
    @property
    def default_pose(self) -> RestingPose:
        """The native upright pose when stable, else the most probable one."""
        return self.resting_poses[self.default_pose_index]

    def T_D_O(self, pose_index: int | None = None, yaw_rad: float = 0.0) -> np.ndarray:
        """Object resting in pose `pose_index` (default pose if None), yawed, in D (4x4)."""
        pose = self.default_pose if pose_index is None else self.resting_poses[pose_index]
        return pose.transform(yaw_rad)

    def mesh_in_d(self, pose_index: int | None = None, yaw_rad: float = 0.0) -> trimesh.Trimesh:
        mesh = self.mesh.copy()
        mesh.apply_transform(self.T_D_O(pose_index, yaw_rad))
        return mesh

    @property
    def convex_parts(self) -> list[trimesh.Trimesh] | None:
        """The convex pieces of the source when it is made of them (None: physics.py runs V-HACD)."""
        if self._geometry.convex_parts is None:
            return None
        return [trimesh.Trimesh(v, f, process=False) for v, f in self._geometry.convex_parts]

    # ------------------------------------------------------------------ samples and distances
    def surface_points(self, n: int = 2048, seed: int = 0, T_D_O: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """n area-uniform surface samples and their outward normals, in O (or in D given T_D_O)."""
        points, faces = trimesh.sample.sample_surface(self.mesh, n, seed=seed)
        normals = self.mesh.face_normals[faces]
        if T_D_O is not None:
            T_D_O = np.asarray(T_D_O, dtype=np.float64)
            points, normals = points @ T_D_O[:3, :3].T + T_D_O[:3, 3], normals @ T_D_O[:3, :3].T
        return np.asarray(points, dtype=np.float64), np.asarray(normals, dtype=np.float64)

    @property
    def sdf(self) -> SdfGrid:
        """The SDF grid in O (loaded from the cache, or computed and cached on first use)."""
        if self._sdf is None:
            path = self.cache_dir / f"sdf-{self.sdf_resolution}.npz"
            arrays = load_npz(path)
            if arrays is not None:
                self._sdf = SdfGrid.from_arrays(arrays)
                self.provenance["sdf"] = "cache"
            else:
                self._sdf = compute_sdf_grid(self.mesh, self.sdf_resolution)
                save_npz(path, **self._sdf.to_arrays())
                self.provenance["sdf"] = "computed"
        return self._sdf

    def signed_distance(self, points: torch.Tensor, T_D_O: np.ndarray | torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Signed distance [...] and unit gradient [..., 3] at points [..., 3].

        Points are in O, or in D when T_D_O is given ([4, 4], or [B, 4, 4] for points [B, N, 3]);
        the gradient is returned in the same frame as the points. Differentiable w.r.t. points.
        """
        if T_D_O is None:
            return self.sdf.query(points)
        T = torch.as_tensor(T_D_O, dtype=points.dtype, device=points.device)
        rotation, translation = T[..., :3, :3], T[..., :3, 3]
        if T.ndim == 3:
            translation = translation.unsqueeze(-2)
        distance, gradient = self.sdf.query((points - translation) @ rotation)
        return distance, gradient @ rotation.transpose(-1, -2)


# ----------------------------------------------------------------------------- loading
def _object_key(source: ObjectSource) -> str:
    return hashlib.sha256(f"gd2p-object-v{PIPELINE_VERSION}\0".encode() + source_fingerprint(source)).hexdigest()


def _mesh_id_index(root: Path, object_id: str) -> Path:
    return root / "ids" / f"{object_id}.json"


def load_object(
    path_or_id: str | Path,
    *,
    density: float | None = None,
    sdf_resolution: int = DEFAULT_RESOLUTION,
    cache_dir: str | Path | None = None,
) -> ObjectModel:
    """Load a library object by id, or a user mesh (OBJ/STL/PLY/GLB in metres) by path.

    Mass: `density` (kg/m^3) times the volume, clamped to MASS_LIMITS_KG; without a density, an
    object's designed mass (everyday procedural families), else DEFAULT_DENSITY.
    A `mesh-<hash>` id works for a mesh file loaded before on this machine (its cached geometry).
    Raises ObjectLoadError (naming the id or file and the problem) for anything unusable.
    """
    if not isinstance(path_or_id, Path) and is_user_mesh_id(str(path_or_id)):
        return load_library_object(str(path_or_id), density=density, sdf_resolution=sdf_resolution, cache_dir=cache_dir)
    return _load_source(resolve_source(path_or_id), cache_root(cache_dir), density, sdf_resolution)


def load_library_object(
    object_id: str,
    *,
    density: float | None = None,
    sdf_resolution: int = DEFAULT_RESOLUTION,
    cache_dir: str | Path | None = None,
) -> ObjectModel:
    """Load a library object, or a user mesh loaded before, by its id only: an id is never read as a
    path, so one from the network cannot name a file. UnknownObjectError for anything else."""
    root = cache_root(cache_dir)
    if is_user_mesh_id(object_id):
        return _load_known_mesh_id(object_id, root, _checked_density(density), sdf_resolution)
    return _load_source(resolve_library_id(object_id), root, density, sdf_resolution)


def _checked_density(density: float | None) -> float | None:
    if density is not None and density <= 0:
        raise ValueError(f"density must be positive, got {density}")
    return density


def _load_source(source: ObjectSource, root: Path, density: float | None, sdf_resolution: int) -> ObjectModel:
    _checked_density(density)
    key = _object_key(source)
    directory = root / key
    arrays = load_npz(directory / "geometry.npz")
    provenance: dict[str, str | None] = {"geometry": "cache", "sdf": None}
    if arrays is None:
        geometry = _compute_geometry(source)
        save_npz(directory / "geometry.npz", **geometry.to_arrays())
        provenance["geometry"] = "computed"
    else:
        geometry = _Geometry.from_arrays(arrays)
    if source.source == "mesh":
        atomic_write_text(_mesh_id_index(root, source.object_id), json.dumps({"key": key, "path": str(source.path)}))
    return ObjectModel(source, key, geometry, density=density, sdf_resolution=sdf_resolution, cache_dir=directory, provenance=provenance)


def _load_known_mesh_id(object_id: str, root: Path, density: float | None, sdf_resolution: int) -> ObjectModel:
    index = _mesh_id_index(root, object_id)
    try:
        entry = json.loads(index.read_text())
    except (OSError, ValueError):
        raise UnknownObjectError(f"{object_id!r}: no mesh with this id was loaded on this machine (cache {root}); pass the mesh file instead") from None
    arrays = load_npz(root / entry["key"] / "geometry.npz")
    if arrays is None:
        raise UnknownObjectError(f"{object_id!r}: its cached geometry is gone from {root}; pass the mesh file {entry.get('path')} instead")
    source = ObjectSource(object_id, "mesh", "user", True, Path(entry["path"]))
    return ObjectModel(
        source, entry["key"], _Geometry.from_arrays(arrays), density=density, sdf_resolution=sdf_resolution,
        cache_dir=root / entry["key"], provenance={"geometry": "cache", "sdf": None},
    )


# ----------------------------------------------------------------------------- listing
def _catalog_path(root: Path) -> Path:
    return root / f"catalog-v{PIPELINE_VERSION}-pybullet-{pybullet.getAPIVersion()}.json"


def list_objects(split: str | None = None, *, cache_dir: str | Path | None = None, progress: bool = False) -> list[ObjectInfo]:
    """Info (class, size, split) of every library object, optionally of one split.

    Procedural objects are described by their designed dimensions. The others need their
    geometry (resting pose) once: the first call loads them (tens of seconds for the 1000
    random_urdfs; the geometry caches are kept) and remembers the results in a catalog file.
    """
    root = cache_root(cache_dir)
    ids = list_object_ids(split)
    path = _catalog_path(root)
    catalog = _read_catalog(path)
    missing = [i for i in ids if not is_procedural_id(i) and i not in catalog]
    for count, object_id in enumerate(tqdm(missing, desc="describing objects", unit="obj", disable=not progress), 1):
        info = load_object(object_id, cache_dir=cache_dir).info
        catalog[object_id] = {"shape_class": info.shape_class, "size_m": list(info.size_m)}
        if count % 100 == 0 or count == len(missing):
            catalog = {**_read_catalog(path), **catalog}  # keep what a concurrent lister added
            atomic_write_text(path, json.dumps(catalog, sort_keys=True))
    infos = []
    for object_id in ids:
        if is_procedural_id(object_id):
            infos.append(procedural_info(object_id))
            continue
        source = resolve_source(object_id)
        entry = catalog[object_id]
        infos.append(ObjectInfo(object_id, entry["shape_class"], source.source, source.family, tuple(entry["size_m"]), split_of(object_id)))
    return infos


def _read_catalog(path: Path) -> dict[str, Any]:
    try:
        catalog: dict[str, Any] = json.loads(path.read_text())
        return catalog
    except (OSError, ValueError):
        return {}
