"""The paper's real-robot protocol, in simulation: methods × objects × directions × trials, with the arm.

Protocol (paper, "Experiment Protocol and Evaluation"): 14 test objects — 8 procedural objects
standing in for the 3D-printed set and 6 everyday-like objects, none of them trained on — 3
directions evenly spread around a circle, one of them the pull toward the robot (180°), 5 trials
per direction with the object placed again each time (a few mm and degrees of placement noise, as a
person re-placing it), a 0.20 m push planned and executed with the arm. A trial succeeds when the
object's centre ends within 0.03 m of the target, it turned ≤ 45° and did not topple
(`shared.world.push_outcome.judge_push`, from the object's true start); "–" marks a trial with no
kinematically feasible plan, counted as a failure. The hand keeping contact throughout is not
judged separately: a 0.20 m push that ends within 3 cm of its target has kept the object in front
of the hand.

The execution world (`--world`, `shared.world.sim.world`): each trial draws one from its own seed — the
same draw for every method, so methods face identical trials. Under `real` the robot executes in
physics the planner does not know (friction, mass, centre of mass, controller) and the object
stands where the planner was not told (±1 cm, ±5°); under `exact` it executes in the planner's world.
With `--cameras N` (1-3) the system is not told the object at all: it receives the point cloud N
simulated depth cameras capture of the object at its true pose (`shared.world.sim.camera`, seeded per
trial) and plans around its own reconstruction; the robot still executes on the true object.

Methods: every pose source runs through the same pipeline, (a) with the plans ranked by arm rollouts
and (b) as a random feasible choice (`PlannerOptions.choice`), so pose quality and ranking are measured
apart; the ranking ablation keeps every stage and rollout and drops only the ranking score:
- `gd2p`: K = 200 diffusion samples, ranked (V = α L_goal + β L_coll + γ L_dir);
- `gd2p-unranked`: the same stages and rollouts, the executed plan drawn at random among the rolled-out ones;
- `gd2p-random`: the same samples, a random feasible plan executed (no prescreen, no rollouts);
- `nearest`: the nearest training object's stored poses (BPS), a random feasible plan (as the paper);
- `nearest-ranked`: the same poses, ranked;
- `fixed`: the spatula pose behind the object (one pose: nothing to rank);
- `grasp`: grasp-only optimiser poses (`grasp_baseline.py`), a random feasible one of the best;
- `grasp-ranked`: the same poses, ranked.

Episodes run in spawn worker processes, each with its own in-process system (`local_system.py`);
every finished episode is recorded at once, so a killed run resumes where it stopped.
"""
from __future__ import annotations

import functools
import hashlib
import math
import multiprocessing as mp
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, astuple, dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial import ConvexHull
from tqdm import tqdm

from evaluation.report import CODE_AT_START
from evaluation.tasks import (
    CLUTTER_BEARINGS_DEG,
    CLUTTER_GAP_M,
    CLUTTER_PROPS,
    NEIGHBOUR_MOVED_M,
    POSE_TASK_TURN_DEG,
    TASKS,
    WALL_ANGLE_DEG,
    WALL_GAP_M,
    WALL_HEIGHT_M,
    WALL_LENGTH_M,
)
from shared.contracts.messages import (
    CircleObstacle,
    ExecutionResult,
    ObjectPose,
    ObjectRef,
    Plan,
    PlannerOptions,
    PushRequest,
    SimWorld,
    WallObstacle,
)
from shared.execution.robots import TRACKING_MODES, TrackingMode
from shared.execution.robots.camera_tracker import CameraRig
from shared.frames import direction_xy, make_transform, yaw_rotation
from shared.world.objects import UNSEEN_FAMILIES, ObjectLoadError, load_object, split_of
from shared.world.objects.catalog import list_object_ids, resolve_library_id
from shared.world.objects.final_split import final_index, is_final_id
from shared.world.objects.geometry import rolls
from shared.world.obstacles import cut_known_obstacles, distance_to_hull
from shared.world.push_outcome import (
    YawGoal,
    judge_push,
    object_pose,
    pose_matrix,
    resting_rotation,
    rollout_predicts_success,
    turn_observable,
)
from shared.world.sim.world import WORLD_LEVELS, ExecutionWorld, WorldLevel, sample_world
from shared.world.sim.world import half_extents as world_half_extents

PROCEDURAL_OBJECTS = ("proc-box-000", "proc-box-001", "proc-box-002", "proc-cylinder-000", "proc-cylinder-001",
                      "proc-ellipsoid-001", "proc-cone-000", "proc-hull-001")
EVERYDAY_OBJECTS = ("pb-duck", "pb-mug", "pb-teddy", "pb-jenga", "pb-toy-prism", "pb-toy-cylinder")
DIRECTIONS_DEG = (60.0, 180.0, 300.0)  # evenly spread; 180° pulls the object toward the robot
TRIALS = 5
PUSH_DISTANCE_M = 0.20
OBJECT_XY = (0.40, 0.0)  # in front of the robot, where both arms reach all three directions (pulls fail at 0.5 m)
PLACEMENT_NOISE_M = 0.01  # uniform in a ±1 cm square
PLACEMENT_NOISE_DEG = 5.0  # uniform yaw in ±5°
# The longest the object is left alone in its world after it is put down, waiting for it to rest before the
# cameras look (a ball off balance on its drawn centre of mass rocks for a while; what stands still stops at once).
SETTLE_S = 3.0
ROBOTS = {"allegro": "panda", "leap": "xarm7"}


