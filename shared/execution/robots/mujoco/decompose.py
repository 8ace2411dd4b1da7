"""Convex decomposition of an object's mesh for MuJoCo's collision (each geom a convex hull).

MuJoCo collides every mesh geom as its convex hull, so a non-convex object needs pieces. The library
is CoACD (approximate convex decomposition by collision-aware cuts; PyPI `coacd`), chosen by
measurement against trimesh's single convex hull and the V-HACD the PyBullet world uses
(`bench/mujoco_decomposition.py`, `bench/results/mujoco_decomposition.json`, docs/architecture.md
"A second world"). A source made of convex pieces (procedural objects) keeps its own pieces, a convex
mesh is its own hull; only the rest runs CoACD, once per object (cached beside the object's other assets).
"""
from __future__ import annotations

import logging
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import trimesh

from shared.atomic import atomic_write_bytes
from shared.world.objects.model import ObjectModel

log = logging.getLogger("gd2p.mujoco.decompose")

# CoACD settings (the bench): concavity threshold 0.1 and a small tree search (60 iterations, 10 nodes)
# keep a mug's handle open in ~10 s on one core; 0.05 or CoACD's defaults (150, 20) cost 3-10x that.
COACD_THRESHOLD = 0.1
COACD_MCTS_ITERATIONS = 60
COACD_MCTS_NODES = 10
MAX_PIECES = 64  # MuJoCo collides each piece with each finger: more only costs time
DECOMPOSE_TIMEOUT_S = 300.0
MIN_PIECE_VOLUME_M3 = 1e-9  # a sliver below this is no collision shape (a degenerate hull)


class DecompositionError(ValueError):
    """An object's mesh cannot be decomposed into convex pieces (names the object)."""


def convex_pieces(obj: ObjectModel) -> list[trimesh.Trimesh]:
    """Convex pieces (in O) of `obj`: its source's own pieces, its mesh if convex, else CoACD's (cached).
    DecompositionError naming the object when the mesh admits none."""
    parts = obj.convex_parts
    if parts is None:
        parts = _cached_coacd(obj)
    pieces = [p for p in (_hull(obj.id, p) for p in parts) if p is not None]
    if not pieces:
        raise DecompositionError(f"object {obj.id}: no convex piece of positive volume in its decomposition")
    return pieces


def decompose_mesh(object_id: str, mesh: trimesh.Trimesh, threshold: float = COACD_THRESHOLD) -> list[trimesh.Trimesh]:
    """CoACD's convex pieces of `mesh`; DecompositionError naming `object_id` if the mesh cannot be decomposed
    (empty, non-finite, flat, or CoACD fails)."""
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    if len(vertices) < 4 or len(faces) < 4:
        raise DecompositionError(f"object {object_id}: mesh has {len(vertices)} vertices and {len(faces)} faces; "
                                 "a solid needs at least 4 of each")
    if not np.isfinite(vertices).all():
        raise DecompositionError(f"object {object_id}: mesh has non-finite vertices")
    if np.linalg.matrix_rank(vertices - vertices.mean(axis=0), tol=1e-9) < 3:
        raise DecompositionError(f"object {object_id}: mesh is flat (its vertices span no volume)")
    if mesh.is_convex:
        return [mesh.convex_hull]
    # CoACD runs in a child process: on some meshes its C++ aborts (std::terminate), which no Python
    # handler catches; the robot's process must survive a bad object.
    with tempfile.TemporaryDirectory() as work:
        source, result = Path(work) / "mesh.npz", Path(work) / "pieces.npz"
        np.savez(source, vertices=vertices, faces=faces, threshold=threshold, watertight=bool(mesh.is_watertight))
        done = subprocess.run([sys.executable, "-m", __name__, str(source), str(result)], capture_output=True,
                              text=True, timeout=DECOMPOSE_TIMEOUT_S)
        if done.returncode != 0 or not result.is_file():
            reason = (done.stderr.strip().splitlines() or [f"exit code {done.returncode}"])[-1]
            raise DecompositionError(f"object {object_id}: CoACD failed: {reason}")
        arrays = np.load(result)
        count = int(arrays["count"])
        pieces = [trimesh.Trimesh(arrays[f"v{i}"], arrays[f"f{i}"], process=False) for i in range(count)]
    if not pieces:
        raise DecompositionError(f"object {object_id}: CoACD returned no pieces")
    return pieces


def _cached_coacd(obj: ObjectModel) -> list[trimesh.Trimesh]:
    cached = obj.cache_dir / f"coacd-{COACD_THRESHOLD:g}.obj"
    if cached.is_file():
        loaded = trimesh.load(str(cached), force="scene", process=False, group_material=False, split_object=True)
        geometries = list(loaded.geometry.values()) if isinstance(loaded, trimesh.Scene) else [loaded]
        return [g for g in geometries if isinstance(g, trimesh.Trimesh)]
    pieces = decompose_mesh(obj.id, obj.mesh)
    scene = trimesh.Scene()
    for index, piece in enumerate(pieces):
        scene.add_geometry(piece, geom_name=f"piece{index}")
    cached.parent.mkdir(parents=True, exist_ok=True)
    text = trimesh.exchange.obj.export_obj(scene, include_normals=False, include_texture=False)
    atomic_write_bytes(cached, text.encode())
    log.info("object %s: %d convex pieces (CoACD)", obj.id, len(pieces))
    return pieces


def _hull(object_id: str, part: trimesh.Trimesh) -> trimesh.Trimesh | None:
    """The convex hull of one piece, None for a degenerate sliver."""
    if len(part.vertices) < 4:
        return None
    try:
        hull = part.convex_hull
    except Exception:  # qhull on a flat piece
        log.debug("object %s: a flat piece was dropped", object_id)
        return None
    return hull if hull.volume > MIN_PIECE_VOLUME_M3 else None


def _run_coacd(source: Path, result: Path) -> None:
    """The child process: CoACD on the mesh in `source` (npz), its pieces to `result`."""
    import coacd  # an engine dependency: imported where it runs

    arrays = np.load(source)
    coacd.set_log_level("error")
    # CoACD's manifold pre-processing ("auto") aborted on a watertight mug: run it only when needed.
    parts = coacd.run_coacd(coacd.Mesh(arrays["vertices"], arrays["faces"]), threshold=float(arrays["threshold"]),
                            preprocess_mode="off" if bool(arrays["watertight"]) else "on",
                            max_convex_hull=MAX_PIECES, mcts_iterations=COACD_MCTS_ITERATIONS,
                            mcts_nodes=COACD_MCTS_NODES, seed=0)
    out: dict[str, np.ndarray] = {"count": np.array(len(parts))}
    for index, (v, f) in enumerate(parts):
        out[f"v{index}"], out[f"f{index}"] = np.asarray(v, dtype=np.float64), np.asarray(f, dtype=np.int64)
    np.savez(result, **out)  # type: ignore[arg-type]


if __name__ == "__main__":
    _run_coacd(Path(sys.argv[1]), Path(sys.argv[2]))
