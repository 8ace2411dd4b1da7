"""A captured cloud as an object the rest of the system plans around: ObjectModel, its pose, its BPS.

    captured = object_from_cloud(points_world)              # reconstruct once, cached by content hash
    captured.model                                          # shared.world.objects.ObjectModel (id mesh-<hash>)
    captured.T_world_O                                      # where the object stands, as captured
    T_world_D = direction_frame(captured.T_world_O[:3, 3], direction_deg)      # shared.frames
    features = bps_from_cloud(captured.object_points, T_world_D, checkpoint_bps)

The reconstruction is written as a PLY mesh in a capture frame C (world axes, origin on the table
under the middle of the object) and loaded through the object library's own mesh path
(`load_object(path)`: cleaning, mass, frame O = centre of mass + principal axes, resting poses,
SDF, URDF), so a captured object is modelled exactly like a mesh upload. The PLY holds the
reconstruction's convex pieces as separate closed bodies: the library takes a mesh made of convex
bodies as its own collision decomposition (shared.world.objects.meshio.convex_bodies) and fuses them
into one solid for mass and shape, so V-HACD never runs on a capture (it took 1.5-2 s for a
captured mug). Its native upright pose is the pose it was captured in, so
`T_world_O = T_world_C @ model.T_source_O`.

Cache: `<objects cache>/clouds/<key>/` holds mesh.ply, the object's points and meta.json, keyed by a
hash of the cloud's bytes, the region and the settings; every service that is handed the same
cloud loads the same mesh instead of reconstructing it again. Writes are atomic, so concurrent
workers reconstructing the same cloud never see half a file.
"""
from __future__ import annotations

import dataclasses
import hashlib
import io
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import trimesh

from shared.atomic import atomic_write_bytes, atomic_write_text
from shared.frames import make_transform, points_world_to_d
from shared.world.bps import BasisPointSet
from shared.world.objects import ObjectLoadError, ObjectModel, load_object
from shared.world.objects.cache import cache_root

from .cloud import check_points, voxel_downsample
from .errors import PerceptionError
from .reconstruct import Reconstruction, ReconstructionSettings, Region, reconstruct

RECONSTRUCTION_VERSION = 2  # bump when the pipeline's output for the same input changes
BPS_POINTS = 2048  # as many points as the mesh BPS samples (shared/sampling/dataset.py SURFACE_POINTS)
BPS_SPACING_M = 0.002  # thinned to uniform density first, so a camera's close-up side does not dominate


@dataclass(eq=False)
class CloudObject:
    """A reconstructed object: its model, where it stands, and the points it was seen as."""

    model: ObjectModel
    T_world_O: np.ndarray  # 4x4
    object_points: np.ndarray  # [M, 3] world frame: the object's cluster, for the BPS
    mesh_path: Path
    key: str
    from_cache: bool
    meta: dict[str, Any]  # meta.json: T_world_C, point counts, cluster gap, convex parts, seconds, ...


def cloud_key(points: np.ndarray, region: Region | None, settings: ReconstructionSettings) -> str:
    """Content hash of a reconstruction's inputs (cloud bytes, region, settings, pipeline version)."""
    digest = hashlib.sha256(f"gd2p-cloud-v{RECONSTRUCTION_VERSION}\0".encode())
    spec = {"region": None if region is None else dataclasses.asdict(region), "settings": dataclasses.asdict(settings)}
    digest.update(json.dumps(spec, sort_keys=True).encode() + b"\0")
    digest.update(np.ascontiguousarray(points, dtype="<f8").tobytes())
    return digest.hexdigest()


def object_from_cloud(
    points: npt.ArrayLike,
    region: Region | None = None,
    settings: ReconstructionSettings | None = None,
    cache_dir: str | Path | None = None,
) -> CloudObject:
    """Reconstruct a world-frame cloud (once per content) and load it as an object; PerceptionError if unusable."""
    points = check_points(points)
    settings = settings or ReconstructionSettings()
    key = cloud_key(points, region, settings)
    directory = cache_root(cache_dir) / "clouds" / key
    cached = _load_cached(directory, key, cache_dir)
    if cached is not None:
        return cached
    return object_from_reconstruction(reconstruct(points, region, settings), cache_dir=cache_dir, key=key)


