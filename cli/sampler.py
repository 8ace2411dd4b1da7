"""`gd2p train`, `gd2p sample`, `gd2p sampler-nn build`: train the pose diffusion model, sample push poses
from it (or from the nearest-neighbour baseline), and build the baseline's index.

    gd2p train --dataset data/allegro --hand allegro --out ckpt/allegro.pt [--fraction 0.2] [--seed 1] [--steps 20000]
    gd2p sample --object proc-box-001 --hand allegro --n 200 [--sampler ddim|nearest] [--checkpoint PATH] [--validate] --json
    gd2p sampler-nn build --dataset data/allegro --hand allegro --out ckpt/allegro_nn.npz [--half]

`train` resumes from `<out>.train.pt` when it exists (same command), `--restart` starts over.
Ctrl-C saves the training state first, so the same command continues later.

`sample` places the object resting in its default pose at the world origin and pushes it along
`--direction-deg` (default 0 = world +x). Its JSON is `{"n", "latency_s", "poses": [{"pose": [25 in
D], "pose_world": [25]}, ...], ...}` — the same "poses" layout `gd2p validate --poses` reads.
`--validate` pushes every pose in the validator's PyBullet simulation (runs locally; needs
services.validator) and adds `"validated_success"` (how many succeeded) and per-pose `"success"`.
`--sampler nearest` returns the stored poses of the training frame nearest in BPS space (at most
`--n`; all of them when it has fewer) from `--nn-index` or the shipped index, and adds
`"matched_object"` and `"bps_distance"`.

`sampler-nn build` indexes every training frame of a dataset store (its BPS and its poses) into one
.npz, with `<out>.manifest.json` beside it; `--half` stores the BPS in float16 and refuses to if that
would change any frame's nearest neighbour.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import shlex
import signal
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from cli.args import (
    FlagError,
    finite_float,
    float_range,
    non_negative_int,
    positive_float,
    positive_int,
    validate_fields,
)

# SampleRequest fields (the sampler service's limits) this command checks, by flag.
SAMPLE_FLAGS = {"k": "--n", "steps": "--steps", "seed": "--seed", "sampler": "--sampler", "noise_scale": "--noise-scale"}


class SamplerCliError(ValueError):
    """A bad command-line input for train / sample."""


def register(subparsers: argparse._SubParsersAction) -> None:
    _register_train(subparsers)
    _register_sample(subparsers)
    _register_nn(subparsers)


# ----------------------------------------------------------------------------- train
def _register_train(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("train", help="train the pose diffusion model on a dataset store (resumable)",
                                   description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--dataset", required=True, type=Path, help="dataset store directory (Parquet shards + manifest)")
    parser.add_argument("--hand", required=True, choices=("allegro", "leap"))
    parser.add_argument("--out", required=True, type=Path, help="checkpoint file to write (e.g. ckpt/allegro.pt)")
    parser.add_argument("--fraction", type=float_range(0.0, 1.0, low_open=True), default=1.0, help="train on this fraction of the training objects (default 1)")
    parser.add_argument("--seed", type=non_negative_int, default=0)
    budget = parser.add_mutually_exclusive_group()
    budget.add_argument("--steps", type=positive_int, default=None, help="optimiser steps in all (default 20000)")
    budget.add_argument("--epochs", type=positive_float, default=None, help="passes over the training poses instead of --steps")
    parser.add_argument("--batch-size", type=positive_int, default=256)
    parser.add_argument("--lr", type=positive_float, default=1e-4)
    parser.add_argument("--warmup-steps", type=non_negative_int, default=500)
    parser.add_argument("--val-fraction", type=float_range(0.0, 1.0, high_open=True), default=0.1, help="objects held out for the validation loss")
    parser.add_argument("--hidden-dim", type=positive_int, default=256, help="width of the residual FiLM blocks")
    parser.add_argument("--num-blocks", type=positive_int, default=4)
    parser.add_argument("--object-dim", type=positive_int, default=128, help="the BPS is compressed to this before FiLM")
    parser.add_argument("--balance", choices=("poses", "objects"), default="poses",
                        help="a batch draws poses uniformly (default; objects with many valid poses weigh more) or "
                             "an object uniformly, then one of its poses (every object weighs the same)")
    parser.add_argument("--condition-dropout", type=float_range(0.0, 1.0, high_open=True), default=0.0,
                        help="train this fraction of each batch without its object (a learned 'no object' embedding), so "
                             "the checkpoint can sample with classifier-free guidance (default 0: off)")
    parser.add_argument("--learn-failures", action="store_true",
                        help="train on the store's failed pushes too, under a learned 'failed push' embedding, so the "
                             "checkpoint can sample guided away from what failed on the object (--guidance-scale; not with "
                             "--condition-dropout)")
    parser.add_argument("--guidance-scale", type=float_range(1.0, 10.0), default=1.0,
                        help="classifier-free guidance weight written into the shipped checkpoint (default 1: none; needs "
                             "--condition-dropout or --learn-failures). Re-running a finished run with another value (its <out>.train.pt "
                             "copied beside the new --out) ships the same weights with that guidance")
    parser.add_argument("--capture-fraction", type=float_range(0.0, 1.0), default=0.0,
                        help="share of each batch conditioned on a simulated camera capture of the pose's object instead "
                             "of its mesh BPS, as the planner sees an object through cameras (needs --captures)")
    parser.add_argument("--captures", type=Path, default=None,
                        help="capture store directory for --capture-fraction: built there first (resumable, "
                             "--capture-workers processes, 2 captures of each training frame by 3 cameras) when not finished")
    parser.add_argument("--capture-workers", type=positive_int, default=2, help="processes capturing the training frames (default 2)")
    parser.add_argument("--val-every", type=positive_int, default=500, help="steps between validation losses")
    parser.add_argument("--checkpoint-every", type=positive_int, default=1000, help="steps between saved training states")
    parser.add_argument("--snapshot-every", type=int, default=0,
                        help="also write the EMA weights every this many steps as OUT-stem.stepN.pt (to choose a step "
                             "by the validated fraction on val objects: `gd2p eval sampler-quality --split val "
                             "--checkpoint ...`); default 0: only the final checkpoint")
    parser.add_argument("--half", action="store_true", help="ship fp16 weights (half the file size)")
    parser.add_argument("--device", default="auto", help="auto (GPU if present), cpu, cuda, cuda:N")
    parser.add_argument("--threads", type=positive_int, default=1,
                        help="torch CPU threads (default 1: extra threads stall on a shared machine, docs/architecture.md §Compute)")
    parser.add_argument("--restart", action="store_true", help="ignore a saved training state and start over")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.add_argument("--json", action="store_true", help="print a JSON summary on stdout")
    parser.set_defaults(func=run_train)


def run_train(args: argparse.Namespace) -> int:
    import torch

    from shared.sampling.checkpoint import CheckpointError
    from shared.sampling.dataset import DatasetError
    from shared.sampling.model import DenoiserConfig
    from shared.sampling.train import RunOptions, TrainConfig, TrainingError, train

    if args.learn_failures and args.condition_dropout > 0:
        print("gd2p train: error: --learn-failures and --condition-dropout do not combine (guidance steers away "
              "from the object's failures or from no object, not both)", file=sys.stderr)
        return 2
    torch.set_num_threads(max(1, args.threads))
    interrupted = _StopFlag()
    try:
        config = TrainConfig(steps=args.steps, epochs=args.epochs, batch_size=args.batch_size, lr=args.lr,
                             warmup_steps=args.warmup_steps, val_fraction=args.val_fraction, fraction=args.fraction,
                             seed=args.seed, model=DenoiserConfig(hidden_dim=args.hidden_dim, num_blocks=args.num_blocks,
                                                                  object_dim=args.object_dim,
                                                                  unconditional=args.condition_dropout > 0,
                                                                  outcome=args.learn_failures),
                             balance=args.balance, condition_dropout=args.condition_dropout,
                             capture_fraction=args.capture_fraction,
                             captures=None if args.captures is None else str(args.captures.resolve()))
        options = RunOptions(device=args.device, val_every=max(1, args.val_every), checkpoint_every=max(1, args.checkpoint_every),
                             snapshot_every=max(0, args.snapshot_every), half=args.half, progress=not args.no_progress, resume=not args.restart,
                             command=shlex.join(["gd2p", *sys.argv[1:]]), should_stop=interrupted,
                             guidance_scale=args.guidance_scale, capture_workers=args.capture_workers)
        with interrupted.on_sigint():
            result = train(args.dataset, args.hand, args.out, config, options)
    except (TrainingError, DatasetError, CheckpointError, ValueError) as exc:
        print(f"gd2p train: error: {exc}", file=sys.stderr)
        return 2
    summary = {
        "checkpoint": str(result.checkpoint_path) if result.checkpoint_path else None,
        "state": str(result.state_path), "loss_plot": str(result.plot_path) if result.plot_path else None,
        "start_step": result.start_step, "step": result.step, "total_steps": result.total_steps, "stopped": result.stopped,
        "final_train_loss": result.final_train_loss, "final_val_loss": result.final_val_loss,
        "samples_per_s": round(result.samples_per_s, 1), "parameters": result.parameters,
    }
    if args.json:
        print(json.dumps(summary))
    elif result.stopped:
        print(f"stopped at step {result.step}/{result.total_steps}; state saved to {result.state_path}; run the same command to resume")
    else:
        print(f"wrote {result.checkpoint_path} (train loss {result.final_train_loss}, val loss {result.final_val_loss}), "
              f"curves {result.plot_path}")
    return 130 if result.stopped else 0


class _StopFlag:
    """Ctrl-C during training: finish the current step, save the state, then exit (resumable)."""

    def __init__(self) -> None:
        self.requested = False

    def __call__(self, step: int) -> bool:
        return self.requested

    @contextlib.contextmanager
    def on_sigint(self) -> Iterator[None]:
        def request(signum, frame) -> None:
            if self.requested:  # a second Ctrl-C aborts at once
                raise KeyboardInterrupt
            self.requested = True
            print("\nstopping after this step (Ctrl-C again to abort without saving)...", file=sys.stderr)

        if threading.current_thread() is not threading.main_thread():  # signals reach the main thread only
            yield
            return
        previous = signal.signal(signal.SIGINT, request)
        try:
            yield
        finally:
            signal.signal(signal.SIGINT, previous)


# ----------------------------------------------------------------------------- sample
def _register_sample(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("sample", help="sample push poses for an object from a trained checkpoint",
                                   description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--object", help="library id (e.g. proc-box-001) or a mesh file in metres")
    source.add_argument("--cloud", type=Path,
                        help="the object as a point cloud (.ply .pcd .npy; world frame, metres, table at z = 0): "
                             "reconstructed for validation, its own points give the BPS")
    parser.add_argument("--hand", required=True, choices=("allegro", "leap"))
    parser.add_argument("--n", type=positive_int, default=200, help="number of poses (1..1000, default 200)")
    parser.add_argument("--sampler", choices=("ddpm", "ddim", "nearest"), default="ddpm",
                        help="DDPM-100 (paper), DDIM fast path, or the nearest-neighbour baseline")
    parser.add_argument("--steps", type=positive_int, default=None, help="DDIM steps (default 10)")
    parser.add_argument("--noise-scale", type=positive_float, default=None,
                        help="diffusion sampling temperature in (0, 1]: initial and DDPM step noise multiplied by it "
                             "(default: $GD2P_SAMPLER_NOISE_SCALE or the sampler's default)")
    parser.add_argument("--critic-guidance", type=positive_float, default=None, metavar="SCALE",
                        help="steer the last denoising steps up the hand's success critic's log P(success) "
                             "($GD2P_CRITIC_CHECKPOINT_<HAND> or the shipped one; it must be made for the checkpoint): each "
                             "guided step moves a pose by SCALE x the gradient in normalised units, at most 0.2 (0.02 "
                             "was chosen on val objects); about 0.2 s per guided step per 200 poses on one thread")
    parser.add_argument("--guided-steps", type=positive_int, default=None, metavar="N",
                        help="with --critic-guidance: the last N of the denoising steps are guided (default 10)")
    parser.add_argument("--checkpoint", type=Path, default=None,
                        help="checkpoint file (default: $GD2P_SAMPLER_CHECKPOINT_<HAND> or the shipped one)")
    parser.add_argument("--nn-index", type=Path, default=None,
                        help="with --sampler nearest: index file (default: $GD2P_SAMPLER_NN_INDEX_<HAND> or the shipped one)")
    parser.add_argument("--seed", type=non_negative_int, default=0)
    parser.add_argument("--direction-deg", type=finite_float, default=0.0, help="push direction in the world (default 0 = +x)")
    parser.add_argument("--validate", action="store_true", help="push every pose in simulation and count successes")
    parser.add_argument("--threads", type=positive_int, default=1, help="torch CPU threads (default 1)")
    parser.add_argument("--json", action="store_true", help="print the JSON result on stdout")
    parser.set_defaults(func=run_sample)


def run_sample(args: argparse.Namespace) -> int:
    try:
        check_sample_flags(args)
        report = _sample(args)
    except FlagError as exc:
        print(exc, file=sys.stderr)
        return 2
    except SamplerCliError as exc:
        print(f"gd2p sample: error: {exc}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(report))
    else:
        _print_summary(report)
    return 0


def check_sample_flags(args: argparse.Namespace) -> None:
    """FlagError (naming the flags) unless the options are within the sampler service's limits (SampleRequest)."""
    from shared.contracts.messages import SampleRequest

    validate_fields(SampleRequest, {"k": args.n, "steps": args.steps, "seed": args.seed, "sampler": args.sampler,
                                    "noise_scale": args.noise_scale}, SAMPLE_FLAGS, command="sample")


