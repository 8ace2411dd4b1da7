"""Ranking feasible push plans by the paper's score V = α L_goal + β L_coll + γ L_dir (lower is better).

- L_goal: distance (m, table plane) of the object's final position from the target in the arm
  rollout (validator, `with_arm=True`);
- L_coll: 1 if the robot touched anything but the object with its hand during the rollout, else 0;
- L_dir = E_dir = -cos(v_palm, u_dir) of the hand pose in the direction frame D (u_dir = +x of D):
  -1 when the palm faces the push direction.

Weights. The terms have different units, so the weights say what trades for what:
- α = 10 per metre: a 3 cm miss (the success tolerance) costs 0.3;
- β = 1: a collision costs as much as a 10 cm miss — more than any successful push's error, so a
  colliding plan is chosen only when every plan collides;
- γ = 0.1: the palm's alignment only separates plans whose rollouts are about equally good (a palm
  60° off the push direction costs 0.05, i.e. a 5 mm miss).
These are set from the units and the success criterion, not yet tuned on data: tuning needs several
rolled-out candidates per request, i.e. the diffusion sampler's poses, and no Allegro checkpoint
existed when this was written (the fixed pose gives one candidate). With one, compare the success
of the chosen plan under a weight grid on the rollouts of bench/push.py's objects and directions.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from shared.frames import pose25_to_matrix
from shared.hands import HandModel
from shared.messages import ScoreTerms

ALPHA = 10.0
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
    return -normals[:, 0] / np.linalg.norm(normals, axis=1)


def score(l_goal: float, l_coll: float, l_dir: float, weights: Weights = Weights()) -> ScoreTerms:
    """The terms and V for one rolled-out plan."""
    v = weights.alpha * l_goal + weights.beta * l_coll + weights.gamma * l_dir
    return ScoreTerms(l_goal=l_goal, l_coll=l_coll, l_dir=l_dir, v=v, alpha=weights.alpha, beta=weights.beta,
                      gamma=weights.gamma)


def best(scores: list[ScoreTerms]) -> int:
    """Index of the plan with the lowest V (the first one on ties)."""
    if not scores:
        raise ValueError("nothing to rank: no scored plans")
    return int(np.argmin([s.v for s in scores]))