def object_from_reconstruction(recon: Reconstruction, cache_dir: str | Path | None = None, key: str | None = None) -> CloudObject:
    """Write the reconstruction's mesh (frame C) to the cache and load it as an ObjectModel."""
    key = key or hashlib.sha256(recon.mesh.vertices.tobytes() + recon.mesh.faces.tobytes()).hexdigest()
    directory = cache_root(cache_dir) / "clouds" / key
    low, high = recon.mesh.bounds
    T_world_C = make_transform(np.eye(3), np.array([(low[0] + high[0]) / 2.0, (low[1] + high[1]) / 2.0, 0.0]))
    pieces_c = trimesh.util.concatenate(recon.convex_parts)  # separate closed convex bodies: the decomposition
    pieces_c.apply_translation(-T_world_C[:3, 3])
    meta = {
        "T_world_C": T_world_C.tolist(), "method": recon.method, "input_points": recon.input_points,
        "object_points": len(recon.object_points), "table_points": recon.table_points,
        "below_table_points": recon.below_table_points, "table_tolerance_m": recon.table_tolerance_m,
        "point_spacing_m": recon.point_spacing_m, "cluster_gap_m": recon.cluster_gap_m,
        "convex_parts": len(recon.convex_parts), "seconds": round(recon.timings.total, 4),
        "other_clusters": [c.tolist() for c in recon.other_clusters],
    }
    buffer = io.BytesIO()
    np.save(buffer, np.asarray(recon.object_points, dtype=np.float64))
    atomic_write_bytes(directory / "object_points.npy", buffer.getvalue())
    atomic_write_bytes(directory / "mesh.ply", trimesh.exchange.ply.export_ply(pieces_c, encoding="binary"))
    atomic_write_text(directory / "meta.json", json.dumps(meta))  # last: its presence marks a complete entry
    return _as_object(directory, key, T_world_C, np.asarray(recon.object_points), meta, False, cache_dir)


def _load_cached(directory: Path, key: str, cache_dir: str | Path | None) -> CloudObject | None:
    try:
        meta = json.loads((directory / "meta.json").read_text())
        object_points = np.load(directory / "object_points.npy", allow_pickle=False)
    except (OSError, ValueError):
        return None
    return _as_object(directory, key, np.asarray(meta["T_world_C"]), object_points, meta, True, cache_dir)


def _as_object(directory: Path, key: str, T_world_C: np.ndarray, object_points: np.ndarray, meta: dict[str, Any],
               from_cache: bool, cache_dir: str | Path | None) -> CloudObject:
    path = directory / "mesh.ply"
    try:
        model = load_object(path, cache_dir=cache_dir)
    except ObjectLoadError as exc:
        raise PerceptionError(f"the reconstructed object cannot be modelled: {exc}") from exc
    return CloudObject(model, T_world_C @ model.T_source_O, object_points, path, key, from_cache, meta)


def bps_from_cloud(
    points_world: npt.ArrayLike,
    T_world_D: np.ndarray,
    bps: BasisPointSet | None = None,
    n_points: int = BPS_POINTS,
    seed: int = 0,
) -> np.ndarray:
    """[bps.n] float32 BPS of an object's captured points, in the direction frame D.

    The same encoding as a mesh's (shared/sampling/dataset.py): D's frame, metres, the basis's own
    ordering, `n_points` points. The cloud is first thinned to uniform density (BPS_SPACING_M) and
    then `n_points` of it are drawn (seeded), like the mesh's area-uniform samples. What the camera
    did not see (the underside, a far side) is missing from the cloud, so basis points near it read
    larger distances than on the mesh: the paper's BPS of a captured cloud has the same limit.
    """
    return (bps or BasisPointSet()).encode(bps_points_in_d(points_world, T_world_D, n_points, seed))


def bps_points_in_d(points_world: npt.ArrayLike, T_world_D: np.ndarray, n_points: int = BPS_POINTS,
                    seed: int = 0) -> np.ndarray:
    """`bps_points` of a cloud, in the direction frame D: exactly the points `bps_from_cloud` encodes."""
    return points_world_to_d(bps_points(points_world, n_points, seed), np.asarray(T_world_D, dtype=np.float64))


def bps_points(points_world: npt.ArrayLike, n_points: int = BPS_POINTS, seed: int = 0) -> np.ndarray:
    """The points a cloud's BPS is computed from: thinned to uniform density (BPS_SPACING_M), then at
    most `n_points` of them drawn (seeded), like the mesh's area-uniform surface samples."""
    points = voxel_downsample(check_points(points_world, "object points"), BPS_SPACING_M)
    if len(points) > n_points:
        points = points[np.random.default_rng(seed).choice(len(points), n_points, replace=False)]
    return points