def _sample(args: argparse.Namespace) -> dict:
    import torch

    from shared.sampling.sampling import SamplerInputError

    torch.set_num_threads(max(1, args.threads))
    validator = _validator_modules() if args.validate else None  # fail before any work if it cannot run
    obj, frame, sampled = _object_and_frame(args)
    try:
        if args.sampler == "nearest":
            result, source = _sample_nearest(args, sampled, frame)
        else:
            result, source = _sample_diffusion(args, sampled, frame)
    except SamplerInputError as exc:
        raise SamplerCliError(str(exc)) from exc
    poses = [{"pose": d.tolist(), "pose_world": w.tolist()}
             for d, w in zip(result.poses_d, result.poses_world, strict=True)]
    report = {"n": len(poses), "latency_s": round(result.latency_s, 6), "poses": poses, "object": obj.id, "hand": args.hand,
              "sampler": result.sampler, "steps": result.steps, "seed": args.seed, "direction_deg": args.direction_deg,
              "noise_scale": result.noise_scale if args.sampler != "nearest" else None, **source}
    if validator is not None:
        successes = validate_sampled_poses(obj, args.hand, result.poses_d, frame, progress=True)
        for entry, success in zip(poses, successes, strict=True):
            entry["success"] = success
        report["validated_success"] = int(sum(successes))
    return report


