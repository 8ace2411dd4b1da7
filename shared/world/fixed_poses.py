"""The fixed hand poses: the "spatula" (the paper's Fixed Hand Pose baseline and the physics sanity check) and
the "fingertip" (a straight-line pusher: one finger pointing along the push at the centre of mass).

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

The fingertip pose is what a user would try before a dexterous hand: the index finger straight and pointing
along the push (+x of D), the middle and ring fingers curled into a loose fist (their flexion joints at
FINGERTIP_CURL of their upper limits), the thumb as the spatula's; the palm faces sideways, turned the way
that puts the fingertip lowest on the hand (on the Allegro only the tucked thumb is below it), and the fingertip sits `SPATULA_GAP_M` behind the object's rear
face on the line through its centre of mass, at the height of the centre of mass (raised, if needed, so the
hand's lowest point clears the table by `SPATULA_TABLE_CLEARANCE_M`). Pushing there moves the object
without turning it, as far as friction is even.
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


FINGERTIP_CURL = 0.8  # the curled fingers' flexion joints at this share of their upper limits
# The pointing finger's tip link per hand (the index finger; the hands order their joints index, middle, ring,
# thumb, four each, so joints 4-11 are the fingers the fingertip pose curls). Not LEAP's: its thumb, straight at
# the index finger's side, hangs 11 cm below the fingertip whichever side the palm faces, and no tucked thumb
# pose has been measured for it.
FINGERTIP_LINKS = {"allegro": "link_3.0_tip"}
CURLED_JOINTS = range(4, 12)
FIXED_POSE_METHODS = ("fixed", "fingertip")  # PlannerOptions.method values whose one pose is built here


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
    surface = _hand_surface_links(hand, tuple(joints))[0] @ rotation.T  # hand surface, rotated, base at origin
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


def fixed_pose(method: str, hand: HandModel, object_vertices_d: np.ndarray, com_d: np.ndarray) -> np.ndarray:
    """The one pose [25] in D of a fixed-pose method (FIXED_POSE_METHODS) for the object given by its vertices in
    D and its centre of mass in D."""
    if method == "fixed":
        return spatula_pose(hand, object_vertices_d)
    if method == "fingertip":
        return fingertip_pose(hand, object_vertices_d, com_d)
    raise FixedPoseError(f"no fixed pose {method!r}; known: {', '.join(FIXED_POSE_METHODS)}")


def fingertip_joints(hand: HandModel) -> np.ndarray:
    """The fingertip pose's joint angles [16]: the spatula's, the middle and ring fingers curled (their flexion
    joints; an abduction joint's limits are symmetric about 0 and it stays at 0)."""
    joints = spatula_joints(hand).copy()
    lower, upper = hand.joint_lower.double().numpy(), hand.joint_upper.double().numpy()
    for i in CURLED_JOINTS:
        if not np.isclose(lower[i], -upper[i], atol=1e-3):
            joints[i] = FINGERTIP_CURL * upper[i]
    curled: np.ndarray = joints
    return curled


def fingertip_pose(hand: HandModel, object_vertices_d: np.ndarray, com_d: np.ndarray) -> np.ndarray:
    """The fingertip pose [25] (in D) for an object given by its vertices in D and its centre of mass in D."""
    vertices = np.asarray(object_vertices_d, dtype=np.float64)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or len(vertices) == 0:
        raise FixedPoseError(f"object vertices must be a non-empty [V, 3] array, got shape {vertices.shape}")
    if hand.name not in FINGERTIP_LINKS:
        raise FixedPoseError(f"no fingertip pose for hand {hand.name!r}; known: {sorted(FINGERTIP_LINKS)}")
    joints = fingertip_joints(hand)
    points, links = _hand_surface_links(hand, tuple(joints))
    is_tip = links == hand.link_index(FINGERTIP_LINKS[hand.name])
    # Of the two sideways palms, the one that puts the pointing finger lowest (the fist above it, off the table).
    rotation = min((_pointing_rotation(hand, side) for side in (1.0, -1.0)),
                   key=lambda r: float((points[is_tip] @ r.T)[:, 2].mean() - (points @ r.T)[:, 2].min()))
    surface = points @ rotation.T
    tip = surface[is_tip]
    tip_centre = tip.mean(axis=0)
    height = max(float(com_d[2]), tip_centre[2] - surface[:, 2].min() + SPATULA_TABLE_CLEARANCE_M)
    # the object's rear face where the finger meets it: its points within 1 cm of the push line at that height
    near = (np.abs(vertices[:, 1] - com_d[1]) < 0.01) & (np.abs(vertices[:, 2] - height) < 0.01)
    rear = float(vertices[near, 0].min() if near.any() else vertices[:, 0].min())
    position = np.array([rear - SPATULA_GAP_M - float(tip[:, 0].max()), float(com_d[1]) - tip_centre[1],
                         height - tip_centre[2]])
    return matrix_to_pose25(make_transform(rotation, position), joints)


def _pointing_rotation(hand: HandModel, side: float) -> np.ndarray:
    """Base rotation in D: finger direction -> +x (along the push), palm normal -> `side` * y (sideways)."""
    normal = hand.palm_normal_base.double().numpy()
    fingers = hand.finger_direction_base.double().numpy()
    base_axes = np.stack([fingers, normal, np.cross(fingers, normal)], axis=1)
    d_axes = np.stack([[1.0, 0.0, 0.0], [0.0, side, 0.0], np.cross([1.0, 0.0, 0.0], [0.0, side, 0.0])], axis=1)
    rotation: np.ndarray = d_axes @ base_axes.T
    return rotation


@functools.lru_cache(maxsize=8)
def _hand_surface_links(hand: HandModel, joints: tuple[float, ...]) -> tuple[np.ndarray, np.ndarray]:
    """Points on every collision primitive of the hand at `joints`, in the base frame [N, 3], and the index of
    the link each lies on [N]."""
    pose = hand.open_pose(1)
    pose[0, 9:] = torch.tensor(joints, dtype=pose.dtype)
    links = hand.forward(pose).links[0].double().numpy()
    rng = np.random.default_rng(_SAMPLES_SEED)
    points, owners = [], []
    for prim in hand.primitives.prims:
        local, _ = surface_samples(prim, _SURFACE_SAMPLES_PER_PRIMITIVE, rng)
        frame = links[prim.link_index]
        points.append(local @ frame[:3, :3].T + frame[:3, 3])
        owners.append(np.full(len(local), prim.link_index))
    return np.concatenate(points), np.concatenate(owners)
