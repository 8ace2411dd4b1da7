"""The stages of one push, each with one job; `pipeline.PushPipeline` runs them in this order.

1. pose source (`candidate_poses`): K hand poses in D — the sampler service's, or one fixed pose (spatula, fingertip);
2. IK and screening (`screen`): batched arm IK, collision check of each pre-contact configuration
   and the push line's reachability, in chunks along the order in which poses would be tried;
3. prescreen (`prescreen`): floating-hand pushes of the first feasible poses on the validator farm;
   those that push well are tried first;
4. planning (`ArmPlanning`): `plan_push` for poses in that order, each plan within the robot
   bridge's limits (`within_limits`: a random path that breaks one is planned again);
5. rollout (`rollout_job`): each plan's arm rollout, sent to the farm as soon as the plan exists;
6. ranking (`rank`, and `plan_and_rank` for the rounds of planning, rollouts and ranking);
   the best plan is then completed with its way back (`ArmPlanning.with_way_back`);
7. execution (`execute`): the robot bridge runs the plan; the object pose it observes is judged.

Every stage checks the request's `Cancellation` where it may take long (its loops, its waits for
the farm, before and after the robot moves) and raises `RequestCancelled`.
"""
from __future__ import annotations

import contextlib
import dataclasses
import functools
import math
import time
from collections import Counter
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Future
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import ConvexHull

from shared.contracts.messages import (
    DirectionFrame,
    PhysicsSettings,
    Plan,
    PushRequest,
    PushStep,
    SampleRequest,
    SampleResponse,
    ScoreTerms,
    SimWorld,
    ValidationJob,
    ValidationResult,
    WallObstacle,
)
from shared.frames import invert_transform, pose25_to_matrix
from shared.planning import ranking
from shared.planning.cancellation import Cancellation
from shared.planning.candidates import CandidatePlan, Candidates, Feasible, Push, RankedPlan
from shared.planning.goals import turning_poses
from shared.planning.monitor import MonitorThresholds, PushMonitor, backed_out
from shared.planning.motion import MotionPlanner, PlanningError
from shared.planning.outcome import Execution, PushError, StepRecord
from shared.robots.hands import HandModel
from shared.robots.robot_limits import LimitViolation, RobotLimits
from shared.world.fixed_poses import FIXED_POSE_METHODS, FixedPoseError, fixed_pose
from shared.world.objects import ObjectModel
from shared.world.obstacles import distance_to_hull, wall_depth_into
from shared.world.push_outcome import (
    SUCCESS_MAX_ROTATION_DEG,
    TOPPLED_TILT_DEG,
    YawGoal,
    judge_push,
    object_pose,
    pose_matrix,
    rotation_between_deg,
)
from shared.world.sim.params import PhysicsParams

# A later push reuses the last sampled candidates when the object sits in its push frame D turned no more than
# this from how it sat in the last one's (the sampler would be asked the same question).
REUSE_SAMPLES_DEG = 10.0
SLIDE_NEAR_M = 0.05  # an obstacle this close to the object's footprint may stand where a hand would (`slide_m`)
DRAW_SEED_STRIDE = 1_000_003  # seed offset of a push's further sampler draws (`PipelineSettings.sample_draws`)
SCREEN_CHUNK = 50  # candidates per batched IK screen (`screen`)
PRESCREEN_CHUNK = 6  # poses per floating-hand validation job: 24 poses in 4 jobs, even rounds on a farm of 2 or 4 workers

Sample = Callable[[SampleRequest], SampleResponse]
# A validation job (floating-hand pushes or an arm rollout) sent to the validator farm; the future
# holds its result, or the error that stopped it.
Validate = Callable[[ValidationJob], Future[ValidationResult]]
# Execute a plan on the robot bridge (resetting its world to the SimWorld first, when one is given); cancelling
# the request must stop the motion, and so must the monitor (closed loop), when it finds a reason to stop.
Execute = Callable[[Plan, SimWorld | None, Cancellation, PushMonitor | None], Execution]