def _object_and_frame(args: argparse.Namespace) -> tuple:
    """(ObjectModel, DirectionFrame, what the sampler encodes): a library object or mesh in its default
    placement; a point cloud reconstructed where it stands, its own points encoded."""
    from shared.contracts.messages import DirectionFrame, ObjectRef
    from shared.sampling.sampling import default_frame
    from shared.world.object_refs import captured_object
    from shared.world.objects import ObjectLoadError, load_object
    from shared.world.perception import PerceptionError, bps_points, cloud_for_request, load_cloud
    from shared.world.push_outcome import object_pose

    try:
        if args.cloud is None:
            obj = load_object(args.object)
            return obj, default_frame(obj, args.direction_deg), obj
        captured = captured_object(ObjectRef(point_cloud=cloud_for_request(load_cloud(args.cloud).points)))
    except (ObjectLoadError, PerceptionError) as exc:
        raise SamplerCliError(str(exc)) from exc
    frame = DirectionFrame(object_pose=object_pose(captured.T_world_O), yaw_deg=args.direction_deg)
    return captured.model, frame, bps_points(captured.object_points)


def _sample_diffusion(args: argparse.Namespace, obj, frame) -> tuple:
    """(SampleResult, report fields naming the checkpoint) from the diffusion model."""
    from shared.sampling.checkpoint import CheckpointError, default_checkpoint_path
    from shared.sampling.sampling import PoseSampler

    path = args.checkpoint or default_checkpoint_path(args.hand)
    if not path.is_file():
        raise SamplerCliError(f"no {args.hand} checkpoint at {path}; train one with `gd2p train --dataset DIR --hand {args.hand} "
                              f"--out {path}` or pass --checkpoint")
    try:
        sampler = PoseSampler(path)
    except CheckpointError as exc:
        raise SamplerCliError(str(exc)) from exc
    if sampler.hand != args.hand:
        raise SamplerCliError(f"{path} is a {sampler.hand} checkpoint, not {args.hand}")
    critic, guidance = _critic_guidance(args, sampler)
    with sampler:
        result = sampler.sample(obj, frame, k=args.n, sampler=args.sampler, steps=args.steps, seed=args.seed,
                                noise_scale=args.noise_scale, critic=critic, guidance=guidance)
    guided = {} if guidance is None else {"critic_guidance": {"scale": guidance.scale, "steps": guidance.steps}}
    return result, {"checkpoint": str(path), "checkpoint_id": sampler.checkpoint_id, **guided}


