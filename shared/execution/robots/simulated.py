"""What the simulated robots (PyBullet's `sim/`, MuJoCo's `mujoco/`) share: how they see the object.

Each engine knows the object's true pose; a robot reports only what its tracker saw of it (`SimTracker`: late,
noisy, at a camera's rate), so the planner's side never reads the truth. `true_object_pose()` is the truth for
the evaluation's judge alone. An engine implements `_true_pose()` and `_joint_state()`; the rest is here.
"""
from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import TypeVar

import numpy as np

from shared.contracts.messages import ExecutionState, ObjectPose, ObjectTrack
from shared.execution.robot import Observation, Robot
from shared.execution.robots.sim.tracker import SimTracker, TrackerConfig
from shared.world.push_outcome import object_pose

SelfRobot = TypeVar("SelfRobot", bound="SimulatedRobot")


class SimulatedRobot(Robot):
    """A simulated arm + hand whose object is seen through a tracker (see the module docstring)."""

    _lock: threading.RLock  # the engine is not thread-safe: one caller at a time

    def _init_tracking(self, config: TrackerConfig) -> None:
        self.tracker = SimTracker(config)
        self.track: Callable[[ObjectTrack], None] | None = None  # gets each tracker frame while a plan runs
        self._tracked: ObjectPose | None = None  # the tracker's latest frame (what the robot reports)
        self._T_O_tracked = np.eye(4)  # the frame the tracker follows, in the object's frame O (TrueWorld)

    def _true_pose(self) -> np.ndarray | None:
        """The object's true pose in the world (None without an object): the engine's."""
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
        return Observation(time.time(), self.joint_names, positions, velocities, object_pose=self._seen())

    def _seen(self) -> ObjectPose | None:
        """The tracker's latest frame, held between frames (the first since the object was placed is taken
        now). Observing draws no noise of its own: the frames, and so a trial, repeat whoever observes how often."""
        with self._lock:
            if self._tracked is None:
                true = self._true_pose()
                if true is not None:
                    self._tracked = self.tracker.frame(true @ self._T_O_tracked)
            return self._tracked

    def true_object_pose(self) -> ObjectPose | None:
        """Where the object's frame O truly is in the world (None without an object): no tracker sees this."""
        true = self._true_pose()
        return None if true is None else object_pose(true)

    def _track_frame(self, plan_time_s: float, command_id: str | None) -> None:
        """One tracker frame: the pose it reports becomes the robot's, and goes to `track`."""
        true = self._true_pose()
        if true is None:
            return
        with self._lock:
            self._tracked = self.tracker.frame(true @ self._T_O_tracked)
        if self.track is not None:
            self.track(ObjectTrack(stamp=time.time(), pose=self._tracked, source=self.tracker.source,
                                   command_id=command_id, plan_time_s=plan_time_s))

    def _executing_state(self, command_id: str | None, plan_time_s: float) -> ExecutionState:
        positions, velocities = self._joint_state()
        return ExecutionState(stamp=time.time(), joint_names=list(self.joint_names), positions=positions,
                              velocities=velocities, object_pose=self._tracked, status="executing",
                              command_id=command_id, plan_time_s=plan_time_s)

    def time_scale(self, realtime_factor: float) -> float:
        return 1.0  # physics keeps the plan's timing whatever the factor: only the wall clock runs faster
