"""Validator benchmark: push throughput, solver-setting agreement, raw vs augmented success.

    python bench/validator.py --json [--source generator|perturbed] [--per-object 12]
                                     [--candidates 20x240,20x120] [--processes 1,2]

Episode set, for each object of `--objects` (boxes, cylinders, a tall box, a convex hull, the duck
and the mug by default) and each hand, `--per-object` poses from one of two sources:
- `generator` (default): candidates optimised by the project's generator (services/generator, its
  default settings, seed 1) - what the validator sees in the data engine;
- `perturbed`: the spatula pose plus perturbations of it, alternately mild (up to 10 deg, 1.6 cm,
  0.12 rad per joint) and strong (25 deg, 4 cm sideways, 6 cm up, 0.3 rad).

Measured:
- `agreement`: for the chosen settings and every `--candidates` setting (ITERATIONSxHZ), the
  fraction of episodes whose success is the same as with the reference settings (50 iterations,
  1/240 s), with ms per episode; and the reference's own `noise_floor`: its agreement with itself
  when every hand pose moves 0.1 mm sideways (no setting can be expected to agree better);
- `throughput`: validated pushes per second, reference and chosen settings, with 1 and 2 worker
  processes (spawn pool, one PyBullet client each; scene builds included), and the CPU time per push
  (`cpu_ms_per_push`), from which `cpu_bound_pushes_per_s_2_cores` estimates two idle cores;
- `augmentation`: success rate of the raw candidates and of the 10 Halton copies of each success.
The last line printed is a JSON object with `validated_pushes_per_s` (chosen settings, most processes).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import multiprocessing
import os
import platform
import sys
import time
from typing import Any

import numpy as np

REPO_DIR = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if REPO_DIR not in sys.path:
    sys.path.insert(0, REPO_DIR)

from scipy.spatial.transform import Rotation  # noqa: E402

DEFAULT_OBJECTS = ("proc-box-000", "proc-box-001", "proc-box-002", "proc-cylinder-001", "proc-cylinder-002",
                   "proc-hull-001", "pb-duck", "pb-mug")
HANDS = ("allegro", "leap")
REFERENCE = (50, 240)


# ----------------------------------------------------------------------------------------- episodes


def candidate_poses(hand, obj, count: int, seed: int) -> np.ndarray:
    """The spatula pose and `count - 1` perturbations of it, alternately mild and strong."""
    from shared.frames import matrix_to_pose25, pose25_to_matrix
    from shared.world.fixed_poses import spatula_pose

    rng = np.random.default_rng(seed)
    base, joints = pose25_to_matrix(spatula_pose(hand, obj.vertices_d))
    lower, upper = hand.joint_lower.double().numpy(), hand.joint_upper.double().numpy()
    poses = [matrix_to_pose25(base, joints)]
    for i in range(count - 1):
        scale = 0.4 if i % 2 == 0 else 1.0
        transform = base.copy()
        transform[:3, :3] = Rotation.from_rotvec(rng.uniform(-1, 1, 3) * np.radians(25 * scale)).as_matrix() @ base[:3, :3]
        transform[:3, 3] += scale * np.array([rng.uniform(-0.01, 0.0), rng.uniform(-0.04, 0.04), rng.uniform(0.0, 0.06)])
        poses.append(matrix_to_pose25(transform, np.clip(joints + scale * rng.uniform(-0.3, 0.3, 16), lower, upper)))
    return np.stack(poses)


def generator_poses(object_id: str, hand_name: str, count: int) -> np.ndarray:
    """`count` candidates from the project's generator (default settings, seed 1)."""
    from shared.synthesis.config import GenerationConfig
    from shared.synthesis.scene import PushScene
    from shared.synthesis.synthesis import generate
    from shared.world.objects import load_object

    config = GenerationConfig(batch_size=count, record_history=False)
    return generate(PushScene.from_object(load_object(object_id)), hand_name, count, seed=1, config=config).poses


def episode_set(object_ids: list[str], per_object: int, source: str) -> list[tuple[str, str, np.ndarray]]:
    """(object id, hand, poses [per_object, 25]) for every object and hand; deterministic."""
    from shared.robots.hands import load_hand
    from shared.validation.push import table_object
    from shared.world.objects import load_object

    out = []
    for object_id in object_ids:
        obj = table_object(load_object(object_id))
        for hand_name in HANDS:
            if source == "generator":
                poses = generator_poses(object_id, hand_name, per_object)
            else:
                seed = int(np.random.SeedSequence([sum(map(ord, object_id + hand_name))]).generate_state(1)[0])
                poses = candidate_poses(load_hand(hand_name), obj, per_object, seed)
            out.append((object_id, hand_name, poses))
    return out