METHODS_FILE = Path(__file__).resolve().parent / "methods.yaml"


@dataclass(frozen=True)
class Method:
    """An evaluation method (evaluation/methods.yaml): the planner options it asks for, and what it changes inside
    the planner for a comparison (physics budget, ranking weights, monitor thresholds, grasp poses)."""

    name: str
    label: str
    options: PlannerOptions
    # Ranking weights (alpha, beta, gamma) instead of the shipped ones: a candidate setting, compared on val objects.
    weights: tuple[float, float, float] | None = None
    # The closed-loop monitor's thresholds (position m, rotation deg, tilt deg) instead of the shipped ones.
    monitor: tuple[float, float, float] | None = None
    # The planner's physics budget (feasible poses prescreened, plans rolled out per round) instead of the shipped
    # one (`PipelineSettings`).
    budget: tuple[int, int] | None = None
    # Poses also tried slid sideways by these (m) near an obstacle instead of the shipped ones
    # (`PipelineSettings.slide_m`; an empty list: none).
    slide: tuple[float, ...] | None = None
    # Whether a push's arm paths reuse the ways around found for its earlier plans, instead of the shipped
    # `PipelineSettings.reuse_arm_paths`.
    reuse_paths: bool | None = None
    grasp: bool = False  # grasp poses (evaluation/grasp_baseline.py) in place of the sampler's
    tuning: bool = False  # a candidate compared on val objects: a full run leaves it out

    @property
    def source(self) -> str:
        """Where its poses come from: the planner's pose source, or "grasp"."""
        return "grasp" if self.grasp else self.options.method


class MethodsFileError(ValueError):
    """evaluation/methods.yaml names an unknown field or a value PlannerOptions refuses."""


def load_methods(path: Path = METHODS_FILE) -> dict[str, Method]:
    """The methods of `path`, by name, in the file's order; MethodsFileError naming the method and the problem."""
    import yaml
    from pydantic import ValidationError

    methods = {}
    for name, entry in (yaml.safe_load(path.read_text()) or {}).items():
        entry = dict(entry or {})
        try:
            options = PlannerOptions(**entry.pop("options", {}) or {})
            fields: dict[str, Any] = {key: tuple(value) if isinstance(value, list) else value
                                      for key, value in entry.items()}
            methods[name] = Method(name=name, options=options, **fields)
        except ValidationError as exc:
            problems = "; ".join(f"options.{'.'.join(str(p) for p in e['loc'])}: {e['msg']}" for e in exc.errors())
            raise MethodsFileError(f"{path.name}: method {name!r}: {problems}") from None
        except TypeError as exc:  # a key Method does not have
            raise MethodsFileError(f"{path.name}: method {name!r}: {exc}") from None
    return methods


METHODS: dict[str, Method] = load_methods()
# Candidate settings compared on val objects while tuning; a full run (no --methods) leaves them out.
TUNING_METHODS = frozenset(name for name, method in METHODS.items() if method.tuning)
DEFAULT_METHODS = tuple(m for m in METHODS if m not in TUNING_METHODS)


@dataclass(frozen=True)
class Episode:
    method: str
    hand: str
    object_id: str
    direction_deg: float
    trial: int
    world: WorldLevel = "real"
    cameras: int = 0  # 0: the system is told the mesh; 1-3: it receives a capture from that many cameras
    tracking: TrackingMode = "image"  # how the robot sees the object while it pushes: rendered images, or "truth"
    task: str = "paper"  # what the trial asks (TASKS); every task meets the same placements and worlds

    @property
    def key(self) -> str:
        key = f"{self.method}/{self.hand}/{self.object_id}/{self.direction_deg:g}/{self.trial}"
        return key if self.task == "paper" else f"{self.task}:{key}"

    @property
    def mirrored(self) -> bool:
        """Whether the trial asks its task's mirror case (pose: turn clockwise; wall: the wall on the other side;
        clutter: one neighbour, not two): on odd trials; on the final split (one trial per object) on odd trials of
        every other object in the split's order, so half its objects meet each case, and with the directions'
        turn of three (`object_directions`) every direction meets both."""
        shift = final_index(self.object_id) if is_final_id(self.object_id) else 0
        return (self.trial + shift) % 2 == 1

    @property
    def goal_turn_deg(self) -> float:
        """The pose task's turn: the goal yaw is the start's turned this far (counterclockwise, or clockwise when
        `mirrored`)."""
        return -POSE_TASK_TURN_DEG if self.mirrored else POSE_TASK_TURN_DEG

    @property
    def world_seed(self) -> int:
        """The execution world's seed: the same draw for every method, independent of the placement's."""
        digest = hashlib.sha256(f"{_seed_prefix(self.object_id)}world/{self.object_id}/{self.direction_deg:g}/{self.trial}".encode()).digest()
        return int.from_bytes(digest[:4], "little") & 0x7FFFFFFF

    @property
    def arm(self) -> str:
        return ROBOTS[self.hand]

    @property
    def seed(self) -> int:
        """The same placement and sampler seed for every method: methods face identical trials."""
        digest = hashlib.sha256(f"{_seed_prefix(self.object_id)}{self.object_id}/{self.direction_deg:g}/{self.trial}".encode()).digest()
        return int.from_bytes(digest[:4], "little") & 0x7FFFFFFF


