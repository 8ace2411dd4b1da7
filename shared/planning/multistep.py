"""Multi-step pushing: a path for the object's centre around circular obstacles, cut into pushes.

The paper plans the object's path with RRT* in the image plane around obstacles of a fixed radius,
then plans one push (hand pose + arm motion) per path edge, re-planning from the observed object
pose after each push. Here the plane is the table (world x, y):

- the object is a disc of radius `object_radius_m` (its footprint's circumradius), so each obstacle
  is inflated by that radius plus `margin_m` and the object's centre plans as a point;
- OMPL RRT* (path-length objective) in R² within `bounds`, for `iterations` iterations (RRT* keeps
  improving until then; more if no path is found yet), seeded, so a request's path does not depend
  on the machine's load or speed; then OMPL's shortcutting to drop needless corners (every corner
  is a new push, i.e. another hand pose and arm plan);
- the path is checked exactly (segment-to-circle distance) after planning, since OMPL checks edges
  at a finite resolution;
- `split_into_pushes` cuts every edge into equal pushes no longer than the longest single push;
- `push_along_path` runs the loop: plan the path from where the object is, push along it as far as one
  straight push goes (`next_push_target`; `push` callback: plan a hand pose and arm motion, execute,
  observe), re-plan from the observed position, until the object is within `goal_tolerance_m` of the goal;
- when the arm cannot make the path's push (the callback raises `DirectionInfeasible`: no hand pose
  for that direction has an IK solution or an arm plan), the same push turned by `TURNS_DEG` is
  tried, each only if its straight line keeps the object clear of every obstacle; re-planning from
  where it lands brings the object back to a path. The object path knows nothing of the arm, and a
  direction the arm cannot push from one spot is often pushable a few tens of degrees off it;
- a pose goal is reached when `at_goal` says so (its yaw too), not at the goal point alone: an object at the
  point but not yet at the goal's yaw gets a turning push (`turning_pushes`), sideways off the point as the
  robot sees it and back along a path planned as any. The loop only says where each push goes; how it turns
  the object is the push callback's (a pose goal's pushes are ranked by their yaw miss too, and offered hand
  poses turned about the object's vertical axis: shared/planning/goals.py).
"""
from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol, cast

import numpy as np
from ompl import base as ob
from ompl import geometric as og

from shared.planning.motion import PlanningError, seed_ompl

DEFAULT_PADDING_M = 0.3  # default bounds: the start-goal box grown by this much on every side
EDGE_CHECK_M = 0.005  # OMPL's edge check spacing: cuts an inflated obstacle's edge by < 0.03 mm (sagitta)
RRT_STAR_ITERATIONS = 1000  # measured: 0.681 m against the shortest 0.677 m around one obstacle, in 0.15 s
MAX_ITERATIONS_FACTOR = 10  # without a path after `iterations`, keep searching up to this many times longer
SHORTCUT_SLACK_M = 0.01  # a push may cut this far into the obstacle margin to skip a corner of the path
TURNS_DEG = (15.0, -15.0, 30.0, -30.0)  # the path's push turned by these, in order, when the arm cannot make it
# A turning push (a pose goal's object at the goal point, its yaw still off) moves it this far off the point:
# far enough past the hand's approach gap that the push moves and turns the object, and the push back as long.
TURNING_PUSH_M = 0.08


class Circle(Protocol):
    """A circle on the table (world x, y, radius in metres): a Disc or a shared.contracts.messages.CircleObstacle."""

    @property
    def x(self) -> float: ...
    @property
    def y(self) -> float: ...
    @property
    def radius(self) -> float: ...


Obstacle = Circle | tuple[float, float, float]
"""An obstacle as the planners take it: a Circle or an (x, y, radius) tuple."""


class DirectionInfeasible(Exception):
    """Raised by a push callback when no push toward its target can be planned (the arm's reach, not the
    object path): `push_along_path` then tries the turned pushes. `error` is the callback's own error,
    re-raised by the caller when no turn helps."""

    def __init__(self, error: Exception):
        super().__init__(str(error))
        self.error = error
        self.turns_tried: list[float] = []  # set by push_along_path: the turned pushes tried after this one


@dataclass(frozen=True)
class Disc:
    """A circular obstacle on the table (world x, y, radius in metres)."""

    x: float
    y: float
    radius: float

    @classmethod
    def of(cls, obstacle: Obstacle) -> Disc:
        """From a Disc, a shared.contracts.messages.CircleObstacle or an (x, y, radius) tuple."""
        if isinstance(obstacle, Disc):
            return obstacle
        if hasattr(obstacle, "radius"):
            circle = cast(Circle, obstacle)  # what has a radius is a Circle (mypy does not narrow a union by hasattr)
            return cls(float(circle.x), float(circle.y), float(circle.radius))
        x, y, radius = obstacle
        return cls(float(x), float(y), float(radius))


