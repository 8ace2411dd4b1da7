"""Do pushes on a reconstruction end like pushes on the true object? And how long is capture-to-mesh?

    python bench/perception_agreement.py                 # full size (resumable); writes bench/results/perception_agreement.*
    python bench/perception_agreement.py --workers 2     # the same, objects in two processes
    python bench/perception_agreement.py --quick --json  # smoke: 2 objects x 10 poses, written to a temporary file

Objects: the 14 evaluation objects (evaluation/push_protocol.py: PROCEDURAL_OBJECTS + EVERYDAY_OBJECTS)
and `--others` (20) other held-out objects: test-split ids not among the 14, taken round-robin over
their families (rnd, pb, proc-box, proc-cylinder, ...), each family's ids in the order of their
SHA-256 (deterministic, unrelated to shape).

Per object, as the evaluation places it: resting in its default pose at OBJECT_XY = (0.40, 0), yaw 0.
1. Poses: `--poses` (200) hand poses, split over the evaluation's three directions (60, 180, 300 deg:
   67 / 67 / 66): diffusion samples (the shipped Allegro checkpoint, DDPM-100, seeded per object
   and direction) of the true object in that direction's frame D. These are the poses the system
   itself pushes with (the planner's K = 200 candidates are exactly these samples), so both the
   successes and the failures are the ones the reconstruction has to predict; generator poses
   cost seconds each, and the fixed spatula pose is one pose.
2. Captures: `shared.world.sim.camera.capture_object` with 1 and with 3 cameras (default size, D435-class
   noise, seeded per object and camera count), thinned as a request carries it
   (`cloud_for_request`), reconstructed and modelled as every service does (`object_from_cloud`).
3. Pushes: the validator's floating-hand push (`shared.validation.push.PushSimulator`, default
   physics, 0.20 m), each pose once on the true object and once on each reconstruction.

The frame (thought through): a pose is a hand pose in D, and it must be the same physical pose for
both objects, so both stand in the same D - the true object's (origin under its centre of mass,
+x along the push). The true object is at `inv(T_world_D) @ T_world_O`, i.e. the validator's
`table_object(obj, None, -direction)`; the reconstruction stands where the camera saw it, in its
captured resting pose, at `inv(T_world_D) @ captured.T_world_O` (not `table_object`, which would put
its own centre of mass on D's origin and hide the reconstruction's position error, a few mm, which
the robot would meet). Checked for every pose set: the reconstruction stands on the table (lowest
point within 2 mm of z = 0), upright, and the two footprints in D overlap (IoU of their convex
outlines >= 0.5, centres within 3 cm); `--quick` asserts it, full runs record it (`frame_ok`).

Reported: the fraction of poses with the same outcome (success or not, `shared.world.push_outcome.judge_push`
via PushSimulator) per object and camera count, pooled over the objects (overall and per group:
evaluation / held-out), the objects at >= 90 %, and the success rates on the true object and the
reconstructions (agreement means little when almost every push fails). A reconstruction that fails
counts as 0 % agreement in the pooled figures (and is listed).

Resumable: one JSON line per finished object is appended to `--out`; objects already there (with
the same poses and cameras) are skipped. `--json` prints the summary as the last line.

Timing (the issue's "capture-to-mesh <= 0.5 s for a 100k-point cloud on one core"; skipped with
--no-timing): the head camera's capture of each evaluation object (848 x 480: ~103k points) is
reconstructed (table, cluster, convex pieces) 3 times in this process pinned to one core with one
torch thread; CPU seconds (= seconds on one idle core) and wall seconds, median and max over the
objects, per stage, and the object model + URDF (the first physics use) after it.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import math
import multiprocessing
import os
import platform
import statistics
import sys
import tempfile
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

REPO_DIR = Path(__file__).resolve().parents[1]
if str(REPO_DIR) not in sys.path:
    sys.path.insert(0, str(REPO_DIR))

from evaluation.push_protocol import (  # noqa: E402
    DIRECTIONS_DEG,
    EVERYDAY_OBJECTS,
    OBJECT_XY,
    PROCEDURAL_OBJECTS,
)

RESULTS = REPO_DIR / "bench" / "results"
OUT = RESULTS / "perception_agreement.jsonl"
CHECKPOINT = REPO_DIR / "shared" / "sampling" / "checkpoints" / "allegro.pt"
HAND = "allegro"
SAMPLER = "ddpm"
POSES = 200
OTHERS = 20
CAMERAS = (1, 3)
QUICK_OBJECTS = ("proc-box-001", "pb-mug")
QUICK_POSES = 10
TARGET = 0.90  # the figure: >= 90 % of poses with the same outcome
TIMING_REPEATS = 3
FOOTPRINT_MIN_IOU = 0.5
CENTRE_MAX_OFFSET_M = 0.03
EVALUATION_OBJECTS = tuple(PROCEDURAL_OBJECTS) + tuple(EVERYDAY_OBJECTS)


# ----------------------------------------------------------------------------- objects and seeds
def family(object_id: str) -> str:
    """rnd, pb, proc-box, proc-cylinder, ...: what the held-out objects are spread over."""
    return "pb" if object_id.startswith("pb-") else object_id.rsplit("-", 1)[0]


def held_out_objects(count: int) -> list[str]:
    """`count` test-split objects not among the evaluation's, round-robin over families (see the docstring)."""
    from shared.world.objects import list_object_ids

    pool = [i for i in list_object_ids("test") if i not in EVALUATION_OBJECTS]
    families: dict[str, list[str]] = {}
    for object_id in sorted(pool, key=lambda i: hashlib.sha256(i.encode()).hexdigest()):
        families.setdefault(family(object_id), []).append(object_id)
    chosen: list[str] = []
    queues = [families[name] for name in sorted(families)]
    while len(chosen) < count and any(queues):
        for queue in queues:
            if queue and len(chosen) < count:
                chosen.append(queue.pop(0))
    return chosen


