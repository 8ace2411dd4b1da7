"""`gd2p push`: ask the running system (`gd2p up`) to push or pull an object.

    gd2p push --object proc-box-013 --direction-deg 90 [--distance 0.2] [--json]
    gd2p push --object mug.obj --position 0.5 0.1 --yaw 30 --goal 0.5 -0.3 --obstacle 0.5 -0.1 0.05
    gd2p push --object proc-box-013 --goal 0.5 -0.15 --goal-yaw 45   # to a pose: within 2 cm and 15 deg
    gd2p push --object proc-box-013 --direction-deg 180 --method nearest --choice random
    gd2p push --cloud scan.ply --direction-deg 90      # the object as a camera saw it (world frame, metres)

With --cloud (.ply, .pcd or .npy: points in the world frame, metres, the table at z = 0) the system
reconstructs the object from the cloud (table removed, the object's cluster kept, a watertight
mesh) and plans around that; the cloud also says where the object stands. Clouds over 200k points
are thinned (voxels) before they are sent.

Prints the result (or, with --json, the PushResponse as JSON). Exit codes:
  0  the push succeeded
  1  the push ran but missed the target
  2  the request could not be served (infeasible, bad object, no planner running, timed out)
  3  outcome unknown: the connection was lost while the request was served (look before retrying)
  130 interrupted (Ctrl-C): the request is cancelled, and the robot stops if it was moving

Ctrl-C, a timeout or a lost connection cancel the request: the client's lease disappears, the
planner stops sampling and planning, and the robot bridge stops the motion (docs/safety.md).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import get_args

from shared.contracts.messages import PoseMethod

CONNECT_TIMEOUT_MS = 3000


# PushRequest fields -> the flags that set them (errors name what the user typed).
FLAGS = {"object": "--object/--cloud", "object_pose": "--position/--yaw", "direction_deg": "--direction-deg",
         "goal_xy": "--goal", "goal_yaw_deg": "--goal-yaw", "distance_m": "--distance", "hand": "--hand", "arm": "--arm",
         "obstacles": "--obstacle / --wall", "seed": "--seed", "options": "the planner options", "options.k": "--k", "options.method": "--method",
         "options.sampler": "--sampler", "options.choice": "--choice", "options.physics_draws": "--physics-draws",
         "options.corrections": "--corrections", "options.closed_loop": "--closed-loop", "options.critic": "--no-critic",
         "options.prescreen": "--no-prescreen"}


def register(subparsers: argparse._SubParsersAction) -> None:
    from cli.args import finite_float, non_negative_int, positive_float, positive_int
    from shared.bus import BusConfig

    parser = subparsers.add_parser("push", help="push or pull an object with the robot (needs `gd2p up`)",
                                   description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--object", help="library object id or mesh file (.obj .stl .ply .glb)")
    source.add_argument("--cloud", type=Path, help="the object as a point cloud (.ply .pcd .npy; world frame, metres)")
    parser.add_argument("--position", nargs=2, type=finite_float, metavar=("X", "Y"), default=None,
                        help="object position on the table in the world, m (default: 0.55 0 in front of the robot)")
    parser.add_argument("--yaw", type=finite_float, default=0.0, help="object yaw about world z, degrees (with --position)")
    target = parser.add_mutually_exclusive_group(required=True)
    target.add_argument("--direction-deg", type=finite_float, help="push direction in the world, degrees (0 = away from the robot)")
    target.add_argument("--goal", nargs=2, type=finite_float, metavar=("X", "Y"), help="goal point: multi-step pushes around obstacles")
    parser.add_argument("--goal-yaw", type=finite_float, default=None, metavar="DEG",
                        help="with --goal, a pose goal: the yaw about world z, degrees, the object is to end with, as "
                             "--yaw places it (its resting pose turned by DEG); the pushes go on until it is within "
                             "2 cm and 15 deg of the pose (or --goal alone: within 3 cm of the point, any yaw). Goals "
                             "off the table or out of the arm's reach are refused before the robot moves")
    parser.add_argument("--distance", type=positive_float, default=0.20, help="push distance (with --goal: longest single push), m")
    parser.add_argument("--hand", choices=("allegro", "leap"), default="allegro")
    parser.add_argument("--arm", choices=("panda", "xarm7"), default=None, help="default: panda for allegro, xarm7 for leap")
    parser.add_argument("--obstacle", nargs=3, type=finite_float, action="append", default=[], metavar=("X", "Y", "R"),
                        help="a cylinder obstacle on the table (repeatable); nothing may touch it")
    parser.add_argument("--wall", nargs=4, type=finite_float, action="append", default=[],
                        metavar=("X", "Y", "YAW", "LENGTH"),
                        help="a wall on the table (repeatable): centre X Y, running along YAW degrees, LENGTH m long, "
                             "2 cm thick, 15 cm tall; the object may slide along it, the robot may not touch it")
    parser.add_argument("--k", type=positive_int, default=200, help="candidate hand poses sampled (default %(default)s)")
    parser.add_argument("--method", choices=get_args(PoseMethod), default="gd2p",
                        help="pose source: the diffusion sampler (gd2p), retrieval (nearest), the fixed spatula pose "
                             "(fixed) or one fingertip pointing along the push (fingertip)")
    parser.add_argument("--sampler", choices=("ddpm", "ddim"), default="ddpm",
                        help="diffusion sampler for --method gd2p: the paper's DDPM-100 or the DDIM-10 fast path")
    parser.add_argument("--no-critic", dest="critic", action="store_false",
                        help="consider the candidates (sampled, or retrieved with --method nearest) best-aligned palm "
                             "first (the paper's L_dir order) instead of in the success critic's order (the default "
                             "when the sampler has a critic)")
    parser.add_argument("--no-prescreen", dest="prescreen", action="store_false",
                        help="push no floating hand before planning: with --sampler ddim the fast path (about 1.2 s "
                             "less to plan; see PlannerOptions.prescreen for what it costs in success)")
    parser.add_argument("--choice", choices=("ranked", "unranked", "random"), default="ranked",
                        help="how the executed plan is chosen: ranked by arm rollouts (GD2P, default); unranked: "
                             "the same rolled-out plans, one drawn at random (the ranking ablation); random: a "
                             "random feasible pose, no rollouts")
    parser.add_argument("--physics-draws", type=non_negative_int, default=0, metavar="N",
                        help="rank for robustness: roll each plan out in N worlds drawn around the nominal physics "
                             "and the given pose (friction, mass, centre of mass, controller, pose off by up to 1 cm / "
                             "5 deg) besides the nominal one, and rank by the mean L_goal (0-16; default 0: the "
                             "nominal rollout only; each draw costs about 0.4 s of CPU per plan)")
    parser.add_argument("--corrections", type=non_negative_int, default=None, metavar="N",
                        help="closed loop at the scale of pushes (with --direction-deg): when a push leaves the "
                             "object more than 3 cm from the target, upright and turned no more than 45 deg, push "
                             "again from where the robot saw it, up to N times (0-5; default 2; 0: open loop, as the "
                             "paper)")
    parser.add_argument("--closed-loop", action=argparse.BooleanOptionalAction, default=None,
                        help="watch the object while each push runs (the robot bridge's object tracking) and stop "
                             "the push when it strays from the path the chosen plan's rollout predicted; the robot "
                             "backs out and, within --corrections, pushes again from where it saw the object "
                             "(default: on; --no-closed-loop runs each push to its end; plans chosen with --choice "
                             "random have no predicted path and run open loop)")
    parser.add_argument("--seed", type=non_negative_int, default=0)
    parser.add_argument("--timeout", type=positive_float, default=600.0, help="seconds to wait for the planner")
    parser.add_argument("--json", action="store_true", help="print the PushResponse as JSON")
    parser.add_argument("--identity", default=None, metavar="CN",
                        help="the identity this client's lease names, gd2p/lease/client/CN/<id>: under the secure "
                             "profile the CN of the certificate in --zenoh-config, the only identity that may hold "
                             "it (default: cli, the identity of every push client today)")
    BusConfig.add_cli_args(parser)
    parser.set_defaults(func=run_push)


def object_ref(args: argparse.Namespace):
    """The ObjectRef of --object (library id or mesh file) or --cloud (CloudFileError for a bad file)."""
    from shared.contracts.messages import MeshBlob, ObjectRef
    from shared.world.perception import cloud_for_request, load_cloud

    if getattr(args, "cloud", None) is not None:
        return ObjectRef(point_cloud=cloud_for_request(load_cloud(args.cloud).points))
    path = Path(args.object)
    if path.suffix and path.is_file():
        return ObjectRef(mesh=MeshBlob.from_file(str(path)))
    return ObjectRef(library_id=args.object)


def build_request(args: argparse.Namespace):
    """The PushRequest the flags describe (ValueError / ObjectLoadError on bad input)."""
    import math

    import numpy as np

    from shared.contracts.messages import CircleObstacle, PushRequest
    from shared.frames import make_transform
    from shared.world.object_refs import load_object_ref
    from shared.world.objects.final_split import check_final_access, is_final_id
    from shared.world.push_outcome import object_pose

    if args.goal_yaw is not None and not args.goal:
        raise ValueError("--goal-yaw is the yaw of a goal pose: give the goal point with --goal X Y too")
    if args.goal and args.corrections is not None:
        raise ValueError("--corrections: a --goal request already pushes again from where the object was seen, up "
                         "to its step limit; corrections are for --direction-deg")
    ref = object_ref(args)
    if ref.library_id is not None and is_final_id(ref.library_id):
        check_final_access(ref.library_id)  # the final split's objects: `gd2p eval --split final` only
    if ref.point_cloud is not None and args.position is not None:
        raise ValueError("--position: the point cloud shows where the object stands; leave --position out")
    pose = None
    if args.position is not None:
        obj = load_object_ref(ref)
        T_world_O = make_transform(np.eye(3), np.array([*args.position, 0.0])) @ obj.T_D_O(yaw_rad=math.radians(args.yaw))
        pose = object_pose(T_world_O)
    arm = args.arm or {"allegro": "panda", "leap": "xarm7"}[args.hand]
    knobs = {name: value for name, value in (("corrections", args.corrections), ("closed_loop", args.closed_loop))
             if value is not None}  # left out: the planner's default
    # A map, not a PlannerOptions: pydantic then reports a bad option beside a bad question field, each by its flag.
    options = dict(k=args.k, choice=args.choice, method=args.method, sampler=args.sampler, critic=args.critic,
                   prescreen=args.prescreen, physics_draws=args.physics_draws, **knobs)
    return PushRequest.model_validate(dict(
        object=ref, object_pose=pose, direction_deg=args.direction_deg, goal_xy=tuple(args.goal) if args.goal else None,
        goal_yaw_deg=args.goal_yaw, distance_m=args.distance, hand=args.hand, arm=arm, seed=args.seed, options=options,
        obstacles=[*(CircleObstacle(x=x, y=y, radius=r) for x, y, r in args.obstacle),
                   *(dict(x=x, y=y, yaw_deg=yaw, length_m=length) for x, y, yaw, length in args.wall)]))


def run_push(args: argparse.Namespace) -> int:
    from pydantic import ValidationError

    from cli.args import describe_validation_error
    from client.push_client import PushFailed, PushOutcomeUnknown, push
    from shared.bus import BusConfig
    from shared.bus.errors import BusError
    from shared.world.objects import ObjectLoadError

    try:
        request = build_request(args)
    except ValidationError as exc:
        print(describe_validation_error(exc, FLAGS, command="push"), file=sys.stderr)
        return 2
    except (ValueError, ObjectLoadError) as exc:
        print(f"gd2p push: bad request: {exc}", file=sys.stderr)
        return 2
    try:
        response = push(request, BusConfig.from_args(args, connect_timeout_ms=CONNECT_TIMEOUT_MS), args.timeout,
                        identity=args.identity)
    except KeyboardInterrupt:
        return _failed(args, "cancelled", "interrupted: the request is cancelled and the robot stops if it was moving",
                       130)
    except PushOutcomeUnknown as exc:
        return _failed(args, exc.code, exc.message, 3)
    except PushFailed as exc:
        return _failed(args, exc.code, exc.message, 2)
    except BusError as exc:
        print(f"gd2p push: {exc} (is `gd2p up` running?)", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(response_json(response)))
    else:
        print(describe(response))
    return 0 if response.success else 1


def _failed(args: argparse.Namespace, code: str, message: str, exit_code: int) -> int:
    if args.json:
        print(json.dumps({"error": code, "message": message}))
    print(f"gd2p push: {code.replace('_', ' ')}: {message}", file=sys.stderr)
    return exit_code


def response_json(response) -> dict:
    """The PushResponse as plain JSON: arrays as nested lists; the plans' trajectories summarised
    (joint names, waypoint count, duration, segments) — the full plans are in the recording."""
    import numpy as np
    from pydantic import BaseModel

    from shared.contracts.messages import NDArray, Plan

    def convert(value):
        if isinstance(value, Plan):
            times = value.times_s.to_numpy()
            return {"arm": value.arm, "hand": value.hand, "joint_names": value.joint_names, "waypoints": len(times),
                    "duration_s": float(times[-1] - times[0]), "segments": [s.model_dump() for s in value.segments]}
        if isinstance(value, NDArray):
            return np.asarray(value.to_numpy()).tolist()
        if isinstance(value, BaseModel):
            return {name: convert(getattr(value, name)) for name in type(value).model_fields}
        if isinstance(value, (list, tuple)):
            return [convert(v) for v in value]
        if isinstance(value, dict):
            return {k: convert(v) for k, v in value.items()}
        return value

    return convert(response)


def describe(response) -> str:
    """A few human-readable lines about a PushResponse."""
    r = response.result
    from_yaw = "" if r.yaw_error_deg is None else f", {r.yaw_error_deg:.1f}° from the goal yaw"
    lines = [(f"{'SUCCESS' if response.success else 'MISSED'}: object ended {r.position_error_m * 100:.1f} cm from the "
              f"target, rotated {r.rotation_deg:.1f}°{from_yaw}{', toppled' if r.toppled else ''} "
              f"({len(response.steps)} push(es))"),
             f"final object position: {', '.join(f'{v:.3f}' for v in r.final_object_pose.position)} m"]
    if response.score is not None:
        s = response.score
        lines.append(f"score of the chosen plan: V = {s.v:.3f} (L_goal {s.l_goal:.3f} m, L_coll {s.l_coll:.0f}, "
                     f"L_dir {s.l_dir:.2f}; α {s.alpha}, β {s.beta}, γ {s.gamma})")
        if s.draws is not None:
            lines.append(f"its rollouts succeeded in {s.draws_succeeded} of {s.draws} physics worlds "
                         "(the nominal one and the drawn ones)")
    lines += [step.reason for step in response.steps if step.reason] + response.notes
    lines.append("timings: " + ", ".join(f"{k} {v:.2f} s" for k, v in response.timings_s.items()))
    if response.recording_path:
        lines.append(f"recording: {response.recording_path}")
        lines.append(f"storyboard: {Path(response.recording_path).with_suffix('.png')}")
    return "\n".join(lines)
