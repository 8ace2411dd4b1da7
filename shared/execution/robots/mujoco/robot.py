"""The MuJoCo arm + hand: a second physics engine behind the robot contract, beside the PyBullet `sim/`.

The same contract and the same world description as the PyBullet robot (`sim.robot.SimRobot`), so the
executor, the evaluation and the bridge can run a plan on either: `connect`, `observe`, `send` a
`JointTrajectory`, `stop`, `recover`, `disconnect`; `reset_world(TrueWorld)` / `reset_told(SimWorld)`.

- Model (`model.py`): the project's combined arm + hand URDF, the table, the object as convex pieces
  of its mesh (`decompose.py`), obstacles; MuJoCo's own soft contacts (config.ContactConfig, chosen by
  `bench/mujoco_contact.py`).
- Control: one position servo per joint tracks the linearly interpolated trajectory with velocity
  feed-forward (force = kp (q_ref - q) + kv (qd_ref - qd), capped at the URDF effort, gravity
  compensated), then holds the final waypoint `settle_s`. Physics follows the trajectory's own times; the
  wall clock is paced `realtime_factor` times faster (`time_scale` is 1, as for the PyBullet robot).
- The object is seen only through a tracker (`simulated.py`): by default registered in depth frames this
  engine renders with the arm and hand in view (`camera_tracker.py`), or "lost"; the truth-plus-noise
  tracker is a named option. `true_object_pose()` is the truth, for the evaluation's judge only.
- The world: a `TrueWorld` with a `mujoco` draw (`shared.world.sim.world.MujocoDraw`, world level
  `mujoco`) sets this engine's own physics: every geom's friction (table, object, each finger's), the
  servos' gains, the fingers' stiffness and damping, the command latency and the object's mass and
  centre of mass (`MujocoConfig.drawn`); without one the config's nominal world. The PyBullet
  `PhysicsParams` of a `TrueWorld` are PyBullet's and are not read here.
- Command latency: each servo command takes effect `command_latency_s` after it is computed (a delay
  line of whole physics steps); until the first arrives the servos hold what they held.
- Depth cameras: `render_depth(cameras, intrinsics)` renders the world as it stands, robot included,
  with each pixel's robot mask (`cameras.py`).
- Collisions: robot contacts with the table, obstacles or (arm links) the object during a motion are
  recorded in `collisions` and named in the report's message, as the PyBullet robot's.
"""
from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Sequence

import mujoco
import numpy as np

from shared.contracts.messages import Obstacle, SimWorld
from shared.execution.executor import StatePublisher
from shared.execution.limits import SafetyRefusal
from shared.execution.robot import ExecutionReport, JointTrajectory, MotionStopped
from shared.execution.robots.camera_tracker import CameraRig
from shared.execution.robots.mujoco.cameras import RendererSlot, render_depth
from shared.execution.robots.mujoco.config import MujocoConfig
from shared.execution.robots.mujoco.decompose import DecompositionError
from shared.execution.robots.mujoco.model import OBJECT_BODY, ModelError, PlacedObject, build_model, neighbour_body
from shared.execution.robots.sim.config import limits
from shared.execution.robots.sim.robot import TrueWorld
from shared.execution.robots.simulated import SimulatedRobot
from shared.robots.arms import load_arm
from shared.robots.hands import load_hand
from shared.world.object_refs import load_object_ref
from shared.world.objects import ObjectLoadError
from shared.world.objects.model import ObjectModel
from shared.world.perception.depth import Intrinsics
from shared.world.sim.camera import CameraPose


