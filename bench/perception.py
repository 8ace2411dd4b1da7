"""How to close what the camera does not see: reconstruction methods measured against the true mesh.

    python bench/perception.py --json                  # writes bench/results/perception.{json,md}
    python bench/perception.py --quick                 # 3 objects, for a smoke run

Each library object rests in its default pose at (0.55, 0) turned by 0.3 rad, and is captured by
shared.world.sim.camera (D435-class noise, 848 x 480, seed 0) with 1 camera (the head camera) and with 3.
The same table removal and object cluster (shared.world.perception.reconstruct) feed every method:

    extrude       the product's solid: the seen surface extruded down to the table (a height map),
                  cut into convex pieces (shared.world.perception.decompose); the mesh is their union
    extrude_mc    the same height map meshed by marching cubes (PyMCubes): the product's surface
                  before the convex pieces, with every detail of the height map
    extrude_vhacd V-HACD's pieces of extrude_mc (shared/world/objects/physics.py's decomposition, 200k
                  voxels): the shape physics simulated before the convex pieces; its seconds are V-HACD's
    hull          convex hull of the cloud and its footprint on the table (the trivial baseline)
    poisson       screened Poisson (open3d, depth 8) of the cloud + footprint points with normals
                  oriented towards the camera that saw them (the best case for Poisson)
    alpha_wrap    CGAL's 3D alpha wrap (alpha 1.5 cm, offset 2 mm) of the cloud + footprint points

poisson and alpha_wrap need open3d / the cgal bindings, which are not project dependencies (open3d's
wheel is 400 MB, 0.9 GB installed; CGAL's bindings are GPL); when they are not importable their rows
are carried over from the last run that measured them (marked so in the tables) instead of being
dropped (put them on PYTHONPATH to measure them again).

Metrics against the true mesh in the world (both meshes' insides from the same ray-vote voxel fill,
shared.world.objects.sdf.inside_mask, 2 mm nodes): volume IoU; Chamfer distance (mean of both directions'
nearest-surface distances, 20k area samples each) and Hausdorff distance (max of both directions);
volume error; centre-of-mass error; watertight; faces; convex pieces (for the methods that give
them); seconds from the object's points to the mesh (one core).
"""
from __future__ import annotations

import argparse
import json
import math
import platform
import statistics
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import numpy as np
import trimesh
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from shared.frames import make_transform
from shared.world.objects import load_object
from shared.world.objects.sdf import inside_mask, node_axes
from shared.world.perception.cloud import voxel_downsample
from shared.world.perception.reconstruct import (
    ReconstructionSettings,
    height_map,
    hull_with_footprint,
    object_cluster,
    remove_table,
    solid,
)
from shared.world.sim.camera import capture_object

OBJECTS = ["proc-box-000", "proc-box-001", "proc-box-002", "proc-cylinder-000", "proc-cylinder-001", "proc-cone-000",
           "proc-cone-002", "proc-ellipsoid-001", "pb-mug", "pb-duck"]
QUICK_OBJECTS = ["proc-box-001", "proc-cone-000", "pb-mug"]
CAMERAS = (1, 3)
POSITION = (0.55, 0.0)
YAW_RAD = 0.3
SIZE = (848, 480)
IOU_PITCH_M = 0.002
SURFACE_SAMPLES = 20_000
RESULTS = Path(__file__).resolve().parent / "results"


@dataclass
class Scene:
    """One capture: the object's points and, per camera, which of them it saw (for Poisson's normals)."""

    object_id: str
    cameras: int
    true_mesh: trimesh.Trimesh
    true_com: np.ndarray
    points: np.ndarray
    camera_of_point: np.ndarray
    camera_eyes: np.ndarray
    capture_points: int
    extra_seconds: float | None = None  # a method that times only part of its work sets this (extrude_vhacd)


