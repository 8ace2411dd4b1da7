"""Which registration library the object tracker (shared/world/perception/tracking.py) uses: each candidate
follows the same rendered pushes, with the robot's arm and hand in view, and is scored against the truth.

    python bench/tracking.py --json    # writes bench/results/tracking.json, ends with one JSON line
    python bench/tracking.py --quick   # 3 objects, nothing written

Scenes: the PyBullet robot (shared.execution.robots.sim: Panda + Allegro, base at the origin) and one library
object, pushed 0.20 m in `STEPS` frames along a direction of its own, turning by up to 30 degrees on the way;
the hand stands behind the object at every frame (placed by PyBullet's IK, three hand postures), so it occludes
part of it from some cameras. After the push the object is taken away for `REMOVED` frames (a pose reported
then is a false track). Depth: 3 default cameras (shared.world.sim.camera.default_cameras, aimed at the middle of
the path), TinyRenderer at 424 x 240 (TrackingConfig.image_size), the D435 noise of that mode (focal length
scaled by 424/848); the robot self-filter mask is the segmentation buffer's robot pixels. The tracker starts
from the first pose off by 5 mm and 3 degrees (a told or perceived pose is never exact).

Candidates, each the tracker's registration step (the segmentation, the prior on unobserved directions and the
checks are the tracker's own, the same for all): Open3D's point-to-plane ICP with the model's face normals (the
tracker's, chosen here), small_gicp's point-to-plane ICP and its GICP (its clouds take no given normals: they
are estimated from the model samples). Plus the tracker without the robot mask, to show what the self-filter is
for. small_gicp is not a project dependency: to measure it, install it aside (`pip install --target DIR
small_gicp`) and pass `--extra-path DIR` (appended to sys.path); without it (`make bench`) its figures are
carried over from the results file's last run that measured them, marked with that run's commit.

Measured per candidate over all pushes: position error (model frame origin) and rotation error against the
truth, median and p95 over tracked frames (for an object symmetric about the vertical the rotation error is the
tilt of its axis: its spin is not observable); lost fraction of the push frames; false-track fraction (a pose
more than 2 cm or 15 degrees off, or any pose while the object is gone) over all frames; ms per update (one
thread; the machine's load average is recorded with it).
"""
from __future__ import annotations

import argparse
import importlib.metadata
import json
import math
import os
import platform
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

# numpy / scipy on one thread; Open3D's TBB threads are limited to one by the tracker itself (its registration),
# small_gicp's by its num_threads argument: every candidate on one thread, as the tracker runs.
os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np
import pybullet as pb
import trimesh
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from shared.contracts.messages import ObjectRef
from shared.execution.robots.sim.config import SimConfig
from shared.execution.robots.sim.robot import SimRobot, TrueWorld
from shared.world.objects import ObjectModel, load_object
from shared.world.perception.depth import DepthFrame
from shared.world.perception.tracking import ObjectTracker, Open3dPointToPlane, Registration, TrackingConfig
from shared.world.sim.camera import FAR_M, NEAR_M, CameraPose, StereoDepthNoise, default_cameras, renderer_intrinsics

RESULTS = Path(__file__).resolve().parent / "results"
OBJECTS = ["proc-box-001", "proc-cylinder-001", "proc-ellipsoid-001", "proc-hull-001", "pb-duck", "pb-mug",
           "pb-jenga", "pb-teddy"]
QUICK_OBJECTS = ["proc-box-001", "proc-cylinder-001", "pb-duck"]
PATH_M, STEPS, REMOVED = 0.20, 16, 2  # 1.25 cm per frame: a 0.125 m/s push at 10 Hz
PATH_CENTRE = (0.45, 0.0)
START_ERROR = (0.005, 3.0)  # m along the push's normal, degrees of yaw
FALSE_M, FALSE_DEG = 0.02, 15.0
# Hand postures: palm orientation (xyz Euler, for a push along +x), palm height (m), sideways offset (m, +y).
POSTURES = {"fingers-forward": ((0.0, math.pi / 2, 0.0), 0.06, 0.0),
            "fingers-down": ((math.pi, 0.0, math.pi / 2), 0.16, 0.0),
            "beside": ((math.pi, -0.6, 0.0), 0.12, -0.05)}