@dataclass(frozen=True)
class PipelineSettings:
    max_plans: int = 6  # feasible plans rolled out and ranked per round (3 missed the demo box; 6 costs ~+1 s)
    # Multi-step: the object's path keeps this far from obstacles beyond its own footprint, room for the
    # hand pushing beside it (at 0.02 and 0.05 m the fingers of every pose sweeping past the obstacle hit it).
    obstacle_margin_m: float = 0.08
    # Feasible poses pushed by a floating hand before planning (0: off; a request with `prescreen` false, the fast
    # path, pushes none); see `prescreen`. Fewer pushes plan sooner but lost success on the val objects, even in
    # the critic's order, so 24 are kept (docs/evaluation.md §Tuned settings).
    prescreen: int = 24
    # The prescreen's floating pushes at this hand speed (m/s; None: the validator's, that of the rollouts and the
    # robot). A faster push simulates fewer steps; a candidate setting, measured (bench/prescreen_speed.py) and on
    # val before it is a default.
    prescreen_push_speed_mps: float | None = None
    max_plan_attempts: int = 10  # poses planned per round before giving up
    # A round in which none of its `max_plan_attempts` poses has an arm plan (the approach or the way out
    # runs out of reach, every path breaks a limit) is followed by one on the next poses, screened as
    # needed, up to this many rounds: a hand pose that screens feasible can still fail there.
    max_planless_rounds: int = 3
    # A diffusion request none of whose K samples is kinematically feasible (the pose family the model favours
    # is out of the arm's reach there) draws K more with another seed, up to this many draws in all. On the LEAP
    # val trials where it happens, a second draw found no feasible pose either: off (1), as measured
    # (docs/evaluation.md §Tuned settings).
    sample_draws: int = 1
    # When no rolled-out plan of a round is predicted to succeed, another round plans and rolls out
    # `max_plans` more (the next poses of the prescreened order); all rounds are ranked together.
    max_plan_rounds: int = 2
    limit_retries: int = 2  # re-plans of a pose whose random path broke a robot limit
    # Rolled-out requests try poses whose hands stand at least this far apart first (`spread_out`; 0: off).
    # The best-aligned samples are often near-copies (median 0.5-1 cm apart); at 1.5 cm the val trials had fewer
    # failures the rollouts predicted and as many world-gap ones, a gain within the interval's noise. Off, as
    # measured (docs/evaluation.md §Tuned settings).
    min_separation_m: float = 0.0
    # With an obstacle or a wall within SLIDE_NEAR_M of the object, the pose source's poses are also tried slid
    # sideways along the face they push by each of these (m, along D's y), after every pose as it is: a hand
    # the sampler put where a wall or a neighbour stands may fit beside it (`slid_poses`). Chosen on val's wall,
    # corner and clutter tasks (docs/evaluation.md §Tuned settings); () turns it off. Far from obstacles it
    # changes nothing.
    slide_m: tuple[float, ...] = (-0.04, -0.02, 0.02, 0.04)
    # A push's arm paths first try the way around found for its earlier plans (`MotionSettings.reuse_paths`);
    # False: RRTConnect for every blocked joint path (the ablation).
    reuse_arm_paths: bool = True
    validation_timeout_s: float = 240.0  # prescreen / rollout jobs still unanswered after this count as failed
    weights: ranking.Weights = ranking.Weights()
    monitor: MonitorThresholds = MonitorThresholds()  # closed loop: when a push is stopped

    def for_push(self, request: PushRequest) -> PipelineSettings:
        """The settings of a push the request asks for: no prescreen pushes when it turns them off (the fast path)."""
        return self if request.options.prescreen else dataclasses.replace(self, prescreen=0)

    def feasible_needed(self, rolled_out: bool) -> int:
        """How many feasible poses the stages after screening can use: screening stops there."""
        return max(self.prescreen, self.max_plan_rounds * self.max_plan_attempts) if rolled_out else self.max_plan_attempts

    def feasible_first(self, rolled_out: bool) -> int:
        """How many feasible poses the first stage after screening takes: the prescreen starts with them."""
        return self.prescreen if rolled_out and self.prescreen > 0 else self.feasible_needed(rolled_out)


@dataclass
class RequestState:
    """Per-request state: the object, where it is now, the robot's joints now, timings, executed pushes."""

    request: PushRequest
    obj: ObjectModel
    urdf: str
    hand: HandModel
    T_world_O: np.ndarray
    cancel: Cancellation = field(default_factory=Cancellation)
    q_robot: np.ndarray | None = None  # None: the bridge world is (re)set, robot at home, hand open
    timings: dict[str, float] = field(default_factory=dict)
    records: list[StepRecord] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)  # what the response should tell besides its steps
    # The last sampled candidates of the request: how the object sat in their D (R_D_O), the poses in D and
    # the critic's P(success) of each (None: no critic).
    sampled: tuple[np.ndarray, np.ndarray, np.ndarray | None] | None = None
    # Whether a camera can see the object turn about its vertical axis (push_outcome.turn_observable): for a body
    # of revolution the tracked turn is a guess, so it neither stops a push nor counts against one.
    turn_observable: bool = True
    # A pose goal's yaw as the judge reads it, and as the ranking's L_goal prices it (None: no goal yaw).
    yaw_goal: YawGoal | None = None
    yaw_term: ranking.YawTerm | None = None

    @property
    def max_turn_deg(self) -> float | None:
        """The turn a push of this object may make and succeed (None: not judged, it cannot be seen, or the
        request's goal yaw judges how the object ends instead)."""
        return SUCCESS_MAX_ROTATION_DEG if self.turn_observable and self.yaw_goal is None else None

    def time(self, stage: str, seconds: float) -> None:
        self.timings[stage] = self.timings.get(stage, 0.0) + seconds

    @contextlib.contextmanager
    def timing(self, stage: str, excluding: str) -> Iterator[None]:
        """Time the block as `stage`, less the time it spent in `excluding` (timed inside it, e.g. the screening
        of a plan-less round's next poses within planning), so no second counts in two stages."""
        started, before = time.perf_counter(), self.timings.get(excluding, 0.0)
        try:
            yield
        finally:
            self.time(stage, time.perf_counter() - started - (self.timings.get(excluding, 0.0) - before))

    @property
    def seed(self) -> int:
        """The seed of the current push's random choices (the request's, offset by the pushes made)."""
        return self.request.seed + len(self.records)

    def advance(self, record: StepRecord) -> None:
        """After an executed push: record it; the object and the robot are where the bridge saw them."""
        self.records.append(record)
        state = record.execution.final
        assert state.object_pose is not None  # `execute` makes no record of a push without an observed object pose
        self.T_world_O = pose_matrix(state.object_pose)
        self.q_robot = state.positions.to_numpy().astype(np.float64)


