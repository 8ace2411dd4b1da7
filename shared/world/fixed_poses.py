"""The fixed "spatula" pose per hand: the paper's Fixed Hand Pose baseline and the physics sanity check.

Fingers straight and flat, palm facing +x of D (the push direction), placed behind the object (-x
side). Orientation: the palm normal along +x and the fingers pointing down (-z), so the wrist is
up where an arm-mounted hand approaches from, and the thumb — the one part that sticks out of the
palm plane — is high up, away from the object's lower part (a protruding part low on the hand
topples nothing; high up it would).

Placement:
- x: the front-most point of the part of the hand facing the object (within the object's width and
  height) `SPATULA_GAP_M` behind the object's rear-most point. The gap
  costs its own size of the 3 cm success budget (the hand travels 0.20 m, the object 0.20 m minus
  the gap), and keeps PyBullet's ~1 mm convex-hull contact margin from registering as penetration.
- z: the middle of the hand's vertical extent at half the object's height, raised when needed so
  the hand's lowest point clears the table by `SPATULA_TABLE_CLEARANCE_M`. The hands are longer
  (Allegro 0.24 m, LEAP 0.17 m) than most objects are tall, so for most objects the hand stands on
  that clearance and covers the object's whole back face.
- y: centred on the object's centroid.

Joints: Allegro's fingers at 0 (straight); its thumb is tucked against the palm (joints 12-15 =
0.263, -0.1, 1.6, 0.0: every thumb link within 7 mm of the palm plane) because the straight thumb
sticks 3 cm out in front of the palm. LEAP's open pose (all 0) is already flat.
"""
from __future__ import annotations

import functools

import numpy as np
import torch

from shared.frames import make_transform, matrix_to_pose25
from shared.robots.hands import HandModel
from shared.robots.hands.primitives import surface_samples

SPATULA_GAP_M = 0.002
SPATULA_TABLE_CLEARANCE_M = 0.005
_SURFACE_SAMPLES_PER_PRIMITIVE = 400  # enough to hit every primitive's extreme faces; exact for boxes
_SAMPLES_SEED = 0

SPATULA_JOINTS: dict[str, dict[str, float]] = {
    "allegro": {"joint_12.0": 0.263, "joint_13.0": -0.1, "joint_14.0": 1.6, "joint_15.0": 0.0},
    "leap": {},
}


class FixedPoseError(ValueError):
    """A fixed pose that cannot be built (unknown hand, object without vertices)."""


def spatula_joints(hand: HandModel) -> np.ndarray:
    """The spatula joint angles [16] in the hand's pose-vector order (unlisted joints 0)."""
    if hand.name not in SPATULA_JOINTS:
        raise FixedPoseError(f"no spatula pose for hand {hand.name!r}; known: {sorted(SPATULA_JOINTS)}")
    values = SPATULA_JOINTS[hand.name]
    return np.array([values.get(name, 0.0) for name in hand.joint_names])


def spatula_rotation(hand: HandModel) -> np.ndarray:
    """Base rotation in D: palm normal -> +x, finger direction -> -z."""
    normal = hand.palm_normal_base.double().numpy()
    fingers = hand.finger_direction_base.double().numpy()
    base_axes = np.stack([normal, fingers, np.cross(normal, fingers)], axis=1)
    d_axes = np.stack([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], np.cross([1.0, 0.0, 0.0], [0.0, 0.0, -1.0])], axis=1)
    rotation: np.ndarray = d_axes @ base_axes.T
    return rotation


def spatula_pose(hand: HandModel, object_vertices_d: np.ndarray) -> np.ndarray:
    """The spatula pose [25] (in D) for an object given by its vertices in D at its resting pose."""
    vertices = np.asarray(object_vertices_d, dtype=np.float64)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or len(vertices) == 0:
        raise FixedPoseError(f"object vertices must be a non-empty [V, 3] array, got shape {vertices.shape}")
    rotation = spatula_rotation(hand)
    joints = spatula_joints(hand)
    surface = _hand_surface_base(hand, tuple(joints)) @ rotation.T  # hand surface, rotated, base at origin
    height = float(vertices[:, 2].max())
    lowest, highest = surface[:, 2].min(), surface[:, 2].max()
    centre_z = max(height / 2.0, SPATULA_TABLE_CLEARANCE_M + (highest - lowest) / 2.0)
    position = np.array([0.0, -(surface[:, 1].max() + surface[:, 1].min()) / 2.0, centre_z - (highest + lowest) / 2.0])
    # The gap is to the part of the hand that faces the object (the thumb may stick out above it).
    placed = surface + position
    facing = ((placed[:, 1] >= vertices[:, 1].min()) & (placed[:, 1] <= vertices[:, 1].max())
              & (placed[:, 2] <= height))
    front = placed[facing, 0].max() if facing.any() else placed[:, 0].max()
    position[0] = vertices[:, 0].min() - SPATULA_GAP_M - front
    return matrix_to_pose25(make_transform(rotation, position), joints)


@functools.lru_cache(maxsize=8)
def _hand_surface_base(hand: HandModel, joints: tuple[float, ...]) -> np.ndarray:
    """Points on every collision primitive of the hand at `joints`, in the base frame [N, 3]."""
    pose = hand.open_pose(1)
    pose[0, 9:] = torch.tensor(joints, dtype=pose.dtype)
    links = hand.forward(pose).links[0].double().numpy()
    rng = np.random.default_rng(_SAMPLES_SEED)
    points = []
    for prim in hand.primitives.prims:
        local, _ = surface_samples(prim, _SURFACE_SAMPLES_PER_PRIMITIVE, rng)
        frame = links[prim.link_index]
        points.append(local @ frame[:3, :3].T + frame[:3, 3])
    return np.concatenate(points)