def seed_of(*parts: object) -> int:
    digest = hashlib.sha256("/".join(str(p) for p in parts).encode()).digest()
    return int.from_bytes(digest[:4], "little") & 0x7FFFFFFF


def poses_per_direction(total: int, directions: Sequence[float] = DIRECTIONS_DEG) -> list[int]:
    """`total` split over the directions as evenly as possible, the first ones taking the remainder."""
    base, extra = divmod(total, len(directions))
    return [base + (1 if k < extra else 0) for k in range(len(directions))]


# ----------------------------------------------------------------------------- one object
@dataclass(frozen=True)
class Job:
    object_id: str
    poses: int
    cameras: tuple[int, ...]
    strict_frames: bool  # raise when the frame check fails (the smoke run) instead of recording it


_SAMPLER: Any = None


def _pose_sampler() -> Any:
    """The process's PoseSampler (loaded once)."""
    global _SAMPLER
    if _SAMPLER is None:
        from shared.sampling.sampling import PoseSampler

        _SAMPLER = PoseSampler(CHECKPOINT)
    return _SAMPLER


def _init_worker() -> None:
    import torch

    torch.set_num_threads(1)


def run_object(job: Job, progress: Callable[[int], None] | None = None) -> dict[str, Any]:
    """Everything measured for one object (one JSON line); see the module docstring."""
    from shared.contracts.messages import DirectionFrame
    from shared.frames import invert_transform, make_transform
    from shared.robots.hands import load_hand
    from shared.validation.push import PushSimulator, TableObject
    from shared.world.objects import load_object, write_object_urdf
    from shared.world.perception import PerceptionError, cloud_for_request, object_from_cloud
    from shared.world.push_outcome import object_pose
    from shared.world.sim import c_stdout_to_stderr
    from shared.world.sim.camera import capture_object

    started = time.perf_counter()
    tick = progress or (lambda n: None)
    row: dict[str, Any] = {"object": job.object_id, "group": "evaluation" if job.object_id in EVALUATION_OBJECTS else "held-out",
                           "poses": job.poses, "cameras": list(job.cameras), "hand": HAND, "sampler": SAMPLER,
                           "directions": list(DIRECTIONS_DEG), "object_xy": list(OBJECT_XY)}
    with c_stdout_to_stderr():
        obj = load_object(job.object_id)
        hand = load_hand(HAND)
        T_world_O = make_transform(np.eye(3), np.array([OBJECT_XY[0], OBJECT_XY[1], 0.0])) @ obj.T_D_O()
        sets = []  # (direction, T_world_D, poses_d)
        for direction, count in zip(DIRECTIONS_DEG, poses_per_direction(job.poses), strict=True):
            frame = DirectionFrame(object_pose=object_pose(T_world_O), yaw_deg=direction)
            sample = _pose_sampler().sample(obj, frame, k=count, sampler=SAMPLER, seed=seed_of("poses", job.object_id, direction))
            sets.append((direction, sample.T_world_D, sample.poses_d))

        def push_all(object_id: str, urdf: Path, T_world_model: np.ndarray, vertices: np.ndarray) -> tuple[list[bool], list[dict[str, Any]]]:
            outcomes: list[bool] = []
            checks = []
            for _direction, T_world_D, poses_d in sets:
                T_D_model = invert_transform(T_world_D) @ T_world_model
                vertices_d = vertices @ T_D_model[:3, :3].T + T_D_model[:3, 3]
                checks.append(vertices_d)
                with PushSimulator(hand, TableObject(object_id, urdf, T_D_model, vertices_d)) as simulator:
                    for pose in poses_d:
                        outcomes.append(bool(simulator.run(pose).success))
                        tick(1)
            return outcomes, [{"vertices_d": v} for v in checks]

        truth, truth_checks = push_all(obj.id, write_object_urdf(obj), T_world_O, obj.mesh.vertices)
        row["true_success"] = "".join("1" if s else "0" for s in truth)
        row["seconds_true"] = round(time.perf_counter() - started, 2)
        for cameras in job.cameras:
            entry: dict[str, Any] = {"capture_seed": seed_of("capture", job.object_id, cameras)}
            row[f"cameras_{cameras}"] = entry
            t0 = time.perf_counter()
            capture = capture_object(obj, T_world_O, n_cameras=cameras, seed=entry["capture_seed"])
            cloud = cloud_for_request(capture.cloud)
            t1 = time.perf_counter()
            try:
                captured = object_from_cloud(cloud)
                urdf = write_object_urdf(captured.model)
            except PerceptionError as exc:
                entry.update(error=str(exc), cloud_points=len(cloud))
                tick(job.poses)
                continue
            t2 = time.perf_counter()
            outcomes, checks = push_all(captured.model.id, urdf, captured.T_world_O, captured.model.mesh.vertices)
            frames = [frame_check(t["vertices_d"], r["vertices_d"]) for t, r in zip(truth_checks, checks, strict=True)]
            # upright as captured: the captured orientation is the model's resting (native) pose turned about z
            turn = captured.T_world_O[:3, :3] @ captured.model.default_pose.rotation.T
            upright = bool(captured.model.default_pose.native and turn[2, 2] > math.cos(math.radians(1.0)))
            frame_ok = bool(all(f["ok"] for f in frames) and upright)
            if job.strict_frames and not frame_ok:
                raise AssertionError(f"{job.object_id}, {cameras} camera(s): the reconstruction does not stand where the "
                                     f"object does in D: {frames}, upright {upright}")
            same = [a == b for a, b in zip(truth, outcomes, strict=True)]
            entry.update(
                cloud_points=len(cloud), object_points=len(captured.object_points), convex_parts=captured.meta.get("convex_parts"),
                volume_ratio=round(float(captured.model.volume / obj.volume), 3),
                success="".join("1" if s else "0" for s in outcomes), agreement=round(float(np.mean(same)), 4),
                both_succeed=sum(a and b for a, b in zip(truth, outcomes, strict=True)),
                only_true_succeeds=sum(a and not b for a, b in zip(truth, outcomes, strict=True)),
                only_reconstruction_succeeds=sum(b and not a for a, b in zip(truth, outcomes, strict=True)),
                frame_ok=frame_ok, footprint_iou_min=min(f["footprint_iou"] for f in frames),
                centre_offset_mm_max=max(f["centre_offset_mm"] for f in frames),
                bottom_mm_max=max(abs(f["bottom_mm"]) for f in frames),
                seconds_capture=round(t1 - t0, 2), seconds_model=round(t2 - t1, 2),
                seconds_pushes=round(time.perf_counter() - t2, 2))
    row["seconds"] = round(time.perf_counter() - started, 2)
    return row


