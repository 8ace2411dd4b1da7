"""The arm's control law and playing a planned joint trajectory with physics: the one physics core.

`ArmController` is the joint controller of every simulated arm: the validator's arm rollouts (the
planner's L_goal / L_coll, `run_plan` here) and the robot bridge's simulated robot
(`shared/execution/robots/sim/robot.py`, which adds pacing, stop and state publishing) follow a plan
with it, so a prediction and an execution differ only in the world they run in (`PhysicsParams`:
friction, mass, the controller's gain and latency; `shared.world.sim.world` draws an execution's).
Control: POSITION_CONTROL tracking the linearly interpolated trajectory, the segment's
finite-difference velocity as feed-forward, URDF efforts as torque caps.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pybullet as pb

from shared.contracts.messages import ObjectPath, Plan
from shared.frames import matrix_to_quat_xyzw
from shared.world.sim.params import PhysicsParams
from shared.world.sim.robot_scene import RobotScene


class ArmController:
    """Drives the scene's arm + hand joints along a trajectory (times [T], positions [T, joints]).

    `window_s` = (start, stop) plays only that part: commands before `start` hold `start`'s
    configuration, and from `stop` on the configuration at `stop` is held at rest.
    """

    def __init__(self, scene: RobotScene, params: PhysicsParams, times: np.ndarray, positions: np.ndarray,
                 window_s: tuple[float, float] | None = None):
        self.scene, self.params = scene, params
        self.times = np.asarray(times, dtype=np.float64)
        self.positions = np.asarray(positions, dtype=np.float64)
        self.velocities = (np.diff(self.positions, axis=0) / np.diff(self.times)[:, None] if len(self.times) > 1
                           else np.zeros((0, self.positions.shape[1])))
        first, last = float(self.times[0]), float(self.times[-1])
        self.start_s, self.stop_s = (first, last) if window_s is None else (max(first, window_s[0]), min(last, window_s[1]))
        self.joints = scene.arm_joints + scene.hand_joints
        self.efforts = robot_efforts(scene)

    @property
    def step_count(self) -> int:
        """Physics steps to play the window, the command latency and the settling after it."""
        p = self.params
        return int(np.ceil((self.stop_s - self.start_s + p.arm_command_latency_s + p.arm_settle_s) / p.time_step_s))

    def time_of(self, step: int) -> float:
        """Trajectory time after `step` physics steps."""
        return self.start_s + step * self.params.time_step_s

    def target(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """The command in force at trajectory time t: the position and feed-forward velocity of
        `arm_command_latency_s` earlier (the window's start before it; at rest from its stop)."""
        t = t - self.params.arm_command_latency_s
        at_rest = np.zeros(self.positions.shape[1])
        if t < self.start_s:
            return self.sample(self.start_s), at_rest
        if t >= self.stop_s or len(self.times) < 2:
            return self.sample(self.stop_s), at_rest
        k = max(0, int(np.searchsorted(self.times, t, side="right")) - 1)
        return self.positions[k] + (t - self.times[k]) * self.velocities[k], self.velocities[k]

    def sample(self, t: float) -> np.ndarray:
        """The linearly interpolated configuration at trajectory time t (held at the ends)."""
        times = self.times
        if t >= times[-1] or len(times) < 2:
            last: np.ndarray = self.positions[-1]
            return last
        k = max(0, int(np.searchsorted(times, t, side="right")) - 1)
        q: np.ndarray = self.positions[k] + (max(t, times[0]) - times[k]) * self.velocities[k]
        return q

    def step(self, step: int) -> float:
        """Command the joints for the time after `step` physics steps, advance the physics one step;
        that time."""
        t = self.time_of(step)
        self.command(*self.target(t))
        self.scene.sim.step()
        return t

    def command(self, q: np.ndarray, qd: np.ndarray) -> None:
        pb.setJointMotorControlArray(self.scene.robot_id, self.joints, pb.POSITION_CONTROL, targetPositions=q.tolist(),
                                     targetVelocities=qd.tolist(), forces=self.efforts.tolist(),
                                     positionGains=[self.params.arm_position_gain] * len(self.joints),
                                     physicsClientId=self.scene.client)

    def hold(self) -> None:
        """Hold the joints where they are."""
        positions, _ = self.scene.joint_state()
        self.command(positions, np.zeros(len(positions)))


OBJECT_PATH_PERIOD_S = 0.05  # the predicted object path's sampling (20 Hz, the simulated tracker's rate)


class PlanRunError(ValueError):
    """A plan that does not fit the scene's robot."""


@dataclass
class PlanRun:
    """What happened while a plan was played."""

    duration_s: float
    collisions: dict[tuple[str, str], float] = field(default_factory=dict)  # (robot link, other) -> first time
    final_q: np.ndarray | None = None
    push_contact_fraction: float = 0.0  # of the "push" segment's physics steps with hand-object contact
    max_tilt_deg: float = 0.0  # how far the object's up axis leaned at worst
    object_obstacle_contact: bool = False  # the object touched an obstacle
    object_path: ObjectPath | None = None  # the object's poses every OBJECT_PATH_PERIOD_S (plan times)


def robot_efforts(scene: RobotScene) -> np.ndarray:
    """Motor torque caps [arm + hand joints] from the URDFs."""
    hand_joints = [scene.hand.robot.joint(name) for name in scene.hand.joint_names]
    return np.concatenate([scene.arm.effort_limits.double().numpy(), [j.effort for j in hand_joints]])


def prepare_robot(scene: RobotScene, hand_joint_damping: float) -> None:
    """Lower the hand's URDF joint damping, which fights the motors and explodes (docs/architecture.md §Simulation)."""
    for link in scene.hand_links:
        pb.changeDynamics(scene.robot_id, link, jointDamping=hand_joint_damping, physicsClientId=scene.client)


def run_plan(scene: RobotScene, plan: Plan, params: PhysicsParams,
             window_s: tuple[float, float] | None = None) -> PlanRun:
    """Follow `plan` with physics (teleported to its first waypoint); contacts recorded.

    `window_s` = (start, stop) plays only that part of the plan (plan times; the robot teleported to
    where it is at `start`, at rest), then holds the configuration at `stop` while it settles.
    Hand-object contact is the push, not a collision; every other robot contact (table, obstacles,
    arm-object) is recorded with the first time it happened.
    """
    names = list(scene.joint_names)
    if list(plan.joint_names) != names:
        raise PlanRunError(f"plan joints {plan.joint_names[:3]}... do not match the scene's robot {names[:3]}...")
    times = plan.times_s.to_numpy().astype(np.float64)
    controller = ArmController(scene, params, times, plan.positions.to_numpy(), window_s)
    n_arm = len(scene.arm_joints)
    q_start = controller.sample(controller.start_s)
    scene.set_configuration(q_start[:n_arm], q_start[n_arm:])
    run = PlanRun(duration_s=controller.stop_s - controller.start_s)
    push = next((s for s in plan.segments if s.label == "push"), None)
    push_window = (times[push.start], times[push.stop - 1]) if push is not None else (np.inf, -np.inf)
    hand_links = set(scene.hand_links)
    up_in_object = scene.object.pose()[:3, :3].T[:, 2] if scene.object is not None else None
    push_steps = contact_steps = 0
    min_up = 1.0
    path_every = max(1, round(OBJECT_PATH_PERIOD_S / params.time_step_s))
    path: list[tuple[float, np.ndarray]] = []
    for step in range(1, controller.step_count + 1):
        t = controller.step(step)
        for contact in scene.contacts(allow_hand_object=True):
            run.collisions.setdefault((contact.robot_link, contact.other), t - controller.start_s)
        if scene.object is not None:
            pose = scene.object.pose()
            if step % path_every == 0:
                path.append((t, pose))
            min_up = min(min_up, float(pose[:3, :3][2] @ up_in_object))
            run.object_obstacle_contact = run.object_obstacle_contact or scene.object_touches_obstacle()
            if push_window[0] <= t <= push_window[1]:
                push_steps += 1
                touching = pb.getContactPoints(scene.robot_id, scene.object.id, physicsClientId=scene.client)
                contact_steps += any(point[3] in hand_links for point in touching)
    run.final_q = scene.joint_state()[0]
    run.push_contact_fraction = contact_steps / push_steps if push_steps else 0.0
    run.max_tilt_deg = float(np.degrees(np.arccos(np.clip(min_up, -1.0, 1.0))))
    run.object_path = _object_path(path)
    return run


def _object_path(path: list[tuple[float, np.ndarray]]) -> ObjectPath | None:
    if not path:
        return None
    return ObjectPath(times_s=np.array([t for t, _ in path]), positions=np.array([T[:3, 3] for _, T in path]),
                      quaternions_xyzw=np.array([matrix_to_quat_xyzw(T[:3, :3]) for _, T in path]))
