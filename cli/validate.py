"""`gd2p validate`: push an object with hand poses in PyBullet and report what happened.

    gd2p validate --object proc-box-001 --hand allegro --fixed-pose spatula --json
    gd2p validate --object scan.ply --hand leap --poses poses.json --trials 5 --seed 1 --json

`--poses` reads the generator's output, `{"poses": [{"pose": [25 floats, in D], ...}, ...]}`.
`--trials K` (K >= 2) pushes every pose K times, each with the object placed with seeded noise
(up to 5 mm off and 5 deg of yaw); the default, 1, is the exact resting placement. Runs locally in
this process (no bus needed).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import numpy as np

from cli.args import FlagError, non_negative_int, positive_float, positive_int, validate_fields

FIXED_POSES = ("spatula",)
# Fields of the validator's messages (ValidationJob, PhysicsSettings) this command checks, by flag.
JOB_FLAGS = {"push_distance_m": "--distance", "seed": "--seed"}
PHYSICS_FLAGS = {"solver_iterations": "--solver-iterations", "time_step_s": "--time-step"}
PROGRESS_MIN_EPISODES = 10


class ValidateInputError(ValueError):
    """A bad command-line input (poses file, object, options)."""


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "validate", help="push an object with hand poses in simulation (success, errors, tilt, contact)",
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--object", required=True, help="library id (e.g. proc-box-001, pb-mug) or a mesh file in metres")
    parser.add_argument("--hand", required=True, choices=("allegro", "leap"))
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--poses", type=Path, help='JSON file {"poses": [{"pose": [25 floats in D]}, ...]}')
    source.add_argument("--fixed-pose", choices=FIXED_POSES, help="a built-in pose (the paper's fixed-hand baseline)")
    parser.add_argument("--trials", type=positive_int, default=1, help="pushes per pose; >= 2 adds placement noise (default 1)")
    parser.add_argument("--seed", type=non_negative_int, default=0, help="seed of the placement noise and augmentation (default 0)")
    parser.add_argument("--augment", action="store_true", help="also push 10 Halton perturbations of each success")
    parser.add_argument("--distance", type=positive_float, default=0.20, help="push distance in metres (default 0.20)")
    parser.add_argument("--solver-iterations", type=positive_int, default=None, help="override the measured default")
    parser.add_argument("--time-step", type=positive_float, default=None, help="seconds; override the measured default")
    parser.add_argument("--json", action="store_true", help='print {"results": [...]} on stdout')
    parser.set_defaults(func=run_validate)


def run_validate(args: argparse.Namespace) -> int:
    try:
        check_flags(args)
        report = _validate(args)
    except FlagError as exc:
        print(exc, file=sys.stderr)
        return 2
    except ValidateInputError as exc:
        print(f"gd2p validate: error: {exc}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(report))
    else:
        _print_table(report["results"])
    return 0


def _validate(args: argparse.Namespace) -> dict:
    from shared.robots.hands import load_hand
    from shared.validation.push import table_object
    from shared.validation.validator import Validator, placement_offsets
    from shared.world.fixed_poses import spatula_pose
    from shared.world.objects import ObjectLoadError, load_object
    from shared.world.sim import PhysicsParams, c_stdout_to_stderr

    params = _params(PhysicsParams(), args)
    with c_stdout_to_stderr():  # PyBullet and V-HACD print on file descriptor 1
        try:
            obj = table_object(load_object(args.object))
        except ObjectLoadError as exc:
            raise ValidateInputError(str(exc)) from exc
        hand = load_hand(args.hand)
        poses = spatula_pose(hand, obj.vertices_d)[None] if args.fixed_pose else read_poses(args.poses)
        repeated = np.repeat(poses, args.trials, axis=0)
        # The same K placements for every pose, so poses are compared on equal terms.
        offsets = list(placement_offsets(args.trials, args.seed)) * len(poses) if args.trials > 1 else None
        with Validator(params) as validator, _progress(len(repeated)) as bar:
            run = validator.validate(obj, hand, repeated, object_offsets=offsets, augment=args.augment,
                                     seed=args.seed, push_distance_m=args.distance, progress=bar.update)
    results = [_result(o, i // args.trials, i % args.trials) for i, o in enumerate(run.outcomes)]
    report: dict = {"object": obj.object_id, "hand": args.hand, "results": results}
    if run.augmented is not None:
        report["augmented"] = [_result(o, int(p), 0) | {"pose": pose.tolist()}
                               for o, p, pose in zip(run.augmented.outcomes, run.augmented.parent_index, run.augmented.poses,
                                                     strict=True)]
    return report


def read_poses(path: Path) -> np.ndarray:
    """[N, 25] poses from a generator output file; ValidateInputError naming what is wrong."""
    try:
        data = json.loads(path.read_text())
    except OSError as exc:
        raise ValidateInputError(f"cannot read poses file {path}: {exc.strerror or exc}") from exc
    except json.JSONDecodeError as exc:
        raise ValidateInputError(f"poses file {path} is not valid JSON: {exc}") from exc
    entries = data.get("poses") if isinstance(data, dict) else None
    if not isinstance(entries, list) or not entries:
        raise ValidateInputError(f'poses file {path} must be an object with a non-empty "poses" list')
    poses = []
    for index, entry in enumerate(entries):
        values = entry.get("pose") if isinstance(entry, dict) else None
        try:
            pose = np.asarray(values, dtype=np.float64)
        except (TypeError, ValueError):
            pose = np.zeros(0)
        if pose.shape != (25,) or not np.all(np.isfinite(pose)):
            raise ValidateInputError(f'{path}: poses[{index}]["pose"] must be 25 finite numbers [p(3), r6(6), q(16)]')
        poses.append(pose)
    return np.stack(poses)


def check_flags(args: argparse.Namespace) -> None:
    """FlagError (naming the flags) unless the options are within the validator service's limits."""
    from shared.contracts.messages import PhysicsSettings, ValidationJob

    problems = []
    for model, values, flags in ((ValidationJob, {"push_distance_m": args.distance, "seed": args.seed}, JOB_FLAGS),
                                 (PhysicsSettings, _physics_changes(args), PHYSICS_FLAGS)):
        try:
            validate_fields(model, values, flags, command="validate")
        except FlagError as exc:
            problems.append(str(exc))
    if problems:
        raise FlagError("\n".join(problems))