# ------------------------------------------------------------------------------------------ candidates


# ICP stops when an iteration moves less than this: small_gicp's defaults (0.1 deg, 1 mm) stop a weakly observed
# rotation (a nearly round object's spin) degrees short. Open3D stops on the change of fit (1e-6 relative).
ROTATION_EPSILON_RAD = 1e-4
TRANSLATION_EPSILON_M = 1e-5


class SmallGicpPointToPlane:
    """small_gicp's point-to-plane ICP onto the model (its KD-tree and normals built once). Its clouds take no
    given normals: they are estimated from 20 model samples."""

    def __init__(self, model_points: np.ndarray, model_normals: np.ndarray) -> None:
        import small_gicp

        self._small_gicp = small_gicp
        self._target = small_gicp.PointCloud(np.asarray(model_points, dtype=np.float64))
        self._tree = small_gicp.KdTree(self._target)
        small_gicp.estimate_normals_covariances(self._target, self._tree, num_neighbors=20)

    def __call__(self, source: np.ndarray, T_init: np.ndarray, max_distance_m: float, iterations: int) -> np.ndarray:
        return self._align(self._small_gicp.PointCloud(source), "PLANE_ICP", T_init, max_distance_m, iterations)

    def _align(self, cloud: Any, kind: str, T_init: np.ndarray, max_distance_m: float, iterations: int) -> np.ndarray:
        result = self._small_gicp.align(
            self._target, cloud, self._tree, init_T_target_source=T_init, registration_type=kind,
            max_correspondence_distance=max_distance_m, max_iterations=iterations, rotation_epsilon=ROTATION_EPSILON_RAD,
            translation_epsilon=TRANSLATION_EPSILON_M, num_threads=1)
        return np.array(result.T_target_source, dtype=np.float64)


class SmallGicpGicp(SmallGicpPointToPlane):
    """small_gicp's GICP: both clouds' local covariances (the scene's from 10 neighbours)."""

    def __call__(self, source: np.ndarray, T_init: np.ndarray, max_distance_m: float, iterations: int) -> np.ndarray:
        cloud = self._small_gicp.PointCloud(source)
        self._small_gicp.estimate_covariances(cloud, num_neighbors=10)
        return self._align(cloud, "GICP", T_init, max_distance_m, iterations)


@dataclass(frozen=True)
class Candidate:
    name: str
    library: str
    make: Callable[[np.ndarray, np.ndarray], Registration] | None  # None: the tracker's own (the chosen library)
    masked: bool = True  # False: the tracker gets no robot mask


def candidates(extra_path: str | None) -> tuple[list[Candidate], list[str]]:
    """The candidates whose libraries import, and notes on those that do not."""
    if extra_path:
        sys.path.append(extra_path)  # last: the aside install must not shadow the project's own packages
    import open3d  # the chosen library: a project dependency

    out, notes = [Candidate("open3d point-to-plane", f"open3d {open3d.__version__}", Open3dPointToPlane)], []
    try:
        import small_gicp  # noqa: F401  (not a project dependency: installed aside to measure it)

        sg = f"small_gicp {importlib.metadata.version('small_gicp')}"
        out += [Candidate("small_gicp point-to-plane", sg, SmallGicpPointToPlane),
                Candidate("small_gicp GICP", sg, SmallGicpGicp)]
    except ImportError as exc:
        notes.append(f"small_gicp not measured: {exc}")
    out.append(Candidate("open3d point-to-plane, no robot mask", f"open3d {open3d.__version__}", None, masked=False))
    return out, notes


def tracker_for(candidate: Candidate, obj: ObjectModel, config: TrackingConfig) -> ObjectTracker:
    make = candidate.make
    if make is None:
        return ObjectTracker.from_mesh(obj.mesh, config)

    class BenchTracker(ObjectTracker):
        def _registration(self) -> Registration:
            assert make is not None
            return make(self.model_points, self.model_normals)

    return BenchTracker.from_mesh(obj.mesh, config)