# ------------------------------------------------------------------------------- 1. pose source


def candidate_poses(state: RequestState, push: Push, sample: Sample, draw: int = 0,
                    slide_m: Sequence[float] = ()) -> Candidates:
    """The request's pose source's candidates for `push` (`PlannerOptions.method`).

    Candidates are poses in D, the frame of the object and the push direction: a later push of the request
    (a correction, the next push of a multi-step request) that sees the object in its D turned no more
    than REUSE_SAMPLES_DEG from how the last sampled push saw it reuses that push's candidates. `draw` > 0:
    another draw of the sampler for the same push (its own seed), never a reused one."""
    request = state.request
    started = time.perf_counter()
    if request.options.method in FIXED_POSE_METHODS:
        T_D_O = invert_transform(push.T_world_D) @ push.T_world_O
        vertices_d = state.obj.mesh.vertices @ T_D_O[:3, :3].T + T_D_O[:3, 3]
        try:
            poses_d = fixed_pose(request.options.method, state.hand, vertices_d, T_D_O[:3, 3])[None]
        except FixedPoseError as exc:
            raise PushError("bad_request", str(exc)) from exc
        p_success = None
    else:
        R_D_O = (invert_transform(push.T_world_D) @ push.T_world_O)[:3, :3]  # how the object sits in D
        reusable = state.sampled is not None and rotation_between_deg(state.sampled[0], R_D_O) <= REUSE_SAMPLES_DEG
        if draw == 0 and reusable:
            assert state.sampled is not None  # `reusable` says so
            _, poses_d, p_success = state.sampled  # a later push sees the object in D as the last one did
        else:
            sampler = "nearest" if request.options.method == "nearest" else request.options.sampler
            seed = (state.seed + DRAW_SEED_STRIDE * draw) % 2**31
            reply = sample(SampleRequest(object=request.object, hand=request.hand, frame=sampling_frame(state, push),
                                         k=request.options.k, sampler=sampler, seed=seed,
                                         score=request.options.critic and rolls_out(request),  # only an order uses scores
                                         critic_guidance=None if sampler == "nearest" else request.options.critic_guidance))
            poses_d = reply.poses_d.to_numpy().astype(np.float64)
            p_success = None if reply.success_probability is None else reply.success_probability.to_numpy()
            state.sampled = (R_D_O, poses_d, p_success)
    state.time("sampling", time.perf_counter() - started)
    state.cancel.check()
    if slide_m and near_an_obstacle(state, push):
        poses_d, p_success, tier = with_slid_copies(state, push, poses_d, p_success, slide_m)
    else:
        tier = None
    if push.turn_deg is not None:
        return with_turning_copies(state, push, poses_d, p_success, tier)
    return Candidates.in_frame(poses_d, push, state.hand, p_success, tier=tier)


def near_an_obstacle(state: RequestState, push: Push) -> bool:
    """Whether an obstacle or a wall of the request stands within SLIDE_NEAR_M of the object's footprint."""
    if not state.request.obstacles:  # the slide is a default now: a request without obstacles skips the hull
        return False
    vertices = state.obj.mesh.vertices @ push.T_world_O[:3, :3].T + push.T_world_O[:3, 3]
    hull = ConvexHull(vertices[:, :2])
    for obstacle in state.request.obstacles:
        if isinstance(obstacle, WallObstacle):
            gap = -wall_depth_into(obstacle, hull.points[hull.vertices])
        else:
            gap = distance_to_hull(hull, np.array([obstacle.x, obstacle.y])) - obstacle.radius
        if gap < SLIDE_NEAR_M:
            return True
    return False


def with_slid_copies(state: RequestState, push: Push, poses_d: np.ndarray, p_success: np.ndarray | None,
                     slide_m: Sequence[float]) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """The poses [K, 25] in D followed by their copies slid sideways by each of `slide_m` (`slid_poses`); each
    copy keeps its pose's P(success). With the tier of each (0: as sampled, 1: slid), which orders every pose
    before any copy."""
    T_D_O = invert_transform(push.T_world_D) @ push.T_world_O
    vertices_d = state.obj.mesh.vertices @ T_D_O[:3, :3].T + T_D_O[:3, 3]
    copies, kept = [poses_d], [np.arange(len(poses_d))]
    for slide in slide_m:
        slid, ok = slid_poses(poses_d, vertices_d, slide)
        copies.append(slid[ok])
        kept.append(np.flatnonzero(ok))
    source = np.concatenate(kept)
    tier = np.concatenate([np.zeros(len(poses_d), dtype=int)] + [np.ones(len(k), dtype=int) for k in kept[1:]])
    return np.concatenate(copies), None if p_success is None else p_success[source], tier


def slid_poses(poses_d: np.ndarray, vertices_d: np.ndarray, slide_m: float) -> tuple[np.ndarray, np.ndarray]:
    """The hand poses [K, 25] in D slid `slide_m` along D's y and moved along x by how much the back of the
    object's footprint (its least x, `vertices_d` [V, 3] in D) moves between the hand's old and new y, so the hand
    keeps its distance to the face it pushes; and which copies still face the object ([K] bool: a hand slid past
    the object's side has nothing to push)."""
    hull = ConvexHull(np.asarray(vertices_d, dtype=np.float64)[:, :2])
    before = _back_of(hull, poses_d[:, 1])
    after = _back_of(hull, poses_d[:, 1] + slide_m)
    ok = np.isfinite(before) & np.isfinite(after)
    slid = np.array(poses_d, dtype=np.float64, copy=True)
    slid[:, 1] += slide_m
    slid[ok, 0] += after[ok] - before[ok]
    return slid, ok


