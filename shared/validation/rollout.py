"""Arm rollouts: play a planned push with the arm in PyBullet and measure L_goal and L_coll.

The planner sends one `ValidationJob(with_arm=True)` per feasible plan. Each rollout builds the
world the robot bridge will execute in — table, the arm + hand at the plan's first waypoint, the
object resting at `frame.object_pose`, the obstacles — and follows the plan with the same control
law as the simulated robot (`shared.world.sim.plan_runner`). Measured:

- L_goal: distance (table plane) of the object's final position from the target, i.e. the start
  plus `push_distance_m` along the push direction;
- L_coll: 1 if the robot touched anything besides the object with the hand (table, an obstacle,
  the object with an arm link) during the rollout, else 0 — the paper's definition;
- obstacle contact: whether the robot or the pushed object touched an obstacle (the planner never
  executes such a plan);
- the usual push outcomes (success within 3 cm and 45°, not toppled; tilt; hand-object contact
  kept through at least 80% of the push segment; hand-table contact).

Robust ranking (`job.physics_draws` = N): the plan is also played in N worlds drawn around the
nominal one (`shared.world.sim.world.rollout_worlds`: friction, mass, centre of mass, controller gain and
latency, the object off its told pose by up to 1 cm / 5 deg), seeded by the job's seed so every plan
of a request meets the same N worlds; their outcomes come back as `draws`, one row each. The scene
is reused: only friction changes between worlds (`RobotScene.use_contact_physics`) and the object is
loaded with each world's mass and centre of mass.

Only the part of the plan near the object is simulated: from `LEAD_S` before the push segment
(the straight Cartesian approach down and in) to `TRAIL_S` after it (the straight back-off), then
the object settles. The joint-space motions before and after (RRTConnect from and back to the
start) were planned with a clearance from everything and keep away from the object. Measured on a
0.20 m box push whose plan lasts 9.7 s: 0.95 s per rollout instead of 1.45 s (most of the rest is
building the scene), with the same L_goal to 1 mm and the same L_coll.
"""
from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pybullet as pb

from shared.contracts.errors import ServiceError
from shared.contracts.messages import ExecutionResult, PushOutcomes, ValidationJob, ValidationResult
from shared.frames import direction_xy
from shared.world.object_refs import load_object_ref
from shared.world.objects import ObjectLoadError, write_object_urdf
from shared.world.push_outcome import judge_push, object_pose, pose_matrix
from shared.world.sim import PhysicsParams
from shared.world.sim.plan_runner import PlanRun, PlanRunError, prepare_robot, run_plan
from shared.world.sim.robot_scene import RobotScene
from shared.world.sim.world import half_extents, rollout_worlds

CONTACT_KEPT_MIN_FRACTION = 0.8  # as the floating-hand validator
LEAD_S = 1.5  # simulated before the push: the Cartesian approach (2 x 5 cm at 0.1 m/s) and some margin
TRAIL_S = 1.5  # simulated after the push: the Cartesian back-off (2 x 5 cm) and some margin

_local = threading.local()


def rollout(job: ValidationJob, params: PhysicsParams) -> ValidationResult:
    """Play `job.plan` with the arm and judge the push it makes (one row: the job's one pose); with
    `job.physics_draws`, also in that many drawn worlds (`draws`, one row each)."""
    assert job.with_arm and job.plan is not None and job.frame is not None and job.arm is not None
    started = time.perf_counter()
    try:
        obj = load_object_ref(job.object)
    except ObjectLoadError as exc:
        raise ServiceError("bad_request", f"validator: {exc}") from exc
    scene = _scene(job.arm, job.hand, params)
    nominal = _play(scene, job, write_object_urdf(obj), pose_matrix(job.frame.object_pose), params,
                    with_penetration=True)
    drawn = []
    if job.physics_draws:  # robust ranking only: the nominal rollout needs no draws
        worlds = rollout_worlds(job.seed, job.physics_draws, half_extents(obj.mesh.vertices), params)
        drawn = [_play(scene, job, write_object_urdf(obj, w.mass_scale, w.com_offset_m),
                       w.pose_error.true_pose(pose_matrix(job.frame.object_pose)), w.physics) for w in worlds]
        scene.use_contact_physics(params)  # the cached scene is the nominal world again
    hand_link_names = {scene.link_names[i] for i in scene.hand_links}
    collided = bool(nominal.run.collisions)
    touched_obstacle = (nominal.run.object_obstacle_contact
                        or any(other.startswith(("obstacle", "wall")) for _, other in nominal.run.collisions))
    return ValidationResult(job_id=job.id, hand=job.hand, object_id=obj.id,
                            goal_error_m=np.array([nominal.result.position_error_m]),
                            collision_cost=np.array([float(collided)]), obstacle_contact=np.array([touched_obstacle]),
                            final_object_poses=[nominal.result.final_object_pose],
                            object_paths=[nominal.run.object_path] if nominal.run.object_path is not None else None,
                            draws=_outcomes(drawn, hand_link_names) if drawn else None,
                            elapsed_s=time.perf_counter() - started,
                            **_fields(_outcomes([nominal], hand_link_names)))


