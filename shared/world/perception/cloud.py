"""Point clouds in the world frame: the typed container, input checks, and .ply / .pcd / .npy files.

    cloud = load_cloud("scan.ply")        # or .pcd (PCL, ascii / binary / binary_compressed), .npy
    save_cloud("scan.pcd", cloud)
    points = check_points(array)          # [N, 3] float64 metres, or a PerceptionError saying why not

PLY goes through trimesh, PCD through pypcd4 (PCL's format, all three encodings), NPY through numpy
with pickles refused. A file holding triangles is a mesh, not a cloud, and is refused as such
(pass it as an object mesh instead).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from .errors import CloudFileError, PerceptionError

CLOUD_SUFFIXES = (".ply", ".pcd", ".npy")
# A robot's view of a tabletop spans metres at most; a cloud spanning more than this is almost
# certainly in millimetres (a 10 cm object 0.5 m away spans ~600 "metres" there).
MAX_SCENE_EXTENT_M = 5.0


@dataclass(frozen=True, eq=False)
class Cloud:
    """A point cloud in the world frame (metres); normals and colours are optional per-point extras."""

    points: np.ndarray  # [N, 3] float64
    normals: np.ndarray | None = None  # [N, 3] unit vectors
    colors: np.ndarray | None = None  # [N, 3] uint8 RGB

    def __post_init__(self) -> None:
        for name in ("normals", "colors"):
            extra = getattr(self, name)
            if extra is not None and np.shape(extra) != np.shape(self.points):
                raise PerceptionError(f"cloud {name} have shape {np.shape(extra)}, points {np.shape(self.points)}")

    def __len__(self) -> int:
        return len(self.points)


def check_points(points: npt.ArrayLike, what: str = "point cloud") -> np.ndarray:
    """[N, 3] finite float64 metres; PerceptionError naming the problem (shape, empty, NaN, millimetres)."""
    array = np.asarray(points, dtype=np.float64)
    if array.ndim != 2 or array.shape[1] != 3:
        raise PerceptionError(f"{what} must be an [N, 3] array of x, y, z in metres, got shape {array.shape}")
    if len(array) == 0:
        raise PerceptionError(f"{what} is empty: no points")
    bad = int(np.count_nonzero(~np.all(np.isfinite(array), axis=1)))
    if bad:
        raise PerceptionError(f"{what}: {bad} of {len(array)} points have NaN/inf coordinates (drop invalid pixels first)")
    low, high = np.percentile(array, [1.0, 99.0], axis=0)
    extent = float(np.max(high - low))
    if extent > MAX_SCENE_EXTENT_M:
        raise PerceptionError(
            f"{what} spans {extent:.3g} units, over {MAX_SCENE_EXTENT_M:g} m for a tabletop view: "
            f"{'it looks like millimetres (scale by 0.001)' if extent < 5e4 else 'is it in metres?'}"
        )
    return array


# ----------------------------------------------------------------------------- files
def load_cloud(path: str | Path) -> Cloud:
    """Read a .ply, .pcd or .npy point cloud (metres, world frame); CloudFileError naming the file otherwise."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in CLOUD_SUFFIXES:
        raise CloudFileError(f"{path}: unsupported point-cloud type {suffix or '(no extension)'!r}; supported: {', '.join(CLOUD_SUFFIXES)}")
    if not path.is_file():
        raise CloudFileError(f"{path}: no such file")
    if path.stat().st_size == 0:
        raise CloudFileError(f"{path}: file is empty")
    cloud = {".ply": _read_ply, ".pcd": _read_pcd, ".npy": _read_npy}[suffix](path)
    try:
        check_points(cloud.points, what=str(path))
    except PerceptionError as exc:
        raise CloudFileError(str(exc)) from None
    return cloud


def save_cloud(path: str | Path, cloud: Cloud | np.ndarray) -> Path:
    """Write a cloud as .ply (binary), .pcd (binary) or .npy ([N, 3] float64), by the file's extension."""
    path = Path(path)
    cloud = cloud if isinstance(cloud, Cloud) else Cloud(check_points(cloud))
    suffix = path.suffix.lower()
    if suffix not in CLOUD_SUFFIXES:
        raise CloudFileError(f"{path}: unsupported point-cloud type {suffix or '(no extension)'!r}; supported: {', '.join(CLOUD_SUFFIXES)}")
    path.parent.mkdir(parents=True, exist_ok=True)
    if suffix == ".npy":
        np.save(path, np.asarray(cloud.points, dtype=np.float64))
    elif suffix == ".pcd":
        _write_pcd(path, cloud)
    else:
        import trimesh

        trimesh.PointCloud(cloud.points, colors=cloud.colors).export(str(path), file_type="ply", encoding="binary")
    return path


def _read_npy(path: Path) -> Cloud:
    try:
        array = np.load(path, allow_pickle=False)
    except (ValueError, OSError, EOFError) as exc:
        raise CloudFileError(f"{path}: not a readable .npy array (pickled objects are refused): {exc}") from None
    if not isinstance(array, np.ndarray) or array.ndim != 2 or array.shape[1] != 3 or not np.issubdtype(array.dtype, np.number):
        raise CloudFileError(f"{path}: expected a numeric [N, 3] array of x, y, z in metres, got {getattr(array, 'dtype', '?')} "
                             f"{getattr(array, 'shape', '?')}")
    return Cloud(array.astype(np.float64))


