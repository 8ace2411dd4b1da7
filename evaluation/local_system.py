"""The push pipeline's services in this process, for evaluation: same algorithms, no bus.

An evaluation runs thousands of push requests; each worker process holds its own pipeline wired to
in-process services — the sampler service's handler, the validator's arm rollout, and the robot
bridge's simulated robot behind its safety executor (`executor.Executor`, the same checks as on the
bus; the request's cancellation releases the command's lease) — so the measured behaviour is the
system's, without a router in the loop. The pose source is pluggable (`PoseSource`), which is how the
baselines that have no service of their own (the grasp-pose baseline) enter the same pipeline.

The simulated bridge here also watches the object against the obstacles while a plan runs (the
bus bridge reports robot contacts only); multi-step evaluation needs both. It executes in the
trial's execution world (`LocalRobot.execution_world`, `shared.world.sim.world`): physics and an object
pose the planner was not told. The simulated robot is always reset to the truth, and this module
computes it (`true_world`): the true object at its true pose, with the world's physics.

`gd2p eval --view` (one trial at a time, in this process) feeds a live view directly, without the bus:
`set_view(view)` before the system is built hands every push's `PushDecision` (shared/planning/decision_tap.py)
and every robot state to it.
"""
from __future__ import annotations

from collections.abc import Callable, Sequence
from concurrent.futures import Future
from dataclasses import dataclass, field, replace
from typing import Any, Protocol

import numpy as np

from shared.contracts.errors import ServiceError
from shared.contracts.messages import (
    ExecutionCommand,
    ExecutionState,
    ObjectPose,
    ObjectRef,
    Obstacle,
    Plan,
    PushDecision,
    SampleRequest,
    SampleResponse,
    SimWorld,
    ValidationJob,
)
from shared.execution.executor import EStopLatch, Executor, LocalLease
from shared.execution.robots import TrackingMode
from shared.execution.robots.camera_tracker import CameraRig
from shared.execution.robots.sim.config import SimConfig
from shared.execution.robots.sim.robot import SimRobot, TrueWorld
from shared.execution.robots.simulated import SimulatedRobot
from shared.frames import invert_transform
from shared.planning.cancellation import Cancellation
from shared.planning.decision_tap import DecisionTap
from shared.planning.monitor import PushMonitor
from shared.planning.outcome import Execution, PushError
from shared.planning.pipeline import PushPipeline, PushServices
from shared.planning.stages import PipelineSettings
from shared.sampling.server import SamplerService
from shared.validation.jobs import validate
from shared.world.push_outcome import object_pose, pose_matrix, rotation_between_deg
from shared.world.sim.world import ExecutionWorld


def engine_of(world: ExecutionWorld | None) -> str:
    """The physics engine a trial's world executes in: MuJoCo for the `mujoco` level, PyBullet otherwise (the
    planner's own engine: its rollouts always run in PyBullet)."""
    return "mujoco" if world is not None and world.level == "mujoco" else "pybullet"

REALTIME_FACTOR = 1000.0  # as the planner service asks of the simulated bridge: as fast as physics runs

PoseSource = Callable[[SampleRequest], SampleResponse]


class ViewSink(Protocol):
    """What the in-process system feeds a live view (visualisation.live.LiveView)."""

    def show_decision(self, decision: PushDecision) -> None: ...

    def show_state(self, state: ExecutionState) -> None: ...


_view: ViewSink | None = None


def set_view(view: ViewSink | None) -> ViewSink | None:
    """Feed `view` from the LocalSystems built from now on in this process (`gd2p eval --view`); the view fed
    before, so a caller can restore it."""
    global _view
    previous, _view = _view, view
    return previous