def make_scene(object_id: str, cameras: int) -> Scene:
    obj = load_object(object_id)
    T_world_O = make_transform(np.eye(3), np.array([*POSITION, 0.0])) @ obj.T_D_O(yaw_rad=YAW_RAD)
    capture = capture_object(obj, T_world_O, n_cameras=cameras, seed=0, size=SIZE)
    settings = ReconstructionSettings()
    above, tolerance, *_ = remove_table(capture.cloud, settings)
    points, _ = object_cluster(above, None, settings, tolerance)
    per_camera = [frame.points_world() for frame in capture.frames]
    tree = cKDTree(points)
    owner = np.zeros(len(points), dtype=np.int64)
    for index, frame_points in enumerate(per_camera):  # which camera saw each kept point (exact matches)
        distance, nearest = tree.query(frame_points, distance_upper_bound=1e-9)
        owner[nearest[np.isfinite(distance)]] = index
    true_mesh = obj.mesh.copy()
    true_mesh.apply_transform(T_world_O)
    eyes = np.array([camera.eye for camera in capture.cameras])
    return Scene(object_id, cameras, true_mesh, T_world_O[:3, 3].copy(), points, owner, eyes, len(capture.cloud))


# ----------------------------------------------------------------------------- candidates
@dataclass
class Candidate:
    """A method's solid and, when it has them, its convex pieces."""

    mesh: trimesh.Trimesh
    pieces: int | None = None


def method_extrude(scene: Scene) -> Candidate:
    settings = ReconstructionSettings()
    parts, mesh = solid(voxel_downsample(scene.points, settings.voxel_m), settings)
    return Candidate(mesh, len(parts))


def method_extrude_mc(scene: Scene) -> Candidate:
    settings = ReconstructionSettings()
    return Candidate(marching_cubes_extrusion(voxel_downsample(scene.points, settings.voxel_m), settings.mesh_pitch_m,
                                              settings.hole_fill_m))


def marching_cubes_extrusion(points: np.ndarray, pitch: float, hole_fill_m: float) -> trimesh.Trimesh:
    """The height map's solid meshed by marching cubes: column (i, j) occupied up to its top, with sub-cell
    tops; node k of the volume is at z = (k - 1.5) * pitch, so the 0.5 level crosses z = 0 and z = top."""
    import mcubes

    heights, origin = height_map(points, pitch, hole_fill_m)
    z = (np.arange(int(np.ceil(heights.max() / pitch)) + 4) - 1.5) * pitch
    volume = np.clip((heights[:, :, None] - z[None, None, :]) / pitch + 0.5, 0.0, 1.0)
    volume[:, :, z < 0.0] = 0.0
    vertices, faces = mcubes.marching_cubes(volume, 0.5)
    mesh = trimesh.Trimesh(vertices * pitch + np.array([origin[0], origin[1], -1.5 * pitch]), faces, process=True)
    trimesh.repair.fix_normals(mesh)  # marching cubes' winding depends on the level's sign convention
    return mesh


def method_extrude_vhacd(scene: Scene) -> Candidate:
    """V-HACD of the marching-cubes solid, as shared/world/objects/physics.py runs it; timed alone."""
    import tempfile

    import pybullet

    from shared.world.objects.physics import VHACD_RESOLUTION, _quiet_stdout

    settings = ReconstructionSettings()
    surface = marching_cubes_extrusion(voxel_downsample(scene.points, settings.voxel_m), settings.mesh_pitch_m,
                                       settings.hole_fill_m)
    with tempfile.TemporaryDirectory() as work:
        source, result, log = (str(Path(work) / name) for name in ("in.obj", "out.obj", "vhacd.log"))
        surface.export(source)
        started = time.perf_counter()
        with _quiet_stdout():
            pybullet.vhacd(source, result, log, resolution=VHACD_RESOLUTION)
        scene.extra_seconds = time.perf_counter() - started
        loaded = cast(trimesh.Trimesh, trimesh.load(result, force="mesh", process=False))  # force="mesh": a mesh
        pieces = list(loaded.split(only_watertight=False))
    hulls = [piece.convex_hull for piece in pieces]
    mesh = hulls[0] if len(hulls) == 1 else trimesh.boolean.union(hulls, engine="manifold")
    return Candidate(mesh, len(hulls))