# ------------------------------------------------------------------------------------------ workers


def _init_worker() -> None:
    import torch

    torch.set_num_threads(1)


def run_chunk(task: tuple) -> dict:
    """Validate one (object, hand, poses, solver, augment) chunk: {"raw": [outcome], "copies": [outcome]}."""
    object_id, hand_name, poses, solver, augment = task
    from shared.robots.hands import load_hand
    from shared.validation.push import table_object
    from shared.validation.validator import Validator
    from shared.world.objects import load_object
    from shared.world.sim import PhysicsParams, c_stdout_to_stderr

    params = dataclasses.replace(PhysicsParams(), solver_iterations=solver[0], time_step_s=1.0 / solver[1])
    cpu_started = time.process_time()
    with c_stdout_to_stderr(), Validator(params) as validator:
        run = validator.validate(table_object(load_object(object_id)), load_hand(hand_name), poses, augment=augment)
    raw = [dataclasses.asdict(o) for o in run.outcomes]
    copies = [dataclasses.asdict(o) for o in run.augmented.outcomes] if run.augmented else []
    return {"raw": raw, "copies": copies, "cpu_s": time.process_time() - cpu_started}


def _warm_worker(_: int) -> None:
    """Import the simulator and load both hands in a pool worker, so the timing excludes start-up."""
    import shared.validation.validator  # noqa: F401  (the import is the warm-up)
    from shared.robots.hands import load_hand

    for hand in HANDS:
        load_hand(hand)
    time.sleep(0.2)  # long enough that every worker takes one of these tasks


def run_all(episodes, solver: tuple[int, int], processes: int, augment: bool = False) -> tuple[list[dict], float, int]:
    """All chunks at one solver setting; (per-chunk results, wall seconds, pushes simulated).

    Chunks are (object, hand) pairs, so scene builds are part of the time, as in a real job stream;
    process start-up is not (the pool is warmed first).
    """
    tasks = [(object_id, hand, poses, solver, augment) for object_id, hand, poses in episodes]
    if processes == 1:
        started = time.perf_counter()
        results = [run_chunk(task) for task in tasks]
        wall = time.perf_counter() - started
    else:
        with multiprocessing.get_context("spawn").Pool(processes, initializer=_init_worker) as pool:
            pool.map(_warm_worker, range(2 * processes), chunksize=1)
            started = time.perf_counter()
            results = pool.map(run_chunk, tasks, chunksize=1)
            wall = time.perf_counter() - started
    pushes = sum(len(r["raw"]) + len(r["copies"]) for r in results)
    return results, wall, pushes


def _cpu_ms_per_push(results: list[dict]) -> float:
    """CPU time per push (scene builds included): unlike wall time, barely affected by other load."""
    pushes = sum(len(r["raw"]) + len(r["copies"]) for r in results)
    return 1000.0 * sum(r["cpu_s"] for r in results) / pushes


def _successes(results: list[dict]) -> np.ndarray:
    return np.array([o["success"] for r in results for o in r["raw"]])


def _warm_caches(episodes) -> None:
    """Object geometry, URDFs and V-HACD are cached on disk on first use: not part of the timing."""
    run_chunk((episodes[0][0], episodes[0][1], episodes[0][2][:1], REFERENCE, False))
    for object_id, hand, poses in episodes:
        run_chunk((object_id, hand, poses[:1], (1, 60), False))


# --------------------------------------------------------------------------------------------- main


def parse_solver(text: str) -> tuple[int, int]:
    try:
        iterations, hz = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"solver setting must be ITERATIONSxHZ, e.g. 20x120, got {text!r}") from None
    return iterations, hz


