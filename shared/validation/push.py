"""The push episode: a floating hand at a pose in D translates along +x; did the object follow?

Scene (world = the direction frame D): table plane z = 0, the object at its resting pose with its
centroid over the origin, the hand's base link at the pose, joints held by position control at the
pose's angles, the base driven kinematically through a fixed constraint whose target moves
`push_distance_m` along +x at `PhysicsParams.push_speed_mps`, then holds for `settle_s` while the
object comes to rest.

Success (paper, "Hand Pose Validation in Simulation"): judged by `shared.world.push_outcome.judge_push`, the
one judge of every push (validation, rollouts, executions): the object's centre (centre of mass)
ends within 3 cm (table plane) of start + push_distance_m * x, turned at most 45° and did not topple.
The other metrics are reported, not judged.

One `PushSimulator` per (object, hand, physics): the scene is built once and its settled state
saved; every episode restores that snapshot (bit-identical outcomes whatever ran before).
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from shared.frames import FrameError, pose25_to_matrix, quat_xyzw_to_matrix
from shared.robots.hands import HandModel
from shared.world.objects import ObjectModel, write_object_urdf
from shared.world.push_outcome import (
    SUCCESS_MAX_ROTATION_DEG,
    SUCCESS_POSITION_TOLERANCE_M,
    TOPPLED_TILT_DEG,
    judge_push,
    object_pose,
)
from shared.world.sim import PhysicsParams, SimScene, pos_quat_to_transform

DEFAULT_PUSH_DISTANCE_M = 0.20
# Contact "kept" if the hand touched the object in at least this share of the push steps: successful pushes of
# generator candidates nearly all touch throughout; the lower bar leaves room for a pre-contact gap (1 cm is a
# twentieth of the push) and brief contact chatter.
CONTACT_KEPT_MIN_FRACTION = 0.8
PENETRATION_PROBE_M = 0.05  # getClosestPoints search radius at t = 0
INITIAL_SETTLE_S = 0.2  # object alone on the table before the snapshot (lets contact margins settle)


class PushInputError(ValueError):
    """A pose or object that cannot be simulated (wrong shape, non-finite values)."""


@dataclass(frozen=True)
class TableObject:
    """An object ready for the push scene: its URDF and where its URDF base frame sits in D."""

    object_id: str
    urdf_path: Path
    transform_d: np.ndarray  # 4x4: URDF base frame in D, resting pose, centroid above the origin
    vertices_d: np.ndarray  # [V, 3] mesh vertices in D at that pose (for fixed poses and extents)

    @property
    def height(self) -> float:
        return float(self.vertices_d[:, 2].max())


def table_object(obj: ObjectModel, pose_index: int | None = None, yaw_rad: float = 0.0, mass_scale: float = 1.0,
                 com_offset_m: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> TableObject:
    """The library object resting in `pose_index` (its default pose if None), yawed by `yaw_rad` in D.

    `mass_scale` / `com_offset_m` (frame O): the true object of an execution world, heavier or lighter than
    the model and unevenly filled (`shared.world.sim.world`); the resting pose is the model's either way."""
    transform = obj.T_D_O(pose_index, yaw_rad)
    vertices = obj.mesh.vertices @ transform[:3, :3].T + transform[:3, 3]
    return TableObject(obj.id, write_object_urdf(obj, mass_scale, com_offset_m), transform, vertices)


@dataclass(frozen=True)
class PushOutcome:
    """Metrics of one push episode."""

    success: bool
    position_error_m: float
    rotation_deg: float
    max_tilt_deg: float
    contact_fraction: float
    contact_kept: bool
    hand_table_contact: bool
    initial_penetration_m: float

    def failure(self) -> str | None:
        """Why the push failed, one of FAILURES (None for a success): the object fell over at some point,
        turned past the success bound, was never touched, or ended off the target."""
        if self.success:
            return None
        if self.max_tilt_deg > TOPPLED_TILT_DEG:
            return "toppled"
        if self.rotation_deg > SUCCESS_MAX_ROTATION_DEG:
            return "turned"
        return "no contact" if self.contact_fraction == 0.0 else "missed"


# PushOutcome.failure's kinds, in the order reports list them, each with the words a report prints (from the
# thresholds themselves, so a report cannot name a bound the judge does not use).
FAILURES = {"turned": f"turned > {SUCCESS_MAX_ROTATION_DEG:g}°",
            "toppled": "toppled",
            "missed": f"missed by > {SUCCESS_POSITION_TOLERANCE_M * 100:g} cm",
            "no contact": "never touched"}