# ------------------------------------------------------------------------------------------- sequences


@dataclass
class Sequence:
    object_id: str
    symmetric_axis_O: np.ndarray | None  # the object's vertical in O when it is symmetric about it
    truth: list[np.ndarray | None]  # per frame T_world_O (None: object taken away)
    frames: list[list[DepthFrame]]
    masks: list[list[np.ndarray]]
    start: np.ndarray  # the pose the tracker is reset to
    occluded: float  # mean share of the object's pixels the robot hides, over push frames and cameras


class Renderer:
    """The PyBullet robot scene and its cameras (TinyRenderer depth and robot mask)."""

    def __init__(self, size: tuple[int, int]) -> None:
        self.robot = SimRobot(SimConfig("panda", "allegro"))
        self.robot.connect()
        self.intrinsics = renderer_intrinsics(size)
        self.noise = StereoDepthNoise(focal_px=StereoDepthNoise().focal_px * size[0] / 848)
        scene = self.robot.scene
        assert scene is not None
        links = {pb.getJointInfo(scene.robot_id, j, physicsClientId=scene.client)[12].decode(): j
                 for j in range(pb.getNumJoints(scene.robot_id, physicsClientId=scene.client))}
        self.palm = links["palm_link"]  # the Allegro's palm in the combined Panda + Allegro URDF

    def load(self, object_id: str, T_world_O: np.ndarray) -> None:
        self.robot.reset_world(TrueWorld(ObjectRef(library_id=object_id), T_world_O))

    def render(self, camera: CameraPose) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(ideal depth, robot mask, object mask) of one camera."""
        scene = self.robot.scene
        assert scene is not None and scene.object is not None
        k = self.intrinsics
        view = np.linalg.inv(camera.T_world_camera() @ np.diag([1.0, -1.0, -1.0, 1.0]))
        projection = pb.computeProjectionMatrixFOV(k.vfov_deg, k.width / k.height, NEAR_M, FAR_M)
        _, _, _, buffer, segmentation = pb.getCameraImage(
            k.width, k.height, viewMatrix=view.T.reshape(-1).tolist(), projectionMatrix=projection,
            renderer=pb.ER_TINY_RENDERER, physicsClientId=scene.client)
        buffer = np.asarray(buffer, dtype=np.float64).reshape(k.height, k.width)
        depth = np.where(buffer < 1.0 - 1e-7, FAR_M * NEAR_M / (FAR_M - (FAR_M - NEAR_M) * buffer), 0.0)
        segmentation = np.asarray(segmentation).reshape(k.height, k.width)
        return depth, segmentation == scene.robot_id, segmentation == scene.object.id

    def place_hand(self, T_world_O: np.ndarray, direction: np.ndarray, reach_m: float, posture: str) -> None:
        """The palm behind the object (against `direction`), by IK from the current arm configuration."""
        scene = self.robot.scene
        assert scene is not None
        euler, height, side = POSTURES[posture]
        normal = np.array([-direction[1], direction[0], 0.0])
        target = T_world_O[:3, 3] - (reach_m + 0.03) * direction + side * normal
        target[2] = height
        yaw = Rotation.from_euler("z", math.atan2(direction[1], direction[0]))
        quaternion = (yaw * Rotation.from_euler("xyz", euler)).as_quat()
        q = pb.calculateInverseKinematics(scene.robot_id, self.palm, target.tolist(), quaternion.tolist(),
                                          maxNumIterations=200, physicsClientId=scene.client)
        arm = len(scene.arm_joints)
        self.robot.reset(list(q[:arm]), list(q[arm:]))

    def take_away(self) -> None:
        scene = self.robot.scene
        assert scene is not None and scene.object is not None
        away = np.eye(4)
        away[:3, 3] = (5.0, 5.0, 0.5)
        scene.object.reset_pose(away)


def symmetric_axis(obj: ObjectModel, T_world_O: np.ndarray) -> np.ndarray | None:
    """The vertical in O if the resting object looks the same turned about its vertical axis through its
    centre of mass (its surface samples so turned stay within 1 mm of the surface), else None."""
    points, _ = obj.surface_points(500, seed=1)
    centre = np.asarray(obj.mesh.center_mass, dtype=np.float64)
    vertical = T_world_O[:3, :3].T @ np.array([0.0, 0.0, 1.0])
    for degrees in (17.0, 45.0, 90.0):
        turned = (points - centre) @ Rotation.from_rotvec(math.radians(degrees) * vertical).as_matrix().T + centre
        _, distance, _ = trimesh.proximity.closest_point(obj.mesh, turned)
        if float(np.max(distance)) > 0.001:
            return None
    return vertical


def make_sequence(renderer: Renderer, object_id: str, index: int, seed: int) -> Sequence:
    obj = load_object(object_id)
    rng = np.random.default_rng(seed + index)
    heading = math.radians(-60.0 + 40.0 * (index % 4)) + rng.uniform(-0.2, 0.2)
    direction = np.array([math.cos(heading), math.sin(heading), 0.0])
    turn = math.radians(rng.choice([-1.0, 1.0]) * rng.uniform(10.0, 30.0))
    posture = list(POSTURES)[index % len(POSTURES)]
    T_D_O = obj.T_D_O(None, rng.uniform(-math.pi, math.pi))
    centre = np.array([*PATH_CENTRE, 0.0])
    poses = []
    for step in range(STEPS + 1):
        T = np.eye(4)
        T[:3, :3] = Rotation.from_euler("z", turn * step / STEPS).as_matrix()
        T[:3, 3] = centre + (step / STEPS - 0.5) * PATH_M * direction
        poses.append(T @ T_D_O)
    reach = 0.5 * float(np.max(np.ptp(obj.mesh.vertices, axis=0)))
    height = float(np.ptp((obj.mesh.vertices @ T_D_O[:3, :3].T)[:, 2]))
    cameras = default_cameras(PATH_CENTRE, 3, height)
    renderer.load(object_id, poses[0])
    frames, masks, truth, occluded = [], [], [], []
    for step in range(len(poses) + REMOVED):
        if step < len(poses):
            assert renderer.robot.scene is not None and renderer.robot.scene.object is not None
            renderer.robot.scene.object.reset_pose(poses[step])
            renderer.place_hand(poses[step], direction, reach, posture)
        elif step == len(poses):
            renderer.take_away()
        views = [renderer.render(camera) for camera in cameras]
        frames.append([DepthFrame(renderer.noise.apply(depth, rng).astype(np.float32), renderer.intrinsics,
                                  camera.T_world_camera()) for (depth, _, _), camera in zip(views, cameras, strict=True)])
        masks.append([robot for _, robot, _ in views])
        truth.append(poses[step] if step < len(poses) else None)
        if step < len(poses) and step % 4 == 0:  # every 4th frame: it renders all cameras again
            occluded += hidden_share(renderer, cameras, [seen for _, _, seen in views])
    start = poses[0].copy()
    start[:3, :3] = Rotation.from_euler("z", START_ERROR[1], degrees=True).as_matrix() @ start[:3, :3]
    start[:3, 3] += START_ERROR[0] * np.array([-direction[1], direction[0], 0.0])
    return Sequence(object_id, symmetric_axis(obj, poses[0]), truth, frames, masks, start, float(np.mean(occluded)))


def hidden_share(renderer: Renderer, cameras: list[CameraPose], seen: list[np.ndarray]) -> list[float]:
    """Per camera, the share of the object's pixels the robot hides (rendered again with the arm folded away)."""
    scene = renderer.robot.scene
    assert scene is not None
    saved = [pb.getJointState(scene.robot_id, j, physicsClientId=scene.client)[0] for j in scene.arm_joints]
    scene.set_configuration([0.0, -1.6, 0.0, -3.0, 0.0, 1.5, 0.78])  # folded back out of the cameras' views
    unoccluded = [renderer.render(camera)[2] for camera in cameras]
    scene.set_configuration(saved)
    return [1.0 - int((mine & whole).sum()) / int(whole.sum()) for mine, whole in zip(seen, unoccluded, strict=True)
            if whole.any()]


