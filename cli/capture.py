"""`gd2p capture`: a simulated RGB-D capture of an object on the table, written as a point cloud.

    gd2p capture --object proc-box-001 --out box.ply
    gd2p capture --object pb-mug --cameras 1 --seed 3 --pose 0.5 0.1 30 --out mug.pcd --plot mug.png
    gd2p capture --object scan.obj --cameras 3 --out scan.npy --json

The object rests in its default pose at `--pose X Y YAW` (world frame: metres, metres, degrees;
default 0.55 0 0, in front of the robot at the origin). 1–3 depth cameras see it (1: a head camera
behind the robot, 2: + a tripod at the side, 3: + a camera across the table), rendered with
PyBullet's CPU renderer and the noise of a RealSense D435-class stereo camera (depth noise growing
with the square of depth, dropouts at depth edges and at random, 1/32-pixel disparity and 1 mm
depth quantisation; `--no-noise` for ideal depth). The cloud is in the world frame (table top at
z = 0), table included, cropped to 0.4 m around the object, as the system receives it. The file
type follows --out's extension: .ply (binary), .pcd (binary) or .npy ([N, 3] float64 metres).
`--plot` writes a PNG of each camera's depth image and of the cloud near the object from above and
from the side.
The same --seed gives the same cloud.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

from cli.args import finite_float, non_negative_int

MAX_DISTANCE_M = 1.2  # object position from the robot: beyond it the head camera sees too little
DEFAULT_POSE = (0.55, 0.0, 0.0)


class CaptureInputError(ValueError):
    """A bad command-line input (object, pose, file names, image size)."""


def camera_count(text: str) -> int:
    """argparse type: 1, 2 or 3 cameras."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be 1, 2 or 3, got {text!r}") from None
    if not 1 <= value <= 3:
        raise argparse.ArgumentTypeError(f"must be 1, 2 or 3, got {text!r}")
    return value


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "capture", help="simulate a depth-camera capture of an object and write its point cloud (.ply/.pcd/.npy)",
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--object", required=True, help="library id (e.g. proc-box-001, pb-mug) or a mesh file in metres")
    parser.add_argument("--cameras", type=camera_count, default=3, help="number of depth cameras, 1-3 (default 3)")
    parser.add_argument("--seed", type=non_negative_int, default=0, help="seed of the sensor noise (default 0)")
    parser.add_argument("--pose", nargs=3, type=finite_float, metavar=("X", "Y", "YAW"), default=list(DEFAULT_POSE),
                        help="object position on the table (m) and yaw (degrees) in the world (default 0.55 0 0)")
    parser.add_argument("--size", default="848x480",
                        help="pixels per depth image, WIDTHxHEIGHT (default 848x480, the D435's depth mode)")
    parser.add_argument("--no-noise", action="store_true", help="ideal depth: no noise, dropouts or quantisation")
    parser.add_argument("--out", type=Path, required=True, help="point-cloud file to write: .ply, .pcd or .npy")
    parser.add_argument("--plot", type=Path, help="also write a PNG of the depth images and the cloud")
    parser.add_argument("--json", action="store_true", help="print a JSON summary instead of a sentence")
    parser.set_defaults(func=run_capture)


