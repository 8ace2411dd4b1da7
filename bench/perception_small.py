"""Small objects through the cameras: how many points the evaluation's 3 captures leave, and how faithful the
reconstruction is once the point minimum lets them through (reconstruct.py `min_object_points`).

    .venv/bin/python bench/perception_small.py test   # small-family objects of the split -> results/perception_small_test.jsonl
    .venv/bin/python bench/perception_small.py val

Each object is captured 3 times at the evaluation's spot (0.40, 0) with 3 simulated depth cameras, the cloud a
request carries (`cloud_for_request`), and reconstructed with the point minimum removed (1), so one run answers
for every threshold: `okN` says whether the capture passes a minimum of N. Also: the reconstruction's volume and
extents against the true mesh, volume IoU (manifold booleans), the pose's xy error, and the sizes of the other
clusters (table noise). Summary: bench/results/perception_small.md.
"""
from __future__ import annotations

import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import trimesh

THRESHOLDS = (50, 64, 100, 200)
VARIANTS = [(0, 0.0, 0.0), (1, 135.0, 0.7), (2, 250.0, 1.9)]  # (camera seed, push direction deg, yaw rad)
OUT = Path(__file__).resolve().parent / "results"


def volume_iou(a: trimesh.Trimesh, b: trimesh.Trimesh) -> float:
    try:
        inter = trimesh.boolean.intersection([a, b], engine="manifold").volume
    except Exception:  # a boolean that fails is reported as NaN, not as a crash of the whole run
        return float("nan")
    return float(inter / (a.volume + b.volume - inter))


def measure(object_id: str, cache: str) -> list[dict]:
    from shared.frames import direction_frame
    from shared.world.objects import load_object
    from shared.world.perception import PerceptionError
    from shared.world.perception.cloud import cloud_for_request
    from shared.world.perception.object_model import object_from_cloud
    from shared.world.perception.reconstruct import (
        ReconstructionSettings,
        euclidean_clusters,
        reconstruct,
        remove_table,
    )
    from shared.world.sim.camera import capture_object

    ungated = ReconstructionSettings(min_object_points=1)
    obj = load_object(object_id)
    rows = []
    for seed, direction_deg, yaw in VARIANTS:
        T_world_O = direction_frame(np.array([0.40, 0.0, 0.0]), direction_deg) @ obj.T_D_O(None, yaw)
        points = cloud_for_request(capture_object(obj, T_world_O, n_cameras=3, seed=seed).cloud)
        truth = obj.mesh.copy()
        truth.apply_transform(T_world_O)
        above, tolerance, _, _ = remove_table(np.asarray(points, dtype=np.float64), ungated)
        row = {"id": object_id, "seed": seed, "true_ext": np.ptp(truth.vertices, axis=0).tolist(),
               "true_vol": truth.volume, "n_cloud": len(points), "n_above": len(above)}
        try:
            recon = reconstruct(points, settings=ungated)
        except PerceptionError as exc:
            rows.append({**row, "error": str(exc)})
            continue
        clusters = euclidean_clusters(above, recon.cluster_gap_m, ungated.min_voxel_points,
                                      sparse_min_z=tolerance + recon.cluster_gap_m / 2.0)
        captured = object_from_cloud(points, settings=ungated, cache_dir=cache)
        row.update(n_cluster=len(recon.object_points), rec_vol=recon.mesh.volume,
                   rec_ext=np.ptp(recon.mesh.vertices, axis=0).tolist(), iou=volume_iou(recon.mesh, truth),
                   noise_clusters=[len(c) for c in clusters][1:6],
                   xy_err_mm=float(np.linalg.norm(captured.T_world_O[:2, 3] - T_world_O[:2, 3]) * 1000),
                   **{f"ok{n}": bool(len(above) >= n and len(recon.object_points) >= n) for n in THRESHOLDS})
        rows.append(row)
    return rows


def main(split: str) -> None:
    from shared.data_engine import select_objects
    from shared.world.objects.catalog import resolve_library_id

    os.environ.setdefault("OMP_NUM_THREADS", "1")
    ids = sorted(i for i in select_objects(split, allow_split=True) if resolve_library_id(i).family == "small")
    with tempfile.TemporaryDirectory(prefix="gd2p-perception-small-") as cache, \
            (OUT / f"perception_small_{split}.jsonl").open("w") as out:
        for object_id in ids:
            started = time.time()
            for row in measure(object_id, cache):
                out.write(json.dumps(row) + "\n")
            print(f"{object_id}: {time.time() - started:.1f} s", flush=True)


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "test")
