"""ObjectRef -> ObjectModel, for every service that simulates or plans around an object's mesh."""
from __future__ import annotations

from shared.messages import ObjectRef
from shared.objects import ObjectLoadError, ObjectModel, load_object
from shared.objects.cache import atomic_write_bytes, cache_root


def load_object_ref(ref: ObjectRef) -> ObjectModel:
    """The library object or uploaded mesh of `ref` (a mesh is written once to the cache by its hash).

    Raises ObjectLoadError for point clouds and scaled objects (no mesh to simulate) and bad meshes.
    """
    if ref.point_cloud is not None:
        raise ObjectLoadError(f"object {ref.object_id}: a point cloud has no mesh to plan around or simulate")
    if ref.scale is not None and ref.scale != 1.0:
        raise ObjectLoadError(f"object {ref.object_id}: scaled objects are not supported")
    if ref.library_id is not None:
        return load_object(ref.library_id)
    assert ref.mesh is not None
    path = cache_root() / "uploads" / f"{ref.mesh.sha256}.{ref.mesh.format}"
    if not path.is_file():
        atomic_write_bytes(path, ref.mesh.data)
    return load_object(path)