def frame_check(truth_d: np.ndarray, reconstruction_d: np.ndarray, pitch: float = 0.001) -> dict[str, Any]:
    """Do the two objects stand in the same place in D? Footprint IoU (convex outlines), centre offset, bottom."""
    from matplotlib.path import Path as Polygon
    from scipy.spatial import ConvexHull

    outlines = [Polygon(v[ConvexHull(v[:, :2]).vertices, :2]) for v in (truth_d, reconstruction_d)]
    low = np.minimum(truth_d[:, :2].min(axis=0), reconstruction_d[:, :2].min(axis=0))
    high = np.maximum(truth_d[:, :2].max(axis=0), reconstruction_d[:, :2].max(axis=0))
    x, y = np.meshgrid(np.arange(low[0], high[0], pitch), np.arange(low[1], high[1], pitch), indexing="ij")
    grid = np.column_stack([x.ravel(), y.ravel()])
    inside = [outline.contains_points(grid) for outline in outlines]
    iou = float(np.count_nonzero(inside[0] & inside[1]) / max(int(np.count_nonzero(inside[0] | inside[1])), 1))
    offset = float(np.linalg.norm(grid[inside[0]].mean(axis=0) - grid[inside[1]].mean(axis=0))) if all(i.any() for i in inside) else math.inf
    bottom = float(reconstruction_d[:, 2].min())
    ok = bool(iou >= FOOTPRINT_MIN_IOU and offset <= CENTRE_MAX_OFFSET_M and abs(bottom) <= 0.002)
    return {"footprint_iou": round(iou, 3), "centre_offset_mm": round(offset * 1e3, 1), "bottom_mm": round(bottom * 1e3, 2), "ok": ok}