FINAL_SEED_PREFIX = "gd2p-final-v1/"


def _seed_prefix(object_id: str) -> str:
    """The final split's placements and world draws come from seeds of their own (`FINAL_SEED_PREFIX`): never a
    development trial's draw. The development, val and unseen trials keep the seeds they always had."""
    return FINAL_SEED_PREFIX if is_final_id(object_id) else ""


def episodes(methods: Sequence[str], hand: str, objects: Sequence[str], directions: Sequence[float],
             trials: int, world: WorldLevel = "real", cameras: int = 0, split: str = "test",
             tracking: TrackingMode = "image", task: str = "paper") -> list[Episode]:
    """The trials of a protocol. Objects must be of `split`: "test" (the development split), "val" to tune,
    "unseen" (test objects of a family no model trains on), "final" (the final split, measured once per release
    by `evaluation/final_run.py` only); never train."""
    if split not in ("test", "val", "unseen", "final"):
        raise ValueError(f"evaluation runs on the development objects (test), the val objects (to tune), a never-trained "
                         f"family of the test split (unseen) or the final split (final), not {split!r}")
    for object_id in objects:
        object_split = split_of(object_id)
        if object_split != ("test" if split == "unseen" else split):
            raise ValueError(f"{object_id} is in the {object_split} split; this evaluation uses {split} objects only")
        if split == "unseen" and resolve_library_id(object_id).family not in UNSEEN_FAMILIES:
            raise ValueError(f"{object_id} is of the {resolve_library_id(object_id).family} family, which models train on; "
                             f"the unseen objects are of {', '.join(UNSEEN_FAMILIES)}")
    unknown = set(methods) - set(METHODS)
    if unknown:
        raise ValueError(f"unknown method(s) {sorted(unknown)}; known: {', '.join(METHODS)}")
    if world not in WORLD_LEVELS:
        raise ValueError(f"unknown world {world!r}; known: {', '.join(WORLD_LEVELS)}")
    if tracking not in TRACKING_MODES:
        raise ValueError(f"unknown tracking {tracking!r}; known: {', '.join(TRACKING_MODES)}")
    if task not in TASKS:
        raise ValueError(f"unknown task {task!r}; known: {', '.join(TASKS)}")
    return [Episode(m, hand, o, d, t, world, cameras, tracking, task) for m in methods for o in objects
            for d in object_directions(o, directions) for t in range(trials)]


def object_directions(object_id: str, directions: Sequence[float]) -> tuple[float, ...]:
    """The directions an object is pushed in: all of them, or on the final split one, rotating through them in the
    split's order (a third of its objects each). The final split spends its trials on more objects, not more
    directions: its intervals are clustered by object, so 72 objects once each say more than 24 three times,
    and an object meets the same direction in every task, so tasks still pair trial by trial."""
    if not is_final_id(object_id):
        return tuple(directions)
    return (directions[final_index(object_id) % len(directions)],)


def task_objects(task: str, objects: Sequence[str]) -> tuple[str, ...]:
    """The objects a task is measured on: for "pose", those whose turn about the vertical a camera can see as they
    rest (a body of revolution has no yaw to ask for: the planner refuses such a goal); all of them otherwise."""
    if task != "pose":
        return tuple(objects)
    models = {o: load_object(o) for o in objects}
    return tuple(o for o, obj in models.items() if turn_observable(obj.mesh, obj.default_pose.rotation[2]))


def camera_rig(episode: Episode, world: ExecutionWorld, T_start: np.ndarray) -> CameraRig:
    """The depth cameras the robot's image tracker sees the trial through: those that captured the object (told
    the mesh: the default three), aimed at where it rests (`T_start`) as for the capture, off their calibration
    by the world's drawn errors."""
    obj = load_object(episode.object_id)
    return CameraRig.around(T_start, obj.mesh, episode.cameras or 3, world.camera_errors)


def put_down(episode: Episode, world: ExecutionWorld) -> np.ndarray:
    """Where the object is truly put down for the trial (T_world_O): the told placement off by the world's pose
    error. It then settles in the world's physics (`LocalRobot.settle_true_object`, SETTLE_S) before anything
    looks at it; where it comes to rest is the trial's true start."""
    return world.pose_error.true_pose(placement(episode))


