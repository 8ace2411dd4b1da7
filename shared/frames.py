"""Frames and the 25-d hand pose vector: one convention for the whole system (docs/architecture.md §Frames).

World: z up, table top at z = 0.
Direction frame D: origin at the object's centroid projected onto the table, +x along the push
(or pull) direction in the table plane, +z up. Data generation always pushes along +x of D, so one
model serves every direction: a request's points and poses are mapped between D and the world here.

Hand pose vector (`POSE_DIM` = 25): `[p(3), r6(6), q(16)]` — the hand base link's position and
orientation in D, then the joint angles. `r6` holds the first two *columns* of the base rotation
matrix; Gram–Schmidt turns any (non-degenerate) 6-vector back into a rotation.

Functions that the optimiser and the sampler use inside torch graphs accept numpy arrays *and*
torch tensors (same layout, batched over leading dimensions); the rest are numpy only.
Quaternions are xyzw (PyBullet's and scipy's order).
"""
from __future__ import annotations

import math
from typing import TYPE_CHECKING, TypeVar

import numpy as np
import torch
from numpy.typing import ArrayLike
from scipy.spatial.transform import Rotation
from typing_extensions import TypeIs

if TYPE_CHECKING:
    from shared.contracts.messages import DirectionFrame

Array = np.ndarray | torch.Tensor
A = TypeVar("A", np.ndarray, torch.Tensor)  # the functions on both kinds return the kind they are given

POSE_DIM = 25
NUM_JOINTS = 16
POSITION = slice(0, 3)
ROTATION_6D = slice(3, 9)
JOINTS = slice(9, 25)

# Below this norm a direction / column counts as zero (metres or unit vectors alike).
_EPS = 1e-9


class FrameError(ValueError):
    """A frame or pose input that cannot be interpreted (wrong shape, zero or vertical direction)."""


# ----------------------------------------------------------------------------- array helpers
def _is_torch(x: object) -> TypeIs[torch.Tensor]:
    return isinstance(x, torch.Tensor)


def _normalize(v: A) -> A:
    if _is_torch(v):
        unit: torch.Tensor = v / v.norm(dim=-1, keepdim=True).clamp_min(_EPS)
        return unit
    normalized: np.ndarray = v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), _EPS)
    return normalized


def _cross(a: A, b: A) -> A:
    if _is_torch(a):
        crossed: torch.Tensor = torch.linalg.cross(a, b, dim=-1)
        return crossed
    return np.cross(a, b)


def _stack_columns(cols: list[A]) -> A:
    return torch.stack(cols, dim=-1) if _is_torch(cols[0]) else np.stack(cols, axis=-1)


def _concat(parts: list[A]) -> A:
    return torch.cat(parts, dim=-1) if _is_torch(parts[0]) else np.concatenate(parts, axis=-1)


def _check_last_dim(x: Array, size: int, what: str) -> None:
    if x.shape[-1:] != (size,):
        raise FrameError(f"{what} must have last dimension {size}, got shape {tuple(x.shape)}")


def _as_array(x: A) -> A:
    if _is_torch(x):
        return x
    return np.asarray(x, dtype=np.float64)


def _like(transform: ArrayLike | torch.Tensor, reference: A) -> A:
    """`transform` as the same kind of array (and torch dtype / device) as `reference`."""
    if _is_torch(reference):
        return torch.as_tensor(transform, dtype=reference.dtype, device=reference.device)
    if _is_torch(transform):
        raise FrameError("cannot apply a torch transform to a numpy array; convert one of them")
    return np.asarray(transform, dtype=np.float64)


# ----------------------------------------------------------------------------- rotations
def r6_to_matrix(r6: A) -> A:
    """[..., 6] (first two columns, unnormalised) -> [..., 3, 3] rotation via Gram–Schmidt.

    numpy input must be non-degenerate (raises FrameError); torch input is clamped instead so a
    batched optimisation never stops on one bad sample.
    """
    r6 = _as_array(r6)
    _check_last_dim(r6, 6, "r6")
    a, b = r6[..., 0:3], r6[..., 3:6]
    if not _is_torch(r6):
        _reject_degenerate_r6(a, b)
    x = _normalize(a)
    z = _normalize(_cross(x, b))
    y = _cross(z, x)
    return _stack_columns([x, y, z])