# ----------------------------------------------------------------------------- the run
def read_done(path: Path, poses: int, cameras: Sequence[int]) -> dict[str, dict[str, Any]]:
    """Finished objects in `path` (refusing lines measured with other poses / cameras: use another --out)."""
    done: dict[str, dict[str, Any]] = {}
    if not path.is_file():
        return done
    for number, line in enumerate(path.read_text().splitlines(), start=1):
        if not line.strip():
            continue
        try:
            row = json.loads(line)
        except json.JSONDecodeError:
            print(f"{path}:{number}: not JSON (a killed run's last line?); ignored", file=sys.stderr)
            continue
        if row.get("poses") != poses or row.get("cameras") != list(cameras):
            raise SystemExit(f"{path}:{number}: {row.get('object')} was measured with {row.get('poses')} poses and cameras "
                             f"{row.get('cameras')}, not {poses} and {list(cameras)}: give another --out")
        done[row["object"]] = row
    return done


def run(jobs: list[Job], out: Path, workers: int) -> None:
    """Measure every job, appending each finished object's line to `out` at once."""
    from tqdm import tqdm

    if not jobs:
        return
    pushes = sum(job.poses * (1 + len(job.cameras)) for job in jobs)
    out.parent.mkdir(parents=True, exist_ok=True)
    with tqdm(total=pushes, unit="push", desc="agreement", dynamic_ncols=True) as bar, out.open("a") as sink:
        def record(row: dict[str, Any]) -> None:
            sink.write(json.dumps(row) + "\n")
            sink.flush()
            agreement = ", ".join(f"{c} cam {row[f'cameras_{c}'].get('agreement', 'failed')}" for c in row["cameras"])
            bar.set_postfix_str(f"{row['object']}: {agreement}")

        if workers <= 1:
            _init_worker()
            for job in jobs:
                bar.set_description(job.object_id)
                record(run_object(job, bar.update))
            return
        context = multiprocessing.get_context("spawn")
        with context.Pool(workers, initializer=_init_worker) as pool:
            for row in pool.imap_unordered(run_object, jobs):
                bar.update(row["poses"] * (1 + len(row["cameras"])))
                record(row)


