"""The data that flows between the planner's stages for one push (`stages.py`).

`Push` (where the object is, which way and how far) -> `Candidates` (the pose source's K hand poses,
in D and in the world) -> `Feasible` (the kinematically feasible ones in the order they are to be
tried, with their pre-contact IK solutions) -> `CandidatePlan`s (an arm plan for a candidate) ->
`RankedPlan`s (scored by their rollouts, best first) -> the executed `RankedPlan`.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from shared.contracts.messages import DirectionFrame, ObjectPath, Plan, ScoreTerms
from shared.frames import direction_frame, pose25_to_matrix, poses_d_to_world
from shared.planning import ranking
from shared.planning.motion import StraightLines
from shared.robots.hands import HandModel
from shared.world.push_outcome import object_pose


@dataclass(frozen=True)
class Push:
    """One straight push: the object at `T_world_O` moved `distance_m` along the horizontal unit `u` (world xy)."""

    T_world_O: np.ndarray
    u: np.ndarray
    distance_m: float
    # How far the push is to turn the object as well (degrees about world z, counterclockwise positive; 0: keep its
    # yaw): a push of a pose goal (`goals.turn_to_make_deg`). The pose source's candidates are then tried both as
    # they are and turned to make it (`goals.turning_poses`); None: as they are.
    turn_deg: float | None = None

    @cached_property
    def T_world_D(self) -> np.ndarray:
        """The direction frame D: at the object, +x along the push."""
        return direction_frame(self.T_world_O[:3, 3], self.u)

    @cached_property
    def frame(self) -> DirectionFrame:
        """D as a message, for the sampler and the validator."""
        return DirectionFrame(object_pose=object_pose(self.T_world_O),
                              direction_xy=(float(self.u[0]), float(self.u[1])))

    @property
    def direction(self) -> np.ndarray:
        """The push direction as a world 3-vector."""
        return np.append(self.u, 0.0)

    @property
    def offset(self) -> np.ndarray:
        """The push's displacement in the world (m)."""
        return self.distance_m * self.direction

    @property
    def target_xy(self) -> np.ndarray:
        """Where the object's centre should end (world xy)."""
        return self.T_world_O[:2, 3] + self.distance_m * self.u


@dataclass(frozen=True)
class Candidates:
    """K candidate hand poses of one push: [K, 25] in D and in the world, their hand-base transforms
    [K, 4, 4] and finger joints [K, n], each pose's direction cost L_dir [K] and, when the sampler has a
    success critic, its P(success) [K]. A push that is to turn the object also holds turned copies of the
    pose source's poses (`Push.turn_deg`): `source` [K] is then the index of the pose each candidate was
    made from (its own for the pose source's), so that a copy is considered beside its pose."""

    poses_d: np.ndarray
    poses_world: np.ndarray
    T_world_hand: np.ndarray
    q_hands: np.ndarray
    l_dir: np.ndarray
    p_success: np.ndarray | None = None
    source: np.ndarray | None = None
    tier: np.ndarray | None = None  # [K] 0: the pose source's (and turned copies), 1: slid copies, tried after

    @classmethod
    def in_frame(cls, poses_d: np.ndarray, push: Push, hand: HandModel, p_success: np.ndarray | None = None,
                 source: np.ndarray | None = None, tier: np.ndarray | None = None) -> Candidates:
        """The candidates for `poses_d` [K, 25], given in the push's frame D."""
        poses_world = poses_d_to_world(poses_d, push.T_world_D)
        T_world_hand, q_hands = pose25_to_matrix(poses_world)
        return cls(poses_d, poses_world, T_world_hand, q_hands, ranking.direction_costs(hand, poses_d), p_success,
                   source, tier)

    @property
    def order_l_dir(self) -> np.ndarray:
        """L_dir as the order reads it: a turned copy's is its pose's (a turned palm's alignment is worse by
        design, and would put every copy behind every pose)."""
        return self.l_dir if self.source is None else self.l_dir[self.source]

    def __len__(self) -> int:
        return len(self.poses_d)

    def raise_poses(self, rows: np.ndarray, lift_m: np.ndarray) -> None:
        """Raise candidates `rows` by `lift_m` (m, one per row) in place, as screening raised them out of the
        table (`ScreenResult.lift_m`): D's z is the world's, so one shift moves the pose in both frames."""
        for poses in (self.poses_d, self.poses_world):
            poses[rows, 2] += lift_m
        self.T_world_hand[rows, 2, 3] += lift_m


@dataclass(frozen=True)
class Feasible:
    """The kinematically feasible candidates (indices into `candidates`) in the order they are to be
    tried, the pre-contact IK solution of every screened candidate (`q_pre` [K, dof]) and the straight
    lines screening tracked from it (`lines` [K], None where not tracked)."""

    candidates: Candidates
    order: np.ndarray
    q_pre: np.ndarray
    lines: list[StraightLines | None] = dataclasses.field(default_factory=list)
    # The candidates not screened yet, in the order they would be (`stages.screen_more` screens them).
    unscreened: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0, dtype=int))

    def lines_of(self, index: int) -> StraightLines | None:
        return self.lines[index] if index < len(self.lines) else None

    def reordered(self, order: np.ndarray) -> Feasible:
        return dataclasses.replace(self, order=order)

    def without_first(self, n: int) -> Feasible:
        """The candidates after the first `n` of the order (those already tried)."""
        return self.reordered(self.order[n:])


@dataclass(frozen=True)
class CandidatePlan:
    """An arm plan for candidate `index`."""

    index: int
    plan: Plan

    def ranked(self, score: ScoreTerms | None, predicted: ObjectPath | None = None) -> RankedPlan:
        return RankedPlan(self.index, self.plan, score, predicted)


@dataclass(frozen=True)
class RankedPlan:
    """A plan chosen or ranked for execution: candidate `index`, its plan, the score of its arm rollout
    (None when the request is not ranked) and the object's path in that rollout (plan times)."""

    index: int
    plan: Plan
    score: ScoreTerms | None
    predicted: ObjectPath | None = None
