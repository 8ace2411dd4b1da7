"""The one judge of a push: where the object ended up against where it should be (the paper's criterion).

Used by the floating-hand validator, the arm rollouts, the planner's result and every evaluation.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import trimesh

from shared.contracts.messages import ExecutionResult, ObjectPose
from shared.frames import matrix_to_quat_xyzw, quat_xyzw_to_matrix
from shared.world.objects.geometry import REVOLUTION_MAX, revolution_deviation

# Below this, turning an object about its vertical axis is invisible to a depth camera (turn_observable). The
# development objects' models: boxes, hulls, the duck, the mug and lying cylinders 0.13-0.31 (their
# reconstructions 0.13-0.24); standing cylinders, the cone and the ellipsoid 0.01-0.04 (reconstructions 0.03-0.08).
TURN_VISIBILITY_MIN = REVOLUTION_MAX
SUCCESS_POSITION_TOLERANCE_M = 0.03
SUCCESS_MAX_ROTATION_DEG = 45.0
# A pose goal (a goal point with a yaw, PushRequest.goal_yaw_deg) is met within these instead: the position
# tighter than a point goal's, and the yaw judged against the goal rather than the turn from the start bounded.
POSE_GOAL_POSITION_TOLERANCE_M = 0.02
POSE_GOAL_YAW_TOLERANCE_DEG = 15.0
TOPPLED_TILT_DEG = 45.0  # the object's up axis leaned over this far: it fell over


def turn_observable(mesh: trimesh.Trimesh, up_O: np.ndarray) -> bool:
    """Whether turning the object (its `mesh`, in its frame O) about its vertical axis (`up_O`, in O) changes what
    a camera can see of it: not for a body of revolution about that axis (a ball, a standing can or cone), whose
    turn no tracker measures, so a turn reported for it is the tracker's guess and neither stops nor judges a push.
    The measure is `revolution_deviation` about the vertical, against TURN_VISIBILITY_MIN."""
    return revolution_deviation(mesh, up_O) >= TURN_VISIBILITY_MIN


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


@dataclass(frozen=True)
class YawGoal:
    """A pose goal's yaw: the object resting on the table as `rest_rotation` holds it (`RestingPose.rotation`,
    O -> the table-aligned frame at yaw 0), turned `yaw_deg` about the world z axis. The yaw `gd2p push --yaw`
    places an object with, in the same pose; for an object standing as modelled (rest rotation the identity)
    it is the yaw of its frame O.

    Measured against the resting pose rather than as O's own Euler yaw: O's axes are the principal axes of
    inertia, and an object resting with O's x axis upright (a mug on its base, say) has an Euler yaw that
    swings through any angle as the tracker's pose tilts by a degree."""

    yaw_deg: float
    rest_rotation: np.ndarray = field(default_factory=lambda: np.eye(3))

    def yaw_of(self, R_world_O: np.ndarray) -> float:
        """The yaw (degrees) of an object at orientation `R_world_O` resting as this goal's pose does: the
        heading of the turn that takes the resting pose at yaw 0 to it."""
        turn = np.asarray(R_world_O, dtype=np.float64) @ self.rest_rotation.T
        return math.degrees(math.atan2(turn[1, 0], turn[0, 0]))

    def turn_deg(self, R_world_O: np.ndarray) -> float:
        """The signed turn about the world z axis (degrees, -180..180, counterclockwise positive) still to make
        from `R_world_O` to the goal yaw, the short way."""
        return (self.yaw_deg - self.yaw_of(R_world_O) + 180.0) % 360.0 - 180.0

    def error_deg(self, R_world_O: np.ndarray) -> float:
        """How far (degrees, 0..180) `R_world_O` is from the goal yaw."""
        return abs(self.turn_deg(R_world_O))


def resting_rotation(rest_rotations: list[np.ndarray], R_world_O: np.ndarray) -> np.ndarray:
    """Of an object's resting poses' rotations (`RestingPose.rotation`), the one it rests in at `R_world_O`:
    the pose whose up axis (in O) is nearest the object's up axis now."""
    up_now = np.asarray(R_world_O, dtype=np.float64)[2, :]  # world z in O: row 2 of R_world_O
    return max(rest_rotations, key=lambda rotation: float(np.asarray(rotation)[2, :] @ up_now))


def position_tolerance_m(yaw_goal: YawGoal | None) -> float:
    """How close to its target the object must end: a pose goal's tolerance with a goal yaw, else a point's."""
    return SUCCESS_POSITION_TOLERANCE_M if yaw_goal is None else POSE_GOAL_POSITION_TOLERANCE_M


def judge_push(T_world_O_start: np.ndarray, target_xy: np.ndarray, final: ObjectPose, *,
               max_rotation_deg: float | None = SUCCESS_MAX_ROTATION_DEG,
               yaw_goal: YawGoal | None = None, rolling: bool = False) -> ExecutionResult:
    """Position error (in the table plane, to the target), rotation, toppling and success of one push.

    `max_rotation_deg=None` does not judge the turn: a multi-step request, whose object may turn
    along its path around obstacles, succeeds when it ends at the goal standing.
    `yaw_goal` (a pose goal): success needs the object within POSE_GOAL_POSITION_TOLERANCE_M of the
    target and its yaw within POSE_GOAL_YAW_TOLERANCE_DEG of the goal yaw; the turn from the start is
    then not bounded (the goal says how the object is to end, and reaching it may take any turn).
    `rolling` (an object that rolls, `shared.world.objects.geometry.rolls`: a ball, a fruit, a can on its
    side): success is the position alone. A ball turns ~350 degrees in a 0.20 m roll and a rolling can's up
    axis goes round with it, so neither the turn nor the tilt says anything about the push; both are still
    reported.
    """
    T_end = pose_matrix(final)
    error = float(np.linalg.norm(T_end[:2, 3] - np.asarray(target_xy, dtype=np.float64)[:2]))
    r_start, r_end = T_world_O_start[:3, :3], T_end[:3, :3]
    rotation = rotation_between_deg(r_start, r_end)
    up_in_object = r_start.T @ np.array([0.0, 0.0, 1.0])  # the object's up axis at the start, in O
    tilt = math.degrees(math.acos(np.clip(float((r_end @ up_in_object)[2]), -1.0, 1.0)))
    toppled = tilt > TOPPLED_TILT_DEG
    if yaw_goal is None:
        yaw_error, off_pose = None, max_rotation_deg is not None and rotation > max_rotation_deg
    else:
        yaw_error = yaw_goal.error_deg(r_end)
        off_pose = yaw_error > POSE_GOAL_YAW_TOLERANCE_DEG
    success = error <= position_tolerance_m(yaw_goal) and (rolling or (not off_pose and not toppled))
    return ExecutionResult(final_object_pose=final, position_error_m=error, rotation_deg=rotation,
                           toppled=toppled, success=success, yaw_error_deg=yaw_error)