@dataclass(frozen=True)
class _Played:
    """One rollout of the plan in one world: the run, its judged push, the hand's initial penetration."""

    run: PlanRun
    result: ExecutionResult
    penetration_m: float


def _play(scene: RobotScene, job: ValidationJob, urdf: Path, T_world_O: np.ndarray, params: PhysicsParams,
          with_penetration: bool = False) -> _Played:
    """The plan played with the object (`urdf`) truly at T_world_O in the world `params`, judged as an
    evaluation judges an execution: from where the object truly stood, `push_distance_m` along the push."""
    assert job.plan is not None and job.frame is not None
    direction = direction_xy(np.degrees(job.frame.yaw_rad()))
    target_xy = T_world_O[:2, 3] + job.push_distance_m * direction
    scene.use_contact_physics(params)
    try:
        scene.add_object(urdf, T_world_O)
        scene.add_obstacles(job.obstacles)
        penetration = _initial_penetration(scene, job) if with_penetration else 0.0
        try:
            run = run_plan(scene, job.plan, params, _window(job))
        except PlanRunError as exc:
            raise ServiceError("bad_request", f"validator: {exc}") from exc
        assert scene.object is not None  # just added
        final = object_pose(scene.object.pose())
    finally:
        scene.clear_environment()
    return _Played(run, judge_push(T_world_O, target_xy, final), penetration)


def _fields(outcomes: PushOutcomes) -> dict[str, np.ndarray]:
    return {name: getattr(outcomes, name) for name in PushOutcomes.model_fields}


def _outcomes(played: list[_Played], hand_link_names: set[str]) -> PushOutcomes:
    """The push outcomes of rollouts, one row each."""
    def table_touched(run: PlanRun) -> bool:
        return any(other == "table" and link in hand_link_names for link, other in run.collisions)
    return PushOutcomes(
        success=np.array([p.result.success for p in played]),
        position_error_m=np.array([p.result.position_error_m for p in played]),
        rotation_deg=np.array([p.result.rotation_deg for p in played]),
        max_tilt_deg=np.array([p.run.max_tilt_deg for p in played]),
        contact_kept=np.array([p.run.push_contact_fraction >= CONTACT_KEPT_MIN_FRACTION for p in played]),
        hand_table_contact=np.array([table_touched(p.run) for p in played]),
        initial_penetration_m=np.array([p.penetration_m for p in played]))


def _scene(arm: str, hand: str, params: PhysicsParams) -> RobotScene:
    """This thread's robot scene for (arm, hand, params), empty (PyBullet clients are per thread here)."""
    scenes: dict[tuple[str, str, PhysicsParams], RobotScene] | None = getattr(_local, "scenes", None)
    if scenes is None:
        scenes = _local.scenes = {}
    key = (arm, hand, params)
    if key not in scenes:
        scene = RobotScene(arm, hand, params=params)
        prepare_robot(scene, params.hand_joint_damping)
        scenes[key] = scene
    return scenes[key]


def _window(job: ValidationJob) -> tuple[float, float] | None:
    """Plan times to simulate: around the push segment (the whole plan if it has none)."""
    assert job.plan is not None  # a rollout job carries its plan (checked by `rollout`)
    push = next((s for s in job.plan.segments if s.label == "push"), None)
    if push is None:
        return None
    times = job.plan.times_s.to_numpy()
    return float(times[push.start]) - LEAD_S, float(times[push.stop - 1]) + TRAIL_S


def _initial_penetration(scene: RobotScene, job: ValidationJob) -> float:
    """How deep the hand is in the object at the start of the push segment (m, >= 0)."""
    assert job.plan is not None and scene.object is not None  # called with the job's object in the scene
    push = next((s for s in job.plan.segments if s.label == "push"), None)
    if push is None:
        return 0.0
    q = job.plan.positions.to_numpy()[push.start].astype(np.float64)
    n_arm = len(scene.arm_joints)
    scene.set_configuration(q[:n_arm], q[n_arm:])
    hand_links = set(scene.hand_links)
    points = pb.getClosestPoints(scene.robot_id, scene.object.id, 0.0, physicsClientId=scene.client)
    depth = min((p[8] for p in points if p[3] in hand_links), default=0.0)
    return max(0.0, -float(depth))

