"""What the simulated robots (PyBullet's `sim/`, MuJoCo's `mujoco/`) share: how they see the object.

Each engine knows the object's true pose; a robot reports only what its tracker saw of it, so the planner's side
never reads the truth. Two trackers:
- `image` (the default): `camera_tracker.CameraTracker`, the pose registered in depth frames the engine renders
  with the arm and hand in view, or "lost" (`ExecutionState.object_lost`) when registration fails; the engine's
  object pose is never read for it;
- `truth` (a named option, `SimTracker`): the true pose, late and with noise, at a camera's rate.
`true_object_pose()` is the truth for the evaluation's judge alone; `judge_frame`, when the evaluation sets it,
gets each tracked frame to compare with the truth (the tracker's error in a trial's record). An engine
implements `_true_pose()`, `_joint_state()` and `render_depth()`; the rest is here.
"""
from __future__ import annotations

import threading
import time
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, TypeVar

import numpy as np

from shared.contracts.messages import ExecutionState, ObjectPose, ObjectRef, ObjectTrack, Obstacle
from shared.execution.executor import StatePublisher
from shared.execution.robot import Observation, Robot
from shared.execution.robots import TRACKING_MODES, TrackingMode
from shared.execution.robots.camera_tracker import CameraRig, CameraTracker
from shared.execution.robots.sim.tracker import SimTracker, TrackerConfig
from shared.world.object_refs import load_object_ref
from shared.world.perception.depth import Intrinsics
from shared.world.perception.tracking import TrackingConfig
from shared.world.push_outcome import object_pose

if TYPE_CHECKING:  # sim/robot.py imports this module
    from shared.execution.robots.sim.robot import TrueWorld


SelfRobot = TypeVar("SelfRobot", bound="SimulatedRobot")
REACQUIRE_S = 1.0  # after a motion that ends with the object lost, how long the still robot's tracker keeps looking