class MujocoRobot(SimulatedRobot):
    """A MuJoCo arm + hand on the table; `reset_world` (or `add_object`) places the object."""

    name = "mujoco"
    streams_states = True

    def __init__(self, config: MujocoConfig, publish: StatePublisher | None = None):
        device_limits = limits(config.arm, config.hand)
        super().__init__(device_limits.joint_names, device_limits)
        self.config = config
        self.world_config = config  # the config of the current world: `config` itself, or drawn from a TrueWorld's
        self.arm_name, self.hand_name = config.arm, config.hand
        self.T_world_base = config.T_world_base
        self.state_rate_hz = config.state_rate_hz
        self.publish = publish
        self._init_tracking(config.tracker, config.tracking, config.image_tracking)
        self.model: mujoco.MjModel | None = None
        self.data: mujoco.MjData | None = None
        self._placed: PlacedObject | None = None
        self._obstacles: tuple[Obstacle, ...] = ()
        self._neighbours: tuple[PlacedObject, ...] = ()
        self._lock = threading.RLock()  # one stepping caller at a time
        self._renderers = RendererSlot()  # taken before `_lock` when both are
        self.collisions: dict[tuple[str, str], float] = {}

    # ------------------------------------------------------------------------------------ lifecycle

    @property
    def connected(self) -> bool:
        return self.data is not None

    def connect(self) -> None:
        with self._lock:
            if self.data is None:
                self._build(None)

    def disconnect(self) -> None:
        with self._renderers.lock:
            self._renderers.close()
        with self._lock:
            self.model, self.data = None, None

    def _build(self, q: np.ndarray | None) -> None:
        """(Re)compile the world with the current object and obstacles; the robot at `q` (None: home)."""
        model = build_model(self.world_config, self._placed, self._obstacles, self._neighbours)
        data = mujoco.MjData(model)
        self._index(model)
        self.model, self.data = model, data
        if q is None:
            self.reset()
        else:
            self._teleport(q)

    def _index(self, model: mujoco.MjModel) -> None:
        joints = [model.joint(name) for name in self.joint_names]
        self._qpos = np.array([model.jnt_qposadr[j.id] for j in joints])
        self._qvel = np.array([model.jnt_dofadr[j.id] for j in joints])
        self._actuators = np.array([model.actuator(name).id for name in self.joint_names])
        self._ff = np.array([-model.actuator_biasprm[a, 2] / model.actuator_gainprm[a, 0] for a in self._actuators])
        self._object_body = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, OBJECT_BODY)
        self._neighbour_bodies = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, neighbour_body(k))
                                  for k in range(len(self._neighbours))]
        last_arm = model.joint(load_arm(self.arm_name).joint_names[-1]).id
        hand_root = int(model.jnt_bodyid[last_arm])  # the flange and the hand: rigid with the last arm joint
        self._body_name = {b: model.body(b).name for b in range(model.nbody)}
        self._robot_bodies = {b for b in range(1, model.nbody) if b != self._object_body} - set(self._neighbour_bodies)
        self._hand_bodies = {b for b in self._robot_bodies if _descends_from(model, b, hand_root)}

    def reset(self, q_arm: Sequence[float] | None = None, q_hand: Sequence[float] | None = None) -> None:
        """Teleport the robot (default: arm home, hand open) and hold it there."""
        arm = (load_arm(self.arm_name).home.double().numpy() if q_arm is None
               else np.asarray(q_arm, dtype=np.float64))
        hand = (load_hand(self.hand_name).open_joint_positions.double().numpy() if q_hand is None
                else np.asarray(q_hand, dtype=np.float64))
        self._teleport(np.concatenate([arm, hand]))

    def _teleport(self, q: np.ndarray) -> None:
        model, data = self._world()
        with self._lock:
            data.qpos[self._qpos] = q
            data.qvel[self._qvel] = 0.0
            data.ctrl[self._actuators] = q
            mujoco.mj_forward(model, data)

    def reset_world(self, world: TrueWorld) -> None:
        """A fresh world: the robot at home with the hand open, the object as it truly is at its true pose,
        the obstacles, the physics of its `mujoco` draw (none: the config's). ObjectLoadError /
        DecompositionError / ModelError if the object cannot be placed or the draw does not fit the hand."""
        obj = load_object_ref(world.obj)
        draw = world.mujoco
        mass_scale, com = (world.mass_scale, world.com_offset_m) if draw is None else (draw.mass_scale, draw.com_offset_m)
        placed = PlacedObject(obj, np.asarray(world.T_world_O, dtype=np.float64), mass_scale, com)
        with self._lock:
            self._placed, self._obstacles = placed, tuple(world.obstacles)
            self._neighbours = tuple(PlacedObject(load_object_ref(ref), np.asarray(T, dtype=np.float64))
                                     for ref, T in world.neighbours)
            self.world_config = self.config if draw is None else self.config.drawn(draw)
            self._build(None)
        self._reset_tracking(world.tracker_seed, world.T_O_tracked, world.tracked_model, world.rig, world.known)

    def reset_told(self, world: SimWorld) -> None:
        """Reset to the told `world` taken as the truth (the bus bridge's); SafetyRefusal("world") if its
        object cannot be loaded or decomposed."""
        try:
            self.reset_world(TrueWorld.told(world))
        except (ObjectLoadError, DecompositionError, ModelError) as exc:
            raise SafetyRefusal("world", str(exc)) from None

    def add_object(self, obj: ObjectModel, T_world_O: np.ndarray) -> None:
        """Place `obj` with its frame O at T_world_O (the robot stays where it is)."""
        with self._lock:
            q = self.observe().positions
            self._placed = PlacedObject(obj, np.asarray(T_world_O, dtype=np.float64))
            self._build(q)
            self._tracked, self._lost = None, None
            self._T_O_tracked = np.eye(4)
            if self.camera_tracker is not None:  # the model is at hand: the cameras track it from where it stands
                self.camera_tracker.reset(obj.mesh, T_world_O, CameraRig.around(T_world_O, obj.mesh), 0)

    def add_obstacles(self, obstacles: Sequence[Obstacle]) -> None:
        """Static cylinders and walls on the table."""
        with self._lock:
            q = self.observe().positions
            self._obstacles = (*self._obstacles, *obstacles)
            self._build(q)

    # ---------------------------------------------------------------------------------------- observe

    def _world(self) -> tuple[mujoco.MjModel, mujoco.MjData]:
        self.require_connected()
        assert self.model is not None and self.data is not None  # require_connected
        return self.model, self.data

    def _joint_state(self) -> tuple[np.ndarray, np.ndarray]:
        _, data = self._world()
        with self._lock:
            return data.qpos[self._qpos].copy(), data.qvel[self._qvel].copy()

    def _has_object(self) -> bool:
        return self._placed is not None

    def _step_held(self, duration_s: float) -> None:
        model, data = self._world()
        data.ctrl[self._actuators] = data.qpos[self._qpos]
        for _ in range(round(duration_s / float(model.opt.timestep))):
            mujoco.mj_step(model, data)

    def object_touches_obstacle(self) -> bool:
        model, data = self._world()
        if self._object_body < 0:
            return False
        with self._lock:
            for contact in data.contact[: data.ncon]:
                bodies = {int(model.geom_bodyid[contact.geom1]), int(model.geom_bodyid[contact.geom2])}
                if self._object_body in bodies:
                    names = (model.geom(contact.geom1).name, model.geom(contact.geom2).name)
                    if any(name.startswith("obstacle") for name in names):
                        return True
        return False

    def _true_pose(self) -> np.ndarray | None:
        if self._object_body < 0:
            return None
        return self._body_pose(self._object_body)

    def neighbour_poses(self) -> list[np.ndarray]:
        """Where each neighbour truly is now (T_world_O; the judge's, as `true_object_pose`)."""
        return [self._body_pose(body) for body in self._neighbour_bodies]

    def _body_pose(self, body: int) -> np.ndarray:
        _, data = self._world()
        with self._lock:
            T = np.eye(4)
            T[:3, :3] = data.xmat[body].reshape(3, 3)
            T[:3, 3] = data.xpos[body]
            return T

    def _record_contacts(self, elapsed: float) -> None:
        """Robot contacts besides the push (hand vs object) and the flange's own table: the first time each."""
        model, data = self._world()
        for contact in data.contact[: data.ncon]:
            b1, b2 = int(model.geom_bodyid[contact.geom1]), int(model.geom_bodyid[contact.geom2])
            for robot_body, geom in ((b1, contact.geom2), (b2, contact.geom1)):
                if robot_body not in self._robot_bodies:
                    continue
                other_body = int(model.geom_bodyid[geom])
                if other_body == self._object_body:
                    if robot_body in self._hand_bodies:
                        continue  # the push
                    other = "object"
                elif other_body == 0:
                    other = model.geom(geom).name or "world"
                elif other_body in self._neighbour_bodies:
                    other = self._body_name[other_body]
                else:
                    continue  # robot vs robot is not modelled
                self.collisions.setdefault((self._body_name[robot_body], other), elapsed)

    # ---------------------------------------------------------------------------------------- cameras

    def render_depth(self, cameras: Sequence[CameraPose | np.ndarray], intrinsics: Intrinsics,
                     windows: Sequence[tuple[slice, slice]] | None = None) -> list[tuple[np.ndarray, np.ndarray]]:
        """Per camera (a CameraPose, or an OpenCV T_world_camera 4x4): ideal metric depth [H, W] along the
        optical axis, 0 where nothing is seen, and the robot mask [H, W] (pixels on a robot link), of the
        world as it stands now (`cameras.py`; RenderUnavailable without a usable OpenGL platform). The whole
        image is drawn whatever `windows` asks (MuJoCo's renderer costs ~7 ms per 424 x 240 camera)."""
        with self._renderers.lock:
            while True:
                model, _ = self._world()
                renderer = self._renderers.get(model, intrinsics)  # may take 0.1-0.3 s: not under `_lock`
                with self._lock:
                    if self.model is model and self.data is not None:  # no rebuild meanwhile
                        renderer.update_scene(self.data)
                        break
            return render_depth(renderer, cameras, intrinsics)

    # ------------------------------------------------------------------------------------------ send

    def send(self, trajectory: JointTrajectory, stop: threading.Event | None = None, *, realtime_factor: float = 1.0,
             command_id: str | None = None) -> ExecutionReport:
        """Follow `trajectory` (physical times) with physics, the wall clock paced `realtime_factor` times
        faster, then hold its end `settle_s`; MotionStopped on stop() / `stop`."""
        if realtime_factor <= 0:
            raise ValueError(f"realtime_factor must be positive, got {realtime_factor}")
        own = self._prepare_send(trajectory, 1.0)
        model, data = self._world()
        dt = float(model.opt.timestep)
        control = self.world_config.control
        total = own.duration_s + control.command_latency_s + control.settle_s
        steps = max(1, int(np.ceil(total / dt)))
        delay = int(round(control.command_latency_s / dt))
        in_flight: deque[np.ndarray] = deque()  # commands computed but not yet at the servos
        held = data.ctrl[self._actuators].copy()
        velocities = own.velocities() if len(own.times_s) > 1 else np.zeros((0, len(self.joint_names)))
        publish_every = max(1, round(1.0 / (self.state_rate_hz * dt)))
        track_every = self.steps_per_frame(dt)
        wall_start = time.monotonic()
        self.collisions = {}
        self.tracker.forget()
        self._track_frame(0.0, command_id)
        for step in range(1, steps + 1):
            t = step * dt
            if self._stopped(stop):
                with self._lock:
                    data.ctrl[self._actuators] = data.qpos[self._qpos]  # hold where it is
                raise MotionStopped(f"{self.name}: stopped {t:.2f} s into a {own.duration_s:.2f} s trajectory")
            command = own.sample(t) + self._ff * _velocity_at(own, velocities, t)
            if delay:
                in_flight.append(command)
                command = in_flight.popleft() if len(in_flight) > delay else held
            with self._lock:
                data.ctrl[self._actuators] = command
                mujoco.mj_step(model, data)
                self._record_contacts(t)
            if step % track_every == 0:
                self._track_frame(min(t, own.duration_s), command_id)
            if self.publish is not None and step % publish_every == 0:
                self.publish(self._executing_state(command_id, min(t, own.duration_s)))
            ahead = t / realtime_factor - (time.monotonic() - wall_start)
            if ahead > 0.0:
                time.sleep(ahead)
        if not np.isfinite(data.qpos).all():
            raise MotionStopped(f"{self.name}: the simulation diverged (non-finite state)")
        self._reacquire(own.duration_s, command_id)
        final = self.observe().positions
        error = float(np.max(np.abs(final - own.final)))
        message = f"final joint error {error:.4f} rad"
        if self.collisions:
            message += "; collisions: " + ", ".join(f"{link} vs {other} at t={t:.2f} s"
                                                    for (link, other), t in self.collisions.items())
        return ExecutionReport(self.name, True, final, own.final, time.monotonic() - wall_start, message,
                               samples=steps)


def _velocity_at(trajectory: JointTrajectory, velocities: np.ndarray, t: float) -> np.ndarray:
    """The planned joint velocity at t (the segment's; zero outside the trajectory)."""
    times = trajectory.times_s
    if len(velocities) == 0 or t <= times[0] or t >= times[-1]:
        return np.zeros(trajectory.positions.shape[1])
    k = int(np.searchsorted(times, t, side="right")) - 1
    return np.asarray(velocities[min(k, len(velocities) - 1)])


def _descends_from(model: mujoco.MjModel, body: int, ancestor: int) -> bool:
    while body > 0:
        if body == ancestor:
            return True
        body = int(model.body_parentid[body])
    return False