def task_obstacles(episode: Episode) -> list[WallObstacle]:
    """The obstacles of the episode's scene, in the world from the start (the object settles beside them): for the
    wall task a wall WALL_GAP_M from the object where it is truly put down, behind it at WALL_ANGLE_DEG to the push
    (turned counterclockwise from the push, clockwise on a mirrored trial), WALL_LENGTH_M long; for the corner
    task both of those walls, each cut where it meets the other, so the object stands in the corner they make
    behind it; none otherwise."""
    if episode.task not in ("wall", "corner"):
        return []
    T_put = put_down(episode, execution_world(episode))
    footprint = load_object(episode.object_id).mesh.vertices @ T_put[:3, :3].T[:, :2]
    thickness = WallObstacle.model_fields["thickness_m"].default
    turns = [-WALL_ANGLE_DEG if episode.mirrored else WALL_ANGLE_DEG]
    if episode.task == "corner":
        turns = [WALL_ANGLE_DEG, -WALL_ANGLE_DEG]
    # each wall: its outward direction from the object (behind the push) and how far its middle plane stands off
    toward = [direction_xy(episode.direction_deg + 3.0 * turn) for turn in turns]
    reach = [float(np.max(footprint @ n)) + WALL_GAP_M + thickness / 2.0 for n in toward]
    walls = []
    for k, (turn, n) in enumerate(zip(turns, toward, strict=True)):
        along = direction_xy(episode.direction_deg + turn)  # the wall's length
        middle = 0.0
        if len(turns) == 2:  # run from the corner (the other wall's far face) along this wall, past the object
            other = toward[1 - k]
            corner = (reach[1 - k] + thickness / 2.0) / float(other @ along)  # where along this wall the corner is
            middle = corner - np.sign(corner) * WALL_LENGTH_M / 2.0
        centre = T_put[:2, 3] + reach[k] * n + middle * along
        walls.append(WallObstacle(x=float(centre[0]), y=float(centre[1]), yaw_deg=float(episode.direction_deg + turn),
                                  length_m=WALL_LENGTH_M, height_m=WALL_HEIGHT_M))
    return walls


Neighbours = tuple[tuple[ObjectRef, np.ndarray], ...]  # each neighbour and where it truly stands (T_world_O)


def task_neighbours(episode: Episode) -> Neighbours:
    """The objects standing beside the one pushed: for the clutter task, one or two of CLUTTER_PROPS (drawn from
    the trial's seed) each CLUTTER_GAP_M from where the object is truly put down, at CLUTTER_BEARINGS_DEG from the
    push; none otherwise. Each is put down with the object and settles with it."""
    if episode.task != "clutter":
        return ()
    T_put = put_down(episode, execution_world(episode))
    footprint = ConvexHull(load_object(episode.object_id).mesh.vertices @ T_put[:3, :3].T[:, :2])
    rng = np.random.default_rng([episode.seed, 7])  # its own stream: the placement's draws stay as they were
    neighbours = []
    for bearing in CLUTTER_BEARINGS_DEG[int(episode.mirrored)]:
        prop = load_object(CLUTTER_PROPS[int(rng.integers(len(CLUTTER_PROPS)))])
        T_D_O = prop.T_D_O()
        radius = float(np.max(np.linalg.norm((prop.mesh.vertices @ T_D_O[:3, :3].T)[:, :2], axis=1)))
        toward = direction_xy(episode.direction_deg + bearing)
        clearance = float(rng.uniform(*CLUTTER_GAP_M)) + radius  # from the footprint to the neighbour's axis
        # Out along the bearing until the footprint's nearest point is that far (a box's corner may be nearest).
        low, high = 0.0, float(np.max(np.linalg.norm(footprint.points, axis=1))) + clearance
        for _ in range(40):
            middle = (low + high) / 2.0
            low, high = (middle, high) if distance_to_hull(footprint, middle * toward) < clearance else (low, middle)
        centre = T_put[:2, 3] + high * toward
        neighbours.append((ObjectRef(library_id=prop.id), make_transform(np.eye(3), np.array([*centre, 0.0])) @ T_D_O))
    return tuple(neighbours)


def neighbour_circles(neighbours: Neighbours) -> list[CircleObstacle]:
    """What the request tells of the neighbours where they stand: each a cylinder around it, as tall as it stands
    (what a user's perception gives), which nothing may touch."""
    circles = []
    for ref, T in neighbours:
        assert ref.library_id is not None  # the clutter props are library objects
        points = load_object(ref.library_id).mesh.vertices @ T[:3, :3].T + T[:3, 3]
        centre = points[:, :2].min(axis=0) / 2.0 + points[:, :2].max(axis=0) / 2.0
        circles.append(CircleObstacle(x=float(centre[0]), y=float(centre[1]), height_m=float(points[:, 2].max()),
                                      radius=float(np.max(np.linalg.norm(points[:, :2] - centre, axis=1)))))
    return circles


def placement(episode: Episode) -> np.ndarray:
    """T_world_O the system is told for the episode's trial: resting at the spot in front of the robot,
    re-placed with noise (the true pose differs by the execution world's pose error)."""
    rng = np.random.default_rng(episode.seed)
    dx, dy = rng.uniform(-PLACEMENT_NOISE_M, PLACEMENT_NOISE_M, 2)
    yaw = math.radians(rng.uniform(-PLACEMENT_NOISE_DEG, PLACEMENT_NOISE_DEG))
    obj = load_object(episode.object_id)
    return make_transform(yaw_rotation(yaw), np.array([OBJECT_XY[0] + dx, OBJECT_XY[1] + dy, 0.0])) @ obj.T_D_O()


def execution_world(episode: Episode) -> ExecutionWorld:
    """The world the episode's plan is executed in (drawn from `world_seed`)."""
    return sample_world(episode.world, episode.world_seed, half_extents(episode.object_id), cameras=episode.cameras)


