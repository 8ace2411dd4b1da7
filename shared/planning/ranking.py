"""Ranking feasible push plans by the paper's score V = α L_goal + β L_coll + γ L_dir (lower is better).

- L_goal: distance (m, table plane) of the object's final position from the target in the arm
  rollout (validator, `with_arm=True`), plus FAILED_PUSH_PENALTY_M when the rollout leaves the
  object rotated by more than 45° or toppled (`goal_cost`). The paper's L_goal is the distance
  alone, but its success criterion also bounds the rotation: measured on the evaluation's GD2P
  failures, several executed plans ended 2–3 cm from the target but rotated 46–88° while other
  ranked plans kept the object upright.
  For a pose goal (`PushRequest.goal_yaw_deg`) L_goal adds the rollout's yaw miss, |final yaw - goal yaw| in
  radians times a length (`YawTerm`) so that the one α prices both misses: the object's footprint diameter,
  twice the arc its rim point farthest from the centre of mass is off by. Twice, because a position miss is
  mended by the next push along the path while a yaw miss takes pushes made to turn the object (with only the
  yaw left, one off the goal and one back), and because turning costs position: a palm turned to turn the
  object meets it at a corner and leaves it about that corner's reach short (measured: 4 cm short on a 30°
  turn of the 14 cm box, pushed 13 cm). Priced by the radius, that push and one keeping the position but not
  turning at all cost the same; priced by the diameter, the turn the goal asks for ranks ahead. A turn from
  the start is then no failure (the goal may ask for it);
- L_coll: 1 if the robot touched anything but the object with its hand during the rollout, else 0;
- L_dir = E_dir = -cos(v_palm, u_dir) of the hand pose in the direction frame D (u_dir = +x of D):
  -1 when the palm faces the push direction.

Robust ranking (`PlannerOptions.physics_draws`, `score_rollout`): L_goal is the mean of the goal cost
over the nominal rollout and the rollouts in the drawn worlds, so a push tuned to the nominal
friction and pose ranks behind one that works across them. The drawn worlds report no final pose, so a
pose goal's yaw miss is the nominal rollout's in every world.

Weights. The terms have different units, so the weights say what trades for what:
- α = 30 per metre: a 3 cm miss (the success tolerance) costs 0.9;
- β = 1: a collision costs as much as a 3.3 cm miss — about the success tolerance, so a colliding plan
  predicted to succeed ranks behind a clean one predicted to succeed, and ahead of a clean one
  predicted to miss;
- γ = 0.1: the palm's alignment only separates plans whose rollouts are about equally good (a palm
  60° off the push direction costs 0.05, i.e. a 1.7 mm miss).
Chosen on val objects (`bench/ranking_weights.py`: each request's plans from the energy optimiser,
planned and rolled out as the planner does, each plan judged by the share of 8 execution worlds —
`real` draws the ranking never saw — in which it succeeds; `bench/results/ranking_weights.json`): the
picks of α = 30, β = 1 succeed in more of those worlds than those of the earlier α = 10 (a collision
worth a 10 cm miss made the ranking prefer clean plans that miss), of β = 0 or of a random plan. End to
end on the val objects the gain is small: with diffusion samples and the prescreen most requests pick the
same plan. Robust ranking (mean L_goal over drawn worlds) picked no better than the nominal rollout at
more than twice the time per trial, so it is off by default (docs/evaluation.md §Tuned settings).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from shared.contracts.messages import ObjectPose, ScoreTerms, ValidationResult
from shared.frames import pose25_to_matrix
from shared.robots.hands import HandModel
from shared.world.push_outcome import (
    SUCCESS_MAX_ROTATION_DEG,
    TOPPLED_TILT_DEG,
    YawGoal,
    pose_matrix,
    rollout_predicts_success,
)

FAILED_PUSH_PENALTY_M = 0.1  # a rotated or toppled rollout ranks behind any clean miss of up to 10 cm
ALPHA = 30.0
BETA = 1.0
GAMMA = 0.1


@dataclass(frozen=True)
class Weights:
    alpha: float = ALPHA
    beta: float = BETA
    gamma: float = GAMMA


@dataclass(frozen=True)
class YawTerm:
    """A pose goal's term of L_goal: its yaw and the length that prices a yaw miss in metres, the object's
    footprint diameter (see the module docstring)."""

    goal: YawGoal
    length_m: float

    def miss_m(self, final: ObjectPose) -> float:
        """How far, in metres of L_goal, an object ending at `final` is from the goal yaw."""
        return self.length_m * math.radians(self.goal.error_deg(pose_matrix(final)[:3, :3]))


def direction_costs(hand: HandModel, poses_d: np.ndarray) -> np.ndarray:
    """L_dir = E_dir = -cos(palm normal, +x of D) for poses [K, 25] in D -> [K]."""
    transforms, _ = pose25_to_matrix(np.asarray(poses_d, dtype=np.float64).reshape(-1, 25))
    normals = transforms[:, :3, :3] @ hand.palm_normal_base.double().numpy()
    return np.asarray(-normals[:, 0] / np.linalg.norm(normals, axis=1))


def goal_cost(position_error_m: float, rotation_deg: float, max_tilt_deg: float,
              yaw_miss_m: float | None = None) -> float:
    """L_goal of one arm rollout: its distance from the target, penalised when the push fails on rotation or tilt.
    For a pose goal, `yaw_miss_m` (`YawTerm.miss_m`) is added and only tilting fails the push."""
    turned_too_far = yaw_miss_m is None and rotation_deg > SUCCESS_MAX_ROTATION_DEG
    failed = turned_too_far or max_tilt_deg > TOPPLED_TILT_DEG
    return position_error_m + (yaw_miss_m or 0.0) + (FAILED_PUSH_PENALTY_M if failed else 0.0)


def score_rollout(result: ValidationResult, l_dir: float, weights: Weights = Weights(),
                  yaw_term: YawTerm | None = None) -> ScoreTerms:
    """The score of one plan from its arm rollout (`ValidationResult` of one row). With physics draws
    (robust ranking), L_goal is the mean of the nominal rollout's and every drawn world's: a plan
    whose push only works in the nominal world ranks behind one that works in most of them. With a
    `yaw_term` (a pose goal), L_goal counts how far the rollout left the object from the goal yaw too."""
    assert result.goal_error_m is not None and result.collision_cost is not None, "an arm rollout's result"
    yaw_miss = None
    if yaw_term is not None:
        assert result.final_object_poses is not None, "an arm rollout reports where it left the object"
        yaw_miss = yaw_term.miss_m(result.final_object_poses[0])
    costs = [goal_cost(float(result.goal_error_m.to_numpy()[0]), float(result.rotation_deg.to_numpy()[0]),
                       float(result.max_tilt_deg.to_numpy()[0]), yaw_miss)]
    if result.draws is not None:
        draws = result.draws
        costs += [goal_cost(float(e), float(r), float(t), yaw_miss) for e, r, t in
                  zip(draws.position_error_m.to_numpy(), draws.rotation_deg.to_numpy(), draws.max_tilt_deg.to_numpy(),
                      strict=True)]
    terms = score(float(np.mean(costs)), float(result.collision_cost.to_numpy()[0]), l_dir, weights)
    if result.draws is None:
        return terms
    succeeded = int(sum(rollout_predicts_success(c) for c in costs))
    return terms.model_copy(update={"draws_succeeded": succeeded, "draws": len(costs)})


def predicts_success(terms: ScoreTerms) -> bool:
    """Whether a rolled-out plan's rollout met the success criterion (within 0.03 m, upright; for a pose goal
    the 0.03 m hold its position and yaw misses together)."""
    return rollout_predicts_success(terms.l_goal)


def score(l_goal: float, l_coll: float, l_dir: float, weights: Weights = Weights()) -> ScoreTerms:
    """The terms and V for one rolled-out plan."""
    v = weights.alpha * l_goal + weights.beta * l_coll + weights.gamma * l_dir
    return ScoreTerms(l_goal=l_goal, l_coll=l_coll, l_dir=l_dir, v=v, alpha=weights.alpha, beta=weights.beta,
                      gamma=weights.gamma)


def order(scores: list[ScoreTerms]) -> list[int]:
    """Indices of the plans from the lowest V to the highest (stable on ties)."""
    if not scores:
        raise ValueError("nothing to rank: no scored plans")
    return [int(i) for i in np.argsort([s.v for s in scores], kind="stable")]
