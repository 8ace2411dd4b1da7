"""The simulated robot: a PyBullet arm + hand (+ object, obstacles) that executes plans with physics.

It is the default robot-bridge backend and follows the same contract as the hardware adapters
(`backend.Backend`: connect / execute / state / stop / recover / disconnect), one device for the arm
and hand together — they share one physics world, stepped by one thread.

- Control: `shared.sim.plan_runner.ArmController`, the control law the planner's rollouts predict
  with (POSITION_CONTROL tracking the linearly interpolated trajectory, velocity feed-forward, URDF
  efforts as torque caps); its gain, latency and settling come from the backend's `PhysicsParams`,
  which an evaluation sets to a drawn execution world (`shared.sim.world`).
- Time: physics follows the trajectory's own times (a push at the planned speed); wall-clock pacing
  is `realtime_factor` times faster (a large factor runs as fast as the CPU allows). A hardware
  backend, by contrast, executes the time-scaled trajectory.
- State: published through `publish` (an ExecutionState with the object pose) every
  1/`state_rate_hz` seconds of robot time; `state()` is safe from any thread.
- Collisions: robot contacts with the table, obstacles or (arm links) the object during an execution
  are recorded in `collisions` (hand-object contact is the push) and named in the final message.

`SimExecutor` runs a plan on it behind the limit checks of `limits.py` (joint positions, velocities,
workspace box) and the start-configuration check. The bus service (service.py) adds the lease and
the e-stop (`safety.py`): its `CommandLease` sets the `stop` event passed to `SimExecutor.execute`
when the lease is lost, and the e-stop calls `stop()`; either halts the robot within one physics step.
"""
from __future__ import annotations

import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from services.robot_bridge.backend import (
    Backend,
    BackendError,
    DeviceRefused,
    ExecutionReport,
    JointState,
    JointTrajectory,
    MotionStopped,
)
from services.robot_bridge.safety import SafetyRefusal
from shared.frames import matrix_to_quat_xyzw
from shared.messages import ExecutionState, ObjectPose, Plan, SimWorld
from shared.object_refs import load_object_ref
from shared.objects import write_object_urdf
from shared.push_outcome import pose_matrix
from shared.robot_limits import DEFAULT_WORKSPACE, LimitViolation, RobotLimits, WorkspaceBox
from shared.sim.params import REFERENCE_PARAMS, PhysicsParams
from shared.sim.plan_runner import ArmController, prepare_robot
from shared.sim.robot_scene import RobotScene
from shared.sim.world import ExecutionWorld

START_TOLERANCE_RAD = 0.05  # a plan must start within this of the current joint positions

StatePublisher = Callable[[ExecutionState], None]


