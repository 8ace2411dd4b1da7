"""The simulated robot: a PyBullet arm + hand (+ object, obstacles) that executes plans with physics.

It is the bridge's default robot and follows the contract of the devices (`robot.Robot`: connect /
observe / send / stop / recover / disconnect), one robot for the arm and hand together — they share
one physics world, stepped by one thread. `executor.Executor` runs commands on it behind the same
checks as on hardware (the bus bridge and the evaluation alike).

- Control: `shared.world.sim.plan_runner.ArmController`, the control law the planner's rollouts predict
  with (POSITION_CONTROL tracking the linearly interpolated trajectory, velocity feed-forward, URDF
  efforts as torque caps); its gain, latency and settling come from the robot's `PhysicsParams`,
  which a reset sets to the world's (an evaluation's drawn execution world, `shared.world.sim.world`).
- World: `reset_world(TrueWorld)` builds a fresh simulation with the object as it truly is, where it
  truly stands. The bus bridge knows only the world it is told (`reset_told`); the evaluation computes
  the truth it keeps from the planner (evaluation/local_system.py).
- Time: physics follows the trajectory's own times (a push at the planned speed, `time_scale` 1); the
  wall clock is paced `realtime_factor` times faster (a large factor runs as fast as the CPU allows).
  A device, by contrast, moves the time-scaled trajectory.
- State: published through `publish` (an ExecutionState with the plan time and the tracked object
  pose) every 1/`state_rate_hz` seconds of robot time; `observe()` (joints and object pose) is safe
  from any thread.
- The object is seen through a tracker, as a real bridge sees it (`simulated.py`): by default registered
  in depth frames rendered here with the arm and hand in view (`camera_tracker.py`), or "lost"; every
  pose the robot reports is the tracker's, each of its frames also goes to `track` (an ObjectTrack, for
  the bus). `true_object_pose()` is the truth, for the evaluation's judge.
- Collisions: robot contacts with the table, obstacles or (arm links) the object during a motion are
  recorded in `collisions` (hand-object contact is the push) and named in the report's message.
"""
from __future__ import annotations

import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from shared.contracts.messages import ObjectRef, Obstacle, SimWorld
from shared.execution.executor import StatePublisher
from shared.execution.limits import SafetyRefusal
from shared.execution.robot import ExecutionReport, JointTrajectory, MotionStopped
from shared.execution.robots.camera_tracker import CameraRig
from shared.execution.robots.sim.config import SimConfig, limits
from shared.execution.robots.simulated import SimulatedRobot
from shared.world.object_refs import load_object_ref
from shared.world.objects import ObjectLoadError, write_object_urdf
from shared.world.perception.depth import Intrinsics
from shared.world.push_outcome import pose_matrix
from shared.world.sim.camera import render_depth
from shared.world.sim.params import PhysicsParams
from shared.world.sim.plan_runner import ArmController, prepare_robot
from shared.world.sim.robot_scene import RobotScene
from shared.world.sim.world import MujocoDraw


@dataclass(frozen=True)
class TrueWorld:
    """What the simulated robot is reset to: the object as it truly is (its mass and centre of mass may
    differ from the model's), where it truly stands, the obstacles, and the physics the robot meets."""

    obj: ObjectRef
    T_world_O: np.ndarray  # the object's true pose
    obstacles: tuple[Obstacle, ...] = ()  # cylinders and walls on the table
    physics: PhysicsParams | None = None  # None: the robot's nominal physics (its config's)
    mass_scale: float = 1.0
    com_offset_m: tuple[float, float, float] = (0.0, 0.0, 0.0)  # in the object's frame O
    tracker_seed: int = 0  # the tracker's noise draws
    # Where the frame the tracker reports sits in the object's frame O (None: O itself). A model-based
    # tracker follows the model the system has: for a reconstruction from a camera cloud, its own frame
    # (centre of mass and principal axes of what was seen), which may be the true O turned 180 degrees.
    # The truth tracker reports this frame; the judge compares the image tracker's poses with it.
    T_O_tracked: np.ndarray | None = None
    # The MuJoCo world's own draw (level `mujoco`): read by the MuJoCo robot only, which then takes the object's
    # mass and centre of mass from it (None: its config's nominal world). PyBullet reads `physics`.
    mujoco: MujocoDraw | None = None
    # The model the system has and where it was told that model stands (the image tracker registers it from
    # there); None: the true object where it truly stands (all a bus bridge knows).
    told_object: tuple[ObjectRef, np.ndarray] | None = None
    rig: CameraRig | None = None  # the depth cameras the image tracker sees through (None: the default, calibrated)
    # Other objects standing beside it (clutter), each where it truly stands, with nominal physics: the robot must
    # leave them be (the judge reads where they end, `neighbour_poses`).
    neighbours: tuple[tuple[ObjectRef, np.ndarray], ...] = ()
    # The obstacles the system knows of (the image tracker leaves their points out); None: `obstacles`. They differ
    # when the system was told a neighbour as a cylinder: the world holds the neighbour, not a cylinder.
    known_obstacles: tuple[Obstacle, ...] | None = None

    @classmethod
    def told(cls, world: SimWorld) -> TrueWorld:
        """`world` taken as the truth: all a bus bridge knows."""
        return cls(world.object, pose_matrix(world.object_pose), tuple(world.obstacles))

    @property
    def known(self) -> tuple[Obstacle, ...]:
        return self.obstacles if self.known_obstacles is None else self.known_obstacles

    @property
    def tracked_model(self) -> tuple[ObjectRef, np.ndarray]:
        """The model the image tracker registers and the pose it starts from."""
        return self.told_object or (self.obj, np.asarray(self.T_world_O, dtype=np.float64))


