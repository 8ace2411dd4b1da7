"""ObjectRef -> ObjectModel, for every service that simulates, plans around or samples for an object.

A point cloud (world frame, metres, as a camera saw the object on the table) is reconstructed by
`shared.world.perception.object_from_cloud` (table removed, the object's cluster kept, a watertight mesh),
once per cloud: the result is cached on disk by the cloud's content hash, so the planner, the
sampler, the validators and the robot bridge handed the same cloud all use the same reconstruction.
The cloud also says where the object stands (`captured_pose`).

A library id is loaded as an id only (`load_library_object`: never a path, whatever it looks like).
An uploaded mesh joins the upload cache (`<cache>/objects/uploads/<sha256>.<format>`, named by its
content) only once it loaded: it is written and loaded in a private temporary directory first, so
a mesh that fails to load (ObjectLoadError) leaves nothing behind.
"""
from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING

from shared.contracts.messages import MeshBlob, ObjectRef
from shared.world.objects import ObjectLoadError, ObjectModel, load_object
from shared.world.objects.cache import cache_root
from shared.world.objects.model import load_library_object

if TYPE_CHECKING:
    from shared.world.perception.object_model import CloudObject


def _upload_path(mesh: MeshBlob) -> Path:
    return cache_root() / "uploads" / f"{mesh.sha256}.{mesh.format}"


def uploaded_mesh_path(mesh: MeshBlob) -> Path:
    """The cached file of an uploaded mesh that loads (written once, named by its content hash).

    Raises ObjectLoadError (and keeps no file) when the mesh does not load.
    """
    path = _upload_path(mesh)
    if not path.is_file():
        _admit_upload(mesh, path)
    return path


def load_uploaded_mesh(mesh: MeshBlob) -> ObjectModel:
    """The ObjectModel of an uploaded mesh; ObjectLoadError (and no cached file) for a bad one."""
    path = uploaded_mesh_path(mesh)
    try:
        return load_object(path)
    except ObjectLoadError:
        path.unlink(missing_ok=True)  # e.g. a file cached before uploads were checked
        raise


def _admit_upload(mesh: MeshBlob, path: Path) -> None:
    """Load the mesh from a temporary directory beside `path`; move it to `path` only if it loaded."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=path.parent, prefix=".upload-") as staging:
        staged = Path(staging) / path.name
        staged.write_bytes(mesh.data)
        try:
            load_object(staged)  # computes and caches the geometry
        except ObjectLoadError as exc:  # name the upload, not the temporary file
            raise ObjectLoadError(str(exc).replace(str(staged), _upload_label(mesh))) from None
        os.replace(staged, path)


def _upload_label(mesh: MeshBlob) -> str:
    content = f"{mesh.sha256[:12]}.{mesh.format}"
    return f"uploaded mesh {mesh.name} ({content})" if mesh.name else f"uploaded mesh {content}"


def load_object_ref(ref: ObjectRef) -> ObjectModel:
    """The library object, uploaded mesh or reconstructed point cloud of `ref`.

    Raises ObjectLoadError for scaled objects, unknown ids, bad meshes and clouds that cannot be
    reconstructed (the perception error's message says why).
    """
    if ref.point_cloud is not None:
        return captured_object(ref).model
    if ref.scale is not None and ref.scale != 1.0:
        raise ObjectLoadError(f"object {ref.object_id}: scaled objects are not supported")
    if ref.library_id is not None:
        return load_library_object(ref.library_id)
    assert ref.mesh is not None
    return load_uploaded_mesh(ref.mesh)


def captured_object(ref: ObjectRef) -> CloudObject:
    """The reconstruction of `ref`'s point cloud (cached by content); ObjectLoadError if it fails."""
    from shared.world.perception import PerceptionError
    from shared.world.perception.object_model import object_from_cloud

    assert ref.point_cloud is not None
    try:
        return object_from_cloud(ref.point_cloud.to_numpy())
    except PerceptionError as exc:
        raise ObjectLoadError(f"object {ref.object_id}: the point cloud cannot be reconstructed: {exc}") from None
