"""The push request algorithm (the paper's deployment loop), independent of Zenoh.

One push runs the stages of `stages.py`: candidate hand poses (in the direction frame D) from a pose
source -> world frame -> `MotionPlanner.screen` (batched arm IK, collision check of each pre-contact
configuration, the push line's reachability), in chunks along the order in which poses would be
tried -> floating-hand pushes of the first feasible ones (prescreen) -> `plan_push` for the most
promising feasible poses until `max_plans` plans exist, each plan's arm rollout in simulation
(validator farm) running while the next is planned -> V = α L_goal + β L_coll + γ L_dir
(`ranking.py`; plans whose rollout touches an obstacle are never executed); when no rollout met the
success criterion, one more round of plans and rollouts -> the best plan is executed by the robot
bridge, and the object pose it observes afterwards is judged. The data passed between the stages
are the dataclasses of `candidates.py`.

Pose sources (`PlannerOptions.method`), so that methods can be compared on the same pipeline:
- "gd2p": K poses from the diffusion sampler service;
- "nearest": the paper's Nearest-Neighbour baseline, also from the sampler service (`sampler="nearest"`):
  the stored poses of the training frame nearest to the object in BPS space, at most K of them;
- "fixed": the one fixed spatula pose behind the object (the paper's Fixed Hand Pose baseline);
- "fingertip": one finger pointing along the push at the centre of mass, the others curled (a straight-line
  pusher, `shared.world.fixed_poses.fingertip_pose`).

`PlannerOptions.choice` says how the executed plan is chosen: "ranked" (GD2P), "unranked" (the ranking
ablation: the same stages and rollouts, the executed plan drawn at random among the rolled-out ones)
or "random" (a random feasible pose planned and executed, with no prescreen or rollouts: the pose
source's quality on its own).

With `goal_xy` the request is multi-step: RRT* plans the object's path around the obstacles
(`multistep.py`); each push goes to the next piece of the path and is planned from the object pose
the robot bridge observed after the previous push. With `goal_yaw_deg` too it is a pose goal: the pushes
go on until the object is within the pose's tolerance (position and yaw), each ranked by its rollout's yaw
miss as well and offered hand poses turned about the object's vertical axis, slanted to turn it toward the
goal yaw or keep it there (`goals.py`); an object at the point but not at the yaw is pushed off it and back. The goal is checked
before the robot moves (`goals.check_goal`: on the table, within reach).

`run` returns a `PushOutcome`: the response and the record of every executed push. A request that
cannot be served raises `PushError`, carrying the records of the pushes it did execute.

The rest of the system is reached through `PushServices` callables (the service adapter fills them
with bus clients; tests may fill them directly).

A request may be cancelled (`cancellation.Cancellation`: its client gave up): the pipeline checks
between stages, in its screening and planning loops and while it waits for the farm, and raises
`RequestCancelled`; the execution service is handed the cancellation so that it can stop the robot.
"""
from __future__ import annotations

import contextlib
import time
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from shared.contracts.messages import ExecutionResult, ObjectPose, PushRequest, PushResponse
from shared.frames import direction_xy, make_transform
from shared.planning import stages
from shared.planning.cancellation import Cancellation
from shared.planning.candidates import Candidates, Feasible, Push, RankedPlan
from shared.planning.goals import check_goal, check_obstacles, turn_to_make_deg
from shared.planning.ik import ArmIK
from shared.planning.motion import MotionPlanner, MotionSettings, PlanningError
from shared.planning.multistep import DirectionInfeasible, push_along_path
from shared.planning.outcome import PushError, PushOutcome
from shared.planning.ranking import YawTerm
from shared.planning.stages import PipelineSettings, RequestState
from shared.robots.hands import load_hand
from shared.robots.robot_limits import RobotLimits
from shared.world.object_refs import captured_object, load_object_ref
from shared.world.objects import ObjectLoadError, ObjectModel, write_object_urdf
from shared.world.obstacles import as_discs, cut_known_obstacles
from shared.world.push_outcome import (
    SUCCESS_MAX_ROTATION_DEG,
    YawGoal,
    judge_push,
    object_pose,
    pose_matrix,
    position_tolerance_m,
    resting_rotation,
    turn_observable,
)
from shared.world.sim.robot_scene import RobotScene

DEFAULT_OBJECT_XY = (0.55, 0.0)  # in front of the robot base: sideways pushes reach well; pulls toward the robot need
# the object nearer (at 0.50 m most pull poses have no IK solution; at 0.40 m all three evaluation directions plan)


