"""ObjectRef -> ObjectModel, for every service that simulates, plans around or samples for an object."""
from __future__ import annotations

from pathlib import Path

from shared.atomic import atomic_write_bytes
from shared.messages import MeshBlob, ObjectRef
from shared.objects import ObjectLoadError, ObjectModel, load_object
from shared.objects.cache import cache_root


def uploaded_mesh_path(mesh: MeshBlob) -> Path:
    """The cached file of an uploaded mesh (written once, named by its content hash)."""
    path = cache_root() / "uploads" / f"{mesh.sha256}.{mesh.format}"
    if not path.is_file():
        atomic_write_bytes(path, mesh.data)
    return path


def load_object_ref(ref: ObjectRef) -> ObjectModel:
    """The library object or uploaded mesh of `ref`.

    Raises ObjectLoadError for point clouds and scaled objects (no mesh to simulate) and bad meshes.
    """
    if ref.point_cloud is not None:
        raise ObjectLoadError(f"object {ref.object_id}: a point cloud has no mesh to plan around or simulate")
    if ref.scale is not None and ref.scale != 1.0:
        raise ObjectLoadError(f"object {ref.object_id}: scaled objects are not supported")
    if ref.library_id is not None:
        return load_object(ref.library_id)
    assert ref.mesh is not None
    return load_object(uploaded_mesh_path(ref.mesh))
