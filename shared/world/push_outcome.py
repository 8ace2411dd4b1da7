"""The one judge of a push: where the object ended up against where it should be (the paper's criterion).

Used by the floating-hand validator, the arm rollouts, the planner's result and every evaluation.
"""
from __future__ import annotations

import math

import numpy as np

from shared.contracts.messages import ExecutionResult, ObjectPose
from shared.frames import matrix_to_quat_xyzw, quat_xyzw_to_matrix

SUCCESS_POSITION_TOLERANCE_M = 0.03
SUCCESS_MAX_ROTATION_DEG = 45.0
TOPPLED_TILT_DEG = 45.0  # the object's up axis leaned over this far: it fell over


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
