"""`gd2p generate`: optimise pre-contact push poses for one object and hand, in this process.

    gd2p generate --object proc-box-003 --hand allegro --n 256 --seed 0 --out poses.json --plot energy.png

Writes {"poses": [{"pose": [25 floats in D], "energy": {term: value}, "palm_normal": [3],
"max_penetration_m": float}, ...]} plus where the object was (`object_pose_d`, resting pose index
and yaw) and the settings used. Energies are the unweighted terms and the weighted "total".
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

from cli.args import FlagError, finite_float, non_negative_int, positive_int, validate_fields
from shared.atomic import atomic_write_text

HANDS = ("allegro", "leap")
# GenerationJob fields (the generator service's limits) checked for this command, by flag.
JOB_FLAGS = {"seed": "--seed", "iterations": "--iterations", "contacts_per_pose": "--contacts"}


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("generate", help="energy-based synthesis of push poses (no bus needed)",
                                   description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--object", required=True, metavar="ID_OR_MESH", help="library id or mesh file (metres)")
    parser.add_argument("--hand", required=True, choices=HANDS)
    parser.add_argument("--n", type=positive_int, required=True, help="number of poses")
    parser.add_argument("--seed", type=non_negative_int, default=0)
    parser.add_argument("--out", required=True, metavar="FILE.json")
    parser.add_argument("--iterations", type=positive_int, default=None, help="optimiser iterations (default: config)")
    parser.add_argument("--contacts", type=positive_int, default=None, help="contacts per pose (default: config)")
    parser.add_argument("--batch-size", type=positive_int, default=None, help="poses optimised together (default: config)")
    parser.add_argument("--grasp-only", action="store_true", help="drop E_dir and E_arm (grasp-pose baseline)")
    parser.add_argument("--resting-pose", type=non_negative_int, default=None, metavar="INDEX",
                        help="which resting pose of the object (default: its default pose)")
    parser.add_argument("--yaw-deg", type=finite_float, default=0.0, help="object yaw about z in D (default 0)")
    parser.add_argument("--threads", type=positive_int, default=1, help="torch threads (default 1: reproducible, and fastest "
                                                               "when other processes share the cores)")
    parser.add_argument("--plot", metavar="FILE.png", default=None, help="save energy-per-iteration curves")
    parser.set_defaults(func=run_generate)


def run_generate(args: argparse.Namespace) -> int:
    from shared.contracts.messages import GenerationJob

    try:
        validate_fields(GenerationJob, {"seed": args.seed, "iterations": args.iterations, "contacts_per_pose": args.contacts},
                        JOB_FLAGS, command="generate")
    except FlagError as exc:
        print(exc, file=sys.stderr)
        return 2
    import torch
    from tqdm import tqdm

    from shared.synthesis.config import GenerationConfig, GenerationConfigError
    from shared.synthesis.init import InitialisationError
    from shared.synthesis.plots import plot_energy_history
    from shared.synthesis.scene import PushScene
    from shared.synthesis.synthesis import GenerationError, generate
    from shared.world.objects import ObjectLoadError, load_object

    torch.set_num_threads(args.threads)
    try:
        config = GenerationConfig().replace(iterations=args.iterations, contacts_per_pose=args.contacts,
                                            batch_size=args.batch_size, grasp_only=args.grasp_only or None)
        obj = load_object(args.object)
        scene = PushScene.from_object(obj, args.resting_pose, math.radians(args.yaw_deg),
                                      surface_points=config.object_points, check_points=config.penetration_check_points)
    except (GenerationConfigError, ObjectLoadError, ValueError) as exc:
        return _fail(str(exc))
    batches = math.ceil(args.n / config.batch_size)
    with tqdm(total=batches * config.iterations, unit="it", desc=f"{obj.id} x{args.n}", file=sys.stderr) as bar:
        try:
            output = generate(scene, args.hand, args.n, args.seed, config, progress=bar.update)
        except (GenerationError, InitialisationError) as exc:
            return _fail(str(exc))
    _write_json(Path(args.out), output_document(output, scene, args.seed, config))
    print(f"{len(output)} poses for {obj.id} in {output.elapsed_s:.1f} s -> {args.out}; "
          f"{output.good().mean():.0%} pass the pre-physics check "
          f"(palm x >= 0.7, penetration <= 5 mm, contacts within 5 mm)", file=sys.stderr)
    if args.plot:
        plot_energy_history(output.history, args.plot, config.effective_weights(),
                            title=f"{obj.id}, {args.hand}, n={args.n}, seed={args.seed}")
        print(f"energy curves -> {args.plot}", file=sys.stderr)
    return 0


def output_document(output, scene, seed: int, config) -> dict:
    """The JSON document of a run (see the module docstring)."""
    from shared.frames import matrix_to_pos_quat

    position, quaternion = matrix_to_pos_quat(scene.transform_d)
    poses = [
        {
            "pose": output.poses[i].tolist(),
            "energy": {name: float(values[i]) for name, values in output.energies.items()},
            "palm_normal": output.palm_normals[i].tolist(),
            "max_penetration_m": float(output.max_penetration_m[i]),
        }
        for i in range(len(output))
    ]
    return {
        "object_id": output.object_id,
        "hand": output.hand,
        "seed": seed,
        "resting_pose_index": scene.pose_index,
        "yaw_deg": math.degrees(scene.yaw_rad),
        "object_pose_d": {"position": position.tolist(), "quaternion_xyzw": quaternion.tolist()},
        "iterations": config.iterations,
        "contacts_per_pose": config.contacts_per_pose,
        "grasp_only": config.grasp_only,
        "weights": config.effective_weights(),
        "elapsed_s": output.elapsed_s,
        "poses": poses,
    }


def _write_json(path: Path, document: dict) -> None:
    """Write atomically (temp file + rename): a reader never sees half a file."""
    atomic_write_text(path, json.dumps(document))


def _fail(message: str) -> int:
    print(f"gd2p generate: {message}", file=sys.stderr)
    return 2