def half_extents(object_id: str) -> np.ndarray:
    """The object's half extents along the axes of its frame O (what a centre-of-mass offset is drawn in)."""
    return world_half_extents(load_object(object_id).mesh.vertices)


def push_request(episode: Episode, T_start: np.ndarray, neighbours: Neighbours = ()) -> PushRequest:
    """What the system is asked: the object as told (mesh and the told pose), or as the cameras see it where it
    truly rests (`T_start`). The paper's task (and each shape task) asks for a push along the direction; the pose
    task for the point
    the push would reach from where the object truly rests (where a user wants it on the table) with the yaw
    the system sees it at turned `goal_turn_deg`. The obstacles: the task's walls, and its `neighbours` (where they
    truly rest) told as cylinders."""
    common = dict(distance_m=PUSH_DISTANCE_M, hand=episode.hand, arm=episode.arm, seed=episode.seed,
                  options=METHODS[episode.method].options,
                  obstacles=[*task_obstacles(episode), *neighbour_circles(neighbours)])
    told: dict[str, Any] = {"object": ObjectRef(library_id=episode.object_id), "object_pose": object_pose(placement(episode))}
    if episode.cameras:
        told = {"object": ObjectRef(point_cloud=captured_cloud(episode, T_start, neighbours))}
    if episode.task != "pose":  # the paper's push (the shape tasks ask it too)
        return PushRequest(direction_deg=episode.direction_deg, **told, **common)
    seen_yaw = _seen_yaw(told["object"], told.get("object_pose"))
    goal = _target(episode, T_start)
    return PushRequest(goal_xy=(float(goal[0]), float(goal[1])),
                       goal_yaw_deg=_wrapped(seen_yaw + episode.goal_turn_deg), **told, **common)


def _seen_yaw(ref: ObjectRef, told_pose: ObjectPose | None) -> float:
    """The yaw (PushRequest.goal_yaw_deg's convention) the system has the object at: its reconstruction's where
    the cloud shows it, or the told mesh's at the told pose."""
    from shared.world.object_refs import captured_object

    if ref.point_cloud is not None:
        try:
            captured = captured_object(ref)
        except ObjectLoadError as exc:  # the system's own refusal of such a cloud (the pipeline's), raised first
            from shared.planning.outcome import PushError

            raise PushError("bad_request", f"bad object: {exc}") from exc
        model, T = captured.model, captured.T_world_O
    else:
        assert told_pose is not None and ref.library_id is not None  # the evaluation tells library meshes with a pose
        model, T = load_object(ref.library_id), pose_matrix(told_pose)
    return _yaw_goal(model.resting_poses, T, 0.0).yaw_of(T[:3, :3])


def _yaw_goal(resting_poses: Sequence[Any], T_world_O: np.ndarray, yaw_deg: float) -> YawGoal:
    return YawGoal(yaw_deg, resting_rotation([pose.rotation for pose in resting_poses], T_world_O[:3, :3]))


def _wrapped(deg: float) -> float:
    return (deg + 180.0) % 360.0 - 180.0


def _target(episode: Episode, T_start: np.ndarray) -> np.ndarray:
    """Where every task wants the object: the push distance along the direction from where it truly started."""
    return T_start[:2, 3] + PUSH_DISTANCE_M * direction_xy(episode.direction_deg)


def captured_cloud(episode: Episode, T_start: np.ndarray, neighbours: Neighbours = ()) -> np.ndarray:
    """The cloud `episode.cameras` depth cameras capture of the object where it truly rests, `T_start` (seeded
    per trial), with the task's walls (left out of the cloud as known) and `neighbours` (in it) in view."""
    from shared.world.perception import cloud_for_request
    from shared.world.sim.camera import capture_object

    world = execution_world(episode)
    capture = capture_object(load_object(episode.object_id), T_start, n_cameras=episode.cameras, seed=episode.world_seed,
                             camera_errors=world.camera_errors, obstacles=task_obstacles(episode),
                             neighbours=[(load_object(ref.library_id).mesh, T) for ref, T in neighbours
                                         if ref.library_id is not None])
    return cloud_for_request(capture.cloud)


def replay_failure(episode: Episode, T_start: np.ndarray, request: PushRequest, plan: Plan) -> dict[str, bool]:
    """Why a plan its rollout predicted to succeed failed: the same plan executed again, in nominal physics,
    (a) on what the planner was told or saw, where it was told it stood ("planner_world": False means the
    rollout and the robot parted in the planner's own world) and (b) on the true object where it truly
    stood ("true_object": False means what the system was told or saw was off enough to fail the push;
    True leaves the execution world's physics - friction, mass, centre of mass, controller - as the cause)."""
    from shared.world.push_outcome import pose_matrix

    system = _system
    assert system is not None  # this worker's, set by _init_worker (the pool's initializer)
    robot = system.robot
    told = told_world(request)
    T_told = pose_matrix(told.object_pose)
    drawn, truth = robot.execution_world, robot.true_object
    try:
        robot.execution_world = robot.true_object = None
        robot.execute(plan, told)
        final = robot.true_object_pose(episode.arm, episode.hand)
        in_planner_world = judged_from(episode, T_told, final).success
        robot.true_object = truth
        robot.execute(plan, told)
        on_true_object = judged_from(episode, T_start, robot.true_object_pose(episode.arm, episode.hand)).success
    finally:
        robot.execution_world, robot.true_object = drawn, truth
    return {"planner_world": bool(in_planner_world), "true_object": bool(on_true_object)}