class SimBackend(Backend):
    """A simulated arm + hand on the table; add an object and obstacles after `connect()`."""

    name = "sim"

    def __init__(
        self,
        arm: str,
        hand: str,
        *,
        T_world_base: np.ndarray | None = None,
        params: PhysicsParams = REFERENCE_PARAMS,
        workspace: WorkspaceBox | None = DEFAULT_WORKSPACE,
        state_rate_hz: float = 50.0,
        publish: StatePublisher | None = None,
    ):
        if state_rate_hz <= 0:
            raise ValueError(f"state_rate_hz must be positive, got {state_rate_hz}")
        self.limits = RobotLimits.for_robot(arm, hand, workspace=workspace, T_world_base=T_world_base)
        super().__init__(self.limits.joint_names)
        self.arm_name, self.hand_name = arm, hand
        self.T_world_base = T_world_base
        self.nominal_params = params  # the physics of a world reset without an execution world
        self.params = params
        self.state_rate_hz = state_rate_hz
        self.publish = publish
        self.realtime_factor = 1.0  # wall-clock pacing when execute() is not given one (e.g. by SafeExecutor)
        self.scene: RobotScene | None = None
        self._lock = threading.RLock()  # PyBullet is not thread-safe: one caller at a time
        # Robot contacts with the table, obstacles (and arm-object) during the last execute(): the first
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

    def __enter__(self) -> SimBackend:
        self.connect()
        return self

    def __exit__(self, *exc) -> None:
        self.disconnect()

    def reset(self, q_arm: Sequence[float] | None = None, q_hand: Sequence[float] | None = None) -> None:
        """Teleport the robot (default: arm home, hand open) and hold it there."""
        self.require_connected()
        scene = self.scene
        q_arm = scene.arm.home.double().numpy() if q_arm is None else np.asarray(q_arm, dtype=np.float64)
        q_hand = (scene.hand.open_joint_positions.double().numpy() if q_hand is None
                  else np.asarray(q_hand, dtype=np.float64))
        q = np.concatenate([q_arm, q_hand])
        with self._lock:
            scene.set_configuration(q_arm, q_hand)
            ArmController(scene, self.params, np.zeros(1), q[None]).command(q, np.zeros(len(q)))

    def reset_world(self, world: SimWorld, execution: ExecutionWorld | None = None) -> None:
        """A fresh simulation: robot at home with the hand open, the object at its pose, the obstacles.

        `execution` (an evaluation's drawn world, `shared.sim.world`) sets the physics and the true
        object (mass, centre of mass), and puts the object at its true pose: `world.object_pose` is
        the pose the planner was told. Without it, the backend's own physics and the told pose.
        """
        obj = load_object_ref(world.object)
        T_world_O = pose_matrix(world.object_pose)
        physics, urdf = self.nominal_params, write_object_urdf(obj)
        if execution is not None:
            physics, T_world_O = execution.physics, execution.pose_error.true_pose(T_world_O)
            urdf = write_object_urdf(obj, execution.mass_scale, execution.com_offset_m)
        with self._lock:
            self.disconnect()
            self.params = physics
            self.connect()
        self.add_object(urdf, T_world_O)
        self.add_obstacles([(o.x, o.y, o.radius) for o in world.obstacles])

    def add_object(self, urdf_path: str | Path, T_world_O: np.ndarray) -> None:
        """Place the object to push (URDF from `shared.objects.write_object_urdf`) with frame O at T_world_O."""
        self.require_connected()
        with self._lock:
            self.scene.add_object(urdf_path, T_world_O)

    def add_obstacles(self, circles: Sequence[tuple[float, float, float]]) -> None:
        """Static cylinders (x, y, radius) on the table."""
        self.require_connected()
        with self._lock:
            self.scene.add_obstacles(circles)

    # ---------------------------------------------------------------------------------------- state

    def state(self) -> JointState:
        self.require_connected()
        with self._lock:
            positions, velocities = self.scene.joint_state()
        return JointState(time.time(), self.joint_names, positions, velocities)

    def object_pose(self) -> ObjectPose | None:
        """The object's frame O in the world (None without an object)."""
        self.require_connected()
        with self._lock:
            if self.scene.object is None:
                return None
            pose = self.scene.object.pose()
        return ObjectPose(position=tuple(pose[:3, 3]), quaternion_xyzw=tuple(matrix_to_quat_xyzw(pose[:3, :3])))

    def execution_state(self, status: str, command_id: str | None = None, message: str = "") -> ExecutionState:
        joints = self.state()
        return ExecutionState(stamp=joints.stamp, joint_names=list(joints.joint_names), positions=joints.positions,
                              velocities=joints.velocities, object_pose=self.object_pose(), status=status,
                              command_id=command_id, message=message)

    # -------------------------------------------------------------------------------------- execute

    def execute(self, trajectory: JointTrajectory, stop: threading.Event | None = None, *,
                realtime_factor: float | None = None, command_id: str | None = None) -> ExecutionReport:
        """Follow `trajectory` (physical times) with physics; MotionStopped on stop() / `stop`.

        `realtime_factor` (default: the attribute) paces the wall clock; `command_id` stamps published states.
        """
        self.require_connected()
        pace = self.realtime_factor if realtime_factor is None else realtime_factor
        if pace <= 0:
            raise ValueError(f"realtime_factor must be positive, got {pace}")
        if self._stop_requested.is_set():
            raise DeviceRefused(f"{self.name}: stopped; call recover() before executing again")
        own = self._own(trajectory)
        controller = ArmController(self.scene, self.params, own.times_s, own.positions)
        publish_every = max(1, round(1.0 / (self.state_rate_hz * self.params.time_step_s)))
        wall_start = time.monotonic()
        self.collisions = {}
        for step in range(1, controller.step_count + 1):
            elapsed = step * self.params.time_step_s
            if self._stop_requested.is_set() or (stop is not None and stop.is_set()):
                with self._lock:
                    controller.hold()
                raise MotionStopped(f"{self.name}: stopped {elapsed:.2f} s into a {own.duration_s:.2f} s trajectory")
            with self._lock:
                controller.step(step)
                for contact in self.scene.contacts(allow_hand_object=True):
                    self.collisions.setdefault((contact.robot_link, contact.other), elapsed)
            if self.publish is not None and step % publish_every == 0:
                self.publish(self.execution_state("executing", command_id))
            ahead = elapsed / pace - (time.monotonic() - wall_start)
            if ahead > 0.0:
                time.sleep(ahead)
        final = self.state().positions
        return ExecutionReport(self.name, True, final, own.final, time.monotonic() - wall_start,
                               samples=controller.step_count)


