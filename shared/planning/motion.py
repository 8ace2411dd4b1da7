"""Arm-hand motion for one push: IK, OMPL RRTConnect approach, Cartesian push, retreat, timing.

The paper plans with cuRobo; here (CPU, no GPU) the same plan is built from pieces. First,
`MotionPlanner.screen` discards the sampled poses that can never be executed (batched IK, then a
collision check of each pre-contact configuration; a pose whose hand is only a few mm in the table is
raised out of it instead, `table_lift_max_m`) and tracks the straight lines of every pose left
(`StraightLines`: approach, push, back-off) in one IK batch. Then, per pose, `plan_push`:

0. tries up to `max_ik_candidates` distinct IK solutions of the pre-contact pose until the straight
   lines below work with one of them (a joint at its stop on one IK branch may be free on another);

1. shape the hand: at the start configuration the fingers move to the pose's joint angles;
2. approach: OMPL RRTConnect in arm joint space from the start (home) to the configuration that
   puts the hand a standoff behind (against the push direction) and a lift above the pre-contact
   pose (the first workable pair of `approaches`), with the PyBullet scene
   (`shared.world.sim.robot_scene`) as the state validity checker, then OMPL's path simplification —
   unless the straight joint-space edge passes the same motion check, which it does for most
   approaches in free space (RRTConnect then ends with that edge too, after 3x the checks), or the
   waypoints between the ends of one of this planner's earlier paths do (`reuse_paths`: a push's poses
   lie close together, so its plans mostly need the same way around the object); then
   two straight Cartesian lines: down, and in along the push direction to the pre-contact pose.
   Free-space motion keeps `clearance_m` from everything; the last few centimetres near the table
   and the object cannot, so they are straight lines (where the hand goes is known), checked with a
   small contact tolerance instead;
3. push: the hand base moves in a straight line along +x of the direction frame D for the push
   distance, IK solved along the line from the previous solution, joint continuity checked, the
   object checked where the push has carried it;
4. retreat: straight back against the push direction (away from the pushed object), up by
   `retreat_lift_m`, then RRTConnect back to the start configuration, around the object placed
   where the push should leave it.

Joint-space motions are timed rest-to-rest per simplified-path edge with a quintic profile whose
peak joint speed is `velocity_scale` × the URDF limit; Cartesian segments move the hand at
`push_speed_mps` (slowed wherever a joint would exceed its scaled limit). Every infeasible request
raises `PlanningError` with a short `reason` ("no IK solution", "no collision-free path", ...).
"""
from __future__ import annotations

import contextlib
import math
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from ompl import base as ob
from ompl import geometric as og
from ompl import util as ou

from shared.contracts.messages import Plan, PlanSegment
from shared.planning.ik import ArmIK
from shared.robots.robot_limits import WorkspaceBox
from shared.world.sim.robot_scene import RobotScene

ou.setLogLevel(ou.LogLevel.LOG_ERROR)

TABLE_LIFT_MARGIN_M = 0.001  # a pose raised out of the table grazes it this much less than the tolerance


def seed_ompl(seed: int) -> None:
    """Seed the RNGs OMPL creates next (the state sampler's, the planner's): the same problem and seed
    plan the same path, whatever was planned before in this process.

    OMPL logs an error when re-seeding after its first random number, yet re-seeding works (its seed
    generator restarts; measured), so the log is silenced for the call. Process-wide: one plan at a time.
    """
    ou.setLogLevel(ou.LogLevel.LOG_NONE)
    ou.RNG.setSeed(seed % (2**31 - 1) + 1)  # OMPL ignores seed 0
    ou.setLogLevel(ou.LogLevel.LOG_ERROR)


class PlanningError(RuntimeError):
    """No plan exists (or none was found) for a request; `reason` is a short, stable phrase."""

    def __init__(self, reason: str, detail: str):
        super().__init__(f"{reason}: {detail}")
        self.reason = reason
        self.detail = detail


@dataclass(frozen=True)
class MotionSettings:
    # The hand comes down from `lift` above a point `standoff` behind the pre-contact pose (against the
    # push), then moves straight in: (standoff, lift) pairs in m, tried in order until one works.
    # 5 cm / 5 cm first. Fingers reaching around the object still overlap it 5 cm behind: 12 cm behind
    # clears them. Pulls on the far side of the object can leave the arm no reach further out: then
    # straight down; from 12 cm when the hand 6 cm above the pose is still within `clearance_m` of the object
    # (LEAP's pulls toward the xArm7 on low boxes: CHANGELOG.md "A way in from higher above"). As on every straight
    # line, the hand may touch the object on the way down (the rollouts simulate it); the arm may not, nor
    # may anything touch an obstacle.
    approaches: tuple[tuple[float, float], ...] = ((0.05, 0.05), (0.12, 0.05), (0.0, 0.06), (0.0, 0.12))
    retreat_m: float = 0.05  # back off against the push direction, lift, then RRTConnect back to the start
    retreat_lift_m: float = 0.05
    cartesian_step_m: float = 0.01  # IK waypoint spacing along straight-line segments
    push_speed_mps: float = 0.10  # the validator's push speed (docs/architecture.md §Simulation)
    velocity_scale: float = 0.5  # joint-space motion at this fraction of the velocity limits
    hand_shaping_s: float = 1.0  # time to move the fingers to the pose's joint angles
    max_joint_step_rad: float = 0.25  # larger jumps between 1 cm Cartesian waypoints = an IK branch switch
    max_ik_candidates: int = 4  # distinct IK solutions of the pre-contact pose tried for the straight lines
    clearance_m: float = 0.005  # free-space motion keeps this distance from table, object, obstacles
    contact_tolerance_m: float = 0.003  # Cartesian segments: the hand may graze the table by this much
    # A pre-contact pose whose hand is in the table by up to this much, and touches nothing else, is
    # raised until it grazes the table by less than `contact_tolerance_m` (`screen`). The floating hand
    # that validates the data is driven kinematically, so the table never pushed it out: learned and
    # retrieved poses sit a few mm low in the URDF's collision shapes. 0: never raised.
    table_lift_max_m: float = 0.02
    planning_time_s: float = 5.0  # RRTConnect time limit
    seed: int = 0  # every RRTConnect call starts from this OMPL seed: the same request plans the same arm paths
    # A joint path whose straight edge is blocked first tries, in the order they were found, the inner waypoints
    # of this planner's earlier RRTConnect paths (the pipeline makes one planner per push, so a request still
    # plans the same arm paths), each edge under the same motion check; RRTConnect only when none passes.
    reuse_paths: bool = True
    check_resolution_rad: float = 0.01  # joint-space collision-check step (max joint change)
    sample_dt_s: float = 0.02  # waypoint spacing of timed joint-space motions