def _critic_guidance(args: argparse.Namespace, sampler) -> tuple:
    """(the critic model, GradientGuidance) for --critic-guidance, else (None, None); SamplerCliError when the hand's
    critic is missing or was made for another checkpoint (it reads that checkpoint's BPS and samples)."""
    from shared.sampling.critic_train import CriticError, default_critic_path, load_critic
    from shared.sampling.diffusion import DiffusionConfigError, GradientGuidance

    if args.critic_guidance is None:
        if args.guided_steps is not None:
            raise SamplerCliError("--guided-steps needs --critic-guidance")
        return None, None
    path = default_critic_path(args.hand)
    if path is None:
        raise SamplerCliError(f"--critic-guidance needs a critic; $GD2P_CRITIC_CHECKPOINT_{args.hand.upper()} says none")
    try:
        guidance = GradientGuidance.of(args.critic_guidance, args.guided_steps)
        critic = load_critic(path)
    except (DiffusionConfigError, CriticError) as exc:
        raise SamplerCliError(f"--critic-guidance: {exc}") from exc
    if critic.sampler_checkpoint_id != sampler.checkpoint_id:
        raise SamplerCliError(f"--critic-guidance: the {args.hand} critic was made for the sampler checkpoint "
                              f"{critic.sampler_checkpoint_id}, not {sampler.checkpoint_id}")
    return critic.model, guidance