@dataclass
class PushServices:
    """How the pipeline reaches the other services."""

    sample: stages.Sample
    # A validation job (floating-hand pushes or an arm rollout) sent to the validator farm; the future
    # holds its result, or the error that stopped it. Sending returns at once: plans are rolled out
    # on the farm while the next ones are planned.
    validate: stages.Validate
    # Execute a plan on the robot; cancelling the request must stop the motion.
    execute: stages.Execute


class PushPipeline:
    """Serves PushRequests with the given services (see the module docstring)."""

    def __init__(self, services: PushServices, settings: PipelineSettings = PipelineSettings()):
        self.services = services
        self.settings = settings
        self._robot_limits: dict[tuple[str, str], RobotLimits] = {}
        self._scenes: dict[tuple[str, str], RobotScene] = {}
        self._iks: dict[tuple[str, str], ArmIK] = {}

    # ------------------------------------------------------------------------------- requests

    def run(self, request: PushRequest, cancel: Cancellation | None = None) -> PushOutcome:
        """Plan, rank and execute `request`: the response and the executed pushes' records. PushError
        (with the records of the pushes executed before) when it cannot be done, RequestCancelled
        when `cancel` is set first."""
        started = time.perf_counter()
        request = cut_known_obstacles(request)
        state = self._start(request, cancel or Cancellation())
        vertices = state.obj.mesh.vertices @ state.T_world_O[:3, :3].T + state.T_world_O[:3, 3]
        check_obstacles(request.obstacles, vertices[:, :2])
        try:
            if request.goal_xy is None:
                assert request.direction_deg is not None  # PushRequest holds exactly one of direction_deg, goal_xy
                push = Push(state.T_world_O.copy(), direction_xy(request.direction_deg), request.distance_m)
                self._push_once(state, push)
                final = self._corrected(state, push)
            else:
                check_goal(request, _footprint_radius(state.obj), self._limits(request.arm, request.hand).T_world_base,
                           state.turn_observable)
                final = self._multi_step(state)
        except PushError as exc:
            exc.records = list(state.records)
            raise
        first = state.records[0].step
        state.timings["total"] = time.perf_counter() - started
        response = PushResponse(request_id=request.id, success=final.success, chosen_pose=first.chosen_pose,
                                chosen_pose_world=first.chosen_pose_world, plan=first.plan, score=first.score,
                                result=final, steps=[r.step for r in state.records], notes=state.notes,
                                timings_s=state.timings)
        return PushOutcome(response, list(state.records))

    @staticmethod
    def _start(request: PushRequest, cancel: Cancellation) -> RequestState:
        cancel.check()
        captured = None
        try:
            if request.object.point_cloud is not None:  # the reconstruction, and where the cloud shows it
                captured = captured_object(request.object)
            obj = captured.model if captured is not None else load_object_ref(request.object)
            urdf = str(write_object_urdf(obj))
        except ObjectLoadError as exc:
            raise PushError("bad_request", f"bad object: {exc}") from exc
        if captured is not None:
            T_world_O = captured.T_world_O.copy()
        elif request.object_pose is not None:
            T_world_O = pose_matrix(request.object_pose)
        else:
            T_world_O = make_transform(np.eye(3), np.array([*DEFAULT_OBJECT_XY, 0.0])) @ obj.T_D_O()
        up_O = T_world_O[:3, :3].T @ np.array([0.0, 0.0, 1.0])
        yaw_goal = yaw_term = None
        if request.goal_yaw_deg is not None:
            rest = resting_rotation([pose.rotation for pose in obj.resting_poses], T_world_O[:3, :3])
            yaw_goal = YawGoal(request.goal_yaw_deg, rest)
            yaw_term = YawTerm(yaw_goal, 2.0 * _footprint_radius(obj))  # the diameter: ranking.py says why
        return RequestState(request, obj, urdf, load_hand(request.hand), T_world_O, cancel,
                            turn_observable=turn_observable(obj.mesh, up_O), yaw_goal=yaw_goal, yaw_term=yaw_term)

    def _multi_step(self, state: RequestState) -> ExecutionResult:
        request = state.request
        assert request.goal_xy is not None  # run() makes a multi-step push of goal_xy requests only
        start_T = state.T_world_O.copy()

        def judged(final: ObjectPose) -> ExecutionResult:  # the request's outcome were it to end with `final`
            return judge_push(start_T, np.asarray(request.goal_xy), final, max_rotation_deg=None,
                              yaw_goal=state.yaw_goal)

        def at_pose(_xy: np.ndarray) -> bool:
            return judged(object_pose(state.T_world_O)).success

        try:
            outcome = push_along_path(start_T[:2, 3], request.goal_xy, as_discs(request.obstacles),
                                      lambda _from_xy, to_xy: self._path_push(state, to_xy),
                                      object_radius_m=_footprint_radius(state.obj), max_push_m=request.distance_m,
                                      margin_m=self.settings.obstacle_margin_m, max_steps=request.options.max_steps,
                                      seed=request.seed, goal_tolerance_m=position_tolerance_m(state.yaw_goal),
                                      at_goal=at_pose if state.yaw_goal is not None else None,
                                      robot_xy=self._limits(request.arm, request.hand).T_world_base[:2, 3])
        except DirectionInfeasible as refusal:
            # `_path_push` raises DirectionInfeasible only around a PushError
            assert isinstance(refusal.error, PushError)
            turned = ", ".join(f"{t:+.0f}" for t in refusal.turns_tried)
            also = f"; turned {turned} deg off the object path it could not be made either" if turned else ""
            raise PushError(refusal.error.code, f"{refusal.error.message}{also}") from refusal.error
        except PlanningError as exc:
            if state.records:  # the object moved, then got stuck: report how far it got
                raise PushError("infeasible", f"after {len(state.records)} push(es): {exc}") from exc
            raise PushError("infeasible", f"no object path to the goal: {exc}") from exc
        if not state.records:
            raise PushError("bad_request", "the object is already at the goal")
        final = judged(state.records[-1].step.result.final_object_pose)
        state.timings["object_path"] = sum(p.planning_s for p in outcome.paths)
        state.notes += [f"push {i + 1} turned {turn:+.0f} deg off the object path: the arm could not make the path's push"
                        for i, turn in enumerate(outcome.turns_deg) if turn]
        return final

    def _path_push(self, state: RequestState, to_xy: np.ndarray) -> np.ndarray:
        """One push of a multi-step request, from where the object was seen toward `to_xy`; where it was seen
        after. A pose goal's push is offered hand poses turned to turn the object toward the goal yaw (or keep
        it) too (`goals.turn_to_make_deg`). DirectionInfeasible when it cannot be planned and nothing moved."""
        state.cancel.check()
        offset = np.asarray(to_xy) - state.T_world_O[:2, 3]  # from where the object really is
        distance = float(np.linalg.norm(offset))
        u = offset / distance
        executed = len(state.records)
        try:
            turn = turn_to_make_deg(state.T_world_O, state.yaw_goal)
            self._push_once(state, Push(state.T_world_O.copy(), u, distance, turn_deg=turn))
        except PushError as exc:
            error = exc
            if state.records:
                where = ", ".join(f"{v:.3f}" for v in state.T_world_O[:2, 3])
                error = PushError(exc.code, f"push {len(state.records) + 1}, with the object at ({where}) after "
                                  f"{len(state.records)} push(es): {exc.message}")
            if exc.code == "infeasible" and len(state.records) == executed:  # nothing moved: another direction may do
                raise DirectionInfeasible(error) from exc
            if error is exc:
                raise
            raise error from exc
        return state.T_world_O[:2, 3]

    def _corrected(self, state: RequestState, push: Push) -> ExecutionResult:
        """The outcome of a direction push after up to `request.options.corrections` corrective pushes.

        A push that left the object more than the success tolerance from the target, upright and turned
        no more than the success bound, is followed by a push from where the robot bridge observed the
        object straight to the target (planned like any push, from its own samples). Corrections stop
        at success, at an outcome no push can mend (toppled, turned too far), or when a correction
        cannot be planned: the pushes made stand, and the outcome is judged as they left it.
        """
        start = state.records[0].T_world_O_start
        final = judge_push(start, push.target_xy, state.records[-1].step.result.final_object_pose,
                           max_rotation_deg=state.max_turn_deg)
        for _ in range(state.request.options.corrections):
            if final.success or not correctable(final, state.turn_observable):
                break
            offset = push.target_xy - state.T_world_O[:2, 3]
            last = len(state.records)
            how = "was stopped with" if state.records[-1].step.stopped else "left"
            reason = f"correction {last}: push {last} {how} the object {final.position_error_m * 100:.1f} cm from the target"
            try:
                self._push_once(state, Push(state.T_world_O.copy(), offset / np.linalg.norm(offset),
                                            float(np.linalg.norm(offset))), reason)
            except PushError as exc:
                if exc.code != "infeasible":
                    raise
                state.notes.append(f"no correction after push {len(state.records)}: {exc.message}")
                break
            final = judge_push(start, push.target_xy, state.records[-1].step.result.final_object_pose,
                               max_rotation_deg=state.max_turn_deg)
        return final

    # ------------------------------------------------------------------------------- one push

    def _push_once(self, state: RequestState, push: Push, reason: str | None = None) -> None:
        """Plan, rank and execute one push from where the object is now (`state.advance`s by it);
        `reason`: why it is made, when it is not the request's first push."""
        request = state.request
        with self.scene(request.arm, request.hand) as scene:
            scene.add_object(state.urdf, push.T_world_O)
            scene.add_obstacles(request.obstacles)
            planner = MotionPlanner(scene, self._ik(request.arm, request.hand, scene),
                                    MotionSettings(reuse_paths=self.settings.reuse_arm_paths),
                                    workspace=self._limits(request.arm, request.hand).workspace)
            rolled_out = stages.rolls_out(request)
            candidates, settings, feasible = self._screened(state, planner, push)
            planning = stages.ArmPlanning(state, planner, push, self._limits(request.arm, request.hand), settings)
            if rolled_out:
                chosen = self._rolled_out_choice(state, planning, feasible)
            else:
                chosen = self._first_planned(state, planning, feasible)
        state.advance(stages.execute(state, push, candidates, chosen, self.services.execute, settings,
                                     self._limits(request.arm, request.hand), reason))

    def _screened(self, state: RequestState, planner: MotionPlanner,
                  push: Push) -> tuple[Candidates, PipelineSettings, Feasible]:
        """The push's candidates, its settings and the kinematically feasible candidates. When none of a
        diffusion draw's K samples is feasible, K more are drawn (another seed), up to `sample_draws` draws."""
        request = state.request
        draws = self.settings.sample_draws if request.options.method == "gd2p" else 1  # retrieval and fixed: the same poses
        for draw in range(draws - 1):
            try:
                return self._screened_draw(state, planner, push, draw)
            except PushError as exc:
                if exc.code != "infeasible":
                    raise
                state.notes.append(f"push {len(state.records) + 1}: none of the sampler's {request.options.k} poses was "
                                   f"kinematically feasible (draw {draw + 1}); drew {request.options.k} more")
        try:
            return self._screened_draw(state, planner, push, draws - 1)
        except PushError as exc:
            if exc.code != "infeasible" or draws == 1:
                raise
            raise PushError(exc.code, f"{exc.message}; none in the {draws - 1} draw(s) of {request.options.k} before "
                            "either") from exc

    def _screened_draw(self, state: RequestState, planner: MotionPlanner, push: Push,
                       draw: int) -> tuple[Candidates, PipelineSettings, Feasible]:
        """Draw `draw`'s candidates, their settings and the feasible ones (PushError "infeasible" if none)."""
        candidates = stages.candidate_poses(state, push, self.services.sample, draw, self.settings.slide_m)
        settings = self.settings.for_push(state.request)
        needed = settings.feasible_first(stages.rolls_out(state.request))
        return candidates, settings, stages.screen(state, planner, candidates, push, settings, needed)

    def _rolled_out_choice(self, state: RequestState, planning: stages.ArmPlanning, feasible: Feasible) -> RankedPlan:
        """The best-ranked plan of the (prescreened) feasible candidates with its way back; for an
        "unranked" request, a random one of the same rolled-out plans."""
        settings = planning.settings
        if settings.prescreen > 0:
            feasible = stages.prescreen(state, planning.planner, feasible, planning.push, self.services.validate,
                                        settings)
        ranked = stages.plan_and_rank(state, planning, feasible, self.services.validate, settings)
        if state.request.options.choice == "unranked":
            ranked = [ranked[i] for i in np.random.default_rng(state.seed).permutation(len(ranked))]
        started = time.perf_counter()
        try:
            return planning.with_way_back(ranked)
        finally:
            state.time("planning", time.perf_counter() - started)

    @staticmethod
    def _first_planned(state: RequestState, planning: stages.ArmPlanning, feasible: Feasible) -> RankedPlan:
        """A random feasible choice: the plan of the first feasible candidate (in random order) that has one."""
        with state.timing("planning", excluding="ik"):
            plans, _ = planning.plans(feasible, Counter())
        return plans[0].ranked(None)

    # ------------------------------------------------------------------------------- resources

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

    def _limits(self, arm: str, hand: str) -> RobotLimits:
        key = (arm, hand)
        if key not in self._robot_limits:
            self._robot_limits[key] = RobotLimits.for_robot(*key)
        return self._robot_limits[key]

    def close(self) -> None:
        for scene in self._scenes.values():
            scene.close()
        self._scenes.clear()


def correctable(result: ExecutionResult, turn_observable: bool = True) -> bool:
    """Whether another push can still make `result` a success: the object stands and has not turned past
    the success bound (a push moves it, it does not turn it back; a turn nobody can see does not count)."""
    return not result.toppled and (not turn_observable or result.rotation_deg <= SUCCESS_MAX_ROTATION_DEG)


def _footprint_radius(obj: ObjectModel) -> float:
    """Radius of the object's footprint around its centre of mass at rest (the multi-step disc)."""
    vertices = obj.mesh_in_d().vertices
    return float(np.linalg.norm(vertices[:, :2], axis=1).max())