@dataclass(frozen=True)
class ObjectPath:
    """The planned path of the object's centre and what it cost."""

    waypoints: np.ndarray  # [n, 2], start first, goal last
    length_m: float
    min_clearance_m: float  # smallest distance from the path to an obstacle's edge (inf without obstacles)
    planning_s: float


def plan_object_path(
    start_xy: Sequence[float] | np.ndarray,
    goal_xy: Sequence[float] | np.ndarray,
    obstacles: Sequence[Obstacle] = (),
    *,
    object_radius_m: float,
    margin_m: float = 0.02,
    bounds: tuple[tuple[float, float], tuple[float, float]] | None = None,
    iterations: int = RRT_STAR_ITERATIONS,
    seed: int = 0,
) -> ObjectPath:
    """RRT* path for the object's centre from `start_xy` to `goal_xy` around circular `obstacles`.

    Raises PlanningError when the start or goal is too close to an obstacle or no path is found.
    """
    if object_radius_m <= 0 or margin_m < 0:
        raise PlanningError("bad request",
                            f"object radius must be > 0 and margin >= 0, got {object_radius_m}, {margin_m}")
    start, goal = np.asarray(start_xy, dtype=np.float64)[:2], np.asarray(goal_xy, dtype=np.float64)[:2]
    inflate = object_radius_m + margin_m
    centres, radii = _centres_and_radii(obstacles)
    radii = radii + inflate
    for name, point in (("start", start), ("goal", goal)):
        gaps = np.linalg.norm(centres - point, axis=1) - radii
        if gaps.size and gaps.min() < 0:
            i = int(gaps.argmin())
            raise PlanningError(f"{name} blocked", f"the object's {name} {point.round(3).tolist()} is within "
                                f"{inflate:.3f} m (object radius + margin) of obstacle {i}")
    low, high = _bounds(start, goal, bounds)
    if np.any(start < low) or np.any(start > high) or np.any(goal < low) or np.any(goal > high):
        raise PlanningError("bad request",
                            f"start and goal must lie inside the bounds {low.tolist()} .. {high.tolist()}")

    started = time.perf_counter()
    waypoints = _rrt_star(start, goal, centres, radii, low, high, iterations, seed)
    planning_s = time.perf_counter() - started
    clearance = _path_clearance(waypoints, centres, radii - inflate)
    if clearance < object_radius_m:  # OMPL's discrete edge checks missed a corner: never hand that out
        raise PlanningError("no collision-free path", f"the object path passes {clearance:.3f} m from an obstacle")
    length = float(np.linalg.norm(np.diff(waypoints, axis=0), axis=1).sum())
    return ObjectPath(waypoints=waypoints, length_m=length, min_clearance_m=clearance, planning_s=planning_s)


def _bounds(start: np.ndarray, goal: np.ndarray,
            bounds: tuple[tuple[float, float], tuple[float, float]] | None) -> tuple[np.ndarray, np.ndarray]:
    if bounds is None:
        return np.minimum(start, goal) - DEFAULT_PADDING_M, np.maximum(start, goal) + DEFAULT_PADDING_M
    low, high = np.asarray(bounds[0], dtype=np.float64), np.asarray(bounds[1], dtype=np.float64)
    if low.shape != (2,) or high.shape != (2,) or np.any(high <= low):
        raise PlanningError("bad request", f"bounds must be ((xmin, ymin), (xmax, ymax)) with max > min, got {bounds}")
    return low, high