def told_world(request: PushRequest) -> SimWorld:
    """The world the planner was told or saw: the object as it read it where it was told it stood, with the
    request's obstacles. A captured cloud is read as the planner reads it, without the points on the known
    obstacles (walls, the neighbours told as cylinders): the neighbours' own points would join the object's
    cloud, or stand apart from it as a second object no reconstruction takes."""
    from shared.world.object_refs import captured_object

    if request.object.point_cloud is not None:
        seen = cut_known_obstacles(request).object
        return SimWorld(object=seen, object_pose=object_pose(captured_object(seen).T_world_O), obstacles=request.obstacles)
    assert request.object_pose is not None  # a told mesh comes with its pose
    return SimWorld(object=request.object, object_pose=request.object_pose, obstacles=request.obstacles)


def judged_from(episode: Episode, T_start: np.ndarray, final: ObjectPose) -> ExecutionResult:
    """The episode's push judged from where the object truly started, `T_start` (the told pose may be off): its
    target is the push distance along the direction from there; an object that rolls there is judged on its
    position alone (`judge_push`). The pose task's yaw goal is the true start's yaw turned `goal_turn_deg`."""
    yaw_goal = None
    if episode.task == "pose":
        obj = load_object(episode.object_id)
        start_yaw = _yaw_goal(obj.resting_poses, T_start, 0.0).yaw_of(T_start[:3, :3])
        yaw_goal = _yaw_goal(obj.resting_poses, T_start, _wrapped(start_yaw + episode.goal_turn_deg))
    return judge_push(T_start, _target(episode, T_start), final, yaw_goal=yaw_goal,
                      rolling=rolls_at(episode.object_id, T_start))


def neighbours_moved_m(start: Neighbours, now: Sequence[np.ndarray]) -> list[float]:
    """How far each neighbour's centre moved on the table since the trial's start (a toppled can's moves too)."""
    return [round(float(np.linalg.norm(T_now[:2, 3] - T[:2, 3])), 4) for (_, T), T_now in zip(start, now, strict=True)]


SMALL_MAX_M = 0.04  # an object no side of which is longer than this is small


def shape_of(object_id: str, T_world_O: np.ndarray) -> str:
    """The shape class a trial's object is reported under (docs/evaluation.md, "Shape classes"): "round" if it
    rolls where it rests, else "small" (no side over SMALL_MAX_M), else its resting class: tall / volumetric /
    flat (`shared.world.objects.geometry.shape_class`)."""
    obj = load_object(object_id)
    if rolls_at(object_id, T_world_O):
        return "round"
    return "small" if max(obj.info.size_m) <= SMALL_MAX_M else obj.info.shape_class


@functools.cache
def default_shape(object_id: str) -> str:
    """`shape_of` the object resting in its default pose."""
    return shape_of(object_id, load_object(object_id).T_D_O())


def shape_task_objects(task: str, split: str, count: int | None) -> tuple[str, ...]:
    """The objects of a shape-class task (evaluation.tasks.SHAPE_TASKS: its class's name): the first `count` (None:
    all) of the split's procedural and everyday objects whose default pose is of that class, taken in turn from
    each family (sorted ids within a family) so the families spread; on the development split the 14 objects every
    change was measured on are left out. ValueError when the split holds fewer (or, for all, none)."""
    if split == "final":
        from shared.world.objects.final_split import load_final_split

        ids = list(load_final_split())
    else:
        ids = [i for i in list_object_ids("test" if split == "unseen" else split)
               if resolve_library_id(i).source != "random_urdfs"
               and i not in PROCEDURAL_OBJECTS + EVERYDAY_OBJECTS]
    families: dict[str, list[str]] = {}
    for object_id in sorted(ids):
        families.setdefault(_family(object_id), []).append(object_id)
    chosen: list[str] = []
    for rank in range(max(map(len, families.values()), default=0)):
        for members in families.values():
            if rank < len(members) and default_shape(members[rank]) == task:
                chosen.append(members[rank])
                if len(chosen) == count:
                    return tuple(chosen)
    if count is None and chosen:
        return tuple(chosen)
    raise ValueError(f"the {split} split holds {len(chosen)} procedural or everyday objects of class {task!r}; "
                     f"the task needs {count}")


def _family(object_id: str) -> str:
    return object_id.rsplit("-", 1)[0] if is_final_id(object_id) else resolve_library_id(object_id).family


def rolls_at(object_id: str, T_world_O: np.ndarray) -> bool:
    """Whether the object rests at `T_world_O` in a way it rolls (`shared.world.objects.geometry.rolls`)."""
    return rolls(load_object(object_id).mesh, np.asarray(T_world_O, dtype=np.float64)[:3, :3])


# ------------------------------------------------------------------------------------------ workers

_system = None
_grasp = None