@dataclass
class TrackingErrors:
    """The tracker's error against the truth, frame by frame, per executed push (the judge's, for trial records)."""

    pushes: list[list[tuple[float, float] | None]] = field(default_factory=list)  # (m, deg) per frame; None: lost
    # Per push, at each lost frame: how far the object truly turned (deg) since the last frame the tracker saw.
    # A tracker that refuses a registration for turning too fast is wrong where the object truly did.
    lost_turns: list[list[float]] = field(default_factory=list)
    _last_seen: np.ndarray | None = field(default=None, init=False, repr=False)  # true orientation, last frame seen

    def start_push(self) -> None:
        self.pushes.append([])
        self.lost_turns.append([])

    def add(self, tracked: ObjectPose | None, truth: ObjectPose | None) -> None:
        if truth is None or not self.pushes:
            return
        T_true = pose_matrix(truth)
        if tracked is None:
            self.pushes[-1].append(None)
            if self._last_seen is not None:
                self.lost_turns[-1].append(rotation_between_deg(self._last_seen, T_true[:3, :3]))
            return
        T_seen = pose_matrix(tracked)
        self._last_seen = T_true[:3, :3]
        error_m = float(np.linalg.norm(T_seen[:3, 3] - T_true[:3, 3]))
        self.pushes[-1].append((error_m, rotation_between_deg(T_true[:3, :3], T_seen[:3, :3])))

    def summary(self) -> list[dict[str, float | int]]:
        """Per push: frames, lost frames, median and worst position (mm) and rotation (deg) error, and when frames
        were lost, the most the object truly turned since the tracker last saw it."""
        out: list[dict[str, float | int]] = []
        for frames, turns in zip(self.pushes, self.lost_turns, strict=True):
            seen = np.array([f for f in frames if f is not None]).reshape(-1, 2)
            row: dict[str, float | int] = {"frames": len(frames), "lost": len(frames) - len(seen)}
            if len(seen):
                row.update(median_mm=round(float(np.median(seen[:, 0])) * 1000, 2),
                           worst_mm=round(float(seen[:, 0].max()) * 1000, 2),
                           median_deg=round(float(np.median(seen[:, 1])), 2), worst_deg=round(float(seen[:, 1].max()), 2))
            if turns:
                row["lost_true_turn_deg"] = round(max(turns), 1)  # the most it truly turned while unseen
            out.append(row)
        return out


@dataclass
class Contacts:
    """What touched an obstacle during the executions since the last `reset()`."""

    robot_obstacle: set[str] = field(default_factory=set)  # robot link names that touched an obstacle or a wall
    object_obstacle: bool = False

    def reset(self) -> None:
        self.robot_obstacle.clear()
        self.object_obstacle = False

    @property
    def any(self) -> bool:
        return bool(self.robot_obstacle) or self.object_obstacle


def true_world(told: SimWorld, execution: ExecutionWorld | None,
               true_object: tuple[ObjectRef, np.ndarray] | None = None, rig: CameraRig | None = None) -> TrueWorld:
    """The world the simulated robot is reset to, from the world the planner was told: the object at its
    true pose — `true_object` (a reconstruction was planned on: the library object where it truly
    stands) or the told object moved by the execution world's pose error — with that world's physics,
    mass and centre of mass (None: the told world, nominal physics). When the planner was told a
    reconstruction, the tracker reports the reconstruction's frame O, rigidly attached to the true
    object where the capture placed it: later pushes of the request (corrections, the next push of a
    multi-step request) and the closed-loop monitor then see the model they plan around, not the
    library object's own frame, which may be the reconstruction's turned upside down. The image tracker
    registers the told model from the told pose, through `rig` (None: the default cameras)."""
    obstacles = tuple(told.obstacles)
    T_O_tracked = None
    if true_object is not None:
        obj, T_true = true_object
        # Through an ObjectPose, as the pose travelled when this was a SimWorld: committed results stay
        # reproducible to the last bit (a quaternion round trip moves the last digit now and then).
        T_world_O = pose_matrix(object_pose(T_true))
        if told.object.point_cloud is not None:  # the tracker follows the reconstruction, from where it was seen
            T_O_tracked = invert_transform(T_world_O) @ pose_matrix(told.object_pose)
    else:
        obj, T_world_O = told.object, pose_matrix(told.object_pose)
        if execution is not None:
            T_world_O = execution.pose_error.true_pose(T_world_O)
    told_object = (told.object, pose_matrix(told.object_pose))
    if execution is None:
        return TrueWorld(obj, T_world_O, obstacles, T_O_tracked=T_O_tracked, told_object=told_object, rig=rig)
    return TrueWorld(obj, T_world_O, obstacles, execution.physics, execution.mass_scale, execution.com_offset_m,
                     tracker_seed=execution.seed, T_O_tracked=T_O_tracked, mujoco=execution.mujoco,
                     told_object=told_object, rig=rig)


SETTLE_STEP_S = 0.1  # how often settle_true_object looks whether the object still moves
SETTLED_MM = 0.2  # moving less than this in a step, it rests (a resting object creeps by micrometres)


