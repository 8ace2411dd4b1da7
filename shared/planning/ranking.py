"""Ranking feasible push plans by the paper's score V = α L_goal + β L_coll + γ L_dir (lower is better).

- L_goal: distance (m, table plane) of the object's final position from the target in the arm
  rollout (validator, `with_arm=True`), plus FAILED_PUSH_PENALTY_M when the rollout leaves the
  object rotated by more than 45° or toppled (`goal_cost`). The paper's L_goal is the distance
  alone, but its success criterion also bounds the rotation: measured on the evaluation's GD2P
  failures, several executed plans ended 2–3 cm from the target but rotated 46–88° while other
  ranked plans kept the object upright;
- L_coll: 1 if the robot touched anything but the object with its hand during the rollout, else 0;
- L_dir = E_dir = -cos(v_palm, u_dir) of the hand pose in the direction frame D (u_dir = +x of D):
  -1 when the palm faces the push direction.

Robust ranking (`PlannerOptions.physics_draws`, `score_rollout`): L_goal is the mean of the goal cost
over the nominal rollout and the rollouts in the drawn worlds, so a push tuned to the nominal
friction and pose ranks behind one that works across them.

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

from dataclasses import dataclass

import numpy as np

from shared.contracts.messages import ScoreTerms, ValidationResult
from shared.frames import pose25_to_matrix
from shared.robots.hands import HandModel
from shared.world.push_outcome import SUCCESS_MAX_ROTATION_DEG, TOPPLED_TILT_DEG, rollout_predicts_success

FAILED_PUSH_PENALTY_M = 0.1  # a rotated or toppled rollout ranks behind any clean miss of up to 10 cm
ALPHA = 30.0
BETA = 1.0
GAMMA = 0.1


@dataclass(frozen=True)
class Weights:
    alpha: float = ALPHA
    beta: float = BETA
    gamma: float = GAMMA


def direction_costs(hand: HandModel, poses_d: np.ndarray) -> np.ndarray:
    """L_dir = E_dir = -cos(palm normal, +x of D) for poses [K, 25] in D -> [K]."""
    transforms, _ = pose25_to_matrix(np.asarray(poses_d, dtype=np.float64).reshape(-1, 25))
    normals = transforms[:, :3, :3] @ hand.palm_normal_base.double().numpy()
    return np.asarray(-normals[:, 0] / np.linalg.norm(normals, axis=1))


def goal_cost(position_error_m: float, rotation_deg: float, max_tilt_deg: float) -> float:
    """L_goal of one arm rollout: its distance from the target, penalised when the push fails on rotation or tilt."""
    failed = rotation_deg > SUCCESS_MAX_ROTATION_DEG or max_tilt_deg > TOPPLED_TILT_DEG
    return position_error_m + (FAILED_PUSH_PENALTY_M if failed else 0.0)


def score_rollout(result: ValidationResult, l_dir: float, weights: Weights = Weights()) -> ScoreTerms:
    """The score of one plan from its arm rollout (`ValidationResult` of one row). With physics draws
    (robust ranking), L_goal is the mean of the nominal rollout's and every drawn world's: a plan
    whose push only works in the nominal world ranks behind one that works in most of them."""
    assert result.goal_error_m is not None and result.collision_cost is not None, "an arm rollout's result"
    costs = [goal_cost(float(result.goal_error_m.to_numpy()[0]), float(result.rotation_deg.to_numpy()[0]),
                       float(result.max_tilt_deg.to_numpy()[0]))]
    if result.draws is not None:
        draws = result.draws
        costs += [goal_cost(float(e), float(r), float(t)) for e, r, t in
                  zip(draws.position_error_m.to_numpy(), draws.rotation_deg.to_numpy(), draws.max_tilt_deg.to_numpy(),
                      strict=True)]
    terms = score(float(np.mean(costs)), float(result.collision_cost.to_numpy()[0]), l_dir, weights)
    if result.draws is None:
        return terms
    succeeded = int(sum(rollout_predicts_success(c) for c in costs))
    return terms.model_copy(update={"draws_succeeded": succeeded, "draws": len(costs)})


def predicts_success(terms: ScoreTerms) -> bool:
    """Whether a rolled-out plan's rollout met the success criterion (within 0.03 m, upright)."""
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
