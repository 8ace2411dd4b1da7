"""Measure the ranking weights (α, β, γ of V = α L_goal + β L_coll + γ L_dir) and robust ranking on
real candidate plans of val objects, judged in execution worlds the ranking never saw.

    python bench/ranking_weights.py --json      # last line: one JSON object

Candidates: push poses from the project's energy-based optimiser (`services.generator`, the
dataset's source — the diffusion model learns to sample like it; unfiltered, with fewer iterations
than the dataset, so there are bad ones among them, as in a sampler's output), for val objects (tuning
never looks at test objects) and a few directions, placed as the planner places them (object at 0.55 m
in front of the robot). Each pose goes through the planner's own steps: IK + collision screen,
`plan_push`, and an arm rollout (`shared.validation.rollout`) in the nominal world plus
`--rank-draws` drawn worlds (what robust ranking sees, `PlannerOptions.physics_draws`).

Truth: each plan is also played in `--truth-worlds` other worlds drawn from the evaluation's `real`
ranges with seeds of their own (friction, mass, centre of mass, controller, the object off its told
pose); a plan's worth is the fraction of them in which the push succeeds. Then, for each request,
every pick rule chooses one plan; reported: the mean truth success of the picked plans and how often
the pick collided, for the shipped weights, a grid around them, L_goal alone, L_dir alone, robust
ranking (mean L_goal over the rank draws, shipped β and γ), a random pick (expected) and the best
achievable (the plan with the highest truth success).
"""
from __future__ import annotations

import argparse
import itertools
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from shared.contracts.messages import DirectionFrame, ObjectRef, ValidationJob
from shared.frames import direction_frame, pose25_to_matrix, poses_d_to_world
from shared.planning import ranking
from shared.planning.motion import MotionPlanner, PlanningError
from shared.robots.hands import load_hand
from shared.synthesis.config import GenerationConfig
from shared.synthesis.synthesis import generate
from shared.validation.jobs import DEFAULT_PARAMS
from shared.validation.rollout import rollout
from shared.world.objects import load_object, write_object_urdf
from shared.world.push_outcome import object_pose
from shared.world.sim.robot_scene import RobotScene

OBJECTS = ("proc-box-010", "proc-cylinder-006", "proc-cone-006", "proc-hull-006", "proc-capsule-016", "rnd-002")
DIRECTIONS_DEG = (90.0, -90.0)
RANK_SEED, TRUTH_SEED = 0, 1_000_003  # the robust ranking's draws and the truth's come from different seeds
GRID = {"alpha": (1.0, 10.0, 30.0), "beta": (0.0, 1.0), "gamma": (0.0, 0.1, 0.5)}


def candidate_rollouts(object_id: str, direction_deg: float, n_poses: int, max_plans: int, iterations: int,
                       seed: int, rank_draws: int, truth_worlds: int) -> list[dict]:
    """Terms, robust L_goal and truth success of up to `max_plans` planned candidates for one object and
    direction."""
    obj = load_object(object_id)
    hand = load_hand("allegro")
    output = generate(obj, hand, n_poses, seed, GenerationConfig(iterations=iterations))
    poses_d = output.poses  # unfiltered, like a sampler's output: ranking has to sort out the bad ones
    # The optimiser placed the object at its default pose, yaw 0 in D: place it in the world that way.
    T_world_D = direction_frame(np.array([0.55, 0.0, 0.0]), direction_deg)
    T_world_O = T_world_D @ output.object_transform_d
    T_world_hand, q_hands = pose25_to_matrix(poses_d_to_world(poses_d, T_world_D))
    l_dir = ranking.direction_costs(hand, poses_d)
    frame = DirectionFrame(object_pose=object_pose(T_world_O), yaw_deg=direction_deg)
    rows: list[dict[str, Any]] = []
    with RobotScene("panda", "allegro") as scene:
        scene.add_object(write_object_urdf(obj), T_world_O)
        planner = MotionPlanner(scene)
        screen = planner.screen(T_world_hand, q_hands)
        for index in np.flatnonzero(screen.feasible):
            if len(rows) == max_plans:
                break
            try:
                plan = planner.plan_push(T_world_hand[index], q_hands[index], T_world_D[:3, 0], 0.20,
                                         q_hand_start=hand.open_joint_positions.numpy(), q_pre_contact=screen.q[index])
            except PlanningError:
                continue
            job = ValidationJob(object=ObjectRef(library_id=object_id), hand="allegro", poses=poses_d[index][None],
                                with_arm=True, arm="panda", plan=plan, frame=frame, seed=RANK_SEED,
                                physics_draws=rank_draws)
            ranked = rollout(job, DEFAULT_PARAMS)
            truth = rollout(job.model_copy(update={"seed": TRUTH_SEED, "physics_draws": truth_worlds}), DEFAULT_PARAMS)
            assert truth.draws is not None  # physics_draws > 0
            nominal = ranking.score_rollout(ranked.model_copy(update={"draws": None}), float(l_dir[index]))
            robust = ranking.score_rollout(ranked, float(l_dir[index]))
            rows.append({"l_goal": nominal.l_goal, "l_goal_robust": robust.l_goal, "l_coll": nominal.l_coll,
                         "l_dir": nominal.l_dir, "nominal_success": bool(ranked.success.to_numpy()[0]),
                         "draws_succeeded": robust.draws_succeeded,
                         "success": float(truth.draws.success.to_numpy().mean())})
    return rows


