"""The push request algorithm (the paper's deployment loop), independent of Zenoh.

One push: candidate hand poses (in the direction frame D) from a pose source -> world frame ->
`MotionPlanner.screen` (batched arm IK, collision check of each pre-contact configuration, the push
line's reachability), in chunks along the order in which poses would be tried -> floating-hand
pushes of the first feasible ones (prescreen) -> `plan_push` for the most promising feasible poses
until `max_plans` plans exist, each plan's arm rollout in simulation (validator farm) running while
the next is planned -> V = α L_goal + β L_coll + γ L_dir (`ranking.py`; plans whose rollout touches
an obstacle are never executed); when no rollout met the success criterion, one more round of plans
and rollouts -> the best plan is executed by the robot bridge, and the object pose it observes
afterwards is judged.

Pose sources (`PushRequest.method`), so that methods can be compared on the same pipeline:
- "gd2p": K poses from the diffusion sampler service;
- "nearest": the paper's Nearest-Neighbour baseline, also from the sampler service (`sampler="nearest"`):
  the stored poses of the training frame nearest to the object in BPS space, at most K of them;
- "fixed": the one fixed spatula pose behind the object (the paper's Fixed Hand Pose baseline).

Without ranking (`ranking=False`, the paper's ablation) a random feasible pose is planned and
executed, with no rollouts.

With `goal_xy` the request is multi-step: RRT* plans the object's path around the obstacles
(`multistep.py`); each push goes to the next piece of the path and is planned from the object pose
the robot bridge observed after the previous push.

The rest of the system is reached through `PushServices` callables (the service adapter fills them
with bus clients; tests may fill them directly).
"""
from __future__ import annotations

import contextlib
import math
import time
from collections import Counter
from collections.abc import Callable, Iterator
from concurrent.futures import Future, wait
from dataclasses import dataclass, field

import numpy as np

from services.planner import ranking
from services.planner.motion import MotionPlanner, PlanningError
from services.planner.multistep import push_along_path
from shared.fixed_poses import FixedPoseError, spatula_pose
from shared.frames import direction_frame, direction_xy, invert_transform, make_transform, pose25_to_matrix, poses_d_to_world
from shared.hands import HandModel, load_hand
from shared.ik import ArmIK
from shared.messages import (
    DirectionFrame,
    ExecutionResult,
    ExecutionState,
    Plan,
    PushRequest,
    PushResponse,
    PushStep,
    SampleRequest,
    SampleResponse,
    ScoreTerms,
    SimWorld,
    ValidationJob,
    ValidationResult,
)
from shared.object_refs import load_object_ref
from shared.objects import ObjectLoadError, ObjectModel, write_object_urdf
from shared.push_outcome import judge_push, object_pose, pose_matrix
from shared.robot_limits import LimitViolation, RobotLimits
from shared.sim.robot_scene import RobotScene

SCREEN_CHUNK = 50  # candidates per batched IK screen (`_feasible_in_order`)
PRESCREEN_CHUNK = 6  # poses per floating-hand validation job: 24 poses in 4 jobs, even rounds on a farm of 2 or 4 workers
DEFAULT_OBJECT_XY = (0.55, 0.0)  # in front of the robot base: sideways pushes reach well; pulls toward the robot need
# the object nearer (at 0.50 m most pull poses have no IK solution; at 0.40 m all three evaluation directions plan)


class PushError(Exception):
    """A push request that cannot be served; `code` is an ErrorReply code (infeasible, bad_request, ...)."""

    def __init__(self, code: str, message: str):
        super().__init__(message)
        self.code = code
        self.message = message


@dataclass
class Execution:
    """What the robot bridge reports for one executed plan: its final state and the states on the way."""

    final: ExecutionState
    states: list[ExecutionState] = field(default_factory=list)


@dataclass
class PushServices:
    """How the pipeline reaches the other services."""

    sample: Callable[[SampleRequest], SampleResponse]
    # A validation job (floating-hand pushes or an arm rollout) sent to the validator farm; the future
    # holds its result, or the error that stopped it. Sending returns at once: plans are rolled out
    # on the farm while the next ones are planned.
    validate: Callable[[ValidationJob], Future]
    execute: Callable[[Plan, SimWorld | None], Execution]