def _physics_changes(args: argparse.Namespace) -> dict:
    return {name: value for name, value in (("solver_iterations", args.solver_iterations), ("time_step_s", args.time_step))
            if value is not None}


def _params(defaults, args: argparse.Namespace):
    return dataclasses.replace(defaults, **_physics_changes(args))


def _result(outcome, pose_index: int, trial: int) -> dict:
    return {
        "pose_index": pose_index,
        "trial": trial,
        "success": outcome.success,
        "position_error_m": round(outcome.position_error_m, 6),
        "rotation_deg": round(outcome.rotation_deg, 4),
        "max_tilt_deg": round(outcome.max_tilt_deg, 4),
        "contact_kept": outcome.contact_kept,
        "contact_fraction": round(outcome.contact_fraction, 4),
        "hand_table_contact": outcome.hand_table_contact,
        "initial_penetration_m": round(outcome.initial_penetration_m, 6),
    }


def _progress(total: int):
    from tqdm import tqdm

    return tqdm(total=total, desc="pushes", unit="push", file=sys.stderr, disable=total < PROGRESS_MIN_EPISODES or None)


def _print_table(results: list[dict]) -> None:
    print(f"{'pose':>4} {'trial':>5} {'success':>7} {'err_m':>7} {'rot_deg':>7} {'tilt_deg':>8} {'contact':>7} {'table':>5} {'pen_m':>7}")
    for r in results:
        print(f"{r['pose_index']:>4} {r['trial']:>5} {str(r['success']):>7} {r['position_error_m']:>7.3f} "
              f"{r['rotation_deg']:>7.1f} {r['max_tilt_deg']:>8.1f} {r['contact_fraction']:>7.2f} "
              f"{str(r['hand_table_contact']):>5} {r['initial_penetration_m']:>7.4f}")
    wins = sum(r["success"] for r in results)
    print(f"{wins}/{len(results)} pushes succeeded")
