"""Measure the ranking weights (α, β, γ of V = α L_goal + β L_coll + γ L_dir) on real candidate plans.

    python bench/ranking_weights.py --json      # last line: one JSON object

Candidates: push poses from the project's energy-based optimiser (`services.generator`, the
dataset's source — the diffusion model learns to sample like it; unfiltered, with fewer iterations
than the dataset, so there are bad ones among them, as in a sampler's output), for a few test objects and
directions, placed as the planner places them (object at 0.55 m in front of the robot). Each pose
goes through the planner's own steps: IK + collision screen, `plan_push`, and an arm rollout
(`services.validator.rollout`). Rollouts are deterministic, so a rollout's success is what the
execution of that plan gives.

Then, for each request, every weight setting picks one plan; reported: the fraction of requests
whose picked plan succeeds (within 3 cm, ≤ 45°, not toppled) and whose picked plan collided, for
the shipped weights, a grid around them, L_goal alone, L_dir alone and a random pick (expected
value), plus the best achievable (any successful plan).
"""
from __future__ import annotations

import argparse
import itertools
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from services.generator.config import GenerationConfig
from services.generator.synthesis import generate
from services.planner import ranking
from services.planner.motion import MotionPlanner, PlanningError
from services.validator.rollout import rollout
from services.validator.service import DEFAULT_PARAMS
from shared.frames import direction_frame, pose25_to_matrix, poses_d_to_world
from shared.hands import load_hand
from shared.messages import DirectionFrame, ObjectRef, ValidationJob
from shared.objects import load_object, write_object_urdf
from shared.push_outcome import object_pose
from shared.sim.robot_scene import RobotScene

OBJECTS = ("proc-box-013", "proc-cylinder-000", "proc-box-000")
DIRECTIONS_DEG = (90.0, -90.0)
GRID = {"alpha": (1.0, 10.0, 30.0), "beta": (0.0, 1.0), "gamma": (0.0, 0.1, 0.5)}


def candidate_rollouts(object_id: str, direction_deg: float, n_poses: int, max_plans: int, iterations: int,
                       seed: int) -> list[dict]:
    """Terms and rollout success of up to `max_plans` planned candidates for one object and direction."""
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
    rows = []
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
                                with_arm=True, arm="panda", plan=plan, frame=frame)
            result = rollout(job, DEFAULT_PARAMS)
            rows.append({"l_goal": ranking.goal_cost(float(result.goal_error_m.to_numpy()[0]),
                                                     float(result.rotation_deg.to_numpy()[0]),
                                                     float(result.max_tilt_deg.to_numpy()[0])),
                         "l_coll": float(result.collision_cost.to_numpy()[0]), "l_dir": float(l_dir[index]),
                         "success": bool(result.success.to_numpy()[0])})
    return rows


def pick_rates(requests: list[list[dict]], alpha: float, beta: float, gamma: float) -> dict:
    picked = [min(rows, key=lambda r: alpha * r["l_goal"] + beta * r["l_coll"] + gamma * r["l_dir"]) for rows in requests]
    return {"success": round(float(np.mean([p["success"] for p in picked])), 3),
            "collided": round(float(np.mean([p["l_coll"] > 0 for p in picked])), 3)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--json", action="store_true")
    parser.add_argument("--poses", type=int, default=48, help="optimised poses per object and direction")
    parser.add_argument("--plans", type=int, default=6, help="planned + rolled-out candidates per request")
    parser.add_argument("--iterations", type=int, default=600, help="optimiser iterations (the dataset uses 1500)")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    started = time.perf_counter()
    requests, per_request = [], []
    for object_id, direction in itertools.product(OBJECTS, DIRECTIONS_DEG):
        rows = candidate_rollouts(object_id, direction, args.poses, args.plans, args.iterations, seed=0)
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
        "random_expected": {"success": round(float(np.mean([np.mean([r["success"] for r in rows]) for rows in requests])), 3)
                            if requests else None},
        "best_possible": round(float(np.mean([any(r["success"] for r in rows) for rows in requests])), 3) if requests else None,
        "grid": grid, "per_request": per_request, "elapsed_s": round(time.perf_counter() - started, 1),
    }
    print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())