@dataclass(frozen=True)
class PipelineSettings:
    max_plans: int = 6  # feasible plans rolled out and ranked per round (3 missed the demo box; 6 costs ~+1 s)
    # Multi-step: the object's path keeps this far from obstacles beyond its own footprint, room for the
    # hand pushing beside it (at 0.02 and 0.05 m the fingers of every pose sweeping past the obstacle hit it).
    obstacle_margin_m: float = 0.08
    prescreen: int = 24  # feasible poses pushed by a floating hand before planning (0: off); see _prescreened
    max_plan_attempts: int = 10  # poses planned per round before giving up
    # When no rolled-out plan of a round is predicted to succeed, another round plans and rolls out
    # `max_plans` more (the next poses of the prescreened order); all rounds are ranked together.
    max_plan_rounds: int = 2
    limit_retries: int = 2  # re-plans of a pose whose random path broke a robot limit
    validation_timeout_s: float = 240.0  # prescreen / rollout jobs still unanswered after this count as failed
    weights: ranking.Weights = ranking.Weights()


@dataclass
class StepRecord:
    """Everything about one executed push, for the response and the recording."""

    step: PushStep
    T_world_O_start: np.ndarray
    execution: Execution
    world: SimWorld | None


@dataclass
class _Request:
    """Per-request state: the object, where it is now, the robot's joints now, timings."""

    request: PushRequest
    obj: ObjectModel
    urdf: str
    hand: HandModel
    T_world_O: np.ndarray
    q_robot: np.ndarray | None = None  # None: the bridge world is (re)set, robot at home, hand open
    timings: dict[str, float] = field(default_factory=dict)
    records: list[StepRecord] = field(default_factory=list)

    def time(self, stage: str, seconds: float) -> None:
        self.timings[stage] = self.timings.get(stage, 0.0) + seconds