def _init_worker(grasp_cache: str) -> None:
    import torch

    torch.set_num_threads(1)
    global _system, _grasp
    from evaluation.grasp_baseline import GraspPoseSource
    from evaluation.local_system import LocalSystem

    _system = LocalSystem()
    _grasp = GraspPoseSource(grasp_cache)


def _ranking_weights(alpha: float, beta: float, gamma: float):  # the planner's type, imported in workers only
    from shared.planning.ranking import Weights

    return Weights(alpha, beta, gamma)


def _monitor_thresholds(position_m: float, rotation_deg: float, tilt_deg: float):  # as _ranking_weights
    from shared.planning.monitor import MonitorThresholds

    return MonitorThresholds(position_m, rotation_deg, tilt_deg)


def run_episode(episode: Episode) -> dict[str, Any]:
    """Plan and execute one trial; a record with the outcome ("infeasible" when no plan exists)."""
    from evaluation.local_system import TrackingErrors, engine_of
    from shared.planning.outcome import PushError

    system = _system
    assert system is not None  # this worker's, set by _init_worker (the pool's initializer)
    started = time.perf_counter()
    method = METHODS[episode.method]
    source = _grasp if method.source == "grasp" else None
    weights = None if method.weights is None else _ranking_weights(*method.weights)
    monitor = None if method.monitor is None else _monitor_thresholds(*method.monitor)
    prescreen, max_plans = method.budget or (None, None)
    pipeline = system.pipeline("grasp" if source is not None else "sampler", source, weights=weights, monitor=monitor,
                               prescreen=prescreen, max_plans=max_plans, slide_m=method.slide,
                               reuse_arm_paths=method.reuse_paths)
    world = execution_world(episode)
    system.robot.execution_world = world
    system.robot.tracking_mode = episode.tracking
    # The robot pushes the true object where it truly rests, whatever the system was told or saw.
    T_put = put_down(episode, world)
    system.robot.true_object = (ObjectRef(library_id=episode.object_id), T_put)
    system.robot.neighbours = task_neighbours(episode)
    system.robot.true_obstacles = tuple(task_obstacles(episode))  # the neighbours' cylinders are told, not there
    T_start = system.robot.settle_true_object(episode.arm, episode.hand, SETTLE_S, task_obstacles(episode))
    neighbours = system.robot.neighbours  # where they came to rest
    system.robot.rig = camera_rig(episode, world, T_start)
    system.robot.tracking = TrackingErrors()
    record: dict[str, Any] = {**asdict(episode), "seed": episode.seed, "world_draw": world.record(),
                              "engine": engine_of(world), "shape": shape_of(episode.object_id, T_start),
                              "settled_m": round(float(np.linalg.norm(T_start[:2, 3] - T_put[:2, 3])), 4)}
    system.robot.contacts.reset()
    try:
        request = push_request(episode, T_start, neighbours)  # with cameras: rendered once (seeded by the trial)
        response = pipeline.run(request).response
    except PushError as exc:
        record.update(outcome="infeasible" if exc.code == "infeasible" else "error", success=False,
                      error_code=exc.code, message=exc.message[:300],
                      tracker={"mode": system.robot.tracking_mode, "pushes": system.robot.tracking.summary()})
    except Exception as exc:  # a crash in one trial is recorded, not fatal to the evaluation
        record.update(outcome="error", success=False, error_code="internal", message=repr(exc)[:300])
    else:  # judged where the object truly is: the system only knows what its tracker saw
        result = judged_from(episode, T_start, system.robot.true_object_pose(episode.arm, episode.hand))
        touched = sorted(system.robot.contacts.robot_obstacle)  # the wall task: the robot must not touch the wall
        if touched:
            record["robot_touched_wall"] = touched
        moved = neighbours_moved_m(neighbours, system.robot.true_neighbour_poses(episode.arm, episode.hand))
        if moved:
            record["neighbours_moved_m"] = moved
        success = result.success and not touched and max(moved, default=0.0) <= NEIGHBOUR_MOVED_M
        record.update(outcome="success" if success else "failure", success=bool(success),
                      position_error_m=result.position_error_m, rotation_deg=result.rotation_deg,
                      toppled=result.toppled, timings_s={k: round(v, 3) for k, v in response.timings_s.items()})
        if result.yaw_error_deg is not None:  # the pose task: how far from the goal yaw it ended
            record["yaw_error_deg"] = round(result.yaw_error_deg, 2)
        record["tracker"] = {"mode": system.robot.tracking_mode, "pushes": system.robot.tracking.summary()}
        if response.score is not None:  # what the chosen plan's arm rollout predicted (ranking's L_goal)
            record["predicted_l_goal"] = round(response.score.l_goal, 4)
            if not result.success and len(response.steps) <= 1 and rollout_predicts_success(response.score.l_goal):
                record["replayed"] = replay_failure(episode, T_start, request, response.plan)
            if response.score.draws is not None:  # robust ranking: in how many rollout worlds it succeeded
                record["predicted_draws"] = [response.score.draws_succeeded, response.score.draws]
        if response.notes:  # e.g. why a correction the request allowed was not made, or a push was stopped
            record["notes"] = [note[:200] for note in response.notes]
        if len(response.steps) > 1:  # corrective pushes: how many, and how far the first push left it
            record["pushes"] = len(response.steps)
            record["first_push_error_m"] = round(response.steps[0].result.position_error_m, 4)
        stopped = [i for i, step in enumerate(response.steps) if step.stopped]
        if stopped:  # closed loop: which pushes the monitor stopped
            record["stopped_pushes"] = stopped
    record["seconds"] = round(time.perf_counter() - started, 2)
    record["code"] = CODE_AT_START  # the commit this trial ran (a run may be resumed by later code)
    record["ranking_weights"] = list(astuple(pipeline.settings.weights))
    if method.options.closed_loop:
        record["monitor"] = list(astuple(pipeline.settings.monitor))
    record["sampler"] = method.options.sampler if method.source == "gd2p" else None
    record["pose_model"] = _pose_model(episode.hand, method.source)
    record["critic"] = method.options.critic and method.source in ("gd2p", "nearest") and _has_critic(episode.hand)
    if record["critic"]:  # which critic ordered the poses (the sampler loads it from the same path)
        record["critic_id"] = _critic_id(episode.hand)
    settings = pipeline.settings
    record["budget"] = [settings.prescreen if method.options.prescreen else 0, settings.max_plans]
    if settings.slide_m:  # the slides its poses were also tried at near an obstacle (off in older records)
        record["slide_m"] = list(settings.slide_m)
    record["reuse_arm_paths"] = settings.reuse_arm_paths  # (absent in older records: every path by RRTConnect)
    return record


