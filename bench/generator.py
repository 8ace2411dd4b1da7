"""Generator benchmark: finished push-pose candidates per second on this machine, and peak memory.

    python bench/generator.py --json [--iterations 1500] [--batch 256] [--processes 2]

- `candidates_per_s`: `--processes` worker processes (spawned, one torch thread each, as the
  generator service runs: one process per core) each optimise one batch of `--batch` poses at the
  given iteration count (default: the config's) on its own object; total poses / wall time of the
  slowest process's `generate` call. Object loading (SDF from the cache) and imports are excluded:
  a worker pays them once per object, not per batch. `end_to_end_candidates_per_s` includes them.
- `candidates_per_s_from_cpu_time`: the same from each process's CPU time, i.e. what the cores would
  give if nothing else ran on them (the wall-clock figure drops when other processes share them).
- `peak_rss_mb_batch_1024`: peak resident memory of a fresh process optimising a batch of 1024 for
  `--memory-iterations` iterations (memory does not grow with iterations: no per-iteration state
  is kept beyond a few floats of history).
- energy curves (batch-mean total and weighted terms per iteration) go to bench/results/*.png.
- `good_fraction`: poses passing the pre-physics check (palm x >= 0.7, penetration <= 5 mm, every
  contact within 5 mm of the pre-contact offset); the validator decides what really pushes.
The last line printed is a JSON object.
"""
from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import platform
import resource
import sys
import time

REPO_DIR = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if REPO_DIR not in sys.path:
    sys.path.insert(0, REPO_DIR)

RESULTS_DIR = os.path.join(REPO_DIR, "bench", "results")
DEFAULT_OBJECTS = ("proc-box-010", "proc-cylinder-004")  # a volumetric box and cylinder (train split)


def run_batch(object_id: str, hand: str, batch: int, iterations: int | None, seed: int, plot: bool) -> dict:
    """One worker process: load the object, optimise one batch, report timing and quality."""
    started = time.perf_counter()
    import torch

    torch.set_num_threads(1)
    from shared.robots.hands import load_hand
    from shared.synthesis.config import GenerationConfig
    from shared.synthesis.plots import plot_energy_history
    from shared.synthesis.scene import PushScene
    from shared.synthesis.synthesis import generate
    from shared.world.objects import load_object

    config = GenerationConfig(batch_size=batch).replace(iterations=iterations)
    scene = PushScene.from_object(load_object(object_id), surface_points=config.object_points,
                                  check_points=config.penetration_check_points)
    hand_model = load_hand(hand)
    ready, cpu_ready = time.perf_counter(), time.process_time()
    output = generate(scene, hand_model, batch, seed, config)
    done, cpu_done = time.perf_counter(), time.process_time()
    result = {
        "object": object_id, "poses": len(output), "iterations": config.iterations,
        "generate_s": round(done - ready, 2), "generate_cpu_s": round(cpu_done - cpu_ready, 2),
        "startup_s": round(ready - started, 2),
        "good_fraction": round(float(output.good().mean()), 3),
        "palm_x_ge_0_7": round(float((output.palm_normals[:, 0] >= 0.7).mean()), 3),
        "penetration_le_5mm": round(float((output.max_penetration_m <= 0.005).mean()), 3),
        "energy_first": round(float(output.history["total"][0]), 2),
        "energy_last": round(float(output.history["total"][-1]), 2),
        "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0, 1),
        "start_wall": ready, "end_wall": done, "first_wall": started,
    }
    if plot:
        os.makedirs(RESULTS_DIR, exist_ok=True)
        path = os.path.join(RESULTS_DIR, f"generator_energy_{object_id}_{hand}.png")
        plot_energy_history(output.history, path, config.effective_weights(),
                            title=f"{object_id}, {hand}, B={batch}, {config.iterations} iterations (batch means)")
        result["plot"] = os.path.relpath(path, REPO_DIR)
    return result


def _star_run_batch(args: tuple) -> dict:
    return run_batch(*args)


def throughput(objects: list[str], hand: str, batch: int, iterations: int | None, processes: int) -> dict:
    jobs = [(objects[i % len(objects)], hand, batch, iterations, i, True) for i in range(processes)]
    with multiprocessing.get_context("spawn").Pool(processes) as pool:
        runs = pool.map(_star_run_batch, jobs)
    poses = sum(r["poses"] for r in runs)
    generate_wall = max(r["end_wall"] for r in runs) - min(r["start_wall"] for r in runs)
    total_wall = max(r["end_wall"] for r in runs) - min(r["first_wall"] for r in runs)
    for r in runs:
        for key in ("start_wall", "end_wall", "first_wall"):
            r.pop(key)
    cpu_per_pose = sum(r["generate_cpu_s"] for r in runs) / poses
    return {
        "candidates_per_s": round(poses / generate_wall, 2),
        # What `processes` cores would give if nothing else ran: contention-free, from CPU time.
        "candidates_per_s_from_cpu_time": round(processes / cpu_per_pose, 2),
        "end_to_end_candidates_per_s": round(poses / total_wall, 2),
        "runs": runs,
    }


def peak_memory(object_id: str, hand: str, iterations: int) -> float:
    """Peak RSS (MB) of a fresh process optimising a batch of 1024."""
    with multiprocessing.get_context("spawn").Pool(1) as pool:
        run = pool.apply(run_batch, (object_id, hand, 1024, iterations, 0, False))
    return run["peak_rss_mb"]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--json", action="store_true", help="print the result as one JSON object (last line)")
    parser.add_argument("--hand", default="allegro", choices=("allegro", "leap"))
    parser.add_argument("--objects", default=",".join(DEFAULT_OBJECTS), help="comma-separated library ids")
    parser.add_argument("--iterations", type=int, default=None, help="default: the generator config's")
    parser.add_argument("--batch", type=int, default=256)
    parser.add_argument("--processes", type=int, default=2)
    parser.add_argument("--memory-iterations", type=int, default=50)
    args = parser.parse_args(argv)
    objects = [o for o in args.objects.split(",") if o]
    # Warm the object caches (geometry, SDF) so neither measurement pays for them.
    from shared.world.objects import load_object

    for object_id in objects:
        _ = load_object(object_id).sdf  # the property builds and caches the SDF
    result = {
        "bench": "generator", "hand": args.hand, "batch": args.batch, "processes": args.processes,
        "cpu_count": os.cpu_count(), "load_avg_at_start": round(os.getloadavg()[0], 2), "python": platform.python_version(),
    }
    result.update(throughput(objects, args.hand, args.batch, args.iterations, args.processes))
    result["peak_rss_mb_batch_1024"] = peak_memory(objects[0], args.hand, args.memory_iterations)
    result["load_avg_at_end"] = round(os.getloadavg()[0], 2)
    if not args.json:
        for run in result["runs"]:
            print(f"{run['object']}: {run['poses']} poses in {run['generate_s']} s, good {run['good_fraction']:.0%}",
                  file=sys.stderr)
        print(f"{result['candidates_per_s']} candidates/s on {args.processes} processes; "
              f"peak RSS at batch 1024: {result['peak_rss_mb_batch_1024']} MB", file=sys.stderr)
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