# -------------------------------------------------------------------------------------------- scoring


def errors(estimate: np.ndarray, truth: np.ndarray, axis_O: np.ndarray | None) -> tuple[float, float]:
    """(position error mm, rotation error deg); about a symmetry axis only the axis' tilt counts."""
    position = float(np.linalg.norm(estimate[:3, 3] - truth[:3, 3]) * 1000.0)
    if axis_O is None:
        rotation = float(np.degrees(np.linalg.norm(Rotation.from_matrix(truth[:3, :3].T @ estimate[:3, :3]).as_rotvec())))
    else:
        cosine = float(np.clip((estimate[:3, :3] @ axis_O) @ (truth[:3, :3] @ axis_O), -1.0, 1.0))
        rotation = math.degrees(math.acos(cosine))
    return position, rotation


def run(candidate: Candidate, sequence: Sequence, config: TrackingConfig) -> list[dict[str, Any]]:
    tracker = tracker_for(candidate, load_object(sequence.object_id), config)
    tracker.reset(sequence.start)
    rows = []
    for step, (frames, masks, truth) in enumerate(zip(sequence.frames, sequence.masks, sequence.truth, strict=True)):
        started = time.perf_counter()
        seen = tracker.update(frames, masks if candidate.masked else [None] * len(frames))
        row: dict[str, Any] = {"candidate": candidate.name, "object": sequence.object_id, "step": step,
                               "present": truth is not None, "ms": round((time.perf_counter() - started) * 1000, 2),
                               "lost": seen.lost, "reason": seen.reason, "fitness": round(seen.fitness, 3),
                               "points": seen.points}
        if seen.T_world_O is not None and truth is not None:
            position, rotation = errors(seen.T_world_O, truth, sequence.symmetric_axis_O)
            row.update(position_mm=round(position, 2), rotation_deg=round(rotation, 2),
                       false=position > FALSE_M * 1000 or rotation > FALSE_DEG)
        else:
            row["false"] = seen.T_world_O is not None  # a pose while the object is gone
        rows.append(row)
    return rows