@dataclass
class PlanStats:
    """What the last plan cost and the configurations it went through (for timings and benchmarks)."""

    ik_s: float = 0.0
    rrt_s: float = 0.0  # all RRTConnect calls, simplification included
    cartesian_s: float = 0.0
    rrt_calls_s: list[float] = field(default_factory=list)
    rrt_states: list[int] = field(default_factory=list)  # simplified path vertices per call
    reused_paths: int = 0  # joint paths made from an earlier path's waypoints, without RRTConnect
    configurations: dict[str, np.ndarray] = field(default_factory=dict)  # "pre_contact", "approach", ...


@dataclass(frozen=True)
class StraightLines:
    """A pose's straight Cartesian segments as IK tracked them from its pre-contact configuration, before
    their collision checks (`plan_push` makes those): tracked for many poses in one batch by `screen`, they
    spare each plan its own waypoint-by-waypoint IK (about half of a plan's time)."""

    push: np.ndarray  # [n, dof] from the pre-contact configuration along the push
    back_off: np.ndarray | None  # [n, dof] from the push's end back and up; None: the arm cannot follow it
    # [n, dof] down from above the first `MotionSettings.approaches` standoff and in to the pre-contact
    # configuration; None: the arm cannot follow it (`plan_push` tries the other approaches)
    approach: np.ndarray | None


@dataclass(frozen=True)
class ScreenResult:
    """Cheap per-pose feasibility of K pre-contact hand poses (before any path planning)."""

    q: np.ndarray  # [K, dof] IK solutions (rows of infeasible poses are undefined)
    feasible: np.ndarray  # [K] bool
    reasons: list[str]  # [K] "" when feasible, else why not ("no IK solution", ...)
    lines: list[StraightLines | None] = field(default_factory=list)  # [K] with a push: each feasible pose's lines
    # [K] how far each pose was raised out of the table (m; `MotionSettings.table_lift_max_m`): q and lines
    # belong to the raised pose, which the caller must plan instead of the one it gave
    lift_m: np.ndarray = field(default_factory=lambda: np.zeros(0))