def run_capture(args: argparse.Namespace) -> int:
    from shared.world.objects import ObjectLoadError
    from shared.world.perception import PerceptionError

    try:
        summary = capture(args)
    except (CaptureInputError, ObjectLoadError, PerceptionError) as exc:
        print(f"gd2p capture: error: {exc}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(summary))
    else:
        plot = f"; plot {summary['plot']}" if summary["plot"] else ""
        print(f"wrote {summary['out']}: {summary['points']} points ({summary['object_pixels']} object pixels) from "
              f"{summary['cameras']} camera(s) ({', '.join(summary['camera_names'])}), seed {summary['seed']}{plot}")
    return 0


def capture(args: argparse.Namespace) -> dict:
    """Check the arguments, capture, write the cloud (and plot); returns the summary."""
    from shared.world.perception import CLOUD_SUFFIXES, save_cloud

    size = parse_size(args.size)
    if args.out.suffix.lower() not in CLOUD_SUFFIXES:
        raise CaptureInputError(f"--out must end in {', '.join(CLOUD_SUFFIXES)}, got {args.out}")
    if args.plot is not None and args.plot.suffix.lower() != ".png":
        raise CaptureInputError(f"--plot must be a .png file, got {args.plot}")
    x, y, yaw_deg = args.pose
    if math.hypot(x, y) > MAX_DISTANCE_M:
        raise CaptureInputError(f"--pose {x:g} {y:g}: the object must be within {MAX_DISTANCE_M} m of the robot at the origin")
    result, obj = _capture(args.object, (x, y, yaw_deg), args.cameras, args.seed, size, not args.no_noise)
    save_cloud(args.out, result.cloud)
    if args.plot is not None:
        plot_capture(result, args.plot, f"{obj.id} · {args.cameras} camera(s) · seed {args.seed}", (x, y))
    return {
        "out": str(args.out), "points": int(len(result.cloud)), "object": obj.id, "cameras": args.cameras,
        "camera_names": [c.name for c in result.cameras], "seed": args.seed, "pose": [x, y, yaw_deg],
        "size": list(size), "noise": not args.no_noise, "object_pixels": int(sum(m.sum() for m in result.object_masks)),
        "plot": str(args.plot) if args.plot is not None else None,
    }


def _capture(object_arg: str, pose: tuple[float, float, float], cameras: int, seed: int, size: tuple[int, int], noisy: bool):
    from shared.frames import make_transform
    from shared.world.objects import load_object
    from shared.world.sim import c_stdout_to_stderr
    from shared.world.sim.camera import StereoDepthNoise, capture_object

    with c_stdout_to_stderr():  # PyBullet prints on file descriptor 1
        obj = load_object(object_arg)
        T_world_O = make_transform(np.eye(3), np.array([pose[0], pose[1], 0.0])) @ obj.T_D_O(yaw_rad=math.radians(pose[2]))
        result = capture_object(obj, T_world_O, n_cameras=cameras, seed=seed, size=size, noise=StereoDepthNoise() if noisy else None)
    return result, obj


def parse_size(text: str) -> tuple[int, int]:
    """'848x480' -> (848, 480); CaptureInputError for anything else."""
    try:
        width, height = (int(p) for p in text.lower().split("x"))
    except ValueError:
        raise CaptureInputError(f"--size must be WIDTHxHEIGHT in pixels, e.g. 848x480, got {text!r}") from None
    if not (32 <= width <= 1280 and 32 <= height <= 960):
        raise CaptureInputError(f"--size must be between 32x32 and 1280x960 pixels, got {text!r}")
    return width, height


def plot_capture(result, path: Path, title: str, center_xy: tuple[float, float], half_width_m: float = 0.2) -> Path:
    """PNG: each camera's depth image (invalid pixels black) above the cloud near the object, from above and the side."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(result.frames)
    figure = plt.figure(figsize=(4.4 * max(n, 2), 7.6))
    for index, (frame, camera) in enumerate(zip(result.frames, result.cameras, strict=True)):
        ax = figure.add_subplot(2, n, index + 1)
        depth = np.ma.masked_less_equal(frame.depth_m, 0.0)
        image = ax.imshow(depth, cmap=matplotlib.colormaps["viridis"].with_extremes(bad="black"), interpolation="nearest")
        ax.set_title(f"{camera.name} camera: depth (m), black = invalid", fontsize=9)
        ax.axis("off")
        figure.colorbar(image, ax=ax, fraction=0.035)
    near = np.all(np.abs(result.cloud[:, :2] - np.asarray(center_xy)) <= half_width_m, axis=1)
    cloud = result.cloud[near][np.random.default_rng(0).permutation(int(near.sum()))[:40_000]]
    views = ((0, 1, "from above: x, y (m)"), (0, 2, "from the side: x, z (m)"))
    for index, (i, j, name) in enumerate(views):
        ax = figure.add_subplot(2, 2, 3 + index)
        ax.scatter(cloud[:, i], cloud[:, j], c=cloud[:, 2], s=0.6, cmap="viridis", vmin=0.0)
        ax.set_aspect("equal")
        ax.set_title(f"cloud within {half_width_m} m of the object, {name}; colour = height", fontsize=9)
    figure.suptitle(f"{title} · {len(result.cloud)} points in the world frame")
    figure.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=90)
    plt.close(figure)
    return path