def weakest_direction(sequence: Sequence, config: TrackingConfig) -> float:
    """The object's least observed motion in its push frames: the median over the frames of the tracker's
    weakest eigenvalue relative to its strongest (ObjectTracker.observability at the true pose). Below
    `TrackingConfig.unobserved_ratio` the tracker keeps its prior along it (a body of revolution's spin)."""
    tracker = ObjectTracker.from_mesh(load_object(sequence.object_id).mesh, config)
    ratios = []
    for frames, masks, truth in zip(sequence.frames, sequence.masks, sequence.truth, strict=True):
        if truth is None:
            continue
        points = tracker.segment(frames, masks, tracker.centre(truth), tracker.radius_m + config.search_margin_m)
        observed = tracker.observability(points, truth)
        if observed is not None:
            ratios.append(float(observed[0][0] / observed[0][-1]))
    return round(float(np.median(ratios)), 5) if ratios else math.nan


def summarise(rows: list[dict[str, Any]]) -> dict[str, Any]:
    tracked = [r for r in rows if r["present"] and not r["lost"]]
    present = [r for r in rows if r["present"]]
    position = [r["position_mm"] for r in tracked]
    rotation = [r["rotation_deg"] for r in tracked]
    ms = [r["ms"] for r in rows]

    def percentile(values: list[float], q: float) -> float | None:
        return round(float(np.percentile(values, q)), 2) if values else None

    return {"frames": len(rows), "position_mm_median": percentile(position, 50), "position_mm_p95": percentile(position, 95),
            "rotation_deg_median": percentile(rotation, 50), "rotation_deg_p95": percentile(rotation, 95),
            "lost_fraction": round(sum(r["lost"] for r in present) / len(present), 3),
            "false_track_fraction": round(sum(r["false"] for r in rows) / len(rows), 3),
            "removed_reported_lost": round(sum(r["lost"] for r in rows if not r["present"])
                                           / max(1, sum(not r["present"] for r in rows)), 3),
            "ms_median": percentile(ms, 50), "ms_p95": percentile(ms, 95)}