def _sample_nearest(args: argparse.Namespace, obj, frame) -> tuple:
    """(SampleResult, report fields naming the index and the match) from the nearest-neighbour baseline."""
    from shared.sampling.nearest_neighbor import NearestNeighborError, NearestNeighborSampler, default_nn_index_path

    if any(value is not None for value in (args.steps, args.noise_scale, args.critic_guidance, args.guided_steps)):
        raise SamplerCliError("--steps, --noise-scale, --critic-guidance and --guided-steps apply to the diffusion samplers, "
                              "not --sampler nearest")
    path = args.nn_index or default_nn_index_path(args.hand)
    try:
        nearest = NearestNeighborSampler.load(path)
    except NearestNeighborError as exc:
        raise SamplerCliError(f"{exc}; build one with `gd2p sampler-nn build --dataset DIR --hand {args.hand} --out {path}` "
                              "or pass --nn-index") from exc
    if nearest.hand != args.hand:
        raise SamplerCliError(f"{path} is a {nearest.hand} nearest-neighbour index, not {args.hand}")
    reply = nearest.sample(obj, frame, k=args.n, seed=args.seed)
    return reply.result, {"checkpoint": str(path), "checkpoint_id": reply.source_id,
                          "matched_object": reply.match.object_id, "bps_distance": round(reply.match.distance, 6)}


def _validator_modules():
    try:
        from shared.validation.push import table_object  # noqa: F401
        from shared.validation.validator import Validator  # noqa: F401
    except ImportError as exc:
        raise SamplerCliError(f"--validate needs the validator's push simulation (services.validator), which cannot be imported: {exc}") from exc
    return True