class MotionPlanner:
    """Plans pushes for one arm + hand in one scene (table, object, obstacles already added)."""

    def __init__(self, scene: RobotScene, ik: ArmIK | None = None, settings: MotionSettings | None = None,
                 workspace: WorkspaceBox | None = None):
        """`workspace`: the robot's safety box (`RobotLimits.workspace`), which joint-space paths then keep
        the flange and the hand base inside; the robot refuses a plan that leaves it, and a straight
        joint-space edge can swing the hand far behind the arm (an xArm7 joint turning half a circle)."""
        self.scene = scene
        self.arm = scene.arm
        self.ik = ik or ArmIK(scene.arm, scene.hand, T_world_base=scene.T_world_base)
        self.settings = settings or MotionSettings()
        self.workspace = workspace
        self.lower = self.arm.joint_lower.double().numpy()
        self.upper = self.arm.joint_upper.double().numpy()
        self.velocity_limits = self.arm.velocity_limits.double().numpy()
        self.stats = PlanStats()
        self._hand_links = {scene.link_names[j] for j in scene.hand_links}
        self._known_vias: list[np.ndarray] = []  # inner waypoints [n, dof] of the RRTConnect paths found so far
        self._robot_links = set(scene.link_names.values())

    # ------------------------------------------------------------------------------------ screen

    def screen(self, T_world_hand: np.ndarray, q_hands: np.ndarray, push: np.ndarray | None = None) -> ScreenResult:
        """Batched IK for K hand poses [K,4,4] (hand joints [K,16]), then a collision check of each pose's
        distinct solutions, best first, until one is free (the elbow of the best may be in an obstacle).

        This discards what can never be executed (unreachable, or arm/hand into the table or an obstacle
        at the pre-contact pose) in about half a second for K = 200, before the per-pose `plan_push`.
        With `push` (the push's displacement in the world, m) the straight push line is tracked from
        each collision-free solution too, all poses in one batch, as `plan_push` would track it: a
        pull far across the workspace often starts reachable and runs out of reach.
        """
        T_world_hand = np.array(T_world_hand, dtype=np.float64).reshape(-1, 4, 4)
        q_hands = np.asarray(q_hands, dtype=np.float64).reshape(len(T_world_hand), -1)
        q, reasons = self._collision_free_solutions(T_world_hand, q_hands)
        lift = self._raise_out_of_table(T_world_hand, q_hands, q, reasons)
        lines: list[StraightLines | None] = [None] * len(T_world_hand)
        if push is not None:
            lines = self._screen_lines(T_world_hand, q, np.asarray(push, dtype=np.float64), reasons)
        return ScreenResult(q=q, feasible=np.array([not r for r in reasons]), reasons=reasons, lines=lines, lift_m=lift)

    def _collision_free_solutions(self, T_world_hand: np.ndarray, q_hands: np.ndarray) -> tuple[np.ndarray, list[str]]:
        """Batched IK of [K,4,4] hand poses, then each pose's first collision-free solution: (q [K, dof], reasons)."""
        started = time.perf_counter()
        options = self.ik.distinct_solutions(T_world_hand, limit=self.settings.max_ik_candidates)
        self.stats.ik_s += time.perf_counter() - started
        chosen = [self._first_collision_free(options_k, q_hand)
                  for options_k, q_hand in zip(options, q_hands, strict=True)]
        return np.array([q_k for q_k, _ in chosen]).reshape(len(options), self.arm.dof), [r for _, r in chosen]

    def _raise_out_of_table(self, T_world_hand: np.ndarray, q_hands: np.ndarray, q: np.ndarray,
                            reasons: list[str]) -> np.ndarray:
        """Raise the poses whose hand is only in the table, by at most `table_lift_max_m`, until it grazes it
        by less than `contact_tolerance_m`, and solve them there. T_world_hand, q and reasons of the poses
        raised and then feasible are updated in place; returns each pose's lift [K] (m, 0: not raised)."""
        s = self.settings
        lift = np.zeros(len(T_world_hand))
        for i, reason in enumerate(reasons):
            depth = self._table_depth(q[i], q_hands[i]) if reason.startswith("pre-contact pose in collision") else None
            if depth is not None and depth <= s.table_lift_max_m:
                lift[i] = depth - s.contact_tolerance_m + TABLE_LIFT_MARGIN_M
        rows = np.flatnonzero(lift > 0)
        if rows.size == 0:
            return lift
        raised = T_world_hand[rows].copy()
        raised[:, 2, 3] += lift[rows]
        q_raised, raised_reasons = self._collision_free_solutions(raised, q_hands[rows])
        for k, row in enumerate(rows):
            if raised_reasons[k]:
                lift[row] = 0.0
            else:
                T_world_hand[row], q[row], reasons[row] = raised[k], q_raised[k], ""
        return lift

    def _table_depth(self, q: np.ndarray, q_hand: np.ndarray) -> float | None:
        """How deep the hand is in the table (m) at (q, q_hand) when that is all it collides with, else None."""
        hits = self.scene.collisions(q, q_hand, clearance_m=-self.settings.contact_tolerance_m, allow_hand_object=True)
        if not hits or any(h.other != "table" or h.robot_link not in self._hand_links for h in hits):
            return None
        return -min(h.distance_m for h in hits)

    def _first_collision_free(self, options: np.ndarray, q_hand: np.ndarray) -> tuple[np.ndarray, str]:
        """The first IK solution among `options` [n, dof] whose arm and hand touch nothing but the object
        (`""`), else the best one and why it is infeasible."""
        if len(options) == 0:
            return self.arm.home.double().numpy(), "no IK solution"
        first_hit = None
        for q in options:
            hits = self.scene.collisions(q, q_hand, clearance_m=-self.settings.contact_tolerance_m,
                                         allow_hand_object=True, first_only=True)
            if not hits:
                return q, ""
            first_hit = first_hit or hits[0]
            if hits[0].robot_link in self._hand_links and hits[0].other not in self._robot_links:
                break  # the hand itself is in the table or an obstacle: the same for every arm solution
        return options[0], f"pre-contact pose in collision: {first_hit}"

    def _screen_lines(self, T_world_hand: np.ndarray, q: np.ndarray, push: np.ndarray,
                      reasons: list[str]) -> list[StraightLines | None]:
        """Each still-feasible pose's straight lines, all poses in one IK batch per path; the poses whose
        push line the arm cannot follow are marked infeasible (in `reasons`)."""
        lines: list[StraightLines | None] = [None] * len(reasons)
        rows = [i for i, r in enumerate(reasons) if not r]
        if not rows:
            return lines
        started = time.perf_counter()
        standoff_m, lift_m = self.settings.approaches[0]
        standoff = standoff_m * _horizontal_unit(push)
        n_push = len(self._line_targets(np.eye(4), push))
        # The push and the back-off after it form one path; so do the approach's two lines, solved back
        # from the pre-contact pose (as `_approach_via` solves them). Both in one batch (a tracking step
        # costs about the same for 1 or 100 paths), the shorter approach held at its end.
        push_paths = np.stack([self._push_targets(T_world_hand[i], push) for i in rows])
        approach_paths = np.stack([self._approach_targets(T_world_hand[i], standoff, lift_m) for i in rows])
        n_approach = approach_paths.shape[1]
        held = np.repeat(approach_paths[:, -1:], max(0, push_paths.shape[1] - n_approach), axis=1)
        both = self._followed(np.concatenate([push_paths, np.concatenate([approach_paths, held], axis=1)]),
                              np.concatenate([q[rows], q[rows]]))
        pushed, approached = both[:len(rows)], [(q_k[:n_approach + 1], why) for q_k, why in both[len(rows):]]
        self.stats.ik_s += time.perf_counter() - started
        for i, (push_q, push_failure), (approach_q, approach_failure) in zip(rows, pushed, approached, strict=True):
            if len(push_q) <= n_push:  # the push itself broke off
                reasons[i] = "push runs out of reach" if push_failure == "reach" else "push needs a joint jump"
                continue
            lines[i] = StraightLines(push=push_q[:n_push + 1], back_off=None if push_failure else push_q[n_push:],
                                     approach=None if approach_failure else approach_q[::-1])
        return lines

    def _followed(self, paths: np.ndarray, q_start: np.ndarray) -> list[tuple[np.ndarray, str]]:
        """Per path of hand poses [K,N,4,4] tracked from q_start [K,dof]: the joint waypoints from q_start up
        to the first waypoint the arm cannot reach or reaches only by a joint jump, and which of the two
        stopped it ("reach" / "jump"; "" when the whole path is followed)."""
        tracked = self.ik.track_many(paths, q_start)
        followed = []
        for q0, q_k, reached in zip(q_start, tracked.q, tracked.success, strict=True):
            q_path = np.concatenate([q0[None], q_k])
            jumped = np.abs(np.diff(q_path, axis=0)).max(axis=1) > self.settings.max_joint_step_rad
            bad = np.flatnonzero(~reached | jumped)
            if bad.size == 0:
                followed.append((q_path, ""))
            else:
                followed.append((q_path[:bad[0] + 1], "reach" if not reached[bad[0]] else "jump"))
        return followed

    def _push_targets(self, T_pre: np.ndarray, push: np.ndarray) -> np.ndarray:
        """Hand poses of the push from the pre-contact pose, then of the back-off after it (`_back_off`)."""
        s = self.settings
        direction = _horizontal_unit(push)
        T_end = _translated(T_pre, push)
        T_back = _translated(T_end, -s.retreat_m * direction)
        return np.concatenate([self._line_targets(T_pre, push), self._line_targets(T_end, -s.retreat_m * direction),
                               self._line_targets(T_back, np.array([0.0, 0.0, s.retreat_lift_m]))])

    def _approach_targets(self, T_pre: np.ndarray, standoff: np.ndarray, lift_m: float) -> np.ndarray:
        """Hand poses from the pre-contact pose back by `standoff`, then up by `lift_m` (the approach reversed)."""
        up = self._line_targets(_translated(T_pre, -standoff), np.array([0.0, 0.0, lift_m]))
        return np.concatenate([self._line_targets(T_pre, -standoff), up]) if standoff.any() else up

    def _line_targets(self, T_start: np.ndarray, displacement: np.ndarray) -> np.ndarray:
        """Hand poses [n,4,4] every `cartesian_step_m` along a straight line by `displacement`, the start excluded."""
        steps = max(1, math.ceil(np.linalg.norm(displacement) / self.settings.cartesian_step_m))
        fractions = np.arange(1, steps + 1) / steps
        targets = np.repeat(np.asarray(T_start, dtype=np.float64)[None], steps, axis=0)
        targets[:, :3, 3] += fractions[:, None] * displacement
        return targets

    # ------------------------------------------------------------------------------------- push

    def plan_push(
        self,
        T_world_hand: np.ndarray,
        q_hand: np.ndarray,
        push_direction: np.ndarray,
        distance_m: float,
        q_start: np.ndarray | None = None,
        q_hand_start: np.ndarray | None = None,
        q_pre_contact: np.ndarray | None = None,
        return_home: bool = True,
        lines: StraightLines | None = None,
    ) -> Plan:
        """A timed approach / push / retreat plan for the hand base pre-contact pose `T_world_hand`.

        `push_direction` is a horizontal world vector (+x of D); `q_start` the arm's current joints
        (default: home), `q_hand_start` the hand's (default: `q_hand`); `q_pre_contact` an IK solution
        already found for `T_world_hand` (e.g. by `screen`), else up to `max_ik_candidates` distinct
        solutions are tried; `lines` the straight lines `screen` tracked from it. Without `return_home` the plan ends backed off and lifted above the pushed
        object — enough to roll it out and rank it; `plan_return` adds the way back for the plan that is
        executed. Raises PlanningError (with a `reason`) when no plan is found.
        """
        self.stats = PlanStats()
        q_hand = np.asarray(q_hand, dtype=np.float64)
        q_start = self.arm.home.double().numpy() if q_start is None else np.asarray(q_start, dtype=np.float64)
        q_hand_start = q_hand if q_hand_start is None else np.asarray(q_hand_start, dtype=np.float64)
        direction = _horizontal_unit(push_direction)
        if distance_m <= 0:
            raise PlanningError("bad request", f"push distance must be positive, got {distance_m}")
        candidates = self._pre_contact_candidates(T_world_hand, q_pre_contact)
        q_pre, approach_line, push_line, back_off = self._straight_segments(
            candidates, T_world_hand, direction, distance_m, q_hand, lines)
        self._require_free(q_start, q_hand_start, "start configuration in collision", "the arm's start configuration")
        self._require_free(q_start, q_hand, "start configuration in collision",
                           "the fingers, shaped for the pose at the start configuration")
        self.stats.configurations.update(pre_contact=q_pre, approach=approach_line[0], push_end=push_line[-1],
                                         back_off=back_off[-1])
        free_path = self.plan_joint_path(q_start, approach_line[0], q_hand)
        home_path = self._home_path(back_off[-1], q_start, q_hand, distance_m * direction) if return_home else None
        return self._assemble(q_start, q_hand_start, q_hand, free_path, approach_line, push_line, back_off, home_path)

    def plan_return(self, plan: Plan, q_start: np.ndarray, push_offset: np.ndarray) -> Plan:
        """`plan` (made with `return_home=False`) extended by the joint-space way back to `q_start`.

        `push_offset` is where the push should move the object (world), which the way back avoids.
        """
        positions, times = plan.positions.to_numpy(), plan.times_s.to_numpy()
        dof = self.arm.dof
        q_end, q_hand = positions[-1, :dof], positions[-1, dof:]
        home_q, home_t = time_parameterise(self._home_path(q_end, np.asarray(q_start, dtype=np.float64), q_hand,
                                                           np.asarray(push_offset, dtype=np.float64)),
                                           self.velocity_limits * self.settings.velocity_scale, self.settings.sample_dt_s)
        extra = np.concatenate([home_q[1:], np.repeat(q_hand[None], len(home_q) - 1, axis=0)], axis=1)
        segments = [PlanSegment(label=seg.label, start=seg.start, stop=len(positions) + len(extra))
                    if seg.label == "retreat" else seg for seg in plan.segments]
        return Plan(arm=plan.arm, hand=plan.hand, joint_names=plan.joint_names,
                    positions=np.concatenate([positions, extra]),
                    times_s=np.concatenate([times, times[-1] + home_t[1:]]), segments=segments)

    def _home_path(self, q_from: np.ndarray, q_start: np.ndarray, q_hand: np.ndarray, push_offset: np.ndarray) -> np.ndarray:
        """Joint path back to the start, around the object where the push should have left it."""
        with self._object_moved(push_offset):
            try:
                return self.plan_joint_path(q_from, q_start, q_hand)
            except PlanningError as exc:
                raise PlanningError(exc.reason, f"retreat: {exc.detail}") from None

    def _approach_line(self, q_pre: np.ndarray, T_pre: np.ndarray, direction: np.ndarray,
                       q_hand: np.ndarray, tracked: StraightLines | None = None) -> np.ndarray:
        """Joint waypoints down from above a standoff, then in along the push to the pre-contact pose,
        for the first of `MotionSettings.approaches` that is reachable and collision-free (the first
        as `tracked` holds it, when it does). When none is, the error names why each way in failed."""
        failed: list[tuple[str, PlanningError]] = []
        for option, (standoff_m, lift_m) in enumerate(self.settings.approaches):
            try:
                if option == 0 and tracked is not None and tracked.approach is not None:
                    return self._checked_approach(tracked.approach, standoff_m * direction, lift_m, q_hand)
                return self._approach_via(q_pre, T_pre, standoff_m * direction, lift_m, q_hand)
            except PlanningError as exc:
                failed.append(("from behind" if standoff_m > 0 else "from above", exc))
        raise _no_approach(failed)

    def _approach_via(self, q_pre: np.ndarray, T_pre: np.ndarray, standoff: np.ndarray, lift_m: float,
                      q_hand: np.ndarray) -> np.ndarray:
        """Down by `lift_m` above the point `standoff` (world) behind the pre-contact pose, then in to it."""
        # Solved in reverse, from the pre-contact configuration: back against the push, then up.
        forward = self._cartesian(q_pre, T_pre, -standoff, q_hand, "approach")[::-1] if standoff.any() else q_pre[None]
        T_standoff = _translated(T_pre, -standoff)
        down = self._cartesian(forward[0], T_standoff, np.array([0.0, 0.0, lift_m]), q_hand, "approach")[::-1]
        self._require_free(down[0], q_hand, "approach configuration in collision",
                           f"the hand {np.linalg.norm(standoff):.2f} m behind and {lift_m:.2f} m above "
                           "the pre-contact pose")
        return np.concatenate([down, forward[1:]])

    def _checked_approach(self, approach: np.ndarray, standoff: np.ndarray, lift_m: float,
                          q_hand: np.ndarray) -> np.ndarray:
        """`_approach_via`'s checks of an approach tracked beforehand (`StraightLines.approach`)."""
        self._check_line(approach, None, q_hand, "approach")
        self._require_free(approach[0], q_hand, "approach configuration in collision",
                           f"the hand {np.linalg.norm(standoff):.2f} m behind and {lift_m:.2f} m above "
                           "the pre-contact pose")
        return approach

    def _back_off(self, q_end: np.ndarray, T_end: np.ndarray, direction: np.ndarray, q_hand: np.ndarray) -> np.ndarray:
        """Joint waypoints straight back from the pushed object, then up, clear for the joint-space return."""
        s = self.settings
        back = self._cartesian(q_end, T_end, -s.retreat_m * direction, q_hand, "retreat")
        T_back = _translated(T_end, -s.retreat_m * direction)
        up = self._cartesian(back[-1], T_back, np.array([0.0, 0.0, s.retreat_lift_m]), q_hand, "retreat")
        return np.concatenate([back, up[1:]])

    @contextlib.contextmanager
    def _object_moved(self, offset: np.ndarray) -> Iterator[None]:
        """Temporarily shift the scene's object by `offset` (world), e.g. to where a push leaves it."""
        with self._movable_object() as move:
            move(offset)
            yield

    @contextlib.contextmanager
    def _movable_object(self) -> Iterator[Callable[[np.ndarray], None]]:
        """A function that shifts the scene's object by an offset (world) from where it is; restored after."""
        body = self.scene.object
        if body is None:
            yield lambda offset: None
            return
        original = body.pose()

        def move(offset: np.ndarray) -> None:
            moved = original.copy()
            moved[:3, 3] += offset
            body.reset_pose(moved)

        try:
            yield move
        finally:
            body.reset_pose(original)

    def _pre_contact_candidates(self, T_world_hand: np.ndarray, q_pre_contact: np.ndarray | None) -> np.ndarray:
        """Arm configurations [n, dof] for the pre-contact pose to try, best first."""
        if q_pre_contact is not None:
            return np.asarray(q_pre_contact, dtype=np.float64).reshape(1, -1)
        started = time.perf_counter()
        solutions = self.ik.distinct_solutions(T_world_hand, limit=self.settings.max_ik_candidates)[0]
        self.stats.ik_s += time.perf_counter() - started
        if len(solutions) == 0:
            best = self.ik.solve_hand_poses(T_world_hand)
            raise PlanningError("no IK solution", f"the arm cannot reach the pre-contact hand pose (best attempt "
                                f"{best.position_error_m[0] * 1000:.0f} mm, "
                                f"{math.degrees(best.rotation_error_rad[0]):.0f} deg off)")
        return solutions

    def _straight_segments(self, candidates: np.ndarray, T_world_hand: np.ndarray, direction: np.ndarray,
                           distance_m: float, q_hand: np.ndarray,
                           lines: StraightLines | None = None) -> tuple[np.ndarray, ...]:
        """(q_pre, approach, push, back-off) for the first IK candidate whose straight-line pieces all work
        (the lines `screen` tracked are only collision-checked here, for the candidate they start from).

        Straight lines are cheap and reject most infeasible poses before any RRT. A candidate fails when
        it collides at the pre-contact pose or a joint runs into its stop along a line; the next IK
        branch may not. The error of the best candidate is reported if none works.
        """
        s = self.settings
        first_error: PlanningError | None = None
        for q_pre in candidates:
            tracked = lines if lines is not None and np.array_equal(lines.push[0], q_pre) else None
            try:
                hits = self.scene.collisions(q_pre, q_hand, clearance_m=-s.contact_tolerance_m, allow_hand_object=True)
                if hits:
                    raise PlanningError("pre-contact pose in collision", ", ".join(str(h) for h in hits[:3]))
                approach_line = self._approach_line(q_pre, T_world_hand, direction, q_hand, tracked)
                if tracked is not None:
                    push_line = tracked.push
                    self._check_line(push_line, distance_m * direction, q_hand, "push")
                else:
                    push_line = self._cartesian(q_pre, T_world_hand, distance_m * direction, q_hand, "push",
                                                carry_object=True)
                T_push_end = _translated(T_world_hand, distance_m * direction)
                with self._object_moved(distance_m * direction):  # where the push leaves it
                    if tracked is not None and tracked.back_off is not None:
                        back_off = tracked.back_off
                        self._check_line(back_off, None, q_hand, "retreat")
                    else:
                        back_off = self._back_off(push_line[-1], T_push_end, direction, q_hand)
                return q_pre, approach_line, push_line, back_off
            except PlanningError as exc:
                first_error = first_error or exc
        assert first_error is not None
        raise first_error

    def _require_free(self, q: np.ndarray, q_hand: np.ndarray, reason: str, what: str) -> None:
        hits = self.scene.collisions(q, q_hand, clearance_m=self.settings.clearance_m)
        if hits:
            raise PlanningError(reason, f"{what}: " + ", ".join(str(h) for h in hits[:3]))

    # ------------------------------------------------------------------------------ joint space

    def plan_joint_path(self, q_start: np.ndarray, q_goal: np.ndarray, q_hand: np.ndarray | None) -> np.ndarray:
        """A collision-free, simplified joint path [n, dof] from `q_start` to `q_goal` (RRTConnect).

        The path's straight edges are collision-checked at `check_resolution_rad`; interpolate them
        no coarser than that before executing (`time_parameterise` does).
        """
        s = self.settings
        dof = self.arm.dof
        space = ob.RealVectorStateSpace(dof)
        bounds = ob.RealVectorBounds(dof)
        for i in range(dof):
            bounds.setLow(i, float(self.lower[i]))
            bounds.setHigh(i, float(self.upper[i]))
        space.setBounds(bounds)
        # OMPL checks an edge every `fraction × maximum extent` in joint-space Euclidean distance.
        space.setLongestValidSegmentFraction(s.check_resolution_rad / space.getMaximumExtent())
        seed_ompl(s.seed)
        setup = og.SimpleSetup(space)
        scene, clearance = self.scene, s.clearance_m
        if q_hand is not None:
            scene.set_configuration(q_start, q_hand)

        def valid(state: Any) -> bool:  # an OMPL state
            return scene.is_collision_free([state[i] for i in range(dof)], clearance_m=clearance) and \
                self._inside_workspace()

        setup.setStateValidityChecker(valid)
        start, goal = space.allocState(), space.allocState()
        for i in range(dof):
            start[i], goal[i] = float(q_start[i]), float(q_goal[i])
        setup.setStartAndGoalStates(start, goal)
        setup.setPlanner(og.RRTConnect(setup.getSpaceInformation()))
        for name, q in (("start", q_start), ("goal", q_goal)):
            hits = scene.collisions(q, clearance_m=clearance)
            if hits:
                raise PlanningError(f"{name} configuration in collision", ", ".join(str(h) for h in hits[:3]))
            if not self._inside_workspace():
                raise PlanningError(f"{name} configuration outside the workspace box",
                                    f"the flange or the hand base is outside {self.workspace}")
        started = time.perf_counter()
        if self._straight_edge_free(q_start, q_goal, valid):
            # Most approaches and ways back are one straight joint-space edge: RRTConnect and the
            # simplifier end there too, after checking about three times as many states.
            waypoints = np.array([q_start, q_goal], dtype=np.float64)
            self._count_rrt(started, waypoints)
            return waypoints
        known = self._known_way(q_start, q_goal, valid) if s.reuse_paths else None
        if known is not None:
            self.stats.reused_paths += 1
            self._count_rrt(started, known)
            return known
        solved = setup.solve(s.planning_time_s)
        if not (solved and setup.haveExactSolutionPath()):
            self.stats.rrt_s += time.perf_counter() - started
            raise PlanningError("no collision-free path",
                                f"RRTConnect found no collision-free arm path to the approach configuration "
                                f"within {s.planning_time_s:.1f} s")
        path = setup.getSolutionPath()
        # Shortcutting only: SimpleSetup.simplifySolution also B-spline-smooths, which costs seconds of
        # collision checks here and is unnecessary (edges are timed rest-to-rest anyway).
        simplifier = og.PathSimplifier(setup.getSpaceInformation())
        simplifier.reduceVertices(path)
        simplifier.partialShortcutPath(path)
        simplifier.reduceVertices(path)
        waypoints = np.array([[st[i] for i in range(dof)] for st in path.getStates()])
        self._count_rrt(started, waypoints)
        if len(waypoints) > 2:
            self._known_vias.append(waypoints[1:-1].copy())
        return waypoints

    def _known_way(self, q_start: np.ndarray, q_goal: np.ndarray, valid: Callable[[Any], bool]) -> np.ndarray | None:
        """A path [n, dof] from `q_start` through the inner waypoints of an earlier path to `q_goal` whose
        waypoints are valid and every edge passes the motion check (`_straight_edge_free`), as OMPL checks a
        motion; earlier paths are tried in the order found, None when none passes. A blocked edge fails within a
        few checks (bisection order)."""
        for vias in self._known_vias:
            path = np.concatenate([np.asarray(q_start, dtype=np.float64)[None], vias,
                                   np.asarray(q_goal, dtype=np.float64)[None]])
            if all(valid(q) for q in vias) and \
                    all(self._straight_edge_free(a, b, valid) for a, b in zip(path[:-1], path[1:], strict=True)):
                return path
        return None

    def _inside_workspace(self) -> bool:
        """Whether the flange and the hand base, as the scene's robot stands, are inside `workspace` (if any)."""
        if self.workspace is None:
            return True
        flange = self.scene.link_pose(self.arm.flange_link)
        points = np.stack([flange[:3, 3], (flange @ self.ik.T_flange_hand)[:3, 3]])
        return bool(np.all(self.workspace.contains(points)))

    def _count_rrt(self, started: float, waypoints: np.ndarray) -> None:
        elapsed = time.perf_counter() - started
        self.stats.rrt_s += elapsed
        self.stats.rrt_calls_s.append(elapsed)
        self.stats.rrt_states.append(len(waypoints))

    def _straight_edge_free(self, q_start: np.ndarray, q_goal: np.ndarray, valid: Callable[[Any], bool]) -> bool:
        """Whether the straight joint-space edge passes OMPL's own motion check: every state at most
        `check_resolution_rad` (Euclidean) apart valid. Bisection order: a blocked edge fails early."""
        q_start, q_goal = np.asarray(q_start, dtype=np.float64), np.asarray(q_goal, dtype=np.float64)
        steps = math.ceil(float(np.linalg.norm(q_goal - q_start)) / self.settings.check_resolution_rad)
        for k in _bisection_order(steps):
            if not valid(q_start + (k / steps) * (q_goal - q_start)):
                return False
        return True

    # --------------------------------------------------------------------------------- Cartesian

    def _cartesian(self, q_start: np.ndarray, T_start: np.ndarray, displacement: np.ndarray, q_hand: np.ndarray,
                   label: str, carry_object: bool = False) -> np.ndarray:
        """Joint waypoints [n, dof] moving the hand base in a straight line by `displacement` (world).

        The first row is `q_start`. Hand-object contact is allowed (that is the push); table contact
        up to `contact_tolerance_m`; obstacles, arm-object and arm-hand contacts are not. With
        `carry_object` (the push) each waypoint is checked with the object moved as far as the hand:
        the object goes ahead of the hand, so the wrist following it through where the object stood
        is no collision (with the object left standing, 7 of 10 pushes of a flat box were rejected
        for the Panda's link 7 sweeping through it).
        """
        s = self.settings
        started = time.perf_counter()
        targets = self._line_targets(T_start, displacement)
        steps = len(targets)
        fractions = np.arange(1, steps + 1) / steps
        result = self.ik.track(targets, q_start)
        self.stats.cartesian_s += time.perf_counter() - started
        if not result.success.all():
            bad = int(np.argmin(result.success))
            raise PlanningError("no IK solution", f"{label} segment: the arm cannot follow the straight line past "
                                f"{fractions[bad] * np.linalg.norm(displacement) * 100:.1f} cm "
                                f"({result.position_error_m[bad] * 1000:.1f} mm, "
                                f"{math.degrees(result.rotation_error_rad[bad]):.1f} deg off"
                                f"{self._limit_note(result.q[bad])})")
        q = np.concatenate([np.asarray(q_start, dtype=np.float64)[None], result.q])
        jumps = np.abs(np.diff(q, axis=0)).max(axis=1)
        if jumps.max() > s.max_joint_step_rad:
            bad = int(jumps.argmax())
            raise PlanningError("discontinuous joint motion", f"{label} segment: a joint jumps "
                                f"{jumps[bad]:.2f} rad between Cartesian waypoints {bad} and {bad + 1}")
        self._check_line(q, displacement if carry_object else None, q_hand, label)
        return q

    def _check_line(self, q: np.ndarray, carried: np.ndarray | None, q_hand: np.ndarray, label: str) -> None:
        """Collision-check a straight line's joint waypoints [n, dof] (`_cartesian`'s rules); `carried`: the
        displacement over which the object goes ahead of the hand (the push), else None."""
        fractions = np.linspace(0.0, 1.0, len(q)) if carried is not None else np.zeros(len(q))
        offsets = fractions[:, None] * (carried if carried is not None else np.zeros(3))
        with self._movable_object() as move_object:
            for row, offset in zip(q, offsets, strict=True):
                move_object(offset)
                hits = self.scene.collisions(row, q_hand, clearance_m=-self.settings.contact_tolerance_m,
                                             allow_hand_object=True)
                if hits:
                    raise PlanningError(f"{label} segment in collision", ", ".join(str(h) for h in hits[:3]))

    def _limit_note(self, q: np.ndarray) -> str:
        """', joint N at its limit' for joints within 0.01 rad of a limit (the usual cause of IK failure)."""
        near = np.flatnonzero((q - self.lower < 0.01) | (self.upper - q < 0.01))
        return "".join(f", {self.arm.joint_names[j]} at its limit" for j in near)

    # ----------------------------------------------------------------------------------- timing

    def _assemble(self, q_start: np.ndarray, q_hand_start: np.ndarray, q_hand: np.ndarray, free_path: np.ndarray,
                  approach_line: np.ndarray, push_line: np.ndarray, back: np.ndarray, home_path: np.ndarray | None,
                  ) -> Plan:
        s = self.settings
        limits = self.velocity_limits * s.velocity_scale
        hand_steps = max(2, math.ceil(s.hand_shaping_s / s.sample_dt_s) + 1)
        shaping_times = np.linspace(0.0, s.hand_shaping_s, hand_steps)
        arm_pieces = [  # (arm joints, relative times), each piece starting where the previous one ended
            (np.repeat(q_start[None], hand_steps, axis=0), shaping_times),
            time_parameterise(free_path, limits, s.sample_dt_s),
            self._cartesian_timing(approach_line),
            self._cartesian_timing(push_line),
            self._cartesian_timing(back),
        ]
        if home_path is not None:
            arm_pieces.append(time_parameterise(home_path, limits, s.sample_dt_s))
        arm_parts: list[np.ndarray] = []
        times: list[np.ndarray] = []
        counts: list[int] = []
        offset = 0.0
        for i, (q, t) in enumerate(arm_pieces):
            skip = 0 if i == 0 else 1  # the first waypoint of a piece is the last of the previous one
            arm_parts.append(q[skip:])
            times.append(offset + t[skip:])
            counts.append(len(q) - skip)
            offset = times[-1][-1]
        arm_q = np.concatenate(arm_parts)
        hand_q = np.repeat(q_hand[None], len(arm_q), axis=0)
        hand_q[:hand_steps] = np.linspace(q_hand_start, q_hand, hand_steps)
        n_approach, n_push = sum(counts[:3]), counts[3]
        return Plan(
            arm=self.arm.name, hand=self.scene.hand.name, joint_names=list(self.scene.joint_names),
            positions=np.concatenate([arm_q, hand_q], axis=1), times_s=np.concatenate(times),
            segments=[PlanSegment(label="approach", start=0, stop=n_approach),
                      PlanSegment(label="push", start=n_approach, stop=n_approach + n_push),
                      PlanSegment(label="retreat", start=n_approach + n_push, stop=len(arm_q))])

    def _cartesian_timing(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Times for Cartesian waypoints: hand speed `push_speed_mps`, slowed where a joint would be too fast."""
        s = self.settings
        nominal = s.cartesian_step_m / s.push_speed_mps
        joint_bound = (np.abs(np.diff(q, axis=0)) / (self.velocity_limits * s.velocity_scale)).max(axis=1)
        return q, np.concatenate([[0.0], np.cumsum(np.maximum(nominal, joint_bound))])


# --------------------------------------------------------------------------------------- helpers


def time_parameterise(path: np.ndarray, velocity_limits: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Rest-to-rest quintic timing of each edge of a joint path; samples every `dt` (and every vertex).

    A quintic blend s(τ) = 10τ³ − 15τ⁴ + 6τ⁵ peaks at 1.875 × the mean speed, so an edge of joint
    change Δ takes T = 1.875 max_j |Δ_j| / v_j: no joint exceeds its limit v_j, and velocity and
    acceleration are zero at every vertex (the robot never has to turn a corner at speed).
    Returns (positions [n, dof], times [n]) starting at t = 0.
    """
    path = np.asarray(path, dtype=np.float64)
    positions, times, offset = [path[0]], [0.0], 0.0
    for a, b in zip(path[:-1], path[1:], strict=True):
        duration = 1.875 * float((np.abs(b - a) / velocity_limits).max())
        if duration <= 0.0:
            continue
        steps = max(1, math.ceil(duration / dt))
        tau = np.arange(1, steps + 1) / steps
        blend = 10 * tau**3 - 15 * tau**4 + 6 * tau**5
        positions.extend(a + blend[:, None] * (b - a))
        times.extend(offset + tau * duration)
        offset += duration
    return np.array(positions), np.array(times)


def _bisection_order(steps: int) -> list[int]:
    """The inner points 1 .. steps-1 of an edge cut in `steps`, middle first, then the quarters, and so on."""
    order: list[int] = []
    seen: set[int] = set()
    level = 1
    while len(order) < steps - 1:
        level *= 2
        for k in range(1, level, 2):
            point = round(k * steps / level)
            if 0 < point < steps and point not in seen:
                seen.add(point)
                order.append(point)
        if level > 4 * steps:  # rounding left some out: add them in order
            order += [k for k in range(1, steps) if k not in seen]
            break
    return order


def _no_approach(failed: list[tuple[str, PlanningError]]) -> PlanningError:
    """The error of a pre-contact pose no approach leads to: the approaches' own reason when they share it,
    else "no approach" with each way's reason, e.g. on an xArm7 pulling toward itself: "no approach
    (from behind: no IK solution; from above: approach configuration in collision)"."""
    assert failed, "MotionSettings.approaches is empty"
    reasons = {exc.reason for _, exc in failed}
    detail = "; ".join(f"{way}: {exc.detail}" for way, exc in failed)
    if len(reasons) == 1:
        return PlanningError(failed[0][1].reason, detail)
    ways = dict.fromkeys(f"{way}: {exc.reason}" for way, exc in failed)  # ordered, without repeats
    return PlanningError(f"no approach ({'; '.join(ways)})", detail)


def _horizontal_unit(direction: np.ndarray) -> np.ndarray:
    direction = np.asarray(direction, dtype=np.float64).reshape(-1)
    if direction.size == 2:
        direction = np.append(direction, 0.0)
    horizontal = np.array([direction[0], direction[1], 0.0])
    norm = np.linalg.norm(horizontal)
    if direction.size != 3 or norm < 1e-9:
        raise PlanningError("bad request", f"push direction must be a horizontal 2- or 3-vector, got {direction}")
    return np.asarray(horizontal / norm)


def _translated(T: np.ndarray, offset: np.ndarray) -> np.ndarray:
    out = np.array(T, dtype=np.float64, copy=True)
    out[:3, 3] += offset
    return out