def _back_of(hull: ConvexHull, y: np.ndarray) -> np.ndarray:
    """The least x of the convex footprint `hull` on each line of constant `y` [K] (inf where the line misses it)."""
    starts = hull.points[hull.vertices]
    ends = np.roll(starts, -1, axis=0)
    y = np.asarray(y, dtype=np.float64)[:, None]
    low, high = np.minimum(starts[:, 1], ends[:, 1]), np.maximum(starts[:, 1], ends[:, 1])
    crosses = (y >= low) & (y <= high) & (high > low)
    t = np.where(crosses, (y - starts[:, 1]) / np.where(high > low, ends[:, 1] - starts[:, 1], 1.0), 0.0)
    x = np.where(crosses, starts[:, 0] + t * (ends[:, 0] - starts[:, 0]), np.inf)
    return np.asarray(x.min(axis=1))


def with_turning_copies(state: RequestState, push: Push, poses_d: np.ndarray,
                        p_success: np.ndarray | None, tier: np.ndarray | None = None) -> Candidates:
    """The candidates of the poses [K, 25] in D followed by copies turned to turn the object by `push.turn_deg`
    (`goals.turning_poses`). A copy keeps its pose's P(success) (the critic's word for the nearest pose it scored)
    and order key (`Candidates.source`): a pose and its copy are considered one after the other, so the plans
    rolled out hold both and the ranking (a pose goal's yaw miss) chooses between them."""
    assert push.turn_deg is not None  # only a push that is to turn the object has turned copies
    T_D_O = invert_transform(push.T_world_D) @ push.T_world_O
    vertices_d = state.obj.mesh.vertices @ T_D_O[:3, :3].T + T_D_O[:3, 3]
    transforms, _ = pose25_to_matrix(poses_d)
    palm_normals = transforms[:, :3, :3] @ state.hand.palm_normal_base.double().numpy()
    turned = turning_poses(poses_d, palm_normals, vertices_d, push.turn_deg)
    both = None if p_success is None else np.concatenate([p_success, p_success])
    source = np.tile(np.arange(len(poses_d)), 2)
    return Candidates.in_frame(np.concatenate([poses_d, turned]), push, state.hand, both, source,
                               None if tier is None else np.tile(tier, 2))


def sampling_frame(state: RequestState, push: Push) -> DirectionFrame:
    """`push`'s direction frame D as the pose source is to read the request's object.

    A point cloud stays where the cameras captured it, while a later push of the request (a correction,
    the next push of a multi-step request) starts where the object went since: that push is carried back
    by the object's motion to where the cloud was captured, so the cloud is seen from the push as the
    object now is (the poses in D are the same). A mesh is placed by the frame itself."""
    if state.request.object.point_cloud is None or not state.records:
        return push.frame
    T_world_O_captured = state.records[0].T_world_O_start  # the first push starts where the cloud showed it
    T_back = T_world_O_captured @ invert_transform(push.T_world_O)  # the object's motion since, undone
    direction = T_back[:3, :3] @ push.direction
    return DirectionFrame(object_pose=object_pose(T_world_O_captured),
                          direction_xy=(float(direction[0]), float(direction[1])))


# ------------------------------------------------------------------------------- 2. IK and screening


def screen(state: RequestState, planner: MotionPlanner, candidates: Candidates, push: Push,
           settings: PipelineSettings, needed: int | None = None) -> Feasible:
    """The kinematically feasible candidates in the order they would be tried, with their IK solutions.

    Screened (`MotionPlanner.screen`: batched IK, collision check, push line) SCREEN_CHUNK at a time
    along `priority` until there are `needed` feasible poses (default: as many as the rest of the
    request can use, `PipelineSettings.feasible_needed`): planning and prescreening only ever take the
    first of them, so the result is that of screening all K, at a quarter of the IK time when the first
    chunk is enough. `screen_more` goes on from where it stopped.
    """
    order = priority(state, candidates)
    if rolls_out(state.request):
        order = spread_out(order, candidates.poses_d[:, :3], settings.min_separation_m)
    empty = Feasible(candidates, np.zeros(0, dtype=int), np.zeros((len(order), planner.arm.dof)),
                     [None] * len(order), unscreened=order)
    return screen_more(state, planner, empty, push, settings, needed)


def screen_more(state: RequestState, planner: MotionPlanner, feasible: Feasible, push: Push,
                settings: PipelineSettings, needed: int | None = None) -> Feasible:
    """`feasible` with more of its unscreened candidates screened, until `needed` are feasible (see `screen`)."""
    started = time.perf_counter()
    needed = settings.feasible_needed(rolls_out(state.request)) if needed is None else needed
    candidates, unscreened = feasible.candidates, feasible.unscreened
    found: list[int] = feasible.order.tolist()
    q_pre, lines = feasible.q_pre.copy(), list(feasible.lines)
    reasons: list[str] = []
    while len(found) < needed and unscreened.size:
        state.cancel.check()
        chunk, unscreened = unscreened[:SCREEN_CHUNK], unscreened[SCREEN_CHUNK:]
        result = planner.screen(candidates.T_world_hand[chunk], candidates.q_hands[chunk], push=push.offset)
        candidates.raise_poses(chunk, result.lift_m)
        q_pre[chunk] = result.q
        for index, tracked in zip(chunk, result.lines, strict=True):
            lines[index] = tracked
        found += chunk[result.feasible].tolist()
        reasons += result.reasons
    state.time("ik", time.perf_counter() - started)
    if not found:
        raise PushError("infeasible", no_feasible_pose_message(reasons))
    return Feasible(candidates, np.array(found, dtype=int), q_pre, lines, unscreened)