# ----------------------------------------------------------------------------- the summary
def summarise(rows: Iterable[dict[str, Any]], cameras: Sequence[int]) -> dict[str, Any]:
    rows = list(rows)
    out: dict[str, Any] = {"objects": len(rows), "per_cameras": {}}
    for count in cameras:
        entries = [(row, row.get(f"cameras_{count}", {})) for row in rows]
        per_group: dict[str, Any] = {}
        for group in ("all", "evaluation", "held-out"):
            mine = [(row, e) for row, e in entries if group == "all" or row["group"] == group]
            if not mine:
                continue
            agreements = [e.get("agreement", 0.0) for _, e in mine]
            poses = sum(row["poses"] for row, _ in mine)
            same = sum(round(e.get("agreement", 0.0) * row["poses"]) for row, e in mine)
            true_rate = sum(row["true_success"].count("1") for row, _ in mine) / max(poses, 1)
            ok = [(row, e) for row, e in mine if "agreement" in e]
            recon_rate = sum(e["success"].count("1") for _, e in ok) / max(sum(row["poses"] for row, _ in ok), 1)
            per_group[group] = {
                "objects": len(mine), "reconstruction_failed": [row["object"] for row, e in mine if "agreement" not in e],
                "agreement_pooled": round(same / max(poses, 1), 4),
                "agreement_mean": round(statistics.fmean(agreements), 4), "agreement_min": round(min(agreements), 4),
                "objects_at_target": sum(a >= TARGET for a in agreements),
                "true_success_rate": round(true_rate, 4), "reconstruction_success_rate": round(recon_rate, 4),
                "frame_not_ok": [row["object"] for row, e in ok if not e.get("frame_ok", True)],
            }
        out["per_cameras"][str(count)] = per_group
    return out


def markdown(summary: dict[str, Any], rows: list[dict[str, Any]], timing: dict[str, Any] | None, command: str,
             cameras: Sequence[int]) -> str:
    lines = [
        "# Pushes on the reconstruction vs on the true object",
        "",
        (f"`{command}` on {platform.node() or 'this machine'}, {time.strftime('%Y-%m-%d')}. {summary['objects']} objects "
         f"at {tuple(OBJECT_XY)}, {rows[0]['poses'] if rows else POSES} diffusion poses each ({HAND}, {SAMPLER}) over the "
         f"directions {', '.join(f'{d:g}' for d in DIRECTIONS_DEG)} deg, each pushed 0.20 m on the true object and on its "
         "reconstruction from 1 and from 3 simulated cameras (bench/perception_agreement.py explains the frame)."),
        "",
        ("| cameras | objects | same outcome (pooled) | mean / min per object | objects >= 90 % | success true / reconstruction "
        "| reconstruction failed |"),
        "|---|---|---|---|---|---|---|",
    ]
    for count in cameras:
        for group, s in summary["per_cameras"][str(count)].items():
            lines.append(f"| {count} ({group}) | {s['objects']} | {s['agreement_pooled']:.1%} | {s['agreement_mean']:.1%} / "
                         f"{s['agreement_min']:.1%} | {s['objects_at_target']} | {s['true_success_rate']:.1%} / "
                         f"{s['reconstruction_success_rate']:.1%} | {', '.join(s['reconstruction_failed']) or '-'} |")
    lines += ["", "Per object (same outcome; success rate true / reconstruction):", "",
              "| object | group | " + " | ".join(f"{c} camera(s)" for c in cameras) + " |",
              "|---|---|" + "---|" * len(cameras)]
    for row in rows:
        cells = []
        true_rate = row["true_success"].count("1") / row["poses"]
        for count in cameras:
            e = row.get(f"cameras_{count}", {})
            cells.append(f"failed: {e.get('error', '?')}" if "agreement" not in e else
                         f"{e['agreement']:.0%} ({true_rate:.0%} / {e['success'].count('1') / row['poses']:.0%})")
        lines.append(f"| {row['object']} | {row['group']} | " + " | ".join(cells) + " |")
    if timing:
        lines += ["", "## Capture to mesh, one core", "", timing_text(timing)]
    return "\n".join(lines) + "\n"