def carry_over(result: dict[str, Any], measured: list[Candidate], previous_path: Path) -> None:
    """Add to `result` the candidates of the previous results file that this run could not measure (their
    library not importable), marked with the commit that measured them."""
    if not previous_path.exists():
        return
    previous = json.loads(previous_path.read_text())
    names = {c.name for c in measured}
    for name, figures in previous.get("summary", {}).items():
        if name in names:
            continue
        result["summary"][name] = {**figures, "carried_from": figures.get("carried_from", previous.get("commit"))}
        result["per_object"].update({k: v for k, v in previous.get("per_object", {}).items()
                                     if k.startswith(f"{name} / ")})
        result["rows"] += [r for r in previous.get("rows", []) if r["candidate"] == name]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--quick", action="store_true", help=f"only {', '.join(QUICK_OBJECTS)}; results not written")
    parser.add_argument("--json", action="store_true", help="write bench/results/tracking.json and end with one JSON line")
    parser.add_argument("--extra-path", help="a directory with open3d installed aside, appended to sys.path")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--output", type=Path, help="where --json writes (default: bench/results/tracking.json; --quick: nowhere)")
    args = parser.parse_args(argv)
    started = time.time()
    config = TrackingConfig()
    chosen, notes = candidates(args.extra_path)
    renderer = Renderer(config.image_size)
    objects = QUICK_OBJECTS if args.quick else OBJECTS
    sequences = []
    for index, object_id in enumerate(objects):
        sequences.append(make_sequence(renderer, object_id, index, args.seed))
        print(f"rendered {object_id}: {len(sequences[-1].frames)} frames, robot hides "
              f"{sequences[-1].occluded:.0%} of the object", file=sys.stderr, flush=True)
    render_s = time.time() - started
    rows: list[dict[str, Any]] = []
    for candidate in chosen:
        for sequence in sequences:
            rows += run(candidate, sequence, config)
    summary = {c.name: {"library": c.library, **summarise([r for r in rows if r["candidate"] == c.name])} for c in chosen}
    per_object = {f"{c.name} / {s.object_id}": summarise([r for r in rows if r["candidate"] == c.name
                                                          and r["object"] == s.object_id])
                  for c in chosen for s in sequences}
    commit = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True,
                            cwd=Path(__file__).resolve().parent).stdout.strip()
    result: dict[str, Any] = {"command": "python bench/tracking.py" + (" --quick" if args.quick else "") + " --json",
              "commit": commit, "machine": {"cpus": os.cpu_count(), "python": platform.python_version(),
                                            "processor": platform.processor() or platform.machine(),
                                            "load_avg_1m": round(os.getloadavg()[0], 2)},
              "date": time.strftime("%Y-%m-%d"), "notes": notes,
              "setup": {"objects": objects, "path_m": PATH_M, "steps": STEPS, "removed_frames": REMOVED,
                        "image_size": list(config.image_size), "cameras": 3, "start_error": list(START_ERROR),
                        "false_track": {"m": FALSE_M, "deg": FALSE_DEG},
                        "robot_hides": {s.object_id: round(s.occluded, 3) for s in sequences},
                        "symmetric": [s.object_id for s in sequences if s.symmetric_axis_O is not None],
                        "weakest_direction": {s.object_id: weakest_direction(s, config) for s in sequences},
                        "unobserved_ratio": config.unobserved_ratio},
              "summary": summary, "per_object": per_object, "render_s": round(render_s, 1),
              "total_s": round(time.time() - started, 1), "rows": rows}
    if args.json and not args.quick:
        carry_over(result, chosen, RESULTS / "tracking.json")
    for name, figures in result["summary"].items():
        print(f"{name:45s} {json.dumps(figures)}", file=sys.stderr)
    if args.json:
        output = args.output or (None if args.quick else RESULTS / "tracking.json")
        if output is not None:
            output.parent.mkdir(parents=True, exist_ok=True)
            output.write_text(json.dumps(result, indent=1) + "\n")
        print(json.dumps({"summary": summary, "total_s": result["total_s"]}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