def validate_sampled_poses(obj, hand_name: str, poses_d: np.ndarray, frame, progress: bool = False) -> list[bool]:
    """Push each pose (in D) in the validator's floating-hand simulation; success per pose.

    The object rests in its default pose (as `default_frame` places it); its yaw in D follows from `frame`.
    """
    from tqdm import tqdm

    from shared.frames import object_yaw_in_d
    from shared.robots.hands import load_hand
    from shared.validation.push import table_object
    from shared.validation.validator import Validator
    from shared.world.sim import c_stdout_to_stderr

    hand = load_hand(hand_name)
    with c_stdout_to_stderr():  # PyBullet prints on file descriptor 1
        placed = table_object(obj, None, yaw_rad=object_yaw_in_d(frame, obj.default_pose.rotation))
        with Validator() as validator, tqdm(total=len(poses_d), desc="validating", unit="push", file=sys.stderr,
                                            disable=not progress) as bar:
            run = validator.validate(placed, hand, np.asarray(poses_d, dtype=np.float64), progress=bar.update)
    return [bool(outcome.success) for outcome in run.outcomes]


def _print_summary(report: dict) -> None:
    print(f"{report['n']} {report['hand']} poses for {report['object']} in {report['latency_s'] * 1000:.1f} ms "
          f"({report['sampler']}, {report['steps']} steps, checkpoint {report['checkpoint_id']})")
    if "validated_success" in report:
        print(f"{report['validated_success']}/{report['n']} validated in simulation")
    for index, entry in enumerate(report["poses"][:5]):
        print(f"  pose {index}: position {np.round(entry['pose'][:3], 3).tolist()}")
    if report["n"] > 5:
        print(f"  ... ({report['n'] - 5} more; use --json for all)")


# ----------------------------------------------------------------------------- sampler-nn build
def _register_nn(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("sampler-nn", help="the nearest-neighbour baseline's index (build)",
                                   description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    actions = parser.add_subparsers(dest="nn_command", required=True)
    build = actions.add_parser("build", help="index every training frame of a dataset store (BPS + stored poses)")
    build.add_argument("--dataset", required=True, type=Path, help="dataset store directory (Parquet shards + manifest)")
    build.add_argument("--hand", required=True, choices=("allegro", "leap"))
    build.add_argument("--out", required=True, type=Path, help="index file to write (e.g. ckpt/allegro_nn.npz)")
    build.add_argument("--half", action="store_true",
                       help="store the BPS in float16 (half the size); refused if any frame's nearest neighbour changes")
    build.add_argument("--captures", type=Path, default=None,
                       help="a finished capture store (gd2p train --captures): its camera captures of the frames are "
                            "keys too, each with the frame's poses moved into the capture's frame")
    build.add_argument("--no-progress", action="store_true", help="no progress bar")
    build.add_argument("--json", action="store_true", help="print a JSON summary on stdout")
    build.set_defaults(func=run_nn_build)


def run_nn_build(args: argparse.Namespace) -> int:
    from shared.sampling.dataset import DatasetError
    from shared.sampling.nearest_neighbor import NearestNeighborError, build_index

    # The command that reproduces the file (from the parsed arguments, so it is right however gd2p was called).
    command = shlex.join(["gd2p", "sampler-nn", "build", "--dataset", str(args.dataset), "--hand", args.hand,
                          "--out", str(args.out), *(["--half"] if args.half else []),
                          *(["--captures", str(args.captures)] if args.captures else [])])
    try:
        index = build_index(args.dataset, args.hand, args.out, half=args.half, command=command,
                            progress=not args.no_progress, captures=args.captures)
    except (DatasetError, NearestNeighborError) as exc:
        print(f"gd2p sampler-nn build: error: {exc}", file=sys.stderr)
        return 2
    summary = {"index": str(args.out), "size_bytes": args.out.stat().st_size, "frames": len(index),
               "poses": index.pose_count, "features_dtype": index.manifest["features_dtype"],
               "float16_check": index.manifest.get("float16_check")}
    if args.json:
        print(json.dumps(summary))
    else:
        print(f"wrote {args.out} ({summary['size_bytes'] / 1e6:.1f} MB): {summary['frames']} frames, {summary['poses']} poses")
    return 0