# ----------------------------------------------------------------------------- timing
def time_capture_to_mesh(objects: Sequence[str] = EVALUATION_OBJECTS, repeats: int = TIMING_REPEATS) -> dict[str, Any]:
    """Seconds from a head-camera cloud (~100k points) to the mesh and to the URDF, pinned to one core."""
    import torch

    from shared.frames import make_transform
    from shared.world.objects import load_object, write_object_urdf
    from shared.world.perception import reconstruct
    from shared.world.perception.object_model import object_from_reconstruction
    from shared.world.sim import c_stdout_to_stderr
    from shared.world.sim.camera import DEFAULT_SIZE, capture_object

    affinity = os.sched_getaffinity(0)
    threads = torch.get_num_threads()
    os.sched_setaffinity(0, {min(affinity)})
    torch.set_num_threads(1)
    per_object: list[dict[str, Any]] = []
    try:
        with c_stdout_to_stderr():
            for object_id in objects:
                obj = load_object(object_id)
                T_world_O = make_transform(np.eye(3), np.array([OBJECT_XY[0], OBJECT_XY[1], 0.0])) @ obj.T_D_O()
                cpu, wall = time.process_time(), time.perf_counter()
                cloud = capture_object(obj, T_world_O, n_cameras=1, seed=0).cloud
                capture = (time.process_time() - cpu, time.perf_counter() - wall)
                runs = []
                for _ in range(repeats):
                    cpu, wall = time.process_time(), time.perf_counter()
                    recon = reconstruct(cloud)
                    mesh = (time.process_time() - cpu, time.perf_counter() - wall)
                    with tempfile.TemporaryDirectory() as cache:
                        cpu, wall = time.process_time(), time.perf_counter()
                        write_object_urdf(object_from_reconstruction(recon, cache_dir=cache).model)
                        physics = (time.process_time() - cpu, time.perf_counter() - wall)
                    runs.append((mesh, physics, recon.timings))
                per_object.append({
                    "object": object_id, "points": len(cloud), "capture_cpu_s": round(capture[0], 3),
                    "mesh_cpu_s": round(statistics.median(r[0][0] for r in runs), 3),
                    "mesh_wall_s": round(statistics.median(r[0][1] for r in runs), 3),
                    "table_s": round(statistics.median(r[2].table for r in runs), 3),
                    "cluster_s": round(statistics.median(r[2].cluster for r in runs), 3),
                    "solid_s": round(statistics.median(r[2].surface for r in runs), 3),
                    "model_urdf_cpu_s": round(statistics.median(r[1][0] for r in runs), 3),
                    "convex_parts": len(recon.convex_parts),
                })
    finally:
        os.sched_setaffinity(0, affinity)
        torch.set_num_threads(threads)

    def stat(key: str) -> dict[str, float]:
        values = [o[key] for o in per_object]
        return {"median": round(statistics.median(values), 3), "max": round(max(values), 3)}

    return {"size": list(DEFAULT_SIZE), "repeats": repeats, "load_average": list(os.getloadavg()),
            "points": stat("points"), "capture_cpu_s": stat("capture_cpu_s"), "mesh_cpu_s": stat("mesh_cpu_s"),
            "mesh_wall_s": stat("mesh_wall_s"), "table_s": stat("table_s"), "cluster_s": stat("cluster_s"),
            "solid_s": stat("solid_s"), "model_urdf_cpu_s": stat("model_urdf_cpu_s"), "per_object": per_object}


