"""Sampler benchmark: latency of 200 poses (DDPM-100, DDIM-10, BPS included), batching, training speed, quality.

    python bench/sampler.py --json [--checkpoint ckpt/allegro.pt] [--threads 1,2]
    python bench/sampler.py --json --checkpoint ckpt/allegro.pt --quality-objects 20 [--nn-index nn.npz]

Latency: `PoseSampler.sample(object, frame, k=200)` end to end — object points in D, BPS (4096
basis points), denoising, un-normalisation, world transform — median over repeats after a warm-up,
per torch thread count. The object's mesh is loaded once (cached by the sampler, as in the
service); `cold_first_call_s` is the first call including that load. Latency does not depend on the
weights: without a checkpoint the default architecture is benchmarked with random weights and
`"weights": "random-init"` says so (no quality figures then).

Critic: the success critic's scores for the 200 poses (`success_probabilities`, what the sampler service adds to
each reply), with and without the contact features (where the hand meets the object); the cost does not depend
on the weights, so the default critic architecture is timed with random weights.

Critic guidance: DDPM-100 with the last 10 (and 30) denoising steps steered up the critic's gradient
(`--critic-guidance 0.02`, the setting chosen on val objects), end to end as the latency above; random critic
weights, as the cost does not depend on them.

Batching: 4 concurrent requests of 200 poses vs the same 4 one after the other.
Training: samples/s of one optimiser step (loss, backward, clip, fused Adam, foreach EMA) at batch
256 on random data, for the default network.

Quality (with a trained checkpoint and `--quality-objects N`): on the first N test-split objects
(never trained on), the fraction of sampled poses that validate in the push simulation for DDPM-100
and DDIM-10, and the number of objects with >= 1 validated pose; with `--nn-index` / `--nn-dataset` the
nearest-neighbour baseline's poses on the same objects. Needs services.validator.
The last line printed is a JSON object.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import threading
import time
from pathlib import Path

REPO_DIR = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if REPO_DIR not in sys.path:
    sys.path.insert(0, REPO_DIR)

import torch  # noqa: E402

from shared.sampling.checkpoint import SamplerCheckpoint, default_checkpoint_path, load_checkpoint  # noqa: E402
from shared.sampling.critic import CriticConfig, SuccessCritic  # noqa: E402
from shared.sampling.critic_features import CONTACT_FEATURES  # noqa: E402
from shared.sampling.critic_train import success_probabilities  # noqa: E402
from shared.sampling.dataset import SURFACE_POINTS, SURFACE_SEED  # noqa: E402
from shared.sampling.diffusion import (  # noqa: E402
    GradientGuidance,
    PoseNormalizer,
    denoising_loss,
    make_ema,
    make_noise_scheduler,
)
from shared.sampling.model import DenoiserConfig, PoseDenoiser, parameter_count  # noqa: E402
from shared.sampling.sampling import PoseSampler, default_frame  # noqa: E402
from shared.sampling.train import hand_joint_limits  # noqa: E402
from shared.world.bps import BasisPointSet  # noqa: E402
from shared.world.objects import list_object_ids, load_object  # noqa: E402

LATENCY_OBJECT = "proc-box-001"
K = 200


def random_checkpoint(hand: str) -> SamplerCheckpoint:
    """The default architecture with random weights: same cost per call as a trained one."""
    model = PoseDenoiser(DenoiserConfig())
    lower, upper = hand_joint_limits(hand)
    normalizer = PoseNormalizer(torch.cat([torch.full((9,), -0.3), lower]), torch.cat([torch.full((9,), 0.3), upper]))
    return SamplerCheckpoint(hand, model.config, model.state_dict(), normalizer, lower, upper, BasisPointSet(),
                             SURFACE_POINTS, SURFACE_SEED, {"weights": "random-init"})


def measure_latency(sampler: PoseSampler, kind: str, steps: int | None, repeats: int) -> dict:
    obj = load_object(LATENCY_OBJECT)
    frame = default_frame(obj, 30.0)
    times = []
    for i in range(repeats + 1):
        started = time.perf_counter()
        sampler.sample(obj, frame, k=K, sampler=kind, steps=steps, seed=i)
        times.append(time.perf_counter() - started)
    return {"median_s": round(statistics.median(times[1:]), 4), "min_s": round(min(times[1:]), 4)}


def measure_bps_ms(sampler: PoseSampler, repeats: int = 20) -> float:
    obj = load_object(LATENCY_OBJECT)
    points, _, _ = sampler.points_in_d(obj, default_frame(obj))
    times = []
    for _ in range(repeats):
        started = time.perf_counter()
        sampler.bps.encode(points)
        times.append(time.perf_counter() - started)
    return round(1000 * statistics.median(times), 2)


def measure_critic_ms(sampler: PoseSampler, hand: str, repeats: int = 10) -> dict:
    obj = load_object(LATENCY_OBJECT)
    frame = default_frame(obj, 30.0)
    result = sampler.sample(obj, frame, k=K, sampler="ddim")
    assert result.bps is not None and result.points_d is not None  # a mesh object: both encoded
    timings = {}
    for name, contact_dim in (("with_contact_features", CONTACT_FEATURES), ("bps_and_pose_only", 0)):
        critic = SuccessCritic(CriticConfig(bps_dim=sampler.bps.n, contact_dim=contact_dim)).eval()
        times = []
        for _ in range(repeats + 1):
            started = time.perf_counter()
            success_probabilities(critic, hand, result.bps, result.points_d, result.poses_d)
            times.append(time.perf_counter() - started)
        timings[name] = round(1000 * statistics.median(times[1:]), 2)
    return timings


def measure_guided_s(sampler: PoseSampler, repeats: int = 3) -> dict:
    critic = SuccessCritic(CriticConfig(bps_dim=sampler.bps.n, contact_dim=CONTACT_FEATURES)).eval()
    timings = {}
    for steps in (10, 30):
        guidance = GradientGuidance(0.02, steps=steps)
        times = []
        for _ in range(repeats + 1):
            started = time.perf_counter()
            sampler.sample(LATENCY_OBJECT, k=K, sampler="ddpm", critic=critic, guidance=guidance)
            times.append(time.perf_counter() - started)
        timings[f"ddpm_100_guided_last_{steps}"] = round(statistics.median(times[1:]), 4)
    return timings


def measure_batching(sampler: PoseSampler, kind: str, requests: int = 4) -> dict:
    objects = [o for o in list_object_ids("test") if o.startswith("proc-")][:requests]
    for o in objects:  # load meshes outside the timing
        sampler.sample(o, k=1, sampler="ddim", steps=1)
    started = time.perf_counter()
    for i, o in enumerate(objects):
        sampler.sample(o, k=K, sampler=kind, seed=i)
    sequential = time.perf_counter() - started
    threads = [threading.Thread(target=sampler.sample, args=(o,), kwargs={"k": K, "sampler": kind, "seed": i})
               for i, o in enumerate(objects)]
    started = time.perf_counter()
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    concurrent = time.perf_counter() - started
    return {"requests": requests, "k": K, "sampler": kind, "sequential_s": round(sequential, 4),
            "concurrent_s": round(concurrent, 4), "speedup": round(sequential / concurrent, 2)}


def measure_training(steps: int = 60, batch: int = 256) -> dict:
    model = PoseDenoiser(DenoiserConfig())
    scheduler, ema = make_noise_scheduler(), make_ema(model)
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-4, weight_decay=1e-6, eps=1e-8, fused=True)
    generator = torch.Generator().manual_seed(0)
    poses, bps = torch.rand(4096, 25) * 2 - 1, torch.rand(4096, 4096) * 0.3
    times = []
    for _ in range(steps):
        rows = torch.randint(0, len(poses), (batch,), generator=generator)
        started = time.perf_counter()
        loss = denoising_loss(model, scheduler, poses[rows], bps[rows], generator)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0, foreach=True)
        optimizer.step()
        ema.step(model.parameters())
        times.append(time.perf_counter() - started)
    return {"batch": batch, "samples_per_s": round(batch / statistics.median(times[5:]), 1), "parameters": parameter_count(model)}


def measure_quality(sampler: PoseSampler, count: int, poses_per_object: int, nn) -> dict:
    from cli.sampler import validate_sampled_poses

    objects = list_object_ids("test")[:count]
    methods = {"ddpm": ("ddpm", None), "ddim": ("ddim", 10)}
    totals: dict[str, dict[str, float]] = {name: {"validated": 0, "poses": 0, "objects_with_success": 0} for name in [*methods, *(["nn"] if nn else [])]}
    for object_id in objects:
        obj = load_object(object_id)
        frame = default_frame(obj)
        for name, (kind, steps) in methods.items():
            poses = sampler.sample(obj, frame, k=poses_per_object, sampler=kind, steps=steps, seed=0).poses_d
            _tally(totals[name], validate_sampled_poses(obj, sampler.hand, poses, frame))
        if nn is not None:
            points, _, _ = sampler.points_in_d(obj, frame)
            poses = nn.query_points(points, k=poses_per_object, seed=0).poses
            _tally(totals["nn"], validate_sampled_poses(obj, sampler.hand, poses, frame))
    for entry in totals.values():
        entry["validated_fraction"] = round(entry["validated"] / max(entry["poses"], 1), 4)
    return {"objects": len(objects), "poses_per_object": poses_per_object, "split": "test", **totals}


def nearest_neighbor(args: argparse.Namespace):
    """The NN baseline from a saved index or built from a dataset store (None: not measured)."""
    from shared.sampling.nearest_neighbor import NearestNeighborBaseline

    if args.nn_index:
        return NearestNeighborBaseline.load(args.nn_index)
    if args.nn_dataset:
        return NearestNeighborBaseline.from_directory(args.nn_dataset, args.hand)
    return None


def _tally(entry: dict, successes: list[bool]) -> None:
    entry["validated"] += int(sum(successes))
    entry["poses"] += len(successes)
    entry["objects_with_success"] += int(any(successes))


def run(args: argparse.Namespace) -> dict:
    path = args.checkpoint or default_checkpoint_path(args.hand)
    trained = path.is_file()
    checkpoint = load_checkpoint(path) if trained else random_checkpoint(args.hand)
    result: dict = {"hand": args.hand, "k": K, "object": LATENCY_OBJECT, "weights": str(path) if trained else "random-init",
                    "parameters": parameter_count(checkpoint.build_model()), "machine": platform.machine(),
                    "cpu_count": os.cpu_count(), "torch": torch.__version__, "latency": {}}
    for threads in args.threads:
        torch.set_num_threads(threads)
        with PoseSampler(checkpoint) as sampler:
            started = time.perf_counter()
            sampler.sample(LATENCY_OBJECT, k=K, sampler="ddim")
            cold = time.perf_counter() - started
            result["latency"][f"threads_{threads}"] = {
                "ddpm_100": measure_latency(sampler, "ddpm", None, args.repeats),
                "ddim_10": measure_latency(sampler, "ddim", 10, args.repeats),
                "bps_encode_ms": measure_bps_ms(sampler),
                "critic_scores_ms": measure_critic_ms(sampler, args.hand),
                "critic_guided_s": measure_guided_s(sampler),
                "cold_first_call_s": round(cold, 4),
            }
    torch.set_num_threads(args.threads[0])
    with PoseSampler(checkpoint) as sampler:
        result["batching"] = measure_batching(sampler, "ddim")
        if args.quality_objects:
            if not trained:
                result["quality"] = {"skipped": "no trained checkpoint (random weights say nothing about quality)"}
            else:
                result["quality"] = measure_quality(sampler, args.quality_objects, args.quality_poses, nearest_neighbor(args))
    result["training"] = measure_training()
    return result


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--json", action="store_true", help="print only the JSON result")
    parser.add_argument("--hand", default="allegro", choices=("allegro", "leap"))
    parser.add_argument("--checkpoint", type=Path, default=None, help="default: the shipped checkpoint (random weights if none)")
    parser.add_argument("--threads", type=lambda s: [int(x) for x in s.split(",")], default=[1, 2],
                        help="torch thread counts to measure latency with (default 1,2)")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--quality-objects", type=int, default=0, help="test-split objects for the quality figures (0: skip)")
    parser.add_argument("--quality-poses", type=int, default=200, help="poses sampled and validated per object and method")
    parser.add_argument("--nn-index", type=Path, default=None, help="nearest-neighbour index (.npz) for the baseline")
    parser.add_argument("--nn-dataset", type=Path, default=None, help="or build the baseline's index from this dataset store")
    args = parser.parse_args()
    result = run(args)
    if not args.json:
        print(json.dumps(result, indent=2))
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