class SimExecutor:
    """Runs plans on a SimBackend behind the limit and start checks; returns ExecutionStates."""

    def __init__(self, backend: SimBackend, start_tolerance_rad: float = START_TOLERANCE_RAD):
        self.backend = backend
        self.start_tolerance_rad = start_tolerance_rad
        self._busy = threading.Lock()

    def check(self, plan: Plan) -> JointTrajectory:
        """Every check before motion (SafetyRefusal naming what is wrong); the plan's trajectory.

        Limits are checked at the plan's own timing: the simulation runs it at that timing whatever
        the realtime factor (which only changes how fast the wall clock goes by).
        """
        backend = self.backend
        if (plan.arm, plan.hand) != (backend.arm_name, backend.hand_name):
            raise SafetyRefusal("plan", f"plan is for {plan.hand}+{plan.arm}; this robot is "
                                f"{backend.hand_name}+{backend.arm_name}")
        try:
            backend.limits.check_plan(plan)
        except LimitViolation as exc:
            raise SafetyRefusal(exc.limit, str(exc)) from None
        trajectory = JointTrajectory.from_plan(plan).select(backend.joint_names)
        current = backend.state().positions
        gap = np.abs(trajectory.positions[0] - current)
        if gap.max() > self.start_tolerance_rad:
            joint = int(gap.argmax())
            raise SafetyRefusal("start", f"the plan starts with {backend.joint_names[joint]} at "
                                f"{trajectory.positions[0, joint]:.4f} rad but the robot is at "
                                f"{current[joint]:.4f} rad "
                                f"(tolerance {self.start_tolerance_rad} rad)")
        return trajectory

    def execute(self, plan: Plan, realtime_factor: float = 1.0, command_id: str | None = None,
                stop: threading.Event | None = None) -> ExecutionState:
        """Check and run `plan`; the final state: "done", "stopped", "refused" or "error" with the reason.

        `stop` (e.g. the command's lease watch) set at any time, even before motion starts, ends it as "stopped".
        """
        backend = self.backend
        if not self._busy.acquire(blocking=False):
            return backend.execution_state("refused", command_id, "busy: another plan is executing")
        try:
            try:
                trajectory = self.check(plan)
            except SafetyRefusal as exc:
                return backend.execution_state("refused", command_id, str(exc))
            try:
                report = backend.execute(trajectory, stop, realtime_factor=realtime_factor, command_id=command_id)
            except MotionStopped as exc:
                return self._finish("stopped", command_id, str(exc))
            except BackendError as exc:
                return self._finish("error", command_id, str(exc))
            message = f"final joint error {report.final_joint_error:.4f} rad"
            if backend.collisions:
                message += "; collisions: " + ", ".join(f"{link} vs {other} at t={t:.2f} s"
                                                        for (link, other), t in backend.collisions.items())
            return self._finish("done", command_id, message)
        finally:
            self._busy.release()

    def _finish(self, status: str, command_id: str | None, message: str) -> ExecutionState:
        state = self.backend.execution_state(status, command_id, message)
        if self.backend.publish is not None:
            self.backend.publish(state)
        return state