def timing_text(timing: dict[str, Any]) -> str:
    t = timing
    return (f"Head-camera clouds of the {len(t['per_object'])} evaluation objects ({t['size'][0]}x{t['size'][1]}, "
            f"{t['points']['median']:.0f} points median), {t['repeats']} runs each, pinned to one core (load average "
            f"{t['load_average'][0]:.1f} while measured): cloud to mesh {t['mesh_cpu_s']['median']} s CPU median, "
            f"{t['mesh_cpu_s']['max']} s max (wall {t['mesh_wall_s']['median']} / {t['mesh_wall_s']['max']} s; table "
            f"{t['table_s']['median']}, cluster {t['cluster_s']['median']}, convex pieces {t['solid_s']['median']} s median); "
            f"then object model + URDF {t['model_urdf_cpu_s']['median']} / {t['model_urdf_cpu_s']['max']} s; the capture "
            f"itself (render + noise) {t['capture_cpu_s']['median']} s. Target: <= 0.5 s cloud to mesh.")


# ----------------------------------------------------------------------------- main
def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--quick", action="store_true",
                        help=f"smoke run: {', '.join(QUICK_OBJECTS)} x {QUICK_POSES} poses, frames asserted, a temporary --out")
    parser.add_argument("--objects", help="comma-separated ids instead of the 14 evaluation + --others held-out objects")
    parser.add_argument("--others", type=int, default=OTHERS, help=f"held-out objects besides the evaluation's (default {OTHERS})")
    parser.add_argument("--poses", type=int, default=None, help=f"poses per object (default {POSES}; --quick {QUICK_POSES})")
    parser.add_argument("--cameras", default=",".join(map(str, CAMERAS)), help="camera counts (default 1,3)")
    parser.add_argument("--workers", type=int, default=1, help="processes, one object each at a time (default 1)")
    parser.add_argument("--out", type=Path, help=f"JSON lines, appended and resumed (default {OUT.relative_to(REPO_DIR)})")
    parser.add_argument("--no-timing", action="store_true", help="skip the capture-to-mesh timing")
    parser.add_argument("--json", action="store_true", help="print the summary as one JSON line, last")
    args = parser.parse_args(argv)
    cameras = tuple(int(c) for c in args.cameras.split(","))
    poses = args.poses if args.poses is not None else (QUICK_POSES if args.quick else POSES)
    if args.objects:
        objects = [o.strip() for o in args.objects.split(",") if o.strip()]
    elif args.quick:
        objects = list(QUICK_OBJECTS)
    else:
        objects = list(EVALUATION_OBJECTS) + held_out_objects(args.others)
    out = args.out or (Path(tempfile.mkdtemp(prefix="perception-agreement-")) / "agreement.jsonl" if args.quick else OUT)
    done = read_done(out, poses, cameras)
    jobs = [Job(o, poses, cameras, strict_frames=args.quick) for o in objects if o not in done]
    print(f"{len(objects)} objects ({len(objects) - len(jobs)} done in {out}), {poses} poses, cameras {list(cameras)}",
          file=sys.stderr)
    timing = None if args.no_timing else time_capture_to_mesh(objects=QUICK_OBJECTS if args.quick else EVALUATION_OBJECTS,
                                                              repeats=1 if args.quick else TIMING_REPEATS)
    if timing is not None:
        print(timing_text(timing), file=sys.stderr)
    run(jobs, out, args.workers)
    rows = [r for o, r in read_done(out, poses, cameras).items() if o in objects]
    rows.sort(key=lambda r: objects.index(r["object"]))
    summary = summarise(rows, cameras)
    summary["timing"] = timing
    command = "python bench/perception_agreement.py" + (" --quick" if args.quick else "")
    text = markdown(summary, rows, timing, command, cameras)
    if not args.quick and not args.objects and len(rows) == len(objects):
        (RESULTS / "perception_agreement.json").write_text(json.dumps({"summary": summary, "rows": rows}, indent=1) + "\n")
        (RESULTS / "perception_agreement.md").write_text(text)
    print(text)
    print(f"lines: {out}", file=sys.stderr)
    if args.json:
        print(json.dumps({k: v for k, v in summary.items() if k != "timing"} | {"timing": None if timing is None else
                          {k: v for k, v in timing.items() if k != "per_object"}}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