def main(argv: list[str] | None = None) -> int:
    from shared.world.sim import PhysicsParams

    defaults = PhysicsParams()
    chosen = (defaults.solver_iterations, round(1.0 / defaults.time_step_s))
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--objects", default=",".join(DEFAULT_OBJECTS), help="comma-separated object ids")
    parser.add_argument("--source", choices=("generator", "perturbed"), default="generator",
                        help="where the candidate poses come from (default generator)")
    parser.add_argument("--per-object", type=int, default=12, help="poses per object and hand (default 12)")
    parser.add_argument("--candidates", default="", help="extra solver settings to compare, e.g. 20x240,30x120")
    parser.add_argument("--processes", default="1,2", help="worker process counts for throughput (default 1,2); "
                        "validated_pushes_per_s is measured with the largest")
    parser.add_argument("--skip-throughput", action="store_true", help="agreement and augmentation only")
    parser.add_argument("--json", action="store_true", help="print only the JSON summary")
    args = parser.parse_args(argv)
    log = (lambda *a: None) if args.json else (lambda *a: print(*a, file=sys.stderr, flush=True))

    import torch

    torch.set_num_threads(1)
    log(f"building the episode set ({args.source})")
    episodes = episode_set([o for o in args.objects.split(",") if o], args.per_object, args.source)
    total = sum(len(p) for _, _, p in episodes)
    _warm_caches(episodes)
    settings = [chosen] + [parse_solver(s) for s in args.candidates.split(",") if s and parse_solver(s) != chosen]
    reference, ref_wall, _ = run_all(episodes, REFERENCE, 1)
    ref_success = _successes(reference)
    agreement: dict[str, Any] = {"reference": {"setting": f"{REFERENCE[0]}x{REFERENCE[1]}", "ms_per_push": 1000 * ref_wall / total,
                               "cpu_ms_per_push": _cpu_ms_per_push(reference), "success_rate": float(ref_success.mean())}}
    shifted = [(o, h, p + np.r_[0.0, 1e-4, np.zeros(23)]) for o, h, p in episodes]
    agreement["noise_floor"] = float(np.mean(_successes(run_all(shifted, REFERENCE, 1)[0]) == ref_success))
    log(f"reference {REFERENCE}: {1000 * ref_wall / total:.1f} ms/push, success {ref_success.mean():.3f}, "
        f"noise floor {agreement['noise_floor']:.3f}")
    for setting in settings:
        results, wall, _ = run_all(episodes, setting, 1)
        success = _successes(results)
        agreement[f"{setting[0]}x{setting[1]}"] = {
            "agreement": float(np.mean(success == ref_success)), "ms_per_push": 1000 * wall / total,
            "cpu_ms_per_push": _cpu_ms_per_push(results),
            "success_rate": float(success.mean()), "chosen": setting == chosen}
        log(f"{setting}: agreement {np.mean(success == ref_success):.3f}, {1000 * wall / total:.1f} ms/push")

    augmented, _, _ = run_all(episodes, chosen, 1, augment=True)
    raw = _successes(augmented)
    copies = np.array([o["success"] for r in augmented for o in r["copies"]])
    augmentation = {"raw_candidates": int(raw.size), "raw_success_rate": float(raw.mean()),
                    "copies": int(copies.size), "copy_success_rate": float(copies.mean()) if copies.size else None,
                    "candidates": args.source}
    log(f"augmentation: raw {raw.mean():.3f} of {raw.size}, copies {copies.mean() if copies.size else float('nan'):.3f} of {copies.size}")

    throughput: dict = {}
    if not args.skip_throughput:
        for processes in (int(p) for p in args.processes.split(",")):
            for name, setting in (("reference", REFERENCE), ("chosen", chosen)):
                _, wall, pushes = run_all(episodes, setting, processes)
                throughput[f"{name}_{processes}proc"] = pushes / wall
                log(f"throughput {name} {setting} x{processes}: {pushes / wall:.1f} pushes/s")
    most = max((int(p) for p in args.processes.split(",")), default=1)
    best = throughput.get(f"chosen_{most}proc")
    chosen_cpu_ms = agreement[f"{chosen[0]}x{chosen[1]}"]["cpu_ms_per_push"]
    summary = {
        "benchmark": "validator", "episodes": total, "source": args.source, "objects": args.objects.split(","), "hands": list(HANDS),
        "chosen_setting": f"{chosen[0]}x{chosen[1]}", "agreement": agreement, "augmentation": augmentation,
        "throughput_pushes_per_s": throughput, "validated_pushes_per_s": best,
        # What two idle cores would do, from CPU time per push (robust to the machine being shared).
        "cpu_bound_pushes_per_s_2_cores": 2000.0 / chosen_cpu_ms,
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version(), "load_avg_1m": os.getloadavg()[0],
                    "note": "shared with other jobs while measured; see load_avg_1m"},
    }
    print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())