class PushSimulator:
    """Runs push episodes of one hand against one object in one PyBullet client."""

    def __init__(self, hand: HandModel, obj: TableObject, params: PhysicsParams | None = None):
        self.hand_model = hand
        self.object = obj
        self.params = params or PhysicsParams()
        self._joint_limits = (hand.joint_lower.double().numpy(), hand.joint_upper.double().numpy())
        self.scene = SimScene(self.params)
        try:
            self.body = self.scene.add_object(obj.urdf_path, obj.transform_d)
            self.hand = self.scene.add_floating_hand(hand.urdf_path, hand.joint_names)
            for _ in range(round(INITIAL_SETTLE_S / self.params.time_step_s)):
                self.scene.step()
            self._rest_pose = self.body.pose()
            self._state = self.scene.save()
        except BaseException:
            self.scene.close()
            raise

    def close(self) -> None:
        self.scene.close()

    def __enter__(self) -> PushSimulator:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def run(self, pose: np.ndarray, push_distance_m: float = DEFAULT_PUSH_DISTANCE_M,
            object_offset: np.ndarray | None = None) -> PushOutcome:
        """Push once. `object_offset` (4x4, in D) moves the resting object first (placement noise).

        Joint angles outside the hand's limits are clipped to them, as the real hand would.
        """
        base, joints = _parse_pose(pose)
        joints = np.clip(joints, *self._joint_limits)
        self.scene.restore(self._state)
        if object_offset is not None:
            self.body.reset_pose(object_offset @ self._rest_pose)
        self.hand.place(base, joints)
        penetration = max(0.0, -self.scene.closest_distance(self.hand, self.body, PENETRATION_PROBE_M))
        return self._simulate(base, push_distance_m, penetration)

    def _simulate(self, base: np.ndarray, distance: float, penetration: float) -> PushOutcome:
        p, scene, hand, body, table = self.params, self.scene, self.hand, self.body, self.scene.table
        start_pos, start_quat = body.com_pose()
        r_start = quat_xyzw_to_matrix(start_quat)
        up_in_object = r_start[2]  # world z expressed in the object's starting frame
        push_steps = max(1, round(distance / (p.push_speed_mps * p.time_step_s)))
        settle_steps = round(p.settle_s / p.time_step_s)
        target = base.copy()
        contact_steps, table_contact, min_up = 0, False, 1.0
        for k in range(push_steps + settle_steps):
            if k < push_steps:
                target[0, 3] = base[0, 3] + distance * (k + 1) / push_steps
                hand.drive(target)
            scene.step()
            if k < push_steps and scene.in_contact(hand, body):
                contact_steps += 1
            table_contact = table_contact or scene.in_contact(hand, table)
            min_up = min(min_up, _up_z(body.com_pose()[1], up_in_object))
        T_start = pos_quat_to_transform(start_pos, start_quat)
        result = judge_push(T_start, T_start[:2, 3] + np.array([distance, 0.0]),
                            object_pose(pos_quat_to_transform(*body.com_pose())))
        fraction = contact_steps / push_steps
        return PushOutcome(
            success=result.success, position_error_m=result.position_error_m, rotation_deg=result.rotation_deg,
            max_tilt_deg=math.degrees(math.acos(min(1.0, max(-1.0, min_up)))), contact_fraction=fraction,
            contact_kept=fraction >= CONTACT_KEPT_MIN_FRACTION, hand_table_contact=table_contact,
            initial_penetration_m=penetration)


def _parse_pose(pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    pose = np.asarray(pose, dtype=np.float64)
    if pose.shape != (25,):
        raise PushInputError(f"a hand pose must have 25 values [p(3), r6(6), q(16)], got shape {pose.shape}")
    if not np.all(np.isfinite(pose)):
        raise PushInputError("a hand pose contains NaN or infinity")
    try:
        return pose25_to_matrix(pose)
    except FrameError as exc:
        raise PushInputError(f"a hand pose has an invalid rotation: {exc}") from exc


def _up_z(quat: Sequence[float], up_in_object: np.ndarray) -> float:
    """z component of the object's initial up direction after rotating by `quat` (cos of the tilt).

    Runs every step, so it is the third row of the rotation matrix written out, not a library call.
    """
    x, y, z, w = quat
    row = (2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y))
    up_z: float = row[0] * up_in_object[0] + row[1] * up_in_object[1] + row[2] * up_in_object[2]
    return up_z
