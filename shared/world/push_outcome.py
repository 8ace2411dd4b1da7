"""The one judge of a push: where the object ended up against where it should be (the paper's criterion).

Used by the floating-hand validator, the arm rollouts, the planner's result and every evaluation.
"""
from __future__ import annotations

import math

import numpy as np
import trimesh

from shared.contracts.messages import ExecutionResult, ObjectPose
from shared.frames import matrix_to_quat_xyzw, quat_xyzw_to_matrix

# Below this, turning an object about its vertical axis is invisible to a depth camera (turn_observable). The
# development objects' models: boxes, hulls, the duck, the mug and lying cylinders 0.13-0.31 (their
# reconstructions 0.13-0.24); standing cylinders, the cone and the ellipsoid 0.01-0.04 (reconstructions 0.03-0.08).
TURN_VISIBILITY_MIN = 0.1
SUCCESS_POSITION_TOLERANCE_M = 0.03
SUCCESS_MAX_ROTATION_DEG = 45.0
TOPPLED_TILT_DEG = 45.0  # the object's up axis leaned over this far: it fell over


def turn_observable(mesh: trimesh.Trimesh, up_O: np.ndarray) -> bool:
    """Whether turning the object (its `mesh`, in its frame O) about its vertical axis (`up_O`, in O) changes what
    a camera can see of it: not for a body of revolution about that axis (a ball, a standing can or cone), whose
    turn no tracker measures, so a turn reported for it is the tracker's guess and neither stops nor judges a push.

    The measure is how much the surface's normal distances change under a small turn about the vertical through
    the centre: the RMS over the surface of ((p - c) x n) . up / radius (0 for a body of revolution, ~0.2-0.3 for a
    box), against TURN_VISIBILITY_MIN."""
    points, faces = trimesh.sample.sample_surface(mesh, 2000, seed=0)
    normals = np.asarray(mesh.face_normals, dtype=np.float64)[faces]
    points = np.asarray(points, dtype=np.float64)
    centre = points.mean(axis=0)
    radius = max(float(np.max(np.linalg.norm(points - centre, axis=1))), 1e-6)
    up = np.asarray(up_O, dtype=np.float64) / np.linalg.norm(up_O)
    lever = np.cross(points - centre, normals) @ up / radius
    return bool(np.sqrt(np.mean(lever**2)) >= TURN_VISIBILITY_MIN)


def rollout_predicts_success(l_goal_m: float) -> bool:
    """Whether a rollout's goal cost (the ranking's L_goal, metres) says the push succeeds: its error is
    within the success tolerance (the rollout's cost already counts toppling and turning as misses)."""
    return l_goal_m <= SUCCESS_POSITION_TOLERANCE_M


def object_pose(T_world_O: np.ndarray) -> ObjectPose:
    return ObjectPose(position=tuple(float(v) for v in T_world_O[:3, 3]),
                      quaternion_xyzw=tuple(float(v) for v in matrix_to_quat_xyzw(T_world_O[:3, :3])))


def pose_matrix(pose: ObjectPose) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = quat_xyzw_to_matrix(np.array(pose.quaternion_xyzw))
    T[:3, 3] = pose.position
    return T


def rotation_between_deg(r_a: np.ndarray, r_b: np.ndarray) -> float:
    """The angle (degrees) of the rotation that turns orientation `r_a` into `r_b` (3x3 each)."""
    return math.degrees(math.acos(np.clip((np.trace(r_b @ r_a.T) - 1.0) / 2.0, -1.0, 1.0)))


def judge_push(T_world_O_start: np.ndarray, target_xy: np.ndarray, final: ObjectPose, *,
               max_rotation_deg: float | None = SUCCESS_MAX_ROTATION_DEG) -> ExecutionResult:
    """Position error (in the table plane, to the target), rotation, toppling and success of one push.

    `max_rotation_deg=None` does not judge the turn: a multi-step request, whose object may turn
    along its path around obstacles, succeeds when it ends at the goal standing.
    """
    T_end = pose_matrix(final)
    error = float(np.linalg.norm(T_end[:2, 3] - np.asarray(target_xy, dtype=np.float64)[:2]))
    r_start, r_end = T_world_O_start[:3, :3], T_end[:3, :3]
    rotation = rotation_between_deg(r_start, r_end)
    up_in_object = r_start.T @ np.array([0.0, 0.0, 1.0])  # the object's up axis at the start, in O
    tilt = math.degrees(math.acos(np.clip(float((r_end @ up_in_object)[2]), -1.0, 1.0)))
    toppled = tilt > TOPPLED_TILT_DEG
    turned_too_far = max_rotation_deg is not None and rotation > max_rotation_deg
    success = error <= SUCCESS_POSITION_TOLERANCE_M and not turned_too_far and not toppled
    return ExecutionResult(final_object_pose=final, position_error_m=error, rotation_deg=rotation,
                           toppled=toppled, success=success)
