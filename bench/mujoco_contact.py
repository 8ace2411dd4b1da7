"""Which MuJoCo contact settings for the MuJoCo robot: a scripted push of a box by the Allegro hand on a Panda
(the planner's IK + RRT + Cartesian push, planned once in PyBullet, 0.15 m sideways), executed in MuJoCo under
each friction cone and contact impedance, at three time steps and two solver iteration counts.

    python bench/mujoco_contact.py   # writes bench/results/mujoco_contact.json

A setting is good when the push's outcome (the box's displacement along and across the push, its yaw)
does not depend on the time step or the iteration count (the physics has converged, the result is the
model's and not the integrator's), when the box does not sink into the table or the fingers, and when it
is cheap. PyBullet's outcome is not a target: the two engines' gap is what the cross-engine evaluation measures.
"""
from __future__ import annotations

import itertools
import json
import platform
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any, Literal

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

IMPEDANCES = {  # name: (solref, solimp)
    "default": ((0.02, 1.0), (0.9, 0.95, 0.001)),
    "stiff": ((0.01, 1.0), (0.95, 0.99, 0.001)),
}
TIME_STEPS = (0.001, 0.002, 0.004)
ITERATIONS = (10, 50)


def planned_push() -> tuple[object, object, np.ndarray, np.ndarray]:
    import torch

    from shared.frames import direction_frame, pose25_to_matrix
    from shared.planning.motion import MotionPlanner
    from shared.robots.hands import load_hand
    from shared.world.fixed_poses import spatula_pose
    from shared.world.objects import load_object, write_object_urdf
    from shared.world.sim.robot_scene import RobotScene

    torch.set_num_threads(1)
    box = load_object("proc-box-013")  # 13.9 x 4.6 x 7.5 cm, 0.24 kg
    T_world_D = direction_frame(np.array([0.55, 0.0, 0.0]), 90.0)
    T_D_O = box.T_D_O(yaw_rad=np.pi / 2)
    T_world_O = T_world_D @ T_D_O
    hand = load_hand("allegro")
    T_D_hand, q_hand = pose25_to_matrix(spatula_pose(hand, box.mesh.vertices @ T_D_O[:3, :3].T + T_D_O[:3, 3]))
    with RobotScene("panda", "allegro") as scene:
        scene.add_object(write_object_urdf(box), T_world_O)
        plan = MotionPlanner(scene).plan_push(T_world_D @ T_D_hand, q_hand, T_world_D[:3, 0], 0.15,
                                              q_hand_start=hand.open_joint_positions.numpy())
    return box, plan, T_world_O, T_world_D


def main() -> None:
    from shared.execution.robot import JointTrajectory
    from shared.execution.robots.mujoco.config import ContactConfig, MujocoConfig
    from shared.execution.robots.mujoco.robot import MujocoRobot

    box, plan, T_world_O, T_world_D = planned_push()
    trajectory = JointTrajectory.from_plan(plan)  # type: ignore[arg-type]
    cones: tuple[Literal["pyramidal", "elliptic"], ...] = ("pyramidal", "elliptic")
    rows: list[dict[str, Any]] = []
    for cone, impedance, dt, iterations in itertools.product(cones, IMPEDANCES, TIME_STEPS, ITERATIONS):
        solref, solimp = IMPEDANCES[impedance]
        contact = replace(ContactConfig(), cone=cone, time_step_s=dt, iterations=iterations, solref=solref,
                          solimp=solimp)
        robot = MujocoRobot(MujocoConfig("panda", "allegro", contact=contact))
        robot.connect()
        robot.add_object(box, T_world_O)  # type: ignore[arg-type]
        robot.reset(list(trajectory.positions[0, :7]), list(trajectory.positions[0, 7:]))
        deepest = [0.0]
        model, data = robot.model, robot.data
        assert model is not None and data is not None
        started = time.perf_counter()
        report = robot.send(trajectory, realtime_factor=1e6)
        seconds = time.perf_counter() - started
        for c in data.contact[: data.ncon]:
            deepest[0] = min(deepest[0], float(c.dist))
        pose = robot.true_object_pose()
        assert pose is not None
        moved = np.array(pose.position) - T_world_O[:3, 3]
        along = float(moved @ T_world_D[:3, 0])
        across = float(moved @ T_world_D[:3, 1])
        from shared.frames import quat_xyzw_to_matrix
        R = quat_xyzw_to_matrix(np.array(pose.quaternion_xyzw)) @ T_world_O[:3, :3].T
        yaw = float(np.degrees(np.arctan2(R[1, 0], R[0, 0])))
        tilt = float(np.degrees(np.arccos(np.clip(R[2, 2], -1, 1))))
        row = {"cone": cone, "impedance": impedance, "time_step_s": dt, "iterations": iterations,
               "along_m": round(along, 4), "across_m": round(across, 4), "yaw_deg": round(yaw, 2),
               "tilt_deg": round(tilt, 2), "final_penetration_mm": round(-deepest[0] * 1000, 3),
               "final_joint_error_rad": round(report.final_joint_error, 4), "seconds": round(seconds, 2),
               "sim_seconds": round(trajectory.duration_s, 2)}
        print(row, flush=True)
        rows.append(row)
    summary = {}
    for cone_name, impedance in itertools.product(cones, IMPEDANCES):
        mine = [r for r in rows if r["cone"] == cone_name and r["impedance"] == impedance]
        along_all = np.array([r["along_m"] for r in mine])
        across_all = np.array([r["across_m"] for r in mine])
        yaw_all = np.array([r["yaw_deg"] for r in mine])
        summary[f"{cone_name}/{impedance}"] = {
            "along_m_mean": round(float(along_all.mean()), 4),
            "along_spread_mm": round(float(np.ptp(along_all) * 1000), 2),  # over time steps and iterations
            "across_spread_mm": round(float(np.ptp(across_all) * 1000), 2),
            "yaw_spread_deg": round(float(np.ptp(yaw_all)), 2),
            "worst_penetration_mm": max(r["final_penetration_mm"] for r in mine),
            "seconds_at_2ms_50it": next(r["seconds"] for r in mine if r["time_step_s"] == 0.002 and r["iterations"] == 50),
        }
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    result = {"command": "python bench/mujoco_contact.py", "commit": commit, "machine": platform.machine(),
              "push": "panda+allegro, proc-box-013 long side across, 0.15 m planned push at 0.1 m/s (MotionPlanner)",
              "summary": summary, "rows": rows}
    out = Path(__file__).resolve().parent / "results" / "mujoco_contact.json"
    out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(summary, indent=2))


if __name__ == "__main__":
    main()