class PushPipeline:
    """Serves PushRequests with the given services (see the module docstring)."""

    def __init__(self, services: PushServices, settings: PipelineSettings = PipelineSettings()):
        self.services = services
        self.settings = settings
        self.last_records: list[StepRecord] = []
        self._robot_limits: dict[tuple[str, str], RobotLimits] = {}
        self._scenes: dict[tuple[str, str], RobotScene] = {}
        self._iks: dict[tuple[str, str], ArmIK] = {}

    # ------------------------------------------------------------------------------- requests

    def run(self, request: PushRequest) -> PushResponse:
        """Plan, rank and execute `request`; PushError when it cannot be done."""
        started = time.perf_counter()
        ctx = self._start(request)
        self.last_records = ctx.records  # also what a failed multi-step request executed before it failed
        if request.goal_xy is None:
            u = direction_xy(request.direction_deg)
            target = ctx.T_world_O[:2, 3] + request.distance_m * u
            self._push_once(ctx, u, request.distance_m)
            final = judge_push(self._first_start(ctx), target, ctx.records[-1].step.result.final_object_pose)
        else:
            final = self._multi_step(ctx)
        first = ctx.records[0].step
        ctx.timings["total"] = time.perf_counter() - started
        return PushResponse(request_id=request.id, success=final.success, chosen_pose=first.chosen_pose,
                            chosen_pose_world=first.chosen_pose_world, plan=first.plan, score=first.score,
                            result=final, steps=[r.step for r in ctx.records], timings_s=ctx.timings)

    def _start(self, request: PushRequest) -> _Request:
        try:
            obj = load_object_ref(request.object)
            urdf = str(write_object_urdf(obj))
        except ObjectLoadError as exc:
            raise PushError("bad_request", f"bad object: {exc}") from exc
        if request.object_pose is not None:
            T_world_O = pose_matrix(request.object_pose)
        else:
            T_world_O = make_transform(np.eye(3), np.array([*DEFAULT_OBJECT_XY, 0.0])) @ obj.T_D_O()
        return _Request(request, obj, urdf, load_hand(request.hand), T_world_O)

    @staticmethod
    def _first_start(ctx: _Request) -> np.ndarray:
        return ctx.records[0].T_world_O_start

    def _multi_step(self, ctx: _Request) -> ExecutionResult:
        request = ctx.request
        start_T = ctx.T_world_O.copy()

        def push(_from_xy: np.ndarray, to_xy: np.ndarray) -> np.ndarray:
            offset = np.asarray(to_xy) - ctx.T_world_O[:2, 3]  # from where the object really is
            try:
                self._push_once(ctx, offset / np.linalg.norm(offset), float(np.linalg.norm(offset)))
            except PushError as exc:
                if not ctx.records:
                    raise
                where = ", ".join(f"{v:.3f}" for v in ctx.T_world_O[:2, 3])
                raise PushError(exc.code, f"push {len(ctx.records) + 1}, with the object at ({where}) after "
                                f"{len(ctx.records)} push(es): {exc.message}") from exc
            return ctx.T_world_O[:2, 3]

        try:
            outcome = push_along_path(start_T[:2, 3], request.goal_xy, request.obstacles, push,
                                      object_radius_m=self._footprint_radius(ctx.obj), max_push_m=request.distance_m,
                                      margin_m=self.settings.obstacle_margin_m, max_steps=request.max_steps,
                                      seed=request.seed)
        except PlanningError as exc:
            if ctx.records:  # the object moved, then got stuck: report how far it got
                raise PushError("infeasible", f"after {len(ctx.records)} push(es): {exc}") from exc
            raise PushError("infeasible", f"no object path to the goal: {exc}") from exc
        if not ctx.records:
            raise PushError("bad_request", "the object is already at the goal")
        final = judge_push(start_T, np.asarray(request.goal_xy), ctx.records[-1].step.result.final_object_pose)
        ctx.timings["object_path"] = sum(p.planning_s for p in outcome.paths)
        return final

    @staticmethod
    def _footprint_radius(obj: ObjectModel) -> float:
        """Radius of the object's footprint around its centre of mass at rest (the multi-step disc)."""
        vertices = obj.mesh_in_d().vertices
        return float(np.linalg.norm(vertices[:, :2], axis=1).max())

    # ------------------------------------------------------------------------------- one push

    def _push_once(self, ctx: _Request, u: np.ndarray, distance_m: float) -> None:
        """Plan, rank and execute one push of `distance_m` along `u` from where the object is now."""
        request = ctx.request
        T_world_O = ctx.T_world_O.copy()
        T_world_D = direction_frame(T_world_O[:3, 3], u)
        frame = DirectionFrame(object_pose=object_pose(T_world_O), direction_xy=(float(u[0]), float(u[1])))
        poses_d = self._candidate_poses(ctx, T_world_D, T_world_O, frame)
        poses_world = poses_d_to_world(poses_d, T_world_D)
        T_world_hand, q_hands = pose25_to_matrix(poses_world)
        with self.scene(request.arm, request.hand) as scene:
            scene.add_object(ctx.urdf, T_world_O)
            scene.add_obstacles([(o.x, o.y, o.radius) for o in request.obstacles])
            planner = MotionPlanner(scene, self._ik(request.arm, request.hand, scene))
            l_dir = ranking.direction_costs(ctx.hand, poses_d)
            started = time.perf_counter()
            order, q_pre = self._feasible_in_order(ctx, planner, T_world_hand, q_hands, distance_m * np.append(u, 0.0),
                                                   self._priority(ctx, l_dir))
            ctx.time("ik", time.perf_counter() - started)
            if request.ranking and self.settings.prescreen > 0:
                order = self._prescreened(ctx, order, poses_d, frame, distance_m)
            if request.ranking:
                ranked = self._plan_and_rank(ctx, planner, order, T_world_hand, q_hands, q_pre, u, distance_m,
                                             poses_d, l_dir, frame)
                started = time.perf_counter()
                (index, plan), score = self._with_way_back(ctx, planner, ranked, distance_m * np.append(u, 0.0))
                ctx.time("planning", time.perf_counter() - started)
            else:
                started = time.perf_counter()
                plans, _ = self._plan_candidates(ctx, planner, order, T_world_hand, q_hands, q_pre, u, distance_m)
                ctx.time("planning", time.perf_counter() - started)
                (index, plan), score = plans[0], None
        self._execute(ctx, plan, poses_d[index], poses_world[index], score, T_world_O, u, distance_m)

    def _candidate_poses(self, ctx: _Request, T_world_D: np.ndarray, T_world_O: np.ndarray,
                         frame: DirectionFrame) -> np.ndarray:
        """[K, 25] poses in D from the request's pose source."""
        request = ctx.request
        started = time.perf_counter()
        if request.method == "fixed":
            T_D_O = invert_transform(T_world_D) @ T_world_O
            vertices_d = ctx.obj.mesh.vertices @ T_D_O[:3, :3].T + T_D_O[:3, 3]
            try:
                poses = spatula_pose(ctx.hand, vertices_d)[None]
            except FixedPoseError as exc:
                raise PushError("bad_request", str(exc)) from exc
        else:
            sampler = "nearest" if request.method == "nearest" else request.sampler
            reply = self.services.sample(SampleRequest(object=request.object, hand=request.hand, frame=frame,
                                                       k=request.k, sampler=sampler, seed=request.seed + len(ctx.records)))
            poses = reply.poses_d.to_numpy().astype(np.float64)
        ctx.time("sampling", time.perf_counter() - started)
        return poses

    def _priority(self, ctx: _Request, l_dir: np.ndarray) -> np.ndarray:
        """The order in which to consider the K candidates: best-aligned palms when ranking, random when not."""
        if ctx.request.ranking:
            return np.argsort(l_dir, kind="stable")
        rng = np.random.default_rng(ctx.request.seed + len(ctx.records))
        return rng.permutation(len(l_dir))

    def _feasible_in_order(self, ctx: _Request, planner: MotionPlanner, T_world_hand: np.ndarray, q_hands: np.ndarray,
                           push: np.ndarray, priority: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(the kinematically feasible candidates in `priority` order, IK solutions [K, dof]).

        Screened (`MotionPlanner.screen`: batched IK, collision check, push line) SCREEN_CHUNK at a
        time along `priority` until there are as many feasible poses as the rest of the request can
        use: planning and prescreening only ever take the first of them, so the result is that of
        screening all K, at a quarter of the IK time when the first chunk is enough.
        """
        settings = self.settings
        needed = (max(settings.prescreen, settings.max_plan_rounds * settings.max_plan_attempts)
                  if ctx.request.ranking else settings.max_plan_attempts)
        q_pre = np.zeros((len(priority), planner.arm.dof))
        feasible: list[int] = []
        reasons: list[str] = []
        for start in range(0, len(priority), SCREEN_CHUNK):
            chunk = priority[start:start + SCREEN_CHUNK]
            screen = planner.screen(T_world_hand[chunk], q_hands[chunk], push=push)
            q_pre[chunk] = screen.q
            feasible += chunk[screen.feasible].tolist()
            reasons += screen.reasons
            if len(feasible) >= needed:
                break
        if not feasible:
            raise PushError("infeasible", _no_feasible_pose_message(reasons))
        return np.array(feasible), q_pre

    def _prescreened(self, ctx: _Request, order: np.ndarray, poses_d: np.ndarray, frame: DirectionFrame,
                     distance_m: float) -> np.ndarray:
        """`order` with the poses that push the object to the target with a floating hand first.

        The first `prescreen` poses of `order` are pushed by the validator's floating hand (about 0.1 s
        of CPU each, in chunks spread over the farm) in the request's frame; those that succeed are
        planned first, closest to the target first. Planning (about 0.2 s a pose) and arm rollouts are
        then spent where the pose itself is known to push well: without it, most of the few plans that
        can be afforded come from poses that fail (measured in `evaluation/`).
        """
        request = ctx.request
        tested = order[: self.settings.prescreen]
        chunks = [c for c in np.array_split(tested, math.ceil(len(tested) / PRESCREEN_CHUNK)) if len(c)]
        jobs = [ValidationJob(object=request.object, hand=request.hand, poses=poses_d[chunk], frame=frame,
                              push_distance_m=distance_m, seed=request.seed) for chunk in chunks]
        started = time.perf_counter()
        results = _results([self.services.validate(job) for job in jobs], self.settings.validation_timeout_s)
        ctx.time("prescreen", time.perf_counter() - started)
        success = np.zeros(len(tested), dtype=bool)
        error = np.full(len(tested), np.inf)
        start = 0
        for chunk, result in zip(chunks, results):
            if not isinstance(result, Exception):  # an unavailable validator only loses the reordering
                success[start:start + len(chunk)] = result.success.to_numpy()
                error[start:start + len(chunk)] = result.position_error_m.to_numpy()
            start += len(chunk)
        passed = tested[success][np.argsort(error[success], kind="stable")]
        return np.concatenate([passed, tested[~success], order[len(tested):]])

    def _plan_and_rank(self, ctx: _Request, planner: MotionPlanner, order: np.ndarray, T_world_hand: np.ndarray,
                       q_hands: np.ndarray, q_pre: np.ndarray, u: np.ndarray, distance_m: float, poses_d: np.ndarray,
                       l_dir: np.ndarray, frame: DirectionFrame) -> list[tuple[tuple[int, Plan], ScoreTerms]]:
        """Ranked plans, best first: rounds of `max_plans` plans rolled out until one is predicted to succeed.

        Each plan's arm rollout is sent to the validator farm as soon as the plan exists, so the farm
        rolls out while the planner plans the next pose; "rollouts" times only the wait after planning.
        """
        ranked: list[tuple[tuple[int, Plan], ScoreTerms]] = []
        failures: Counter = Counter()
        rolled_out = 0
        for _ in range(self.settings.max_plan_rounds):
            rollouts: list[Future] = []

            def roll_out(index: int, plan: Plan) -> None:
                rollouts.append(self.services.validate(self._rollout_job(ctx, plan, poses_d[index], frame, distance_m)))

            started = time.perf_counter()
            try:
                plans, used = self._plan_candidates(ctx, planner, order, T_world_hand, q_hands, q_pre, u, distance_m,
                                                    failures, on_plan=roll_out)
            except PushError:
                if ranked or rolled_out:  # a later round found nothing new: rank what the earlier rounds found
                    break
                raise
            finally:
                ctx.time("planning", time.perf_counter() - started)
            rolled_out += len(plans)
            ranked += self._rank(ctx, plans, rollouts, l_dir)
            ranked = [ranked[i] for i in ranking.order([terms for _, terms in ranked])] if ranked else []
            order = order[used:]
            if (ranked and ranking.predicts_success(ranked[0][1])) or order.size == 0:
                break
        if not ranked:
            raise PushError("infeasible", f"each of the {rolled_out} rolled-out plan(s) made the robot or the object "
                            "touch an obstacle")
        return ranked

    def _plan_candidates(self, ctx: _Request, planner: MotionPlanner, order: np.ndarray, T_world_hand: np.ndarray,
                         q_hands: np.ndarray, q_pre: np.ndarray, u: np.ndarray, distance_m: float,
                         failures: Counter | None = None,
                         on_plan: Callable[[int, Plan], None] | None = None) -> tuple[list[tuple[int, Plan]], int]:
        """[(pose index, plan)] for up to `max_plans` poses taken in `order` (one plan when not ranking),
        and how many poses of `order` were tried; `on_plan(index, plan)` is called as each plan is made.

        Plans to be ranked end above the pushed object: only the executed one needs the way back
        (`_with_way_back`), which saves an RRTConnect per ranked plan.
        """
        wanted = self.settings.max_plans if ctx.request.ranking else 1
        q_arm_start, q_hand_start = self._robot_start(ctx, planner)
        plans, failures = [], Counter() if failures is None else failures
        used = 0
        for index in order[: self.settings.max_plan_attempts]:
            used += 1
            plan = self._plan_within_limits(ctx, planner, failures, T_world_hand[index], q_hands[index],
                                            np.append(u, 0.0), distance_m, q_arm_start, q_hand_start, q_pre[index])
            if plan is None:
                continue
            plans.append((int(index), plan))
            if on_plan is not None:
                on_plan(int(index), plan)
            if len(plans) == wanted:
                break
        if not plans:
            tried = sum(failures.values())
            raise PushError("infeasible", f"no collision-free arm plan for any of the {tried} feasible pose(s) tried ("
                            + ", ".join(f"{n}× {reason}" for reason, n in failures.most_common()) + ")")
        return plans, used

    def _plan_within_limits(self, ctx: _Request, planner: MotionPlanner, failures: Counter, T_world_hand, q_hand,
                            direction, distance_m, q_arm_start, q_hand_start, q_pre) -> Plan | None:
        """A plan for one pose that the robot bridge will accept (joint, velocity, workspace limits), or None.

        RRTConnect paths are random: one that swings the hand out of the workspace box is planned
        again (`limit_retries` times) before the pose is given up.
        """
        limits = self._limits(ctx)
        for _ in range(1 + self.settings.limit_retries):
            try:
                plan = planner.plan_push(T_world_hand, q_hand, direction, distance_m, q_start=q_arm_start,
                                         q_hand_start=q_hand_start, q_pre_contact=q_pre,
                                         return_home=not ctx.request.ranking)
                limits.check_plan(plan)
                return plan
            except PlanningError as exc:
                failures[exc.reason] += 1
                return None
            except LimitViolation as exc:
                failures[f"plan breaks the robot's {exc.limit} limit"] += 1
        return None

    @contextlib.contextmanager
    def scene(self, arm: str, hand: str) -> Iterator[RobotScene]:
        """The pipeline's robot scene for (arm, hand), emptied after use (one request at a time uses it).

        Kept between pushes: loading the robot is most of a scene's cost (~0.7 s).
        """
        key = (arm, hand)
        if key not in self._scenes:
            self._scenes[key] = RobotScene(arm, hand)
        scene = self._scenes[key]
        try:
            yield scene
        finally:
            scene.clear_environment()

    def _ik(self, arm: str, hand: str, scene: RobotScene) -> ArmIK:
        key = (arm, hand)
        if key not in self._iks:
            self._iks[key] = ArmIK(scene.arm, scene.hand, T_world_base=scene.T_world_base)
        return self._iks[key]

    def close(self) -> None:
        for scene in self._scenes.values():
            scene.close()
        self._scenes.clear()

    def _limits(self, ctx: _Request) -> RobotLimits:
        key = (ctx.request.arm, ctx.request.hand)
        if key not in self._robot_limits:
            self._robot_limits[key] = RobotLimits.for_robot(*key)
        return self._robot_limits[key]

    @staticmethod
    def _robot_start(ctx: _Request, planner: MotionPlanner) -> tuple[np.ndarray, np.ndarray]:
        """Where the robot is: home with the hand open for a fresh world, else as the last push left it."""
        if ctx.q_robot is None:
            return planner.arm.home.double().numpy(), ctx.hand.open_joint_positions.double().numpy()
        n_arm = planner.arm.dof
        return ctx.q_robot[:n_arm], ctx.q_robot[n_arm:]

    def _with_way_back(self, ctx: _Request, planner: MotionPlanner, ranked: list[tuple[tuple[int, Plan], ScoreTerms]],
                       push_offset: np.ndarray) -> tuple[tuple[int, Plan], ScoreTerms]:
        """The best-ranked plan completed with its way back to the start (the next best if that fails)."""
        q_arm_start, _ = self._robot_start(ctx, planner)
        limits, failures = self._limits(ctx), Counter()
        for (index, plan), terms in ranked:
            for _ in range(1 + self.settings.limit_retries):
                try:
                    full = planner.plan_return(plan, q_arm_start, push_offset)
                    limits.check_plan(full)
                    return (index, full), terms
                except PlanningError as exc:
                    failures[exc.reason] += 1
                    break
                except LimitViolation as exc:
                    failures[f"way back breaks the robot's {exc.limit} limit"] += 1
        raise PushError("infeasible", f"no way back to the start for any of the {len(ranked)} ranked plan(s) ("
                        + ", ".join(f"{n}× {reason}" for reason, n in failures.most_common()) + ")")

    def _rollout_job(self, ctx: _Request, plan: Plan, pose_d: np.ndarray, frame: DirectionFrame,
                     distance_m: float) -> ValidationJob:
        request = ctx.request
        return ValidationJob(object=request.object, hand=request.hand, poses=pose_d[None], push_distance_m=distance_m,
                             with_arm=True, arm=request.arm, plan=plan, frame=frame, obstacles=request.obstacles,
                             seed=request.seed)

    def _rank(self, ctx: _Request, plans: list[tuple[int, Plan]], rollouts: list[Future],
              l_dir: np.ndarray) -> list[tuple[tuple[int, Plan], ScoreTerms]]:
        """Score every plan by its arm rollout (`rollouts[i]` is plan i's); the plans from best (lowest V) to worst.

        A plan whose rollout made the robot or the object touch an obstacle is left out: it is never
        executed, whatever its score (the obstacles are there to be avoided, and may be fragile).
        """
        started = time.perf_counter()
        results = _results(rollouts, self.settings.validation_timeout_s)
        ctx.time("rollouts", time.perf_counter() - started)
        scored, errors = [], []
        for (index, plan), result in zip(plans, results):
            if isinstance(result, Exception):
                errors.append(str(result))
                continue
            if result.obstacle_contact is not None and bool(result.obstacle_contact.to_numpy()[0]):
                continue
            l_goal = ranking.goal_cost(float(result.goal_error_m.to_numpy()[0]), float(result.rotation_deg.to_numpy()[0]),
                                       float(result.max_tilt_deg.to_numpy()[0]))
            terms = ranking.score(l_goal, float(result.collision_cost.to_numpy()[0]), float(l_dir[index]),
                                  self.settings.weights)
            scored.append(((index, plan), terms))
        if errors and len(errors) == len(plans):
            raise PushError("unavailable", "every arm rollout failed: " + "; ".join(errors[:3]))
        return [scored[i] for i in ranking.order([terms for _, terms in scored])] if scored else []

    def _execute(self, ctx: _Request, plan: Plan, pose_d: np.ndarray, pose_world: np.ndarray,
                 score: ScoreTerms | None, T_world_O: np.ndarray, u: np.ndarray, distance_m: float) -> None:
        request = ctx.request
        world = None
        if ctx.q_robot is None:
            world = SimWorld(object=request.object, object_pose=object_pose(T_world_O), obstacles=request.obstacles)
        started = time.perf_counter()
        execution = self.services.execute(plan, world)
        ctx.time("execution", time.perf_counter() - started)
        state = execution.final
        if state.status != "done":
            code = "infeasible" if state.status == "refused" else "internal"
            raise PushError(code, f"the robot bridge did not execute the plan ({state.status}): {state.message}")
        if state.object_pose is None:
            raise PushError("internal", "the robot bridge observed no object pose after the push")
        target = T_world_O[:2, 3] + distance_m * u
        result = judge_push(T_world_O, target, state.object_pose)
        step = PushStep(chosen_pose=pose_d, chosen_pose_world=pose_world, plan=plan, score=score, result=result)
        ctx.records.append(StepRecord(step, T_world_O, execution, world))
        ctx.T_world_O = pose_matrix(state.object_pose)
        ctx.q_robot = state.positions.to_numpy().astype(np.float64)


def _results(futures: list[Future], timeout_s: float) -> list[ValidationResult | Exception]:
    """Each future's result, or the exception it ended with (one failed job does not fail the others);
    a job unfinished after `timeout_s` counts as a TimeoutError."""
    wait(futures, timeout=timeout_s)
    results: list[ValidationResult | Exception] = []
    for future in futures:
        try:
            results.append(future.result(timeout=0))
        except Exception as exc:  # noqa: BLE001 - reported with the job's other failures
            results.append(exc)
    return results


def _no_feasible_pose_message(reasons: list[str]) -> str:
    counts = Counter(r.split(":")[0] for r in reasons if r)
    example = {r.split(":")[0]: r.split(":", 1)[1].strip() for r in reversed(reasons) if ":" in r}
    summary = ", ".join(f"{n}× {reason}" + (f" (e.g. {example[reason]})" if reason in example else "")
                        for reason, n in counts.most_common())
    hint = ""
    if counts.get("no IK solution", 0) == len(reasons):
        hint = " — the object is probably out of the arm's reach"
    return f"no kinematically feasible hand pose among {len(reasons)} candidate(s) ({summary}){hint}"