def method_hull(scene: Scene) -> Candidate:
    return Candidate(hull_with_footprint(voxel_downsample(scene.points, ReconstructionSettings().voxel_m)), 1)


def _footprint(points: np.ndarray, spacing: float = 0.003) -> np.ndarray:
    return voxel_downsample(points * np.array([1.0, 1.0, 0.0]), spacing)


def method_poisson(scene: Scene) -> Candidate:
    import open3d as o3d

    clouds = []
    for index, eye in enumerate(scene.camera_eyes):
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(voxel_downsample(scene.points[scene.camera_of_point == index], 0.002)))
        if len(cloud.points) < 10:
            continue
        cloud.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(20))
        cloud.orient_normals_towards_camera_location(eye)
        clouds.append(cloud)
    footprint = _footprint(scene.points)
    base = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(footprint))
    base.normals = o3d.utility.Vector3dVector(np.tile([0.0, 0.0, -1.0], (len(footprint), 1)))
    merged = base
    for cloud in clouds:
        merged += cloud
    mesh, _ = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(merged, depth=8, scale=1.1)
    return Candidate(trimesh.Trimesh(np.asarray(mesh.vertices), np.asarray(mesh.triangles), process=True))


def method_alpha_wrap(scene: Scene, alpha: float = 0.015, offset: float = 0.002) -> Candidate:
    import tempfile

    from CGAL.CGAL_Alpha_wrap_3 import Point_3_Vector, alpha_wrap_3
    from CGAL.CGAL_Kernel import Point_3
    from CGAL.CGAL_Polyhedron_3 import Polyhedron_3

    points = np.concatenate([voxel_downsample(scene.points, 0.002), _footprint(scene.points)])
    vector = Point_3_Vector()
    for x, y, z in points:
        vector.append(Point_3(float(x), float(y), float(z)))
    wrap = Polyhedron_3()
    alpha_wrap_3(vector, alpha, offset, wrap)
    with tempfile.TemporaryDirectory() as work:
        path = Path(work) / "wrap.off"
        wrap.write_to_file(str(path))
        return Candidate(cast(trimesh.Trimesh, trimesh.load(str(path), file_type="off", process=True, force="mesh")))


METHODS: dict[str, Callable[[Scene], Candidate]] = {
    "extrude": method_extrude, "extrude_mc": method_extrude_mc, "extrude_vhacd": method_extrude_vhacd, "hull": method_hull,
    "poisson": method_poisson, "alpha_wrap": method_alpha_wrap,
}
OPTIONAL = {"poisson": "open3d", "alpha_wrap": "CGAL"}


def available_methods() -> list[str]:
    names = []
    for name in METHODS:
        module = OPTIONAL.get(name)
        if module is not None:
            try:
                __import__(module)
            except ImportError:
                print(f"{name}: skipped ({module} is not importable)", file=sys.stderr)
                continue
        names.append(name)
    return names


# ----------------------------------------------------------------------------- metrics
def volume_iou(truth: trimesh.Trimesh, reconstruction: trimesh.Trimesh) -> float:
    lower = np.minimum(truth.bounds[0], reconstruction.bounds[0]) - 0.005
    upper = np.maximum(truth.bounds[1], reconstruction.bounds[1]) + 0.005
    resolution = int(math.ceil(float(np.max(upper - lower)) / IOU_PITCH_M)) + 1
    axes = node_axes(lower, lower + (resolution - 1) * IOU_PITCH_M, resolution)
    a, b = inside_mask(truth, axes), inside_mask(reconstruction, axes)
    return float(np.count_nonzero(a & b) / max(int(np.count_nonzero(a | b)), 1))


def surface_distances(truth: trimesh.Trimesh, reconstruction: trimesh.Trimesh) -> tuple[float, float]:
    """(Chamfer: mean of the two directions' mean distances, Hausdorff: max of both), metres."""
    a, _ = trimesh.sample.sample_surface(truth, SURFACE_SAMPLES, seed=0)
    b, _ = trimesh.sample.sample_surface(reconstruction, SURFACE_SAMPLES, seed=0)
    ab, _ = cKDTree(b).query(a)
    ba, _ = cKDTree(a).query(b)
    return 0.5 * (float(ab.mean()) + float(ba.mean())), max(float(ab.max()), float(ba.max()))