def orders_by_critic(request: PushRequest, candidates: Candidates) -> bool:
    """Whether the request's candidates are considered in the critic's order: it asks (`PlannerOptions.critic`),
    its plans are rolled out, and the sampler scored them."""
    return request.options.critic and rolls_out(request) and candidates.p_success is not None


def rolls_out(request: PushRequest) -> bool:
    """Whether the request's plans are rolled out (ranked or not), i.e. not a random feasible choice."""
    return request.options.choice != "random"


def priority(state: RequestState, candidates: Candidates) -> np.ndarray:
    """The order in which to consider the K candidates when plans are rolled out: most likely to push well
    first by the critic (when it scored them and the request asks for it), best-aligned palms first (L_dir)
    on ties and without it; random for a random feasible choice. Either way slid copies (`slide_m`) come after
    every pose as it was sampled (their tier, the first key): a fallback for poses an obstacle blocks."""
    l_dir = candidates.order_l_dir
    tier = np.zeros(len(l_dir), dtype=int) if candidates.tier is None else candidates.tier
    if not rolls_out(state.request):
        shuffled = np.random.default_rng(state.seed).permutation(len(l_dir))
        return shuffled[np.argsort(tier[shuffled], kind="stable")]
    # Ties go by the pose source's index: a turned copy right after its pose (lexsort is stable).
    source = np.arange(len(l_dir)) if candidates.source is None else candidates.source
    if orders_by_critic(state.request, candidates):
        assert candidates.p_success is not None
        return np.lexsort((source, l_dir, -candidates.p_success, tier))
    return np.lexsort((source, l_dir, tier))


def spread_out(order: np.ndarray, positions: np.ndarray, min_separation_m: float) -> np.ndarray:
    """`order` with near-copies moved back: walking it, a candidate whose hand position (`positions` [K, 3])
    lies within `min_separation_m` of one kept before it goes after every kept one (keeping its own order),
    so that the first poses tried differ. 0 leaves `order` as it is."""
    if min_separation_m <= 0 or len(order) < 2:
        return order
    kept: list[int] = []
    deferred: list[int] = []
    for index in order.tolist():
        near = kept and np.linalg.norm(positions[kept] - positions[index], axis=1).min() < min_separation_m
        (deferred if near else kept).append(index)
    return np.array(kept + deferred, dtype=order.dtype)


def no_feasible_pose_message(reasons: list[str]) -> str:
    counts = Counter(r.split(":")[0] for r in reasons if r)
    example = {r.split(":")[0]: r.split(":", 1)[1].strip() for r in reversed(reasons) if ":" in r}
    summary = ", ".join(f"{n}× {reason}" + (f" (e.g. {example[reason]})" if reason in example else "")
                        for reason, n in counts.most_common())
    hint = ""
    if counts.get("no IK solution", 0) == len(reasons):
        hint = " — the object is probably out of the arm's reach"
    return f"no kinematically feasible hand pose among {len(reasons)} candidate(s) ({summary}){hint}"


# ------------------------------------------------------------------------------- 3. prescreen


def prescreen(state: RequestState, planner: MotionPlanner, feasible: Feasible, push: Push, validate: Validate,
              settings: PipelineSettings) -> Feasible:
    """`feasible`, screened as far as the request needs, with the poses that push the object to the target
    with a floating hand first.

    The first `settings.prescreen` poses of the order are pushed by the validator's floating hand
    (about 0.1 s of CPU each, in chunks spread over the farm) in the push's frame; those that succeed
    are planned first, closest to the target first (for a pose goal as `prescreen_judged` says). Planning
    and arm rollouts (about 0.25 s of CPU each) are then spent where the pose itself is known to push
    well: without it, most of the few plans that can be afforded come from poses that fail (measured in
    `evaluation/`). While the farm pushes, the planner screens the further candidates that planning may
    need (`screen_more`).
    """
    request, tested = state.request, feasible.order[: settings.prescreen]
    chunks = [c for c in np.array_split(tested, math.ceil(len(tested) / PRESCREEN_CHUNK)) if len(c)]
    jobs = [ValidationJob(object=request.object, hand=request.hand, poses=feasible.candidates.poses_d[chunk],
                          frame=push.frame, push_distance_m=push.distance_m, seed=request.seed,
                          settings=prescreen_physics(settings)) for chunk in chunks]
    futures = [validate(job) for job in jobs]
    feasible = screen_more(state, planner, feasible, push, settings)
    started = time.perf_counter()
    results = wait_for_results(futures, settings.validation_timeout_s, state.cancel)
    state.time("prescreen", time.perf_counter() - started)
    success = np.zeros(len(tested), dtype=bool)
    error = np.full(len(tested), np.inf)
    start = 0
    for chunk, result in zip(chunks, results, strict=True):
        if not isinstance(result, Exception):  # an unavailable validator only loses the reordering
            success[start:start + len(chunk)], error[start:start + len(chunk)] = prescreen_judged(state, push, result)
        start += len(chunk)
    passed = spread_out(tested[success][np.argsort(error[success], kind="stable")],
                        feasible.candidates.poses_d[:, :3], settings.min_separation_m)
    order = feasible.order
    return feasible.reordered(np.concatenate([passed, tested[~success], order[len(tested):]]))