class SimRobot(SimulatedRobot):
    """A simulated arm + hand on the table; add an object and obstacles after `connect()`."""

    name = "sim"
    streams_states = True

    def __init__(self, config: SimConfig, publish: StatePublisher | None = None):
        device_limits = limits(config.arm, config.hand)
        super().__init__(device_limits.joint_names, device_limits)
        self.config = config
        self.arm_name, self.hand_name = config.arm, config.hand
        self.T_world_base = config.T_world_base
        self.nominal_params = config.params  # the physics of a world reset without its own
        self.params = config.params
        self.state_rate_hz = config.state_rate_hz
        self.publish = publish
        self._init_tracking(config.tracker, config.tracking, config.image_tracking)
        self.scene: RobotScene | None = None
        self._lock = threading.RLock()  # PyBullet is not thread-safe: one caller at a time
        # Robot contacts with the table, obstacles (and arm-object) during the last send(): the first
        # time each (robot link, other) pair touched. Hand-object contact is the push, not a collision.
        self.collisions: dict[tuple[str, str], float] = {}

    # ------------------------------------------------------------------------------------ lifecycle

    @property
    def connected(self) -> bool:
        return self.scene is not None

    def connect(self) -> None:
        with self._lock:
            if self.scene is not None:
                return
            self.scene = RobotScene(self.arm_name, self.hand_name, T_world_base=self.T_world_base, params=self.params)
            prepare_robot(self.scene, self.params.hand_joint_damping)
            self.reset()

    def disconnect(self) -> None:
        with self._lock:
            if self.scene is not None:
                self.scene.close()
                self.scene = None

    def reset(self, q_arm: Sequence[float] | None = None, q_hand: Sequence[float] | None = None) -> None:
        """Teleport the robot (default: arm home, hand open) and hold it there."""
        scene = self._scene()
        arm = scene.arm.home.double().numpy() if q_arm is None else np.asarray(q_arm, dtype=np.float64)
        hand = (scene.hand.open_joint_positions.double().numpy() if q_hand is None
                else np.asarray(q_hand, dtype=np.float64))
        q = np.concatenate([arm, hand])
        with self._lock:
            scene.set_configuration(arm, hand)
            ArmController(scene, self.params, np.zeros(1), q[None]).command(q, np.zeros(len(q)))

    def reset_world(self, world: TrueWorld) -> None:
        """A fresh simulation in `world`: its physics, the robot at home with the hand open, the object as
        it truly is at its true pose, the obstacles. ObjectLoadError if the object cannot be loaded."""
        obj = load_object_ref(world.obj)
        urdf = write_object_urdf(obj, world.mass_scale, world.com_offset_m)
        with self._lock:
            self.disconnect()
            self.params = self.nominal_params if world.physics is None else world.physics
            self.connect()
        self.add_object(urdf, world.T_world_O)
        for ref, T_world_N in world.neighbours:
            with self._lock:
                self._scene().add_neighbour(write_object_urdf(load_object_ref(ref)), T_world_N)
        self.add_obstacles(world.obstacles)
        # The next observation is a frame of this world's object.
        self._reset_tracking(world.tracker_seed, world.T_O_tracked, world.tracked_model, world.rig, world.known)

    def reset_told(self, world: SimWorld) -> None:
        """Reset to the told `world` taken as the truth (the bus bridge's); SafetyRefusal("world") if its
        object cannot be loaded."""
        try:
            self.reset_world(TrueWorld.told(world))
        except ObjectLoadError as exc:
            raise SafetyRefusal("world", str(exc)) from None

    def add_object(self, urdf_path: str | Path, T_world_O: np.ndarray) -> None:
        """Place the object to push (URDF from `shared.world.objects.write_object_urdf`) with frame O at T_world_O."""
        scene = self._scene()
        with self._lock:
            scene.add_object(urdf_path, T_world_O)
            self._tracked, self._lost = None, None
            self._T_O_tracked = np.eye(4)  # tracked in its own frame, unless the world says otherwise (reset_world)

    def add_obstacles(self, obstacles: Sequence[Obstacle]) -> None:
        """Static cylinders and walls on the table."""
        scene = self._scene()
        with self._lock:
            scene.add_obstacles(obstacles)

    # ---------------------------------------------------------------------------------------- observe

    def _scene(self) -> RobotScene:
        self.require_connected()
        assert self.scene is not None  # require_connected
        return self.scene

    def _joint_state(self) -> tuple[np.ndarray, np.ndarray]:
        scene = self._scene()
        with self._lock:
            return scene.joint_state()

    def neighbour_poses(self) -> list[np.ndarray]:
        """Where each neighbour truly is now (T_world_O; the judge's, as `true_object_pose`)."""
        scene = self._scene()
        with self._lock:
            return [body.pose() for body in scene.neighbours]

    def _true_pose(self) -> np.ndarray | None:
        scene = self._scene()
        with self._lock:
            return None if scene.object is None else scene.object.pose()

    def _has_object(self) -> bool:
        return self.scene is not None and self.scene.object is not None

    def _step_held(self, duration_s: float) -> None:
        scene = self._scene()
        positions, _ = scene.joint_state()
        ArmController(scene, self.params, np.zeros(1), positions[None]).command(positions, np.zeros(len(positions)))
        for _ in range(round(duration_s / self.params.time_step_s)):
            scene.sim.step()

    def object_touches_obstacle(self) -> bool:
        with self._lock:
            return self.scene is not None and self.scene.object_touches_obstacle()

    def render_depth(self, cameras: Sequence[np.ndarray], intrinsics: Intrinsics,
                     windows: Sequence[tuple[slice, slice]] | None = None) -> list[tuple[np.ndarray, np.ndarray]]:
        """Per camera: ideal depth of the scene as it is now (TinyRenderer: the arm, hand, object and obstacles)
        and the robot's self-filter mask (the pixels its links cover); only each window is drawn."""
        scene = self._scene()
        with self._lock:
            drawn: Sequence[tuple[slice, slice] | None] = [None] * len(cameras) if windows is None else windows
            seen = [render_depth(scene.client, T_world_camera, intrinsics, window)
                    for T_world_camera, window in zip(cameras, drawn, strict=True)]
        return [(depth, bodies == scene.robot_id) for depth, bodies in seen]

    # ------------------------------------------------------------------------------------------ send

    def send(self, trajectory: JointTrajectory, stop: threading.Event | None = None, *, realtime_factor: float = 1.0,
             command_id: str | None = None) -> ExecutionReport:
        """Follow `trajectory` (physical times) with physics, the wall clock paced `realtime_factor` times
        faster; MotionStopped on stop() / `stop`. `command_id` stamps the published states."""
        if realtime_factor <= 0:
            raise ValueError(f"realtime_factor must be positive, got {realtime_factor}")
        own = self._prepare_send(trajectory, 1.0)
        scene = self._scene()
        controller = ArmController(scene, self.params, own.times_s, own.positions)
        publish_every = max(1, round(1.0 / (self.state_rate_hz * self.params.time_step_s)))
        track_every = self.steps_per_frame(self.params.time_step_s)
        wall_start = time.monotonic()
        self.collisions = {}
        self.tracker.forget()  # the latency is within a command: its first frame is the object as it is now
        self._track_frame(controller.time_of(0), command_id)
        for step in range(1, controller.step_count + 1):
            elapsed = step * self.params.time_step_s
            if self._stopped(stop):
                with self._lock:
                    controller.hold()
                raise MotionStopped(f"{self.name}: stopped {elapsed:.2f} s into a {own.duration_s:.2f} s trajectory")
            with self._lock:
                controller.step(step)
                for contact in scene.contacts(allow_hand_object=True):
                    self.collisions.setdefault((contact.robot_link, contact.other), elapsed)
            if step % track_every == 0:
                self._track_frame(controller.time_of(step), command_id)
            if self.publish is not None and step % publish_every == 0:
                self.publish(self._executing_state(command_id, controller.time_of(step)))
            ahead = elapsed / realtime_factor - (time.monotonic() - wall_start)
            if ahead > 0.0:
                time.sleep(ahead)
        self._reacquire(controller.time_of(controller.step_count), command_id)
        final = self.observe().positions
        error = float(np.max(np.abs(final - own.final)))
        message = f"final joint error {error:.4f} rad"
        if self.collisions:
            message += "; collisions: " + ", ".join(f"{link} vs {other} at t={t:.2f} s"
                                                    for (link, other), t in self.collisions.items())
        return ExecutionReport(self.name, True, final, own.final, time.monotonic() - wall_start, message,
                               samples=controller.step_count)
