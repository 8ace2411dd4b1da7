"""`gd2p show`: a picture of an object on the table with hand poses — the picture people judge a pose by.

    gd2p show --object proc-box-001 --out box.png
    gd2p show --object proc-box-001 --hand allegro --fixed-pose spatula --candidates --out spatula.png
    gd2p show --object scan.ply --hand leap --poses poses.json --max-poses 4 --direction-deg 30 --out scan.png

`--poses` reads the generator's output, `{"poses": [{"pose": [25 floats, in D], ...}, ...]}`; the first
`--max-poses` are drawn, each hand in its own colour, or just the one at `--index`. The object rests in
its default resting pose (or `--resting-pose K`) with its centre over D's origin — the placement the
generator and the validator use — and D's +x points `--direction-deg` degrees from the world's +x. A
black arrow shows the push (`--distance`, default 0.20 m) and a ring the success tolerance (3 cm)
around the target. Rendering is PyBullet's CPU TinyRenderer: no GPU or display needed.
"""
from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cli.args import finite_float, float_range

FIXED_POSES = ("spatula",)
SUCCESS_TOLERANCE_M = 0.03  # the paper's success radius, drawn around the target
MULTI_POSE_ALPHA = 0.75  # several hands: see-through so the object stays visible


class ShowInputError(ValueError):
    """A bad command-line input (object, hand, poses file, options)."""


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "show", help="render an object on the table with hand poses to a PNG (CPU renderer)",
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--object", required=True, help="library id (e.g. proc-box-001, pb-mug) or a mesh file in metres")
    parser.add_argument("--hand", help="hand model: allegro or leap (needed with --poses, --fixed-pose, --candidates)")
    source = parser.add_mutually_exclusive_group()
    source.add_argument("--poses", type=Path, help='JSON file {"poses": [{"pose": [25 floats in D]}, ...]}')
    source.add_argument("--fixed-pose", choices=FIXED_POSES, help="a built-in pose (the paper's fixed-hand baseline)")
    parser.add_argument("--index", type=int, help="draw only this pose of the file (0-based)")
    parser.add_argument("--max-poses", type=int, default=8, help="draw at most this many poses (default 8)")
    parser.add_argument("--candidates", action="store_true", help="also draw the hands' contact candidates")
    parser.add_argument("--direction-deg", type=finite_float, default=0.0, help="push direction in the world, degrees (default 0)")
    parser.add_argument("--distance", type=float_range(0.0, 1.0, low_open=True), default=0.20, help="push distance drawn, metres (default 0.20)")
    parser.add_argument("--resting-pose", type=int, help="the object's resting pose index (default: its default pose)")
    parser.add_argument("--views", default="iso,side,top", help="comma-separated views: iso, side, top, front, back")
    parser.add_argument("--size", default="480x360", help="pixels per view, WIDTHxHEIGHT (default 480x360)")
    parser.add_argument("--out", type=Path, required=True, help="PNG file to write")
    parser.set_defaults(func=run_show)


def run_show(args: argparse.Namespace) -> int:
    from visualisation.render import RenderError

    try:
        path, summary = show(args)
    except (ShowInputError, RenderError) as exc:
        print(f"gd2p show: error: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {path} ({summary})")
    return 0


def show(args: argparse.Namespace) -> tuple[Path, str]:
    """Build the scene described by the arguments and write the PNG; returns (path, summary)."""
    from shared.world.sim import c_stdout_to_stderr
    from visualisation.render import render_scene, views_by_name

    size = parse_size(args.size)
    views = views_by_name([v.strip() for v in args.views.split(",") if v.strip()])
    if not 0.0 < args.distance <= 1.0:
        raise ShowInputError(f"--distance must be in (0, 1] m, got {args.distance}")
    if not np.isfinite(args.direction_deg):
        raise ShowInputError(f"--direction-deg must be finite, got {args.direction_deg}")
    if args.out.suffix.lower() != ".png":
        raise ShowInputError(f"--out must be a .png file, got {args.out}")
    _check_pose_options(args)
    with c_stdout_to_stderr():  # PyBullet prints on file descriptor 1
        obj = _load_object(args.object)
        T_D_O = _object_placement(obj, args.resting_pose)
        hand, poses_d, indices = _hand_and_poses(args, obj.mesh.vertices @ T_D_O[:3, :3].T + T_D_O[:3, 3])
        labels = [f"{args.fixed_pose} pose" if args.fixed_pose else f"pose {i}" for i in indices]
        scene = show_scene(obj, T_D_O, hand, poses_d, labels, direction_deg=args.direction_deg,
                           distance_m=args.distance, candidates=args.candidates)
        path = render_scene(scene.items, args.out, views=views, size=size, heading_deg=args.direction_deg,
                            title=scene.title, legend=scene.legend)
    return path, f"{_count(len(views), 'view')}, {_count(len(indices), 'pose')}"


@dataclass
class ShowScene:
    items: list
    legend: list
    title: str