def prescreen_physics(settings: PipelineSettings) -> PhysicsSettings | None:
    """The prescreen jobs' physics: the validator's own (None), or its solver at the prescreen's push speed."""
    if settings.prescreen_push_speed_mps is None:
        return None
    nominal = PhysicsParams()
    return PhysicsSettings(solver_iterations=nominal.solver_iterations, time_step_s=nominal.time_step_s,
                           push_speed_mps=settings.prescreen_push_speed_mps)


def prescreen_judged(state: RequestState, push: Push, result: ValidationResult) -> tuple[np.ndarray, np.ndarray]:
    """Per floating push of `result`: whether it pushed well, and how far it left the object from what `push` asks.

    A push's own judge (within the success tolerance of its target) and its distance from the target; for a pose
    goal, whether it left the object standing and its distance plus its yaw miss, priced as the ranking prices it
    (`ranking.YawTerm`): a push that turns the object as asked may fall a few centimetres short and is still
    the one to plan. A floating push reports how far it turned the object, not which way, so the turn it made
    stands in for the turn asked for (a pose turned to turn the object turns it the way it is turned; the
    ranking, from the arm rollouts' final poses, tells the ways apart)."""
    position_error: np.ndarray = result.position_error_m.to_numpy().astype(np.float64)
    if state.yaw_goal is None or state.yaw_term is None:
        return result.success.to_numpy(), position_error
    asked = abs(state.yaw_goal.turn_deg(push.T_world_O[:3, :3]))
    turn_miss = np.radians(np.abs(result.rotation_deg.to_numpy() - asked))
    standing = result.max_tilt_deg.to_numpy() <= TOPPLED_TILT_DEG
    return standing, position_error + state.yaw_term.length_m * turn_miss


# ------------------------------------------------------------------------------- 4. planning


def within_limits(make: Callable[[], Plan], limits: RobotLimits, attempts: int, failures: Counter[str],
                  what: str) -> Plan | None:
    """`make()`'s plan if the robot bridge will accept it (joint, velocity, workspace limits), else None.

    RRTConnect paths are random: one that breaks a limit (e.g. swings the hand out of the workspace
    box) is made again, `attempts` times in all. A PlanningError gives up at once. Each failure is
    counted in `failures` by its reason ("<what> breaks the robot's <limit> limit" for limits).
    """
    for _ in range(attempts):
        try:
            plan = make()
            limits.check_plan(plan)
            return plan
        except PlanningError as exc:
            failures[exc.reason] += 1
            return None
        except LimitViolation as exc:
            failures[f"{what} breaks the robot's {exc.limit} limit"] += 1
    return None


class ArmPlanning:
    """Arm plans for one push's candidates, from where the robot is, within the robot's limits.

    Plans to be ranked end above the pushed object (`plan_push(return_home=False)`): only the
    executed one needs the way back (`with_way_back`), which saves an RRTConnect per ranked plan.
    """

    def __init__(self, state: RequestState, planner: MotionPlanner, push: Push, limits: RobotLimits,
                 settings: PipelineSettings):
        self.state, self.planner, self.push = state, planner, push
        self.limits, self.settings = limits, settings
        self.q_arm_start, self.q_hand_start = robot_start(state, planner)

    def plans(self, feasible: Feasible, failures: Counter[str],
              on_plan: Callable[[CandidatePlan], None] | None = None) -> tuple[list[CandidatePlan], Feasible]:
        """Plans for up to `max_plans` candidates taken in `feasible.order` (one plan for a random choice),
        and the candidates after those tried; `on_plan(plan)` is called as each plan is made.

        When none of a round's `max_plan_attempts` poses has a plan, the next poses (screened as needed) get
        another round, up to `max_planless_rounds`. Failures are counted in `failures` (PushError
        "infeasible" with them when no plan is found)."""
        for round_ in range(self.settings.max_planless_rounds):
            plans, used = self._round(feasible, failures, on_plan)
            feasible = feasible.without_first(used)
            if plans:
                return plans, feasible
            if round_ + 1 == self.settings.max_planless_rounds:
                break
            try:
                feasible = screen_more(self.state, self.planner, feasible, self.push, self.settings,
                                       needed=self.settings.max_plan_attempts)
            except PushError:  # no candidate left that screens feasible
                break
        raise PushError("infeasible", f"no collision-free arm plan for any of the {sum(failures.values())} "
                        f"feasible pose(s) tried ({_counted(failures)}){_reach_hint(failures)}")

    def _round(self, feasible: Feasible, failures: Counter[str],
               on_plan: Callable[[CandidatePlan], None] | None) -> tuple[list[CandidatePlan], int]:
        """One round of `plans`: the plans of the first `max_plan_attempts` poses of the order (stopping at
        `max_plans`, or one for a random choice) and how many poses were tried."""
        wanted = self.settings.max_plans if rolls_out(self.state.request) else 1
        plans: list[CandidatePlan] = []
        used = 0
        for index in feasible.order[: self.settings.max_plan_attempts]:
            self.state.cancel.check()
            used += 1
            plan = within_limits(functools.partial(self._plan_push, feasible, int(index)), self.limits,
                                 1 + self.settings.limit_retries, failures, "plan")
            if plan is None:
                continue
            plans.append(CandidatePlan(int(index), plan))
            if on_plan is not None:
                on_plan(plans[-1])
            if len(plans) == wanted:
                break
        return plans, used

    def _plan_push(self, feasible: Feasible, index: int) -> Plan:
        candidates = feasible.candidates
        return self.planner.plan_push(candidates.T_world_hand[index], candidates.q_hands[index], self.push.direction,
                                      self.push.distance_m, q_start=self.q_arm_start, q_hand_start=self.q_hand_start,
                                      q_pre_contact=feasible.q_pre[index], return_home=not rolls_out(self.state.request),
                                      lines=feasible.lines_of(index))

    def with_way_back(self, ranked: list[RankedPlan]) -> RankedPlan:
        """The best-ranked plan completed with its way back to the start (the next best if that fails)."""
        failures: Counter[str] = Counter()
        for choice in ranked:
            full = within_limits(functools.partial(self.planner.plan_return, choice.plan, self.q_arm_start,
                                                   self.push.offset),
                                 self.limits, 1 + self.settings.limit_retries, failures, "way back")
            if full is not None:
                return RankedPlan(choice.index, full, choice.score, choice.predicted)
        raise PushError("infeasible", f"no way back to the start for any of the {len(ranked)} ranked plan(s) "
                        f"({_counted(failures)})")