def pose_model_ids(hand: str) -> dict[str, str | float | None]:
    """The ids of the diffusion checkpoint and NN index the sampler loads for `hand` (the shipped ones or the
    $GD2P_SAMPLER_* overrides the workers inherit); None for a missing file. A sampling temperature other
    than 1 is named too (only then, so that stores made before it existed still resume)."""
    from shared.sampling.checkpoint import checkpoint_id, default_checkpoint_path
    from shared.sampling.diffusion import default_noise_scale
    from shared.sampling.nearest_neighbor import default_nn_index_path

    ids: dict[str, str | float | None] = {
        kind: checkpoint_id(path) if path.is_file() else None
        for kind, path in (("diffusion", default_checkpoint_path(hand)), ("nearest", default_nn_index_path(hand)))}
    if (noise_scale := default_noise_scale()) != 1.0:
        ids["diffusion_noise_scale"] = noise_scale
    return ids


def _pose_model(hand: str, source: str) -> str | None:
    """The weights (diffusion checkpoint) or index (Nearest Neighbor) the trial's poses came from."""
    system = _system  # this worker's, set by _init_worker (the pool's initializer) for the sources that use it
    if source == "gd2p":
        from shared.sampling.diffusion import default_noise_scale

        assert system is not None
        noise_scale = default_noise_scale()  # the temperature the sampler service gives the planner's requests
        temperature = "" if noise_scale == 1.0 else f"@noise{noise_scale:g}"
        return f"{hand}:{system.sampler.sampler(hand).checkpoint_id}{temperature}"
    if source == "nearest":
        assert system is not None
        return f"{hand}:{system.sampler.nearest(hand).index_id}"
    return None


def _has_critic(hand: str) -> bool:
    """Whether the sampler scores its samples with a success critic for `hand` (the planner then orders by it)."""
    system = _system
    assert system is not None  # this worker's, set by _init_worker (the pool's initializer)
    sampler = system.sampler
    return sampler.critic(hand, sampler.sampler(hand)) is not None


def _critic_id(hand: str) -> str | None:
    from shared.sampling.checkpoint import checkpoint_id
    from shared.sampling.critic_train import default_critic_path

    path = default_critic_path(hand)
    return checkpoint_id(path) if path is not None and path.is_file() else None


def _keyed(job: tuple[Callable[[Any], dict[str, Any]], Any]) -> tuple[str, dict[str, Any]]:
    work, item = job
    return item.key, work(item)


def run_in_workers(items: Sequence[Any], work: Callable[[Any], dict[str, Any]], store, workers: int,
                   grasp_cache: Path, label: str, initializer: Callable[[str], None] | None = None) -> None:
    """`work(item)` for every item (each with a `.key`) over `workers` spawn processes, each record
    stored as soon as it arrives (resumable); a progress bar shows the live success rate. `initializer`
    (a module-level function of the grasp cache path) replaces `_init_worker` (the final split's opens its access)."""
    initializer = initializer or _init_worker
    if not items:
        return
    grasp_cache.mkdir(parents=True, exist_ok=True)
    jobs = [(work, item) for item in items]
    with tqdm(total=len(items), desc=label, unit="trial") as bar:
        if workers <= 1:
            initializer(str(grasp_cache))
            _consume(map(_keyed, jobs), store, bar)
            return
        context = mp.get_context("spawn")
        with context.Pool(workers, initializer=initializer, initargs=(str(grasp_cache),)) as pool:
            _consume(pool.imap_unordered(_keyed, jobs), store, bar)


def _consume(results, store, bar) -> None:
    done = successes = 0
    for key, record in results:
        store.add(key, record)
        done += 1
        successes += int(record["success"])
        bar.set_postfix(success=f"{successes / done:.0%}", last=f"{record['object_id']}:{record['outcome']}")
        bar.update()