def _reject_degenerate_r6(a: np.ndarray, b: np.ndarray) -> None:
    na = np.linalg.norm(a, axis=-1)
    cross = np.linalg.norm(np.cross(a, b), axis=-1)
    if np.any(na < _EPS) or np.any(cross < _EPS * np.maximum(na, 1.0)):
        raise FrameError("r6 is degenerate: its first column is zero or its two columns are parallel")


def matrix_to_r6(rotation: A) -> A:
    """[..., 3, 3] rotation -> [..., 6]: column 0 then column 1."""
    rotation = _as_array(rotation)
    if tuple(rotation.shape[-2:]) != (3, 3):
        raise FrameError(f"rotation must be [..., 3, 3], got shape {tuple(rotation.shape)}")
    return _concat([rotation[..., :, 0], rotation[..., :, 1]])


def quat_xyzw_to_matrix(quat: ArrayLike) -> np.ndarray:
    """[..., 4] xyzw quaternion -> [..., 3, 3] (normalised by scipy)."""
    quat = np.asarray(quat, dtype=np.float64)
    _check_last_dim(quat, 4, "quaternion")
    flat = quat.reshape(-1, 4)
    if np.any(np.linalg.norm(flat, axis=-1) < _EPS):
        raise FrameError("quaternion has zero norm")
    matrices: np.ndarray = Rotation.from_quat(flat).as_matrix()
    return matrices.reshape(quat.shape[:-1] + (3, 3))


def matrix_to_quat_xyzw(rotation: np.ndarray) -> np.ndarray:
    """[..., 3, 3] -> [..., 4] xyzw quaternion with w >= 0 (one canonical sign)."""
    rotation = np.asarray(rotation, dtype=np.float64)
    flat = rotation.reshape(-1, 3, 3)
    quat: np.ndarray = Rotation.from_matrix(flat).as_quat()
    quat = np.where(quat[:, 3:4] < 0, -quat, quat)
    return quat.reshape(rotation.shape[:-2] + (4,))


def pos_quat_to_matrix(position: np.ndarray, quat_xyzw: np.ndarray) -> np.ndarray:
    """Position [..., 3] + xyzw quaternion [..., 4] -> homogeneous [..., 4, 4]."""
    position = np.asarray(position, dtype=np.float64)
    _check_last_dim(position, 3, "position")
    return make_transform(quat_xyzw_to_matrix(quat_xyzw), position)