def _rrt_star(start: np.ndarray, goal: np.ndarray, centres: np.ndarray, radii: np.ndarray, low: np.ndarray,
              high: np.ndarray, iterations: int, seed: int) -> np.ndarray:
    seed_ompl(seed)
    space = ob.RealVectorStateSpace(2)
    limits = ob.RealVectorBounds(2)
    for i in range(2):
        limits.setLow(i, float(low[i]))
        limits.setHigh(i, float(high[i]))
    space.setBounds(limits)
    space.setLongestValidSegmentFraction(EDGE_CHECK_M / space.getMaximumExtent())
    setup = og.SimpleSetup(space)

    discs = [(float(x), float(y), float(r) ** 2) for (x, y), r in zip(centres, radii, strict=True)]

    def valid(state: Any) -> bool:  # plain floats: called thousands of times per plan, numpy's overhead dominates
        x, y = state[0], state[1]
        return all((x - cx) ** 2 + (y - cy) ** 2 > r2 for cx, cy, r2 in discs)

    setup.setStateValidityChecker(valid)
    start_state, goal_state = space.allocState(), space.allocState()
    for i in range(2):
        start_state[i], goal_state[i] = float(start[i]), float(goal[i])
    setup.setStartAndGoalStates(start_state, goal_state)
    info = setup.getSpaceInformation()
    setup.setOptimizationObjective(ob.PathLengthOptimizationObjective(info))
    planner, count = og.RRTstar(info), [0]
    setup.setPlanner(planner)

    def done() -> bool:  # RRT* asks once per iteration; its best cost is finite once it has a path
        count[0] += 1
        return count[0] > iterations * MAX_ITERATIONS_FACTOR or (
            count[0] > iterations and math.isfinite(planner.bestCost().value()))

    solved = setup.solve(ob.PlannerTerminationCondition(done))
    if not (solved and setup.haveExactSolutionPath()):
        raise PlanningError("no collision-free path", f"RRT* found no path for the object around the obstacles "
                            f"in {iterations * MAX_ITERATIONS_FACTOR} iterations")
    path = setup.getSolutionPath()
    simplifier = og.PathSimplifier(info)
    simplifier.reduceVertices(path)
    simplifier.partialShortcutPath(path)
    simplifier.reduceVertices(path)
    return np.array([[s[0], s[1]] for s in path.getStates()])


def _path_clearance(waypoints: np.ndarray, centres: np.ndarray, radii: np.ndarray) -> float:
    """Smallest distance from the polyline to any circle's edge (exact segment-point distance)."""
    if len(centres) == 0:
        return math.inf
    a, b = waypoints[:-1, None, :], waypoints[1:, None, :]  # [E, 1, 2]
    ab = b - a
    t = np.clip(np.sum((centres[None] - a) * ab, axis=-1) / np.maximum(np.sum(ab * ab, axis=-1), 1e-12), 0.0, 1.0)
    nearest = a + t[..., None] * ab
    return float((np.linalg.norm(centres[None] - nearest, axis=-1) - radii[None]).min())


def split_into_pushes(waypoints: np.ndarray, max_push_m: float) -> list[tuple[np.ndarray, np.ndarray]]:
    """(from_xy, to_xy) pushes along the path, each edge cut into equal pieces no longer than `max_push_m`."""
    if max_push_m <= 0:
        raise PlanningError("bad request", f"max push distance must be positive, got {max_push_m}")
    waypoints = np.asarray(waypoints, dtype=np.float64)
    pushes = []
    for a, b in zip(waypoints[:-1], waypoints[1:], strict=True):
        length = float(np.linalg.norm(b - a))
        if length < 1e-9:
            continue
        pieces = math.ceil(length / max_push_m - 1e-9)
        cuts = [a + (b - a) * k / pieces for k in range(pieces + 1)]
        pushes += list(zip(cuts[:-1], cuts[1:], strict=True))
    return pushes


@dataclass(frozen=True)
class MultiStepResult:
    """How a multi-step push ended: every observed object position, the paths planned, success."""

    positions: list[np.ndarray]  # observed object centre (x, y) before the first push and after each
    paths: list[ObjectPath]  # the path planned before each push
    success: bool  # final position within the goal tolerance
    message: str
    turns_deg: list[float] = field(default_factory=list)  # per push: how far it was turned off its path (0: on it)


PushStep = Callable[[np.ndarray, np.ndarray], np.ndarray]
"""push(from_xy, to_xy) -> the object's observed (x, y) after pushing it toward to_xy."""

AtGoal = Callable[[np.ndarray], bool]
"""at_goal(xy) -> whether the object, observed at xy after the last push, needs no more pushes."""