def show_scene(obj, T_D_O: np.ndarray, hand, poses_d: np.ndarray, labels: list[str], *, direction_deg: float = 0.0,
               distance_m: float = 0.20, candidates: bool = False) -> ShowScene:
    """The picture's items in the world: D's origin at the world origin, its +x `direction_deg` from world +x.

    `obj` is an ObjectModel resting at T_D_O; `poses_d` [N,25] are poses of `hand` in D, named by `labels`.
    Several hands are drawn see-through (alpha MULTI_POSE_ALPHA) so the object stays visible.
    """
    from shared.frames import direction_frame, poses_d_to_world
    from visualisation.render import (
        CANDIDATE_COLORS,
        HAND_COLORS,
        MARKER_RGBA,
        OBJECT_RGBA,
        WORLD_X_RGBA,
        WORLD_Y_RGBA,
        Item,
        LegendEntry,
        candidate_items,
        hand_item,
        mesh_item,
        push_markers,
    )

    T_world_D = direction_frame(np.zeros(3), direction_deg)
    items: list[Item] = [mesh_item(obj.id, obj.mesh, T_world_D @ T_D_O, OBJECT_RGBA)]
    legend = [LegendEntry(obj.id, OBJECT_RGBA)]
    alpha = 1.0 if len(poses_d) <= 1 else MULTI_POSE_ALPHA
    for number, (label, pose_d) in enumerate(zip(labels, poses_d, strict=False)):
        color = HAND_COLORS[number % len(HAND_COLORS)]
        pose_world = poses_d_to_world(np.asarray(pose_d, dtype=np.float64), T_world_D)
        items.append(hand_item(label, hand, pose_world, (*color[:3], alpha)))
        legend.append(LegendEntry(label, color))
        if candidates:
            items += candidate_items(label, hand, pose_world)
    if candidates and len(poses_d):
        legend += [LegendEntry(f"{kind} candidates", rgba) for kind, rgba in CANDIDATE_COLORS.items()]
    items += push_markers(T_world_D, distance_m, SUCCESS_TOLERANCE_M)
    legend += [LegendEntry(f"push {distance_m:.2f} m, target ±{SUCCESS_TOLERANCE_M * 100:.0f} cm", MARKER_RGBA),
               LegendEntry("world +x", WORLD_X_RGBA), LegendEntry("world +y", WORLD_Y_RGBA)]
    hand_text = f" · {hand.name} · {_count(len(poses_d), 'pose')}" if hand is not None else ""
    title = f"{obj.id}{hand_text} · push direction {direction_deg:g}° in the world · grid 5 cm"
    return ShowScene(items, legend, title)


def parse_size(text: str) -> tuple[int, int]:
    """'480x360' -> (480, 360); ShowInputError for anything else."""
    parts = text.lower().split("x")
    try:
        width, height = (int(p) for p in parts)
    except ValueError:
        raise ShowInputError(f"--size must be WIDTHxHEIGHT in pixels, e.g. 480x360, got {text!r}") from None
    if not (64 <= width <= 4096 and 64 <= height <= 4096):
        raise ShowInputError(f"--size must be between 64x64 and 4096x4096 pixels per view, got {text!r}")
    return width, height


def _load_object(object_id: str):
    from shared.world.objects import ObjectLoadError, load_object

    try:
        return load_object(object_id)
    except ObjectLoadError as exc:
        raise ShowInputError(str(exc)) from exc


def _object_placement(obj, resting_pose: int | None) -> np.ndarray:
    if resting_pose is not None and not 0 <= resting_pose < len(obj.resting_poses):
        raise ShowInputError(f"--resting-pose {resting_pose}: {obj.id} has {len(obj.resting_poses)} resting poses "
                             f"(0..{len(obj.resting_poses) - 1})")
    return obj.T_D_O(resting_pose)


def _check_pose_options(args: argparse.Namespace) -> None:
    """Reject option combinations that cannot be drawn, before anything slow is loaded."""
    wants_hand = args.poses is not None or args.fixed_pose is not None or args.candidates
    if args.hand is not None and args.poses is None and args.fixed_pose is None:
        raise ShowInputError("--hand needs --poses FILE or --fixed-pose spatula to place it")
    if wants_hand and args.hand is None:
        raise ShowInputError("--poses, --fixed-pose and --candidates need --hand (allegro or leap)")
    if args.index is not None and args.poses is None:
        raise ShowInputError("--index selects a pose of a --poses file")
    if args.max_poses < 1:
        raise ShowInputError(f"--max-poses must be >= 1, got {args.max_poses}")


def _hand_and_poses(args: argparse.Namespace, object_vertices_d: np.ndarray):
    """(hand model or None, poses [N,25] in D, their indices in the file) chosen by the arguments."""
    if args.hand is None:
        return None, np.zeros((0, 25)), []
    hand = _load_hand(args.hand)
    if args.fixed_pose is not None:
        from shared.world.fixed_poses import spatula_pose

        return hand, spatula_pose(hand, object_vertices_d)[None], [0]
    poses = _read_poses(args.poses)
    return (hand, *select_poses(poses, args.index, args.max_poses))


def _load_hand(name: str):
    from shared.robots.hands import HandModelError, load_hand

    try:
        return load_hand(name)
    except HandModelError as exc:
        raise ShowInputError(str(exc)) from exc


def _read_poses(path: Path) -> np.ndarray:
    from cli.validate import ValidateInputError, read_poses  # the one reader of the generator's pose files

    try:
        return read_poses(path)
    except ValidateInputError as exc:
        raise ShowInputError(str(exc)) from exc


def select_poses(poses: np.ndarray, index: int | None, max_poses: int) -> tuple[np.ndarray, list[int]]:
    """The poses to draw and their indices: the one at `index`, else the first `max_poses`."""
    if max_poses < 1:
        raise ShowInputError(f"--max-poses must be >= 1, got {max_poses}")
    if index is not None:
        if not 0 <= index < len(poses):
            raise ShowInputError(f"--index {index} is out of range: the file has {len(poses)} poses (0..{len(poses) - 1})")
        return poses[index:index + 1], [index]
    count = min(len(poses), max_poses)
    return poses[:count], list(range(count))


def _count(n: int, noun: str) -> str:
    return f"{n} {noun}{'' if n == 1 else 's'}"