def matrix_to_pos_quat(transform: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Homogeneous [..., 4, 4] -> (position [..., 3], xyzw quaternion [..., 4])."""
    transform = np.asarray(transform, dtype=np.float64)
    return transform[..., :3, 3].copy(), matrix_to_quat_xyzw(transform[..., :3, :3])


def yaw_rotation(yaw_rad: float) -> np.ndarray:
    """3x3 rotation about +z."""
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


# ----------------------------------------------------------------------------- transforms
def make_transform(rotation: A, translation: A) -> A:
    """Rotation [..., 3, 3] + translation [..., 3] -> homogeneous [..., 4, 4]."""
    if _is_torch(rotation):
        top = torch.cat([rotation, translation.unsqueeze(-1)], dim=-1)
        bottom = torch.zeros(top.shape[:-2] + (1, 4), dtype=top.dtype, device=top.device)
        bottom[..., 0, 3] = 1.0
        return torch.cat([top, bottom], dim=-2)
    rotation, translation = np.asarray(rotation, np.float64), np.asarray(translation, np.float64)
    shape = np.broadcast_shapes(rotation.shape[:-2], translation.shape[:-1])
    out = np.zeros(shape + (4, 4))
    out[..., :3, :3] = rotation
    out[..., :3, 3] = translation
    out[..., 3, 3] = 1.0
    return out


def invert_transform(transform: A) -> A:
    """Inverse of a rigid [..., 4, 4] transform (uses R^T, not a general inverse)."""
    rotation, translation = transform[..., :3, :3], transform[..., :3, 3]
    rotation_t = rotation.transpose(-1, -2) if _is_torch(rotation) else np.swapaxes(rotation, -1, -2)
    return make_transform(rotation_t, -(rotation_t @ translation[..., None])[..., 0])


def transform_points(transform: ArrayLike | torch.Tensor, points: A) -> A:
    """Apply a rigid 4x4 transform to points [..., 3]."""
    points = _as_array(points)
    _check_last_dim(points, 3, "points")
    matrix = _like(transform, points)
    moved: A = points @ matrix[:3, :3].T + matrix[:3, 3]
    return moved


# ----------------------------------------------------------------------------- 25-d pose
def pose25_to_matrix(pose: A) -> tuple[A, A]:
    """[..., 25] pose -> (hand base transform [..., 4, 4] in the pose's frame, joints [..., 16])."""
    pose = _as_array(pose)
    _check_last_dim(pose, POSE_DIM, "pose")
    return make_transform(r6_to_matrix(pose[..., ROTATION_6D]), pose[..., POSITION]), pose[..., JOINTS]


def matrix_to_pose25(transform: A, joints: A) -> A:
    """Hand base transform [..., 4, 4] + joints [..., 16] -> [..., 25] pose."""
    transform = _as_array(transform)
    joints = _as_array(joints)
    _check_last_dim(joints, NUM_JOINTS, "joints")
    return _concat([transform[..., :3, 3], matrix_to_r6(transform[..., :3, :3]), joints])


def transform_poses(poses: A, transform: ArrayLike | torch.Tensor) -> A:
    """Re-express [..., 25] poses under a rigid transform T (new = T · old); joints unchanged.

    The rotation acts on both r6 columns directly, so no Gram–Schmidt round trip is needed and
    an unnormalised r6 stays exactly as unnormalised as it was.
    """
    poses = _as_array(poses)
    _check_last_dim(poses, POSE_DIM, "poses")
    transform = _like(transform, poses)
    rotation, translation = transform[:3, :3], transform[:3, 3]
    position = poses[..., POSITION] @ rotation.T + translation
    col0 = poses[..., 3:6] @ rotation.T
    col1 = poses[..., 6:9] @ rotation.T
    return _concat([position, col0, col1, poses[..., JOINTS]])


def poses_d_to_world(poses_d: A, T_world_D: ArrayLike | torch.Tensor) -> A:
    """Hand poses [..., 25] in D -> in the world."""
    return transform_poses(poses_d, T_world_D)


def poses_world_to_d(poses_world: A, T_world_D: A) -> A:
    """Hand poses [..., 25] in the world -> in D."""
    T_world_D = T_world_D if _is_torch(T_world_D) else np.asarray(T_world_D, dtype=np.float64)
    return transform_poses(poses_world, invert_transform(T_world_D))


def points_world_to_d(points_world: A, T_world_D: A) -> A:
    """Points [..., 3] in the world -> in D."""
    T_world_D = T_world_D if _is_torch(T_world_D) else np.asarray(T_world_D, dtype=np.float64)
    return transform_points(invert_transform(T_world_D), points_world)


def points_d_to_world(points_d: A, T_world_D: ArrayLike | torch.Tensor) -> A:
    """Points [..., 3] in D -> in the world."""
    return transform_points(T_world_D, points_d)


# ----------------------------------------------------------------------------- direction frame D
def direction_xy(direction: float | np.ndarray | list[float] | tuple[float, ...]) -> np.ndarray:
    """Unit push direction in the table plane from yaw degrees or an xy / xyz vector.

    A 3-vector is projected onto the table; a zero or vertical direction raises FrameError
    (there is no horizontal push direction to follow).
    """
    if isinstance(direction, (int, float, np.integer, np.floating)):
        yaw = math.radians(float(direction))
        if not math.isfinite(yaw):
            raise FrameError(f"direction yaw must be finite, got {direction!r}")
        return np.array([math.cos(yaw), math.sin(yaw)])
    vector = np.asarray(direction, dtype=np.float64).reshape(-1)
    if vector.size not in (2, 3) or not np.all(np.isfinite(vector)):
        raise FrameError(f"direction must be yaw degrees or a finite 2-/3-vector, got {direction!r}")
    horizontal = vector[:2]
    norm = float(np.linalg.norm(horizontal))
    if norm < _EPS or norm < 1e-6 * float(np.linalg.norm(vector)):
        raise FrameError(f"direction {vector.tolist()} is zero or vertical: it has no component in the table plane")
    return horizontal / norm


def direction_toward(from_position: np.ndarray, to_position: np.ndarray) -> np.ndarray:
    """Unit table-plane direction from one point to another (a goal point, or the robot for a pull)."""
    delta = np.asarray(to_position, dtype=np.float64)[:2] - np.asarray(from_position, dtype=np.float64)[:2]
    return direction_xy(delta)


def direction_frame(object_position_world: np.ndarray,
                    direction: float | np.ndarray | list[float] | tuple[float, ...]) -> np.ndarray:
    """T_world_D: origin = object centroid projected to z = 0, +x along `direction`, +z up.

    `direction` is yaw in degrees (about world z, 0 = world +x) or an xy / xyz vector. A pull is
    simply the direction toward the robot (see `direction_toward`).
    """
    position = np.asarray(object_position_world, dtype=np.float64).reshape(-1)
    if position.size != 3 or not np.all(np.isfinite(position)):
        raise FrameError(f"object position must be a finite 3-vector, got {object_position_world!r}")
    x_axis = direction_xy(direction)
    rotation = np.array([[x_axis[0], -x_axis[1], 0.0], [x_axis[1], x_axis[0], 0.0], [0.0, 0.0, 1.0]])
    return make_transform(rotation, np.array([position[0], position[1], 0.0]))


def direction_yaw_deg(T_world_D: np.ndarray) -> float:
    """The push direction of a direction frame as yaw degrees in (-180, 180]."""
    T_world_D = np.asarray(T_world_D, dtype=np.float64)
    return math.degrees(math.atan2(T_world_D[1, 0], T_world_D[0, 0]))


# ---------------------------------------------------------------------- DirectionFrame messages
# (duck-typed: anything with `object_pose.position`, `object_pose.quaternion_xyzw`, `yaw_deg` and
# `direction_xy`, i.e. shared.contracts.messages.DirectionFrame, which this module does not import)


def frame_transform(frame: DirectionFrame) -> np.ndarray:
    """T_world_D of a DirectionFrame."""
    direction = frame.yaw_deg if frame.yaw_deg is not None else np.asarray(frame.direction_xy)
    return direction_frame(np.asarray(frame.object_pose.position), direction)


def frame_object_transform(frame: DirectionFrame) -> np.ndarray:
    """T_world_O of a DirectionFrame's object."""
    return pos_quat_to_matrix(np.asarray(frame.object_pose.position), np.asarray(frame.object_pose.quaternion_xyzw))


def object_yaw_in_d(frame: DirectionFrame, rest_rotation: np.ndarray) -> float:
    """The yaw (radians, about D's z) that turns the resting pose `rest_rotation` into the frame's object.

    `ObjectModel.T_D_O(pose, yaw)` is Rz(yaw) @ rest_rotation, so Rz(yaw) = R_D_O @ rest_rotation^T;
    this is what the validator's `table_object(obj, pose_index, yaw)` needs to place the object the same way.
    """
    turn = _turn_from_rest(frame, rest_rotation)
    return math.atan2(turn[1, 0], turn[0, 0])


def resting_tilt_deg(frame: DirectionFrame, rest_rotation: np.ndarray) -> float:
    """How far (degrees) the frame's object leans away from resting pose `rest_rotation` turned about z.

    0 when the object is exactly that resting pose at some yaw, which `object_yaw_in_d` then gives.
    """
    turn = _turn_from_rest(frame, rest_rotation)
    return math.degrees(math.acos(float(np.clip(turn[2, 2], -1.0, 1.0))))


def _turn_from_rest(frame: DirectionFrame, rest_rotation: np.ndarray) -> np.ndarray:
    """R_D_O @ rest_rotation^T: the rotation (a turn about z when the object rests so) from the resting pose."""
    R_D_O = (invert_transform(frame_transform(frame)) @ frame_object_transform(frame))[:3, :3]
    turn: np.ndarray = R_D_O @ np.asarray(rest_rotation, dtype=np.float64).T
    return turn