def push_along_path(
    start_xy: Sequence[float] | np.ndarray,
    goal_xy: Sequence[float] | np.ndarray,
    obstacles: Sequence[Obstacle],
    push: PushStep,
    *,
    object_radius_m: float,
    max_push_m: float = 0.20,
    margin_m: float = 0.02,
    goal_tolerance_m: float = 0.03,
    max_steps: int = 10,
    bounds: tuple[tuple[float, float], tuple[float, float]] | None = None,
    iterations: int = RRT_STAR_ITERATIONS,
    seed: int = 0,
    turns_deg: Sequence[float] = TURNS_DEG,
    at_goal: AtGoal | None = None,
    robot_xy: Sequence[float] | np.ndarray = (0.0, 0.0),
) -> MultiStepResult:
    """Push the object from `start_xy` to `goal_xy` around `obstacles`, each push as far along the path as one reaches.

    After every push the path is planned again from the observed position (the paper's re-planning):
    a push that lands off the path is corrected by the next one. Raises PlanningError when no path
    exists from where the object is; `push` raises its own errors, and `DirectionInfeasible` when the arm
    cannot make a push (then the push turned by each of `turns_deg` that keeps clear of the obstacles is
    tried; when none can be made either, the first push's DirectionInfeasible is raised).

    `at_goal` (default: within `goal_tolerance_m` of the goal) ends the pushes; a pose goal's also asks for
    the yaw, and an object within `goal_tolerance_m` of the point but not at the goal gets a turning push
    (`turning_pushes`, sideways as seen from the robot at `robot_xy`).
    """
    goal = np.asarray(goal_xy, dtype=np.float64)[:2]
    positions: list[np.ndarray] = [np.asarray(start_xy, dtype=np.float64)[:2]]
    paths: list[ObjectPath] = []
    turns: list[float] = []

    def at_the_point(xy: np.ndarray) -> bool:
        return bool(np.linalg.norm(xy - goal) <= goal_tolerance_m)

    arrived = at_goal or at_the_point
    for _ in range(max_steps):
        if arrived(positions[-1]):
            return MultiStepResult(positions, paths, True, f"reached the goal in {len(paths)} push(es)", turns)
        # A push may leave the object inside the margin band around an obstacle (never inside the obstacle
        # plus the object's radius, or it would have hit it): plan the way out with the margin it has left.
        margin = min(margin_m, _margin_left(positions[-1], obstacles, object_radius_m))
        if at_the_point(positions[-1]):
            path, options = _turning_path(positions[-1], robot_xy, obstacles, object_radius_m, margin, turns_deg,
                                          min(TURNING_PUSH_M, max_push_m))
        else:
            path = plan_object_path(positions[-1], goal, obstacles, object_radius_m=object_radius_m, margin_m=margin,
                                    bounds=bounds, iterations=iterations, seed=seed + len(paths))
            target = next_push_target(path.waypoints, obstacles, object_radius_m, margin, max_push_m)
            options = [(0.0, target)] + turned_pushes(positions[-1], target, obstacles, object_radius_m, margin,
                                                      turns_deg)
        paths.append(path)
        turn, observed = _first_pushable(push, positions[-1], options)
        positions.append(observed)
        turns.append(turn)
    reached = arrived(positions[-1])
    return MultiStepResult(positions, paths, bool(reached),
                           f"{'reached' if reached else 'did not reach'} the goal after {max_steps} pushes "
                           f"({np.linalg.norm(positions[-1] - goal):.3f} m away)", turns)


def next_push_target(waypoints: np.ndarray, obstacles: Sequence[Obstacle], object_radius_m: float, margin_m: float,
                     max_push_m: float, slack_m: float = SHORTCUT_SLACK_M) -> np.ndarray:
    """Where the next push goes: the farthest end of a piece of the path (`split_into_pushes`) that one straight
    push from the path's start reaches (<= `max_push_m`) keeping the object `object_radius_m + margin_m - slack_m`
    clear of every obstacle; the first piece's end when no farther one qualifies.

    A path around a round obstacle is a polygon hugging its inflated circle, and a path planned from just outside
    that circle often starts with a corner a centimetre or two away: pushed piece by piece, that is a push too short
    to move the object (the hand's approach gap) and one more push of the request's budget spent."""
    waypoints = np.asarray(waypoints, dtype=np.float64)
    pieces = split_into_pushes(waypoints, max_push_m)
    start, target = waypoints[0], pieces[0][1]
    centres, radii = _centres_and_radii(obstacles)
    needed = object_radius_m + max(margin_m - slack_m, 0.0)
    for _, end in pieces[1:]:
        if np.linalg.norm(end - start) > max_push_m + 1e-9:
            break
        if _path_clearance(np.stack([start, end]), centres, radii) >= needed:
            target = end
    return target


