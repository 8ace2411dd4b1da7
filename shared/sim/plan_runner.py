"""Play a planned joint trajectory on a `RobotScene` with physics, recording what the robot touches.

Used by the validator's arm rollouts (the planner's L_goal / L_coll) — the robot bridge's simulated
backend follows the same control law (POSITION_CONTROL tracking the linearly interpolated
trajectory, finite-difference velocity as feed-forward, URDF efforts as torque caps), with pacing,
stop and state publishing added on top.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pybullet as pb

from shared.messages import Plan
from shared.sim.robot_scene import RobotScene

POSITION_GAIN = 0.3  # the simulated backend's measured gain (services/robot_bridge/sim_backend.py)
SETTLE_S = 0.3  # the final waypoint is held this long, so the object comes to rest


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


def robot_efforts(scene: RobotScene) -> np.ndarray:
    """Motor torque caps [arm + hand joints] from the URDFs."""
    hand_joints = [scene.hand.robot.joint(name) for name in scene.hand.joint_names]
    return np.concatenate([scene.arm.effort_limits.double().numpy(), [j.effort for j in hand_joints]])


def prepare_robot(scene: RobotScene, hand_joint_damping: float) -> None:
    """Lower the hand's URDF joint damping, which fights the motors and explodes (DESIGN.md §6)."""
    for link in scene.hand_links:
        pb.changeDynamics(scene.robot_id, link, jointDamping=hand_joint_damping, physicsClientId=scene.client)


def run_plan(scene: RobotScene, plan: Plan, efforts: np.ndarray, time_step_s: float,
             window_s: tuple[float, float] | None = None) -> PlanRun:
    """Follow `plan` with physics (teleported to its first waypoint); contacts recorded.

    `window_s` = (start, stop) plays only that part of the plan (plan times; the robot teleported to
    where it is at `start`, at rest), then holds the configuration at `stop` for SETTLE_S.
    Hand-object contact is the push, not a collision; every other robot contact (table, obstacles,
    arm-object) is recorded with the first time it happened.
    """
    names = list(scene.joint_names)
    if list(plan.joint_names) != names:
        raise PlanRunError(f"plan joints {plan.joint_names[:3]}... do not match the scene's robot {names[:3]}...")
    positions, times = plan.positions.to_numpy().astype(np.float64), plan.times_s.to_numpy().astype(np.float64)
    joints = scene.arm_joints + scene.hand_joints
    velocities = np.diff(positions, axis=0) / np.diff(times)[:, None] if len(times) > 1 else np.zeros((1, len(names)))
    start_s, stop_s = (times[0], times[-1]) if window_s is None else (max(times[0], window_s[0]), min(times[-1], window_s[1]))
    n_arm = len(scene.arm_joints)
    q_start = _sample(times, positions, velocities, start_s)
    scene.set_configuration(q_start[:n_arm], q_start[n_arm:])
    run = PlanRun(duration_s=float(stop_s - start_s))
    push = next((s for s in plan.segments if s.label == "push"), None)
    push_window = (times[push.start], times[push.stop - 1]) if push is not None else (np.inf, -np.inf)
    hand_links = set(scene.hand_links)
    up_in_object = scene.object.pose()[:3, :3].T[:, 2] if scene.object is not None else None
    push_steps = contact_steps = 0
    min_up = 1.0
    steps = int(np.ceil((run.duration_s + SETTLE_S) / time_step_s))
    for step in range(1, steps + 1):
        t = start_s + step * time_step_s
        if t >= stop_s:
            q, qd = _sample(times, positions, velocities, stop_s), np.zeros(len(names))
        else:
            k = max(0, int(np.searchsorted(times, t, side="right")) - 1)
            q = positions[k] + (t - times[k]) * velocities[k]
            qd = velocities[k]
        pb.setJointMotorControlArray(scene.robot_id, joints, pb.POSITION_CONTROL, targetPositions=q.tolist(),
                                     targetVelocities=qd.tolist(), forces=efforts.tolist(),
                                     positionGains=[POSITION_GAIN] * len(joints), physicsClientId=scene.client)
        scene.sim.step()
        for contact in scene.contacts(allow_hand_object=True):
            run.collisions.setdefault((contact.robot_link, contact.other), step * time_step_s)
        if scene.object is not None:
            min_up = min(min_up, float(scene.object.pose()[:3, :3][2] @ up_in_object))
            run.object_obstacle_contact = run.object_obstacle_contact or scene.object_touches_obstacle()
            if push_window[0] <= t <= push_window[1]:
                push_steps += 1
                touching = pb.getContactPoints(scene.robot_id, scene.object.id, physicsClientId=scene.client)
                contact_steps += any(point[3] in hand_links for point in touching)
    run.final_q = scene.joint_state()[0]
    run.push_contact_fraction = contact_steps / push_steps if push_steps else 0.0
    run.max_tilt_deg = float(np.degrees(np.arccos(np.clip(min_up, -1.0, 1.0))))
    return run


def _sample(times: np.ndarray, positions: np.ndarray, velocities: np.ndarray, t: float) -> np.ndarray:
    """The linearly interpolated configuration at plan time t (held at the ends)."""
    if t >= times[-1]:
        return positions[-1]
    k = max(0, int(np.searchsorted(times, t, side="right")) - 1)
    return positions[k] + (max(t, times[0]) - times[k]) * velocities[k]
