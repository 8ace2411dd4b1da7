"""Which convex decomposition for the MuJoCo world's objects: time and piece count, and how well the pieces
cover the mesh, on a few library objects, for CoACD (two thresholds), V-HACD (PyBullet's, as the PyBullet
world uses) and trimesh's single convex hull.

    python bench/mujoco_decomposition.py   # writes bench/results/mujoco_decomposition.json

Fidelity: the volume of the pieces' union (voxelised at 2 mm... approximated by the sum of the pieces'
volumes, which overlap little) over the mesh's volume (1.0 is exact; a hull over a concave object
is well above 1: it fills the mug's inside and the gap under a handle), and the largest distance from a
sample of the pieces' surfaces to the mesh surface (how far a contact may sit off the true surface).
"""
from __future__ import annotations

import json
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import trimesh

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

OBJECTS = ["proc-mug-003", "proc-banana-003", "proc-bottle-003", "rnd-003", "pb-duck"]


def coverage(mesh: trimesh.Trimesh, pieces: list[trimesh.Trimesh]) -> dict[str, float]:
    volume = sum(p.volume for p in pieces)
    samples = np.concatenate([p.sample(max(50, 2000 // len(pieces)), seed=0) for p in pieces])
    _, distance, _ = trimesh.proximity.closest_point(mesh, samples)
    return {"volume_ratio": round(float(volume / mesh.volume), 3),
            "surface_gap_p95_mm": round(float(np.percentile(distance, 95) * 1000), 2),
            "surface_gap_max_mm": round(float(distance.max() * 1000), 2)}


def vhacd(mesh: trimesh.Trimesh) -> list[trimesh.Trimesh]:
    from shared.world.objects.physics import _run_vhacd
    with tempfile.TemporaryDirectory() as work:
        out = Path(work) / "v.obj"
        _run_vhacd(mesh, out)
        loaded = trimesh.load(str(out), force="mesh", process=False)
        assert isinstance(loaded, trimesh.Trimesh)
        return list(loaded.split(only_watertight=False))


def main() -> None:
    import coacd

    from shared.execution.robots.mujoco.decompose import decompose_mesh
    from shared.world.objects import load_object

    coacd.set_log_level("error")
    methods = {
        "trimesh_convex_hull": lambda i, m: [m.convex_hull],
        "coacd_0.1": lambda i, m: decompose_mesh(i, m, threshold=0.1),
        "coacd_0.05": lambda i, m: decompose_mesh(i, m, threshold=0.05),
        "vhacd_pybullet": lambda i, m: vhacd(m),
    }
    rows: list[dict[str, Any]] = []
    for object_id in OBJECTS:
        obj = load_object(object_id)
        mesh = obj.mesh
        for name, method in methods.items():
            started = time.perf_counter()
            pieces = method(object_id, mesh)
            seconds = time.perf_counter() - started
            row = {"object": object_id, "faces": len(mesh.faces), "convex": bool(mesh.is_convex), "method": name,
                   "seconds": round(seconds, 3), "pieces": len(pieces), **coverage(mesh, pieces)}
            print(row, flush=True)
            rows.append(row)
    summary = {}
    for name in methods:
        mine = [r for r in rows if r["method"] == name]
        summary[name] = {"median_seconds": round(float(np.median([r["seconds"] for r in mine])), 3),
                         "max_seconds": max(r["seconds"] for r in mine),
                         "median_pieces": float(np.median([r["pieces"] for r in mine])),
                         "median_volume_ratio": round(float(np.median([r["volume_ratio"] for r in mine])), 3),
                         "worst_surface_gap_max_mm": max(r["surface_gap_max_mm"] for r in mine)}
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    result = {"command": "python bench/mujoco_decomposition.py", "commit": commit, "machine": platform.processor() or platform.machine(),
              "coacd": coacd.__version__ if hasattr(coacd, "__version__") else "1.0.14", "trimesh": trimesh.__version__,
              "summary": summary, "rows": rows}
    out = Path(__file__).resolve().parent / "results" / "mujoco_decomposition.json"
    out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(summary, indent=2))


if __name__ == "__main__":
    main()