def turned_pushes(from_xy: np.ndarray, to_xy: np.ndarray, obstacles: Sequence[Obstacle], object_radius_m: float,
                  margin_m: float, turns_deg: Sequence[float] = TURNS_DEG) -> list[tuple[float, np.ndarray]]:
    """(turn, target): the push from `from_xy` to `to_xy` turned about its start by each of `turns_deg`,
    same length, kept when its straight line stays `object_radius_m + margin_m` clear of every obstacle."""
    start = np.asarray(from_xy, dtype=np.float64)[:2]
    offset = np.asarray(to_xy, dtype=np.float64)[:2] - start
    centres, radii = _centres_and_radii(obstacles)
    kept = []
    for turn in turns_deg:
        c, s = math.cos(math.radians(turn)), math.sin(math.radians(turn))
        target = start + np.array([c * offset[0] - s * offset[1], s * offset[0] + c * offset[1]])
        if _path_clearance(np.stack([start, target]), centres, radii) >= object_radius_m + margin_m:
            kept.append((float(turn), target))
    return kept


def turning_pushes(from_xy: np.ndarray, robot_xy: Sequence[float] | np.ndarray, obstacles: Sequence[Obstacle],
                   object_radius_m: float, margin_m: float, length_m: float = TURNING_PUSH_M,
                   turns_deg: Sequence[float] = TURNS_DEG) -> list[tuple[float, np.ndarray]]:
    """(turn, target): pushes of `length_m` that move an object at its goal point off it so that a push can turn
    it (a pose goal's yaw), in the order to try: sideways as seen from the robot at `robot_xy` (the robot's
    front along world +x), toward its centre line where sideways pushes reach well; that push turned by each of
    `turns_deg`; the other way (turn 180). Only those whose straight line keeps clear of the obstacles."""
    start = np.asarray(from_xy, dtype=np.float64)[:2]
    lateral = float(start[1] - np.asarray(robot_xy, dtype=np.float64)[1])
    toward_centre = np.array([0.0, -1.0 if lateral > 0 else 1.0])
    return turned_pushes(start, start + length_m * toward_centre, obstacles, object_radius_m, margin_m,
                         (0.0, *turns_deg, 180.0))


def _turning_path(from_xy: np.ndarray, robot_xy: Sequence[float] | np.ndarray, obstacles: Sequence[Obstacle],
                  object_radius_m: float, margin_m: float, turns_deg: Sequence[float],
                  length_m: float) -> tuple[ObjectPath, list[tuple[float, np.ndarray]]]:
    """A turning push's options (`turning_pushes`) and the straight path of the first (what a push's path is)."""
    options = turning_pushes(from_xy, robot_xy, obstacles, object_radius_m, margin_m, length_m, turns_deg)
    if not options:
        raise PlanningError("no turning push", f"every push of {length_m:.2f} m off the goal point "
                            f"{np.round(from_xy, 3).tolist()} to turn the object passes too close to an obstacle")
    waypoints = np.stack([np.asarray(from_xy, dtype=np.float64)[:2], options[0][1]])
    centres, radii = _centres_and_radii(obstacles)
    return ObjectPath(waypoints=waypoints, length_m=length_m, min_clearance_m=_path_clearance(waypoints, centres, radii),
                      planning_s=0.0), options


def _centres_and_radii(obstacles: Sequence[Obstacle]) -> tuple[np.ndarray, np.ndarray]:
    """The obstacles' centres [n, 2] and radii [n] (metres)."""
    discs = [Disc.of(o) for o in obstacles]
    return np.array([[d.x, d.y] for d in discs]).reshape(-1, 2), np.array([d.radius for d in discs])


def _first_pushable(push: PushStep, start: np.ndarray, options: list[tuple[float, np.ndarray]]) -> tuple[float, np.ndarray]:
    """(turn, observed position) of the first of `options` the arm can push; the first refusal when none."""
    first_refusal: DirectionInfeasible | None = None
    for turn, target in options:
        try:
            return turn, np.asarray(push(start, target), dtype=np.float64)[:2]
        except DirectionInfeasible as refusal:
            first_refusal = first_refusal or refusal
    if first_refusal is None:  # no push was tried (else it returned or was refused): never `raise None`
        raise ValueError("no push to try: `options` is empty")
    first_refusal.turns_tried = [turn for turn, _ in options[1:]]
    raise first_refusal


def _margin_left(position: np.ndarray, obstacles: Sequence[Obstacle], object_radius_m: float) -> float:
    """How much margin `position` keeps beyond every obstacle's radius + the object's radius (>= 0)."""
    gaps = [np.hypot(position[0] - d.x, position[1] - d.y) - d.radius - object_radius_m
            for d in map(Disc.of, obstacles)]
    return max(0.0, min(gaps, default=np.inf) - 1e-3)