def measure(scene: Scene, method: str) -> dict[str, Any]:
    started = time.perf_counter()
    scene.extra_seconds = None
    try:
        candidate = METHODS[method](scene)
    except Exception as exc:  # a candidate that fails on an object is a result, not a crash
        return {"object": scene.object_id, "cameras": scene.cameras, "method": method, "error": f"{type(exc).__name__}: {exc}"}
    seconds = time.perf_counter() - started if scene.extra_seconds is None else scene.extra_seconds
    mesh = candidate.mesh
    watertight = bool(mesh.is_watertight and mesh.is_winding_consistent)
    chamfer, hausdorff = surface_distances(scene.true_mesh, mesh)
    com = np.asarray(mesh.center_mass) if watertight else mesh.bounds.mean(axis=0)
    return {
        "object": scene.object_id, "cameras": scene.cameras, "method": method, "object_points": len(scene.points),
        "iou": round(volume_iou(scene.true_mesh, mesh), 4),
        "chamfer_mm": round(chamfer * 1e3, 2), "hausdorff_mm": round(hausdorff * 1e3, 1),
        "volume_error_pct": round(100.0 * (abs(float(mesh.volume)) / scene.true_mesh.volume - 1.0), 1) if watertight else None,
        "com_error_mm": round(float(np.linalg.norm(com - scene.true_com)) * 1e3, 1),
        "watertight": watertight, "faces": int(len(mesh.faces)), "pieces": candidate.pieces, "seconds": round(seconds, 4),
    }


def summarise(rows: list[dict[str, Any]], methods: list[str]) -> list[dict[str, Any]]:
    out = []
    for cameras in CAMERAS:
        for method in methods:
            mine = [r for r in rows if r["method"] == method and r["cameras"] == cameras]
            ok = [r for r in mine if "error" not in r]
            if not ok:
                continue
            pieces = [r["pieces"] for r in ok if r.get("pieces") is not None]
            out.append({
                "cameras": cameras, "method": method, "objects": len(mine), "failed": len(mine) - len(ok),
                "watertight": sum(r["watertight"] for r in ok),
                "iou_mean": round(statistics.fmean(r["iou"] for r in ok), 3),
                "iou_min": round(min(r["iou"] for r in ok), 3),
                "chamfer_mm_mean": round(statistics.fmean(r["chamfer_mm"] for r in ok), 2),
                "hausdorff_mm_mean": round(statistics.fmean(r["hausdorff_mm"] for r in ok), 1),
                "com_error_mm_mean": round(statistics.fmean(r["com_error_mm"] for r in ok), 1),
                "faces_median": int(statistics.median(r["faces"] for r in ok)) if all("faces" in r for r in ok) else None,
                "pieces_max": max(pieces) if pieces else None,
                "seconds_median": round(statistics.median(r["seconds"] for r in ok), 3),
                "seconds_max": round(max(r["seconds"] for r in ok), 3),
                "carried": any(r.get("carried") for r in ok),
            })
    return out