class SimulatedRobot(Robot):
    """A simulated arm + hand whose object is seen through a tracker (see the module docstring)."""

    _lock: threading.RLock  # the engine is not thread-safe: one caller at a time
    publish: StatePublisher | None  # gets each state while a plan runs
    # Robot contacts with the table, obstacles (and arm-object) during the last send(): the first time each
    # (robot link, other) pair touched. Hand-object contact is the push, not a collision.
    collisions: dict[tuple[str, str], float]

    def _init_tracking(self, config: TrackerConfig, mode: TrackingMode = "image",
                       image: TrackingConfig = TrackingConfig()) -> None:
        if mode not in TRACKING_MODES:
            raise ValueError(f"unknown tracking {mode!r}; known: {', '.join(TRACKING_MODES)}")
        self.tracker = SimTracker(config)
        self.camera_tracker = CameraTracker(self.render_depth, image) if mode == "image" else None
        self.track: Callable[[ObjectTrack], None] | None = None  # gets each tracker frame while a plan runs
        # The evaluation's judge: each frame the tracker reported (None: lost) and its plan time, to compare with
        # the truth. Never set on the planner's side.
        self.judge_frame: Callable[[ObjectPose | None, float], None] | None = None
        self._tracked: ObjectPose | None = None  # the tracker's latest frame (what the robot reports)
        self._lost: str | None = None  # why the image tracker lost the object (None: tracked)
        self._fitness: float | None = None
        self._T_O_tracked = np.eye(4)  # the frame the tracker follows, in the object's frame O (TrueWorld)

    @property
    def tracking_rate_hz(self) -> float:
        return self.camera_tracker.config.rate_hz if self.camera_tracker is not None else self.tracker.config.rate_hz

    def _reset_tracking(self, seed: int, T_O_tracked: np.ndarray | None, told: tuple[ObjectRef, np.ndarray],
                        rig: CameraRig | None, obstacles: Sequence[Obstacle] = ()) -> None:
        """A new world: forget what was seen. `told`: the model the system has and where it was told the model
        stands (the image tracker registers that model from there); `rig`: the cameras (None: the default rig
        aimed at the told pose, calibrated); `obstacles`: the known ones, which the image tracker leaves out."""
        self.tracker.reset(seed)
        self._T_O_tracked = np.eye(4) if T_O_tracked is None else np.asarray(T_O_tracked, dtype=np.float64)
        if self.camera_tracker is not None:
            ref, T_told = told
            model = load_object_ref(ref).mesh
            self.camera_tracker.reset(model, T_told, rig or CameraRig.around(T_told, model), seed, obstacles)
        self._tracked, self._lost, self._fitness = None, None, None

    def render_depth(self, cameras: Sequence[np.ndarray], intrinsics: Intrinsics,
                     windows: Sequence[tuple[slice, slice]] | None = None) -> list[tuple[np.ndarray, np.ndarray]]:
        """Per camera (its OpenCV T_world_camera): ideal metric depth [H, W] (0: nothing) and the robot's
        self-filter mask, of at least the camera's window (rows, columns; None: the whole image): the engine's."""
        raise NotImplementedError

    def object_touches_obstacle(self) -> bool:
        """Whether the object touched an obstacle in the last physics step (the evaluation's judge): the engine's."""
        raise NotImplementedError

    def reset_world(self, world: TrueWorld) -> None:
        """A fresh world: the robot at home with the hand open, the object as it truly is where it truly stands."""
        raise NotImplementedError

    def _has_object(self) -> bool:
        """Whether an object stands in the engine's world (not where: that is the truth): the engine's."""
        raise NotImplementedError

    def let_object_settle(self, duration_s: float) -> None:
        """Run the physics `duration_s` with the robot held where it is, so an object put down where it cannot
        rest goes where it would (a ball whose drawn centre of mass is off its middle rolls away): the evaluation's,
        before its cameras look. The tracker's next frame is of the object where it came to rest."""
        with self._lock:
            self._step_held(duration_s)
            self._tracked, self._lost = None, None

    def _step_held(self, duration_s: float) -> None:
        """Physics for `duration_s`, the robot's joints commanded to stay where they are: the engine's."""
        raise NotImplementedError

    def _reacquire(self, plan_time_s: float, command_id: str | None) -> None:
        """After a motion that ended with the image tracker's object lost: the robot holds still and the tracker
        keeps looking, a frame at a time (its search widening while it finds nothing), for up to REACQUIRE_S of
        robot time, until a frame is tracked. A real perception stack does not stop when the arm does, and the
        moment a push ends (the hand still at the object, the object still moving) is when a frame is most often
        lost; a push must not end unjudged on that one frame. Nothing is invented: still lost, it says so."""
        if self.camera_tracker is None:
            return
        for _ in range(round(REACQUIRE_S * self.tracking_rate_hz)):
            with self._lock:
                if self._lost is None:
                    return
                self._step_held(1.0 / self.tracking_rate_hz)
            self._track_frame(plan_time_s, command_id)

    def _true_pose(self) -> np.ndarray | None:
        """The object's true pose in the world (None without an object): the engine's."""
        raise NotImplementedError

    def neighbour_poses(self) -> list[np.ndarray]:
        """Where the object's neighbours truly are (T_world_O each, in the world's order): the engine's."""
        raise NotImplementedError

    def _joint_state(self) -> tuple[np.ndarray, np.ndarray]:
        """(positions, velocities) of the robot's joints now: the engine's."""
        raise NotImplementedError

    def __enter__(self: SelfRobot) -> SelfRobot:
        self.connect()
        return self

    def __exit__(self, *exc: object) -> None:
        self.disconnect()

    def observe(self) -> Observation:
        positions, velocities = self._joint_state()
        seen = self._seen()
        return Observation(time.time(), self.joint_names, positions, velocities, object_pose=seen,
                           object_lost=self._lost if seen is None else None)

    def _seen(self) -> ObjectPose | None:
        """The tracker's latest frame, held between frames (the first since the object was placed is taken
        now). Observing draws no noise of its own: the frames, and so a trial, repeat whoever observes how often."""
        with self._lock:
            if self._tracked is None and self._lost is None:
                self._take_frame()
            return self._tracked

    def _take_frame(self) -> bool:
        """One tracker frame: the robot's reported pose (or loss) becomes the frame's; False without an object."""
        if self.camera_tracker is not None:
            if not self.camera_tracker.ready:
                if not self._has_object():
                    return False
                # An object placed without its model (add_object): nothing to register, so no pose, said plainly.
                self._tracked, self._lost = None, "the image tracker has no model of the object: reset the world with it"
                return True
            seen = self.camera_tracker.frame()
            pose = None if seen.T_world_O is None else object_pose(seen.T_world_O)
            self._tracked, self._lost, self._fitness = pose, seen.reason, seen.fitness
            return True
        true = self._true_pose()
        if true is None:
            return False
        self._tracked, self._lost = self.tracker.frame(true @ self._T_O_tracked), None
        return True

    def true_object_pose(self) -> ObjectPose | None:
        """Where the object's frame O truly is in the world (None without an object): no tracker sees this."""
        true = self._true_pose()
        return None if true is None else object_pose(true)

    def _track_frame(self, plan_time_s: float, command_id: str | None) -> None:
        """One tracker frame while a plan runs: the pose it reports (or its loss) becomes the robot's, goes to
        `track` (a pose only: a lost frame has none), and to the judge."""
        with self._lock:
            if not self._take_frame():
                return
            tracked = self._tracked
        if self.judge_frame is not None:
            self.judge_frame(tracked, plan_time_s)
        if self.track is not None and tracked is not None:
            source = self.tracker.source if self.camera_tracker is None else self.camera_tracker.source
            self.track(ObjectTrack(stamp=time.time(), pose=tracked, source=source, command_id=command_id,
                                   plan_time_s=plan_time_s, fitness=self._fitness))

    def steps_per_frame(self, time_step_s: float) -> int:
        """Physics steps between two tracker frames."""
        return max(1, round(1.0 / (self.tracking_rate_hz * time_step_s)))

    def true_tracked_pose(self) -> ObjectPose | None:
        """Where the frame the tracker reports truly is (the judge's reference for the tracker's error)."""
        true = self._true_pose()
        return None if true is None else object_pose(true @ self._T_O_tracked)

    def _executing_state(self, command_id: str | None, plan_time_s: float) -> ExecutionState:
        positions, velocities = self._joint_state()
        return ExecutionState(stamp=time.time(), joint_names=list(self.joint_names), positions=positions,
                              velocities=velocities, object_pose=self._tracked, object_lost=self._lost,
                              status="executing", command_id=command_id, plan_time_s=plan_time_s)

    def time_scale(self, realtime_factor: float) -> float:
        return 1.0  # physics keeps the plan's timing whatever the factor: only the wall clock runs faster
