"""Physics assets of an object: convex decomposition and a URDF PyBullet loads.

The URDF's link frame is the object frame O (centre of mass, principal axes), so its inertial
origin is the identity and the diagonal inertia PyBullet keeps is the full tensor; PyBullet's
base pose of the loaded body is then exactly T_world_O (load with URDF_USE_INERTIA_FROM_FILE, as
`load_in_pybullet` does, or PyBullet recomputes the inertia from a bounding box). No contact parameters are written:
friction, restitution and damping are set by the simulation (`changeDynamics`), which chooses
them by measurement.
"""
from __future__ import annotations

import contextlib
import os
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import cast
from xml.sax.saxutils import quoteattr

import numpy as np
import pybullet
import trimesh
from scipy.spatial.transform import Rotation

from shared.atomic import atomic_write_bytes, atomic_write_text

from .model import ObjectModel

# V-HACD voxel resolution: 2e5 resolves a mug handle in ~1.5 s (1e5: coarser, 4e5: ~3.5 s).
VHACD_RESOLUTION = 200_000


def convex_decomposition(obj: ObjectModel) -> list[trimesh.Trimesh]:
    """Convex pieces (in O) for collision: the source's own pieces, the mesh if convex, else V-HACD.

    V-HACD runs once per object and is cached (`vhacd.obj` in the object's cache directory).
    """
    parts = obj.convex_parts
    if parts is not None:
        return parts
    cached = obj.cache_dir / "vhacd.obj"
    if not cached.is_file():
        _run_vhacd(obj.mesh, cached)
    parts_mesh = cast(trimesh.Trimesh, trimesh.load(str(cached), force="mesh", process=False))  # force="mesh"
    return list(parts_mesh.split(only_watertight=False))


def _run_vhacd(mesh: trimesh.Trimesh, out_path: Path) -> None:
    out_path.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=out_path.parent) as work:
        source, result, log = (Path(work) / name for name in ("in.obj", "out.obj", "vhacd.log"))
        mesh.export(str(source))
        with _quiet_stdout():  # V-HACD prints its progress from C straight to file descriptor 1
            pybullet.vhacd(str(source), str(result), str(log), resolution=VHACD_RESOLUTION)
        if not result.is_file() or result.stat().st_size == 0:
            raise RuntimeError(f"V-HACD produced no output for {out_path.parent.name}; see {log}")
        atomic_write_bytes(out_path, result.read_bytes())


@contextlib.contextmanager
def _quiet_stdout() -> Iterator[None]:
    sys.stdout.flush()
    saved = os.dup(1)
    try:
        with open(os.devnull, "wb") as devnull:
            os.dup2(devnull.fileno(), 1)
            yield
    finally:
        os.dup2(saved, 1)
        os.close(saved)


def write_object_urdf(obj: ObjectModel, mass_scale: float = 1.0,
                      com_offset_m: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> Path:
    """Write (once) and return the URDF of `obj`: visual mesh, convex collision pieces, mass, inertia.

    `mass_scale` and `com_offset_m` (in the object's frame O) describe an object whose true mass and
    centre of mass differ from the model's (an execution world, `shared.world.sim.world`); the link frame
    stays O, so poses mean the same.
    """
    if mass_scale <= 0 or not np.isfinite(mass_scale) or not np.all(np.isfinite(com_offset_m)):
        raise ValueError(f"mass_scale must be positive and finite and com_offset_m finite, got {mass_scale}, {com_offset_m}")
    mass = obj.mass * mass_scale
    name = f"object-m{mass:.6f}.urdf"  # mass depends on the density chosen at load time
    if any(com_offset_m):
        name = f"object-m{mass:.6f}-c{'_'.join(f'{v * 1000:.2f}' for v in com_offset_m)}.urdf"
    path = obj.cache_dir / name
    if path.is_file():
        return path
    visual = obj.cache_dir / "visual.obj"
    if not visual.is_file():
        atomic_write_text(visual, trimesh.exchange.obj.export_obj(obj.mesh, include_normals=False, include_texture=False))
    collision = obj.cache_dir / "collision.obj"
    if not collision.is_file():
        scene = trimesh.Scene()
        for index, part in enumerate(convex_decomposition(obj)):
            scene.add_geometry(part, geom_name=f"hull{index}")
        # one OBJ object per piece: PyBullet builds a compound of their convex hulls
        atomic_write_text(collision, trimesh.exchange.obj.export_obj(scene, include_normals=False, include_texture=False))
    atomic_write_text(path, _urdf_text(obj, mass_scale, com_offset_m))
    return path


def load_in_pybullet(obj: ObjectModel, T_world_O: np.ndarray, physics_client_id: int = 0) -> int:
    """Load `obj` into a PyBullet world at pose T_world_O; returns the body id.

    Uses URDF_USE_INERTIA_FROM_FILE: without it PyBullet replaces the inertia with that of the
    collision shape's bounding box.
    """
    T_world_O = np.asarray(T_world_O, dtype=np.float64)
    quat = Rotation.from_matrix(T_world_O[:3, :3]).as_quat()  # xyzw, PyBullet's order
    body: int = pybullet.loadURDF(
        str(write_object_urdf(obj)),
        T_world_O[:3, 3].tolist(),
        quat.tolist(),
        flags=pybullet.URDF_USE_INERTIA_FROM_FILE,
        physicsClientId=physics_client_id,
    )
    return body


def _urdf_text(obj: ObjectModel, mass_scale: float, com_offset_m: tuple[float, float, float]) -> str:
    i = obj.inertia * mass_scale
    x, y, z = com_offset_m
    return f"""<?xml version="1.0"?>
<robot name={quoteattr(obj.id)}>
  <link name="object">
    <inertial>
      <origin xyz="{x:.9g} {y:.9g} {z:.9g}" rpy="0 0 0"/>
      <mass value="{obj.mass * mass_scale:.9g}"/>
      <inertia ixx="{i[0, 0]:.9g}" ixy="{i[0, 1]:.9g}" ixz="{i[0, 2]:.9g}" iyy="{i[1, 1]:.9g}" iyz="{i[1, 2]:.9g}" izz="{i[2, 2]:.9g}"/>
    </inertial>
    <visual>
      <origin xyz="0 0 0" rpy="0 0 0"/>
      <geometry><mesh filename="visual.obj"/></geometry>
    </visual>
    <collision>
      <origin xyz="0 0 0" rpy="0 0 0"/>
      <geometry><mesh filename="collision.obj"/></geometry>
    </collision>
  </link>
</robot>
"""