def markdown(summary: list[dict[str, Any]], rows: list[dict[str, Any]], command: str) -> str:
    lines = [
        "# Closing the unseen side: reconstruction methods against the true mesh",
        "",
        (f"`{command}` on {platform.node() or 'this machine'} ({platform.processor() or platform.machine()}), "
         f"{time.strftime('%Y-%m-%d')}. Capture: shared.world.sim.camera, D435-class noise, {SIZE[0]}x{SIZE[1]}, seed 0; "
         f"object at {POSITION} turned {YAW_RAD} rad. IoU on 2 mm nodes; Chamfer = mean of both directions' mean "
         "nearest-surface distance; Hausdorff = max; seconds = object points to mesh, one core (extrude_vhacd: "
         "V-HACD alone)."),
        "",
        ("Methods (bench/perception.py): `extrude` is the product's solid, the height map cut into convex pieces "
         "(the shape physics simulates, no V-HACD); `extrude_mc` the same height map meshed by marching cubes (the "
         "detailed surface, which physics cannot simulate as is); `extrude_vhacd` V-HACD's pieces of that surface "
         "(what physics simulated before the convex pieces; its seconds are V-HACD's alone); `hull`, `poisson`, "
         "`alpha_wrap` the alternatives."),
        "",
        ("| cameras | method | objects (failed) | watertight | IoU mean | IoU min | Chamfer mm | Hausdorff mm | CoM error mm "
        "| faces (median) | convex pieces (max) | s (median / max) |"),
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for s in summary:
        method = s["method"] + (" *" if s.get("carried") else "")
        lines.append(f"| {s['cameras']} | {method} | {s['objects']} ({s['failed']}) | {s['watertight']} | {s['iou_mean']} | "
                     f"{s['iou_min']} | {s['chamfer_mm_mean']} | {s['hausdorff_mm_mean']} | {s['com_error_mm_mean']} | "
                     f"{s.get('faces_median') or '—'} | {s.get('pieces_max') or '—'} | "
                     f"{s['seconds_median']} / {s.get('seconds_max', '—')} |")
    if any(s.get("carried") for s in summary):
        lines += ["", ("\\* carried over from the last run that could import open3d / CGAL (they are not project "
                  "dependencies); the other rows are from this run.")]
    methods = sorted({r["method"] for r in rows}, key=list(METHODS).index)
    lines += ["", "Per object (IoU / Chamfer mm / Hausdorff mm / s):", "",
              "| object | cameras | " + " | ".join(methods) + " |",
              "|---|---|" + "---|" * len(methods)]
    for key in dict.fromkeys((r["object"], r["cameras"]) for r in rows):
        cells = []
        for method in methods:
            row = next((r for r in rows if (r["object"], r["cameras"], r["method"]) == (*key, method)), None)
            cells.append("—" if row is None else ("failed" if "error" in row else
                         f"{row['iou']:.2f} / {row['chamfer_mm']:.1f} / {row['hausdorff_mm']:.0f} / {row['seconds']:.2f}"
                         + ("" if row["watertight"] else " (open)")))
        lines.append(f"| {key[0]} | {key[1]} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def carried_rows(methods: list[str], objects: list[str]) -> list[dict[str, Any]]:
    """Rows of the methods that could not run here, from the committed results (marked `carried`)."""
    path = RESULTS / "perception.json"
    if not path.is_file():
        return []
    missing = [m for m in OPTIONAL if m not in methods]
    rows = [dict(r, carried=True) for r in json.loads(path.read_text()).get("rows", [])
            if r.get("method") in missing and r.get("object") in objects]
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--quick", action="store_true", help=f"only {', '.join(QUICK_OBJECTS)}; results not written")
    parser.add_argument("--json", action="store_true", help="end with one JSON line (always printed last)")
    args = parser.parse_args(argv)
    methods = available_methods()
    objects = QUICK_OBJECTS if args.quick else OBJECTS
    rows: list[dict[str, Any]] = []
    for object_id in objects:
        for cameras in CAMERAS:
            scene = make_scene(object_id, cameras)
            for method in methods:
                row = measure(scene, method)
                rows.append(row)
                print(json.dumps(row), file=sys.stderr)
    if not args.quick:
        rows += carried_rows(methods, objects)
    all_methods = [m for m in METHODS if any(r["method"] == m for r in rows)]
    summary = summarise(rows, all_methods)
    command = "python bench/perception.py" + (" --quick" if args.quick else "")
    text = markdown(summary, rows, command)
    if not args.quick:
        RESULTS.mkdir(exist_ok=True)
        (RESULTS / "perception.json").write_text(json.dumps({"summary": summary, "rows": rows}, indent=1) + "\n")
        (RESULTS / "perception.md").write_text(text)
    print(text)
    if args.json:
        print(json.dumps({"summary": summary}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