def robot_start(state: RequestState, planner: MotionPlanner) -> tuple[np.ndarray, np.ndarray]:
    """Where the robot is: home with the hand open for a fresh world, else as the last push left it."""
    if state.q_robot is None:
        return planner.arm.home.double().numpy(), state.hand.open_joint_positions.double().numpy()
    n_arm = planner.arm.dof
    return state.q_robot[:n_arm], state.q_robot[n_arm:]


def _counted(failures: Counter[str]) -> str:
    return ", ".join(f"{n}× {reason}" for reason, n in failures.most_common())


def _reach_hint(failures: Counter[str]) -> str:
    """Why, when every pose tried was reached but no way in to it was. Seen on the xArm7's pulls toward itself,
    with the object at 0.36 m as at 0.40 m: a hand facing the robot folds the wrist near its joint stop."""
    if failures and all(reason.startswith("no approach (from behind: no IK solution") for reason in failures):
        return (" — the arm reaches these hand poses but cannot come in to them from behind (beyond its reach "
                "or a joint's range for the hand's orientation)")
    return ""


# ------------------------------------------------------------------------------- 5. rollout


def rollout_job(request: PushRequest, push: Push, pose_d: np.ndarray, plan: Plan) -> ValidationJob:
    """The arm rollout of `plan` (for the pose `pose_d` in D) in simulation, with the request's obstacles."""
    return ValidationJob(object=request.object, hand=request.hand, poses=pose_d[None], push_distance_m=push.distance_m,
                         with_arm=True, arm=request.arm, plan=plan, frame=push.frame, obstacles=request.obstacles,
                         seed=request.seed, physics_draws=request.options.physics_draws)


# ------------------------------------------------------------------------------- 6. ranking


def rank(state: RequestState, plans: list[CandidatePlan], rollouts: list[Future[ValidationResult]], l_dir: np.ndarray,
         settings: PipelineSettings) -> list[RankedPlan]:
    """Score every plan by its arm rollout (`rollouts[i]` is plan i's); the plans from best (lowest V) to worst.

    A plan whose rollout made the robot or the object touch an obstacle is left out: it is never
    executed, whatever its score (the obstacles are there to be avoided, and may be fragile).
    """
    started = time.perf_counter()
    results = wait_for_results(rollouts, settings.validation_timeout_s, state.cancel)
    state.time("rollouts", time.perf_counter() - started)
    scored: list[RankedPlan] = []
    errors: list[str] = []
    for candidate, result in zip(plans, results, strict=True):
        if isinstance(result, Exception):
            errors.append(str(result))
            continue
        if result.obstacle_contact is not None and bool(result.obstacle_contact.to_numpy()[0]):
            continue
        terms = ranking.score_rollout(result, float(l_dir[candidate.index]), settings.weights, state.yaw_term)
        scored.append(candidate.ranked(terms, result.object_paths[0] if result.object_paths else None))
    if errors and len(errors) == len(plans):
        raise PushError("unavailable", "every arm rollout failed: " + "; ".join(errors[:3]))
    return best_first(scored)


def best_first(ranked: list[RankedPlan]) -> list[RankedPlan]:
    """`ranked` from the lowest V to the highest (stable on ties)."""
    return [ranked[i] for i in ranking.order([_score(r) for r in ranked])] if ranked else []


def _score(plan: RankedPlan) -> ScoreTerms:
    """The score of a plan that `rank` scored (by its arm rollout)."""
    assert plan.score is not None  # `rank`'s plans are rolled out: each has its rollout's score
    return plan.score


