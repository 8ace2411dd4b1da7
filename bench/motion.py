"""Benchmarks of the planner's motion pieces: batched IK, one RRTConnect plan, one whole push plan.

    python bench/motion.py --json      # last line: one JSON object

- IK: K = 200 push-like hand poses of the Allegro on the Panda (palm facing a random horizontal
  direction, random roll, 5-25 cm above the table, 0.35-0.70 m in front of the base), solved in
  one batch (16 seeds per target); reports the wall time and the fraction solved.
- screen: the same K poses through `MotionPlanner.screen` (batched IK + a collision check of each
  pre-contact configuration) in the box scene.
- RRTConnect: home -> the configuration above a spatula pose behind a box (the approach's joint-space
  part, simplification included), in the box scene with collision checking, measured inside the full
  `plan_push` (IK, Cartesian approach / push / back-off, two RRTConnect plans, timing), which is
  timed too; sideways pushes of a box 0.55 m in front of the base.
Torch runs single-threaded, as every worker process does (docs/architecture.md §Compute).
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from shared.frames import direction_frame, make_transform, pose25_to_matrix
from shared.planning.ik import ArmIK
from shared.planning.motion import MotionPlanner
from shared.robots.hands import load_hand
from shared.world.fixed_poses import spatula_pose
from shared.world.objects import load_object, write_object_urdf
from shared.world.sim.robot_scene import RobotScene


def push_like_hand_poses(count: int, seed: int = 0) -> np.ndarray:
    """Allegro base poses [count,4,4]: palm (base +x) horizontal toward a random yaw, random roll."""
    rng = np.random.default_rng(seed)
    poses = []
    for _ in range(count):
        yaw, roll = rng.uniform(-np.pi, np.pi), rng.uniform(-np.pi, np.pi)
        normal = np.array([np.cos(yaw), np.sin(yaw), 0.0])
        side = np.array([-np.sin(yaw), np.cos(yaw), 0.0])
        fingers = np.cos(roll) * np.array([0.0, 0.0, -1.0]) + np.sin(roll) * side
        rotation = np.stack([normal, np.cross(fingers, normal), fingers], axis=1)
        position = [rng.uniform(0.35, 0.70), rng.uniform(-0.30, 0.30), rng.uniform(0.05, 0.25)]
        poses.append(make_transform(rotation, np.array(position)))
    return np.array(poses)


def bench_ik(k: int, repeats: int) -> dict:
    ik = ArmIK("panda", "allegro")
    targets = push_like_hand_poses(k)
    ik.solve_hand_poses(targets[:8])  # warm-up
    samples, solved = [], 0.0
    for _ in range(repeats):
        started = time.perf_counter()
        result = ik.solve_hand_poses(targets)
        samples.append(time.perf_counter() - started)
        solved = float(result.success.mean())
    return {"k": k, "seeds": len(ik.seeds), "median_s": round(statistics.median(samples), 3),
            "min_s": round(min(samples), 3), "solved_fraction": round(solved, 3)}


def bench_screen(k: int, repeats: int) -> dict:
    """Batched IK + pre-contact collision check of K push-like poses in the box scene."""
    scene, _, _, q_hand = box_scene(90.0)
    planner = MotionPlanner(scene)
    targets = push_like_hand_poses(k)
    q_hands = np.repeat(q_hand[None], k, axis=0)
    samples, feasible = [], 0.0
    for _ in range(repeats):
        started = time.perf_counter()
        result = planner.screen(targets, q_hands)
        samples.append(time.perf_counter() - started)
        feasible = float(result.feasible.mean())
    scene.close()
    return {"k": k, "median_s": round(statistics.median(samples), 3), "feasible_fraction": round(feasible, 3)}


def box_scene(yaw_deg: float):
    box = load_object("proc-box-013")
    T_world_D = direction_frame(np.array([0.55, 0.0, 0.0]), yaw_deg)
    T_D_O = box.T_D_O(yaw_rad=np.pi / 2)
    scene = RobotScene("panda", "allegro")
    scene.add_object(write_object_urdf(box), T_world_D @ T_D_O)
    vertices_d = box.mesh.vertices @ T_D_O[:3, :3].T + T_D_O[:3, 3]
    T_D_hand, q_hand = pose25_to_matrix(spatula_pose(load_hand("allegro"), vertices_d))
    return scene, T_world_D, T_world_D @ T_D_hand, q_hand


def bench_planning(repeats: int) -> dict:
    out: dict = {}
    for yaw in (90.0, -90.0):
        scene, T_world_D, T_world_hand, q_hand = box_scene(yaw)
        planner = MotionPlanner(scene)
        planner.plan_push(T_world_hand, q_hand, T_world_D[:3, 0], 0.15)  # warm-up
        rrt, push, stats = [], [], None
        for _ in range(repeats):
            started = time.perf_counter()
            plan = planner.plan_push(T_world_hand, q_hand, T_world_D[:3, 0], 0.15)
            push.append(time.perf_counter() - started)
            stats = planner.stats
            rrt.append(stats.rrt_calls_s[0])  # home -> above the standoff, simplification included
        assert stats is not None  # repeats >= 1
        out[f"yaw_{yaw:+.0f}"] = {
            "rrtconnect_median_s": round(statistics.median(rrt), 3),
            "plan_push_median_s": round(statistics.median(push), 3),
            "plan_push_breakdown_s": {"ik": round(stats.ik_s, 3), "cartesian": round(stats.cartesian_s, 3),
                                      "rrt_total": round(stats.rrt_s, 3)},
            "plan_duration_s": round(float(plan.times_s.to_numpy()[-1]), 2),
        }
        scene.close()
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--json", action="store_true", help="print one JSON object as the last line")
    parser.add_argument("--k", type=int, default=200)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    result = {"ik": bench_ik(args.k, args.repeats), "screen": bench_screen(args.k, args.repeats),
              "planning": bench_planning(args.repeats)}
    if args.json:
        print(json.dumps(result))
    else:
        print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
