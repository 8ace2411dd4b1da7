"""Benchmarks of the shared models: BPS encoding, object SDF lookup, mesh loading, hand FK.

    python bench/models.py --json      # last line: one JSON object

Targets on 2 cores: BPS of a 2048-point cloud <= 5 ms, SDF lookup of 1e5 points
<= 20 ms, FK of a 1024 batch <= 10 ms. Loading a 10k-vertex mesh is reported cold (geometry +
64³ SDF computed) and warm (both from the on-disk cache). Torch runs single-threaded, as every
worker process does (docs/architecture.md §Compute).
"""
from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
import trimesh

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from shared.world.bps import BasisPointSet
from shared.world.objects import load_object


def _timed_ms(function, repeats: int, warmup: int = 3) -> dict:
    for _ in range(warmup):
        function()
    samples = []
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        samples.append((time.perf_counter() - start) * 1e3)
    return {"median_ms": round(statistics.median(samples), 3), "p90_ms": round(float(np.percentile(samples, 90)), 3), "repeats": repeats}


def bench_bps(cache_dir: Path, repeats: int = 200) -> dict:
    """One 2048-point surface cloud of a library object in D, against 4096 basis points."""
    obj = load_object("proc-box-001", cache_dir=cache_dir)
    points, _ = obj.surface_points(2048, seed=0, T_D_O=obj.T_D_O())
    bps = BasisPointSet()
    return {"points": 2048, "basis": bps.n, **_timed_ms(lambda: bps.encode(points), repeats), "target_ms": 5.0}


def bench_sdf_lookup(cache_dir: Path, repeats: int = 50) -> dict:
    """1e5 points in and around the grid (forward only; forward + backward reported beside)."""
    obj = load_object("proc-box-001", cache_dir=cache_dir)
    grid = obj.sdf
    rng = np.random.default_rng(0)
    span = grid.upper - grid.lower
    points = torch.tensor(rng.uniform(grid.lower - 0.1 * span, grid.upper + 0.1 * span, (100_000, 3)), dtype=torch.float32)

    def lookup():
        with torch.no_grad():
            grid.query(points)

    leaf = points.clone().requires_grad_(True)

    def lookup_backward():
        leaf.grad = None
        distance, _ = grid.query(leaf)
        distance.sum().backward()

    return {
        "points": 100_000,
        "grid": list(grid.resolution),
        **_timed_ms(lookup, repeats),
        "with_backward_median_ms": _timed_ms(lookup_backward, repeats)["median_ms"],
        "target_ms": 20.0,
    }


def _scan_like_mesh(closed: bool) -> trimesh.Trimesh:
    """~10k vertices: a lumpy closed blob, or a subdivided box missing its top (an open scan)."""
    if closed:
        mesh = trimesh.creation.icosphere(subdivisions=5, radius=1.0)
        v = mesh.vertices
        bumps = 1.0 + 0.12 * np.sin(3 * v[:, 0]) * np.cos(2 * v[:, 1]) + 0.08 * np.sin(5 * v[:, 2])
        mesh.vertices = v * bumps[:, None] * np.array([0.06, 0.045, 0.04])
        return mesh
    box = trimesh.creation.box(extents=(0.10, 0.08, 0.06)).subdivide_to_size(0.0028)
    keep = box.triangles_center[:, 2] < 0.03 - 1e-9
    mesh = trimesh.Trimesh(box.vertices, box.faces[keep], process=False)
    mesh.remove_unreferenced_vertices()
    return mesh


def bench_mesh_load(closed: bool) -> dict:
    mesh = _scan_like_mesh(closed)
    with tempfile.TemporaryDirectory() as work:
        path = Path(work) / "scan.ply"
        mesh.export(path)
        cache = Path(work) / "cache"
        timings: dict[str, object] = {}
        for phase in ("cold", "warm"):
            start = time.perf_counter()
            obj = load_object(path, cache_dir=cache)
            _ = obj.sdf
            timings[f"{phase}_s"] = round(time.perf_counter() - start, 3)
            timings[f"{phase}_provenance"] = dict(obj.provenance)
    return {"vertices": len(mesh.vertices), "watertight_input": bool(mesh.is_watertight), "sdf_grid": 64, **timings}


def bench_fk(repeats: int = 50) -> dict:
    """FK of a [1024, 25] batch with shared.robots.hands (reported as skipped when that module is absent)."""
    try:
        from shared.robots.hands import load_hand
    except ImportError as exc:
        return {"skipped": f"shared.robots.hands not importable: {exc}"}
    results: dict[str, dict[str, object]] = {}
    for name in ("allegro", "leap"):
        try:
            hand = load_hand(name)
            pose = hand.open_pose(1024)
        except Exception as exc:  # a hand whose assets are missing is reported, not fatal
            results[name] = {"skipped": f"{type(exc).__name__}: {exc}"}
            continue

        def forward(hand=hand, pose=pose):  # this iteration's hand and pose
            with torch.no_grad():
                hand.forward(pose)

        results[name] = {"batch": 1024, **_timed_ms(forward, repeats), "target_ms": 10.0}
    return results


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", action="store_true", help="end with one JSON line (always printed last)")
    parser.add_argument("--threads", type=int, default=1, help="torch intra-op threads (default 1, as workers use)")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    with tempfile.TemporaryDirectory() as cache:
        cache_dir = Path(cache)
        report = {
            "bps_2048": bench_bps(cache_dir),
            "sdf_lookup_1e5": bench_sdf_lookup(cache_dir),
            "mesh_10k_closed": bench_mesh_load(closed=True),
            "mesh_10k_open": bench_mesh_load(closed=False),
            "fk_1024": bench_fk(),
            "torch_threads": args.threads,
        }
    if not args.json:
        for name, value in report.items():
            print(f"{name}: {value}")
    print(json.dumps(report, default=lambda v: None if isinstance(v, float) and math.isnan(v) else v))
    return 0


if __name__ == "__main__":
    sys.exit(main())