def plan_and_rank(state: RequestState, planning: ArmPlanning, feasible: Feasible, validate: Validate,
                  settings: PipelineSettings) -> list[RankedPlan]:
    """Ranked plans, best first: rounds of `max_plans` plans rolled out until one is predicted to succeed.

    Each plan's arm rollout is sent to the validator farm as soon as the plan exists, so the farm
    rolls out while the planner plans the next pose; "rollouts" times only the wait after planning.
    """
    ranked: list[RankedPlan] = []
    failures: Counter[str] = Counter()  # over all rounds
    rolled_out = 0
    for _ in range(settings.max_plan_rounds):
        rollouts: list[Future[ValidationResult]] = []

        # This round's `feasible` and `rollouts`, bound now: the loop rebinds both for the next round.
        def roll_out(candidate: CandidatePlan, feasible: Feasible = feasible,
                     rollouts: list[Future[ValidationResult]] = rollouts) -> None:
            pose_d = feasible.candidates.poses_d[candidate.index]
            rollouts.append(validate(rollout_job(state.request, planning.push, pose_d, candidate.plan)))

        with state.timing("planning", excluding="ik"):
            try:
                plans, rest = planning.plans(feasible, failures, on_plan=roll_out)
            except PushError:
                if ranked or rolled_out:  # a later round found nothing new: rank what the earlier rounds found
                    break
                raise
        rolled_out += len(plans)
        ranked = best_first(ranked + rank(state, plans, rollouts, feasible.candidates.l_dir, settings))
        feasible = rest
        if (ranked and ranking.predicts_success(_score(ranked[0]))) or feasible.order.size == 0:
            break
    if not ranked:
        raise PushError("infeasible", f"each of the {rolled_out} rolled-out plan(s) made the robot or the object "
                        "touch an obstacle")
    return ranked


def wait_for_results(futures: list[Future[ValidationResult]], timeout_s: float,
                     cancel: Cancellation) -> list[ValidationResult | Exception]:
    """Each future's result, or the exception it ended with (one failed job does not fail the others);
    a job unfinished after `timeout_s` counts as a TimeoutError. RequestCancelled when cancelled first."""
    cancel.wait(futures, timeout_s)
    results: list[ValidationResult | Exception] = []
    for future in futures:
        try:
            results.append(future.result(timeout=0))
        except Exception as exc:  # reported with the job's other failures
            results.append(exc)
    return results


# ------------------------------------------------------------------------------- 7. execution


def execute(state: RequestState, push: Push, candidates: Candidates, chosen: RankedPlan,
            run_plan: Execute, settings: PipelineSettings, limits: RobotLimits, reason: str | None = None) -> StepRecord:
    """Execute `chosen` on the robot bridge (`run_plan`); the record of the push, its outcome judged
    from the object pose the bridge observed. PushError when the bridge did not execute it.

    Closed loop (`request.options.closed_loop`): a monitor follows the tracked object against the path the plan's
    rollout predicted; when it stops the push, the robot backs out the way it came (`_backed_out`) and
    the push is judged where it left the object."""
    request = state.request
    world = None
    if state.q_robot is None:
        world = SimWorld(object=request.object, object_pose=object_pose(push.T_world_O), obstacles=request.obstacles)
    monitor = None
    if request.options.closed_loop and chosen.predicted is not None:  # unranked choices have no rollout to follow
        monitor = PushMonitor(chosen.plan, chosen.predicted, push.direction[:2], settings.monitor,
                              watch_turn=state.turn_observable)
    state.cancel.check()
    started = time.perf_counter()
    execution = run_plan(chosen.plan, world, state.cancel, monitor)
    state.cancel.check()  # a motion stopped by the cancellation is the cancellation's outcome
    stopped = monitor.stop_reason if monitor is not None and execution.final.status == "stopped" else None
    if stopped is not None:
        assert monitor is not None  # only a monitor stops a push
        execution = _backed_out(state, chosen.plan, monitor, execution, run_plan, limits)
    state.time("execution", time.perf_counter() - started)
    final = execution.final
    if final.status != "done":
        code = "infeasible" if final.status == "refused" else "internal"
        raise PushError(code, f"the robot bridge did not execute the plan ({final.status}): {final.message}")
    if final.object_pose is None:
        if final.object_lost is not None:  # no judging, no correction on a pose nobody saw
            raise PushError("lost", f"after the push the tracker had lost the object: {final.object_lost}")
        raise PushError("internal", "the robot bridge observed no object pose after the push")
    result = judge_push(push.T_world_O, push.target_xy, final.object_pose, max_rotation_deg=state.max_turn_deg)
    index = chosen.index
    step = PushStep(chosen_pose=candidates.poses_d[index], chosen_pose_world=candidates.poses_world[index],
                    plan=chosen.plan, score=chosen.score, result=result, reason=reason, stopped=stopped)
    return StepRecord(step, push.T_world_O, execution, world)


def _backed_out(state: RequestState, plan: Plan, monitor: PushMonitor, stopped: Execution, run_plan: Execute,
                limits: RobotLimits) -> Execution:
    """After the monitor stopped `plan`: the robot backs out the way it came, to where the plan started.
    The execution of both, ending where the way back left the robot and the object."""
    assert monitor.stop_time_s is not None
    way_back = backed_out(plan, monitor.stop_time_s, stopped.final.positions.to_numpy(), limits.lower, limits.upper,
                          limits.velocity)
    back = run_plan(way_back, None, state.cancel, None)
    state.cancel.check()
    if back.final.status != "done":
        raise PushError("internal", f"the push was stopped ({monitor.stop_reason}), but backing out failed "
                        f"({back.final.status}): {back.final.message}")
    state.notes.append(f"push {len(state.records) + 1} stopped: {monitor.stop_reason}")
    return Execution(final=back.final, states=[*stopped.states, *back.states])