def _read_ply(path: Path) -> Cloud:
    import trimesh

    try:
        loaded = trimesh.load(str(path), file_type="ply", process=False)
    except Exception as exc:  # trimesh raises many types for corrupt input; report them all alike
        raise CloudFileError(f"{path}: cannot parse as PLY: {type(exc).__name__}: {exc}") from None
    if isinstance(loaded, trimesh.Trimesh) and len(loaded.faces):
        raise CloudFileError(f"{path}: holds a triangle mesh ({len(loaded.faces)} faces), not a point cloud; "
                             "pass a mesh as the object instead")
    if not isinstance(loaded, (trimesh.PointCloud, trimesh.Trimesh)) or len(loaded.vertices) == 0:
        raise CloudFileError(f"{path}: no vertices (loaded as {type(loaded).__name__})")
    colors = getattr(loaded, "colors", None)
    colors = np.asarray(colors)[:, :3].astype(np.uint8) if colors is not None and len(colors) == len(loaded.vertices) else None
    return Cloud(np.asarray(loaded.vertices, dtype=np.float64), _ply_normals(loaded), colors)


def _ply_normals(loaded: Any) -> np.ndarray | None:
    """nx, ny, nz vertex properties when the PLY has them (trimesh keeps them in the raw element)."""
    raw = loaded.metadata.get("_ply_raw", {}).get("vertex", {}).get("data")
    names = getattr(getattr(raw, "dtype", None), "names", None) or ()
    if not {"nx", "ny", "nz"} <= set(names):
        return None
    return np.stack([raw["nx"], raw["ny"], raw["nz"]], axis=1).astype(np.float64).reshape(-1, 3)


def _read_pcd(path: Path) -> Cloud:
    from pypcd4 import PointCloud as PcdCloud

    try:
        pcd = PcdCloud.from_path(path)
    except Exception as exc:  # pypcd4 raises pydantic / value / struct errors for malformed headers and data
        message = str(exc).splitlines()[0] if str(exc) else ""
        raise CloudFileError(f"{path}: cannot parse as PCD: {type(exc).__name__}: {message}") from None
    fields = set(pcd.fields)
    if not {"x", "y", "z"} <= fields:
        raise CloudFileError(f"{path}: PCD has fields {sorted(fields)}, no x, y, z")
    points = pcd.numpy(("x", "y", "z")).astype(np.float64)
    normals = pcd.numpy(("normal_x", "normal_y", "normal_z")).astype(np.float64) if {"normal_x", "normal_y", "normal_z"} <= fields else None
    colors = PcdCloud.decode_rgb(pcd.numpy(("rgb",)).reshape(-1)) if "rgb" in fields else None
    return Cloud(points.reshape(-1, 3), normals, None if colors is None else np.asarray(colors, dtype=np.uint8).reshape(-1, 3))


def _write_pcd(path: Path, cloud: Cloud) -> None:
    from pypcd4 import PointCloud as PcdCloud

    points = np.asarray(cloud.points, dtype=np.float32)
    if cloud.colors is not None:
        rgb = PcdCloud.encode_rgb(np.asarray(cloud.colors, dtype=np.uint8))
        pcd = PcdCloud.from_xyzrgb_points(np.column_stack([points, rgb.astype(np.float32)]))
    else:
        pcd = PcdCloud.from_xyz_points(points)
    pcd.save(path)


def voxel_downsample(points: np.ndarray, voxel_m: float) -> np.ndarray:
    """One point per occupied voxel (the mean of its points): bounded size, uniform density.

    Memory and time are linear in N (one integer key per point), so a 5-million-point cloud is
    reduced in about a second before anything quadratic runs.
    """
    if not voxel_m > 0 or not math.isfinite(voxel_m):
        raise PerceptionError(f"voxel size must be positive, got {voxel_m}")
    keys = np.floor(points / voxel_m).astype(np.int64)
    keys -= keys.min(axis=0)
    span = keys.max(axis=0) + 1
    flat = (keys[:, 0] * span[1] + keys[:, 1]) * span[2] + keys[:, 2]
    _, inverse, counts = np.unique(flat, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    sums = np.stack([np.bincount(inverse, weights=points[:, axis], minlength=len(counts)) for axis in range(3)], axis=1)
    return sums / counts[:, None]


MAX_REQUEST_POINTS = 200_000  # ~2.4 MB as float32: well inside a bus message, dense enough (~1 mm) for a tabletop


def cloud_for_request(points: np.ndarray, max_points: int = MAX_REQUEST_POINTS) -> np.ndarray:
    """A cloud as a request carries it: checked, float32, and voxel-thinned (1 mm, doubling) until at most
    `max_points` remain, so a 5-million-point scan travels as a bounded message."""
    points = check_points(points)
    voxel_m = 0.001
    while len(points) > max_points:
        points = voxel_downsample(points, voxel_m)
        voxel_m *= 2.0
    return points.astype(np.float32)