class LocalRobot:
    """Simulated robots (one per arm + hand) executing plans in this process, each behind an executor."""

    def __init__(self, tracking: TrackingMode = "image") -> None:
        self.tracking_mode = tracking  # how the robots see the object: rendered images, or the truth with noise
        self._executors: dict[tuple[str, str, str, TrackingMode], Executor] = {}
        self.contacts = Contacts()
        # The world a reset builds: the physics the robot meets and the object's true pose (None: the
        # planner's own world). Set per trial by the evaluation; the planner never sees it.
        self.execution_world: ExecutionWorld | None = None
        # The true object and its true pose (T_world_O), when the planner plans around something else (a
        # reconstruction from a camera cloud): a reset puts this object there. None: the planner's object.
        self.true_object: tuple[ObjectRef, np.ndarray] | None = None
        # The cameras the robot's image tracker sees through (set per trial: the capture's, with their drawn
        # calibration errors); None: the default rig, calibrated.
        self.rig: CameraRig | None = None
        # Other objects beside the true one (clutter), each where it truly stands: in every world a reset builds,
        # never told to the planner (a request may tell it where they are as obstacles). Set per trial.
        self.neighbours: tuple[tuple[ObjectRef, np.ndarray], ...] = ()
        # The obstacles truly standing, when they are not what the planner was told (a neighbour told as a cylinder
        # is a neighbour, not a cylinder); None: the told ones. Set per trial.
        self.true_obstacles: tuple[Obstacle, ...] | None = None
        self._watching: tuple[PushMonitor, LocalLease] | None = None  # the executing push's monitor, and its lease
        self.view: ViewSink | None = _view  # a live view shown every state (`gd2p eval --view`)
        self.tracking = TrackingErrors()  # the judge's comparison of every tracked frame with the truth

    def executor(self, arm: str, hand: str) -> Executor:
        """The executor of `arm` + `hand` in the engine of the trial's world (MuJoCo for a `mujoco` world, PyBullet
        otherwise), seeing the object as `tracking_mode` says; each built and connected on first use."""
        engine = engine_of(self.execution_world)
        key = (arm, hand, engine, self.tracking_mode)
        if key not in self._executors:
            robot = self._build_robot(arm, hand, engine)
            watch = robot.publish = lambda state, robot=robot: self._on_state(robot, state)
            robot.judge_frame = lambda pose, t, robot=robot: self.tracking.add(pose, robot.true_tracked_pose())
            robot.connect()
            # Nothing here engages the e-stop: only a protective stop could, and the simulated robot measures no effort.
            self._executors[key] = Executor(arm, hand, [robot], EStopLatch(), publish=watch)
        return self._executors[key]

    def _build_robot(self, arm: str, hand: str, engine: str) -> SimulatedRobot:
        if engine == "mujoco":
            from shared.execution.robots.mujoco.config import MujocoConfig
            from shared.execution.robots.mujoco.robot import MujocoRobot

            return MujocoRobot(MujocoConfig(arm, hand, tracking=self.tracking_mode))
        return SimRobot(SimConfig(arm, hand, tracking=self.tracking_mode))

    def robot(self, arm: str, hand: str) -> SimulatedRobot:
        robot = self.executor(arm, hand).robots[0]
        assert isinstance(robot, SimulatedRobot)  # what `executor` builds
        return robot

    def execute(self, plan: Plan, world: SimWorld | None, cancel: Cancellation | None = None,
                monitor: PushMonitor | None = None) -> Execution:
        """Run `plan` (in a fresh `world`, if given); a lost lease — the request cancelled, or `monitor`
        finding a reason to stop (closed loop) — stops it."""
        executor, robot = self.executor(plan.arm, plan.hand), self.robot(plan.arm, plan.hand)
        if world is not None:
            robot.reset_world(self._true_world(world, self.rig))
        self.tracking.start_push()
        lease = LocalLease()
        unregister = cancel.on_cancel(lambda: lease.release("the request was cancelled")) if cancel is not None else (lambda: None)
        self._watching = (monitor, lease) if monitor is not None else None
        try:
            command = ExecutionCommand(plan=plan, lease_token="local", realtime_factor=REALTIME_FACTOR)
            state: ExecutionState = executor.execute(command, lease)
        finally:
            unregister()
            self._watching = None
        self.contacts.robot_obstacle.update(link for link, other in robot.collisions
                                            if other.startswith(("obstacle", "wall")))
        return Execution(final=state)

    def settle_true_object(self, arm: str, hand: str, max_s: float, obstacles: Sequence[Obstacle] = ()) -> np.ndarray:
        """Put the trial's true object (`true_object`) down in its world with `arm` + `hand` at home, leave it until
        it rests (it moves less than SETTLED_MM in SETTLE_STEP_S) or `max_s` has passed, and make where it came to
        rest its true pose, among `obstacles` (its `neighbours` settle too, and stand where they came to rest);
        that pose (T_world_O). What the cameras then capture, the robot pushes and the judge
        measures from is where the object truly rests, not where it was put: a ball with a drawn centre of mass
        rolls off its spot, a box stays within a fraction of a millimetre."""
        if self.true_object is None:
            raise RuntimeError("no true object to settle: set LocalRobot.true_object first")
        ref, T_put = self.true_object
        robot = self.robot(arm, hand)
        told = SimWorld(object=ref, object_pose=object_pose(T_put), obstacles=list(obstacles))
        robot.reset_world(self._true_world(told, None))
        before = pose_matrix(self.true_object_pose(arm, hand))
        for _ in range(max(1, round(max_s / SETTLE_STEP_S))):
            robot.let_object_settle(SETTLE_STEP_S)
            now = pose_matrix(self.true_object_pose(arm, hand))
            moved = float(np.linalg.norm(now[:3, 3] - before[:3, 3]))
            before = now
            if moved < SETTLED_MM / 1000.0:
                break
        self.true_object = (ref, before)
        self.neighbours = tuple((n_ref, T) for (n_ref, _), T in zip(self.neighbours, robot.neighbour_poses(), strict=True))
        return before

    def _true_world(self, told: SimWorld, rig: CameraRig | None) -> TrueWorld:
        """`true_world` of the told world with this trial's neighbours and true obstacles."""
        world = true_world(told, self.execution_world, self.true_object, rig)
        obstacles = world.obstacles if self.true_obstacles is None else self.true_obstacles
        return replace(world, neighbours=self.neighbours, obstacles=obstacles, known_obstacles=tuple(told.obstacles))

    def true_neighbour_poses(self, arm: str, hand: str) -> list[np.ndarray]:
        """Where the neighbours truly are now (T_world_O each, as `neighbours` lists them)."""
        return self.robot(arm, hand).neighbour_poses()

    def true_object_pose(self, arm: str, hand: str) -> ObjectPose:
        """Where the object truly is now (what the evaluation judges; the planner sees the tracker's pose)."""
        pose = self.robot(arm, hand).true_object_pose()
        if pose is None:
            raise RuntimeError(f"the simulated {arm} + {hand} has no object")
        return pose

    def _on_state(self, robot: SimulatedRobot, state: ExecutionState) -> None:
        """Each state the robot publishes while it moves (on its thread): does the object touch an obstacle;
        closed loop, does the monitor stop the push?"""
        if self.view is not None:
            self.view.show_state(state)
        if not self.contacts.object_obstacle:
            self.contacts.object_obstacle = robot.object_touches_obstacle()
        if self._watching is not None:
            monitor, lease = self._watching
            reason = monitor.observe_state(state)
            if reason is not None:
                lease.release(f"closed loop: {reason}")

    def close(self) -> None:
        for executor in self._executors.values():
            for robot in executor.robots:
                robot.disconnect()
        self._executors.clear()