def pick_rates(requests: list[list[dict]], alpha: float, beta: float, gamma: float, goal: str = "l_goal") -> dict:
    """The truth success and collision rate of the plans V picks, with L_goal read from `goal`."""
    picked = [min(rows, key=lambda r: alpha * r[goal] + beta * r["l_coll"] + gamma * r["l_dir"]) for rows in requests]
    return {"success": round(float(np.mean([p["success"] for p in picked])), 3),
            "collided": round(float(np.mean([p["l_coll"] > 0 for p in picked])), 3)}


def pick_by_draws(requests: list[list[dict]]) -> dict:
    """The truth success of picking the plan that succeeded in the most rank worlds (ties: the shipped V)."""
    def key(r: dict) -> tuple[float, float]:
        return -r["draws_succeeded"], ranking.ALPHA * r["l_goal"] + ranking.BETA * r["l_coll"] + ranking.GAMMA * r["l_dir"]
    picked = [min(rows, key=key) for rows in requests]
    return {"success": round(float(np.mean([p["success"] for p in picked])), 3),
            "collided": round(float(np.mean([p["l_coll"] > 0 for p in picked])), 3)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--json", action="store_true")
    parser.add_argument("--poses", type=int, default=48, help="optimised poses per object and direction")
    parser.add_argument("--plans", type=int, default=6, help="planned + rolled-out candidates per request")
    parser.add_argument("--iterations", type=int, default=600, help="optimiser iterations (the dataset uses 1500)")
    parser.add_argument("--rank-draws", type=int, default=4, help="drawn worlds robust ranking rolls each plan out in")
    parser.add_argument("--truth-worlds", type=int, default=8, help="execution worlds each plan is judged in")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    started = time.perf_counter()
    requests, per_request = [], []
    for object_id, direction in itertools.product(OBJECTS, DIRECTIONS_DEG):
        rows = candidate_rollouts(object_id, direction, args.poses, args.plans, args.iterations, seed=0,
                                  rank_draws=args.rank_draws, truth_worlds=args.truth_worlds)
        per_request.append({"object": object_id, "direction_deg": direction, "plans": len(rows),
                            "successful_plans": sum(r["success"] for r in rows), "rows": rows})
        if not args.json:
            print(json.dumps(per_request[-1]))
        if rows:
            requests.append(rows)
    grid = {f"a{a}_b{b}_g{g}": pick_rates(requests, a, b, g) for a, b, g in itertools.product(*GRID.values())}
    summary = {
        "requests_with_plans": len(requests), "plans": sum(len(r) for r in requests),
        "shipped": {"alpha": ranking.ALPHA, "beta": ranking.BETA, "gamma": ranking.GAMMA,
                    **pick_rates(requests, ranking.ALPHA, ranking.BETA, ranking.GAMMA)},
        "goal_only": pick_rates(requests, 1.0, 0.0, 0.0),
        "dir_only": pick_rates(requests, 0.0, 0.0, 1.0),
        "robust": {"rank_draws": args.rank_draws,
                   **pick_rates(requests, ranking.ALPHA, ranking.BETA, ranking.GAMMA, goal="l_goal_robust")},
        "robust_most_draws": pick_by_draws(requests),
        "robust_grid": {f"a{a}_b{b}_g{g}": pick_rates(requests, a, b, g, goal="l_goal_robust")
                        for a, b, g in itertools.product(*GRID.values())},
        "truth_worlds": args.truth_worlds, "objects": list(OBJECTS), "directions_deg": list(DIRECTIONS_DEG),
        "random_expected": {"success": round(float(np.mean([np.mean([r["success"] for r in rows]) for rows in requests])), 3)
                            if requests else None},
        "best_possible": round(float(np.mean([max(r["success"] for r in rows) for rows in requests])), 3) if requests else None,
        "grid": grid, "per_request": per_request, "elapsed_s": round(time.perf_counter() - started, 1),
    }
    print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())