def validate_here(job: ValidationJob) -> Future:
    """The validator farm's job, run in this process before returning (the future is already done)."""
    future: Future = Future()
    try:
        future.set_result(validate(job))
    except ServiceError as exc:
        future.set_exception(exc)
    return future


def sampler_source(service: SamplerService) -> PoseSource:
    """The sampler service's handler as a pose source (service errors become PushErrors, as over the bus)."""

    def sample(request: SampleRequest) -> SampleResponse:
        try:
            return service.handle(request)
        except ServiceError as exc:
            raise PushError(exc.code, f"sampler: {exc}") from exc

    return sample


class LocalSystem:
    """A push pipeline per pose source, sharing one simulated robot."""

    def __init__(self, settings: PipelineSettings = PipelineSettings()):
        self.settings = settings
        self.robot = LocalRobot()
        self.sampler = SamplerService()
        self._pipelines: dict[str, PushPipeline] = {}

    def pipeline(self, source_name: str, source: PoseSource | None = None, **overrides: Any) -> PushPipeline:
        """The pipeline whose pose source is `source` (default: the sampler service), with the system's
        `PipelineSettings` but for `overrides` (any of its fields: ranking weights, monitor thresholds,
        physics budget), None values meaning "as the system's"."""
        settings = replace(self.settings, **{k: v for k, v in overrides.items() if v is not None})
        key = f"{source_name}/{settings}"
        if key not in self._pipelines:
            services = PushServices(sample=source or sampler_source(self.sampler), validate=validate_here,
                                    execute=self.robot.execute)
            if _view is not None:  # each push's decision to the live view, before the robot moves
                services = DecisionTap(services, _view.show_decision, keep=1).services()
            self._pipelines[key] = PushPipeline(services, settings)
        return self._pipelines[key]

    def close(self) -> None:
        for pipeline in self._pipelines.values():
            pipeline.close()
        self.robot.close()
        self.sampler.close()
