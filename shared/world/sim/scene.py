"""The PyBullet scene shared by the validator, the planner's collision checks and the simulated robot.

One `SimScene` owns one PyBullet DIRECT client: a table plane at z = 0, objects loaded from their
URDFs, floating hands and fixed-base robots. Conventions that PyBullet gets wrong by default are
handled here once (docs/architecture.md §Simulation):

- PyBullet's base pose is the base's centre of mass, not the URDF link frame. Every pose this
  module accepts or returns is the *URDF base frame* as a 4x4 transform; conversion happens inside.
- The Allegro URDF's joint damping (3-10) makes a floating hand explode with no contact at all, so
  the hand's joint damping is overridden (`PhysicsParams.hand_joint_damping`).
- Objects are loaded with the inertia their URDF declares (the object library computes it from the
  mesh); hands use PyBullet's shape-derived inertia because the Allegro URDF's finger inertias are
  invalid (PyBullet would zero them and print a warning per link).

Reuse: build the scene once per (object, hand), `save()` its state, and `restore()` it before each
episode. Measured here (Allegro + proc-box-001 / pb-mug, loaded machine): restoreState 0.002 /
0.4 ms, removing and re-adding hand and object 37 / 39 ms, resetSimulation + reload 48 / 66 ms -
against ~40-100 ms for the push itself. All three gave bit-identical outcomes for the same episode
whatever ran before it.
"""
from __future__ import annotations

import contextlib
import os
import sys
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pybullet as pb

from shared.frames import matrix_to_quat_xyzw
from shared.world.sim.params import PhysicsParams

TABLE_TOP_HALF_EXTENTS_M = (1.5, 1.5, 0.01)


class SimError(RuntimeError):
    """A scene that cannot be built (unloadable URDF, unknown joint, closed client)."""


# ----------------------------------------------------------------------------------------- transforms


def transform_to_pos_quat(transform: np.ndarray) -> tuple[list[float], list[float]]:
    """4x4 rigid transform -> (position, xyzw quaternion) as PyBullet wants them."""
    transform = np.asarray(transform, dtype=np.float64)
    if transform.shape != (4, 4):
        raise SimError(f"expected a 4x4 transform, got shape {transform.shape}")
    return transform[:3, 3].tolist(), matrix_to_quat_xyzw(transform[:3, :3]).tolist()


def pos_quat_to_transform(position: Sequence[float], quat_xyzw: Sequence[float]) -> np.ndarray:
    """(position, xyzw quaternion) -> 4x4 rigid transform."""
    out = np.eye(4)
    out[:3, :3] = np.asarray(pb.getMatrixFromQuaternion(quat_xyzw)).reshape(3, 3)
    out[:3, 3] = position
    return out


@contextlib.contextmanager
def c_stdout_to_stderr() -> Iterator[None]:
    """Send C-level stdout to stderr: PyBullet prints warnings on fd 1, which would corrupt JSON output."""
    sys.stdout.flush()
    saved = os.dup(1)
    try:
        os.dup2(2, 1)
        yield
    finally:
        sys.stdout.flush()
        os.dup2(saved, 1)
        os.close(saved)


# -------------------------------------------------------------------------------------------- bodies


@dataclass
class Body:
    """A body in the scene and the offset between its URDF base frame and PyBullet's base (COM) frame."""

    scene: SimScene
    id: int
    com_offset: np.ndarray  # T_base_com: URDF base frame -> centre-of-mass frame

    def pose(self) -> np.ndarray:
        """The URDF base frame in the world (4x4)."""
        pos, quat = pb.getBasePositionAndOrientation(self.id, physicsClientId=self.scene.client)
        return pos_quat_to_transform(pos, quat) @ np.linalg.inv(self.com_offset)

    def com_pose(self) -> tuple[tuple[float, ...], tuple[float, ...]]:
        """PyBullet's base pose: centre-of-mass position and xyzw quaternion."""
        pose: tuple[tuple[float, ...], tuple[float, ...]] = pb.getBasePositionAndOrientation(
            self.id, physicsClientId=self.scene.client)
        return pose

    def reset_pose(self, transform: np.ndarray) -> None:
        """Teleport the URDF base frame to `transform` and zero the base velocity."""
        pos, quat = transform_to_pos_quat(np.asarray(transform) @ self.com_offset)
        pb.resetBasePositionAndOrientation(self.id, pos, quat, physicsClientId=self.scene.client)
        pb.resetBaseVelocity(self.id, [0.0, 0.0, 0.0], [0.0, 0.0, 0.0], physicsClientId=self.scene.client)


class FloatingHand(Body):
    """A free-floating hand whose base is driven kinematically by a fixed constraint to the world.

    Joints are held by PyBullet position control at the commanded angles (gain
    `PhysicsParams.hand_position_gain`), each with its URDF effort limit times
    `PhysicsParams.hand_joint_force_scale` as the force limit.
    """

    def __init__(self, scene: SimScene, body_id: int, com_offset: np.ndarray, joint_names: Sequence[str]):
        super().__init__(scene, body_id, com_offset)
        by_name = scene.joint_indices(body_id)
        missing = [n for n in joint_names if n not in by_name]
        if missing:
            raise SimError(f"hand URDF has no joints {missing}")
        self.joint_indices = [by_name[n] for n in joint_names]
        client = scene.client
        efforts = [pb.getJointInfo(body_id, j, physicsClientId=client)[10] for j in self.joint_indices]
        self.joint_forces = [scene.params.hand_joint_force_scale * f for f in efforts]
        pos, quat = self.com_pose()
        self.constraint = pb.createConstraint(
            body_id, -1, -1, -1, pb.JOINT_FIXED, [0, 0, 0], [0, 0, 0], pos, childFrameOrientation=quat,
            physicsClientId=client)
        self._rotation_cache: tuple[np.ndarray, list[float]] | None = None

    def place(self, transform: np.ndarray, joints: Sequence[float]) -> None:
        """Teleport the base to `transform` (URDF base frame), joints to `joints`, and hold both there."""
        joints = [float(q) for q in joints]
        if len(joints) != len(self.joint_indices):
            raise SimError(f"hand has {len(self.joint_indices)} joints, got {len(joints)} angles")
        self.reset_pose(transform)
        client = self.scene.client
        for index, angle in zip(self.joint_indices, joints, strict=True):
            pb.resetJointState(self.id, index, angle, 0.0, physicsClientId=client)
        pb.setJointMotorControlArray(
            self.id, self.joint_indices, pb.POSITION_CONTROL, targetPositions=joints,
            forces=self.joint_forces, positionGains=[self.scene.params.hand_position_gain] * len(joints),
            physicsClientId=client)
        self.drive(transform)

    def drive(self, transform: np.ndarray) -> None:
        """Move the constraint target of the base to `transform` (URDF base frame); takes effect on step."""
        com = np.asarray(transform, dtype=np.float64) @ self.com_offset
        pb.changeConstraint(self.constraint, com[:3, 3].tolist(), self._quaternion(com[:3, :3]),
                            maxForce=self.scene.params.base_constraint_force_n, physicsClientId=self.scene.client)

    def _quaternion(self, rotation: np.ndarray) -> list[float]:
        """Quaternion of `rotation`, cached: a push drives the base at a constant orientation."""
        cached = self._rotation_cache
        if cached is None or not np.array_equal(cached[0], rotation):
            cached = self._rotation_cache = (rotation.copy(), matrix_to_quat_xyzw(rotation).tolist())
        return cached[1]

    def joint_positions(self) -> np.ndarray:
        states = pb.getJointStates(self.id, self.joint_indices, physicsClientId=self.scene.client)
        return np.array([s[0] for s in states])


# --------------------------------------------------------------------------------------------- scene


class SimScene:
    """A PyBullet DIRECT world with a table plane at z = 0. Use as a context manager, or call close()."""

    table: Body  # the plane at z = 0, added by reset()

    def __init__(self, params: PhysicsParams | None = None):
        self.params = params or PhysicsParams()
        self.client = pb.connect(pb.DIRECT)
        if self.client < 0:
            raise SimError("could not start a PyBullet DIRECT client")
        self.reset()

    # ------------------------------------------------------------------------------------ lifecycle

    def reset(self) -> None:
        """Empty the world (resetSimulation) and add the table again."""
        client = self.client
        pb.resetSimulation(physicsClientId=client)
        pb.setPhysicsEngineParameter(
            fixedTimeStep=self.params.time_step_s, numSolverIterations=self.params.solver_iterations,
            erp=self.params.constraint_erp, deterministicOverlappingPairs=1, physicsClientId=client)
        pb.setGravity(0.0, 0.0, -self.params.gravity_mps2, physicsClientId=client)
        plane = pb.createCollisionShape(pb.GEOM_PLANE, physicsClientId=client)
        # What a depth camera sees of the table: a 3 m square top (one box). Without a visual shape TinyRenderer
        # draws the plane's own tessellated stand-in, 3x the cost of the rest of the robot's scene.
        top = pb.createVisualShape(pb.GEOM_BOX, halfExtents=TABLE_TOP_HALF_EXTENTS_M,
                                   visualFramePosition=(0.0, 0.0, -TABLE_TOP_HALF_EXTENTS_M[2]), physicsClientId=client)
        table_id = pb.createMultiBody(0.0, plane, top, physicsClientId=client)
        pb.changeDynamics(table_id, -1, lateralFriction=self.params.table_friction, physicsClientId=client)
        self.table = Body(self, table_id, np.eye(4))

    def close(self) -> None:
        if self.client >= 0:
            pb.disconnect(physicsClientId=self.client)
            self.client = -1

    def __enter__(self) -> SimScene:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def save(self) -> int:
        """Snapshot the whole world in memory (positions, velocities, contact caches)."""
        state_id: int = pb.saveState(physicsClientId=self.client)
        return state_id

    def restore(self, state_id: int) -> None:
        """Return to a `save()`d snapshot; bodies and constraints must be the same as when saved."""
        pb.restoreState(stateId=state_id, physicsClientId=self.client)

    def step(self) -> None:
        pb.stepSimulation(physicsClientId=self.client)

    # ----------------------------------------------------------------------------------------- bodies

    def add_object(self, urdf_path: str | Path, transform: np.ndarray) -> Body:
        """Load an object URDF (its declared mass and inertia) with its base frame at `transform`."""
        body_id = self._load_urdf(urdf_path, flags=pb.URDF_USE_INERTIA_FROM_FILE)
        body = Body(self, body_id, self._com_offset(body_id))
        pb.changeDynamics(body_id, -1, lateralFriction=self.params.object_friction,
                          rollingFriction=self.params.object_rolling_friction, physicsClientId=self.client)
        body.reset_pose(transform)
        return body

    def add_floating_hand(self, urdf_path: str | Path, joint_names: Sequence[str]) -> FloatingHand:
        """Load a hand URDF as a free body driven by a base constraint; joints in pose-vector order."""
        # Implicit cylinders: exact shapes, not PyBullet's default faceted hulls with a 1 mm margin.
        body_id = self._load_urdf(urdf_path, flags=pb.URDF_USE_IMPLICIT_CYLINDER, base_position=(0.0, 0.0, 10.0))
        for link in range(-1, pb.getNumJoints(body_id, physicsClientId=self.client)):
            mass = pb.getDynamicsInfo(body_id, link, physicsClientId=self.client)[0]
            pb.changeDynamics(body_id, link, mass=mass * self.params.hand_mass_scale,
                              lateralFriction=self.params.hand_friction,
                              jointDamping=self.params.hand_joint_damping, physicsClientId=self.client)
        return FloatingHand(self, body_id, self._com_offset(body_id), joint_names)

    def add_fixed_robot(self, urdf_path: str | Path, base_transform: np.ndarray) -> Body:
        """Load a fixed-base robot (an arm, or arm + hand) with its URDF base frame at `base_transform`."""
        pos, quat = transform_to_pos_quat(base_transform)
        body_id = self._load_urdf(urdf_path, flags=0, base_position=pos, base_orientation=quat, fixed=True)
        return Body(self, body_id, self._com_offset(body_id))

    def add_cylinder_obstacle(self, x: float, y: float, radius: float, height: float = 0.3) -> Body:
        """A static vertical cylinder standing on the table."""
        shape = pb.createCollisionShape(pb.GEOM_CYLINDER, radius=radius, height=height, physicsClientId=self.client)
        body_id = pb.createMultiBody(0.0, shape, basePosition=[x, y, height / 2], physicsClientId=self.client)
        return Body(self, body_id, np.eye(4))

    def add_box_obstacle(self, T_world_box: np.ndarray, half_extents: np.ndarray) -> Body:
        """A static box (a wall) with its centre at T_world_box."""
        shape = pb.createCollisionShape(pb.GEOM_BOX, halfExtents=[float(h) for h in half_extents],
                                        physicsClientId=self.client)
        pos, quat = transform_to_pos_quat(T_world_box)
        body_id = pb.createMultiBody(0.0, shape, basePosition=pos, baseOrientation=quat, physicsClientId=self.client)
        return Body(self, body_id, np.eye(4))

    def joint_indices(self, body_id: int) -> dict[str, int]:
        """Movable joint name -> PyBullet joint index."""
        out = {}
        for j in range(pb.getNumJoints(body_id, physicsClientId=self.client)):
            info = pb.getJointInfo(body_id, j, physicsClientId=self.client)
            if info[2] in (pb.JOINT_REVOLUTE, pb.JOINT_PRISMATIC):
                out[info[1].decode()] = j
        return out

    # -------------------------------------------------------------------------------------- queries

    def in_contact(self, a: Body, b: Body) -> bool:
        """True if the last step produced a contact point between `a` and `b`."""
        return bool(pb.getContactPoints(a.id, b.id, physicsClientId=self.client))

    def closest_distance(self, a: Body, b: Body, max_distance: float) -> float:
        """Signed distance between two bodies (negative = penetration), capped at `max_distance`."""
        points = pb.getClosestPoints(a.id, b.id, max_distance, physicsClientId=self.client)
        return min((pt[8] for pt in points), default=max_distance)

    # ------------------------------------------------------------------------------------- internals

    def _load_urdf(self, urdf_path: str | Path, flags: int, base_position: Sequence[float] = (0.0, 0.0, 0.0),
                   base_orientation: Sequence[float] = (0.0, 0.0, 0.0, 1.0), fixed: bool = False) -> int:
        path = Path(urdf_path)
        if not path.is_file():
            raise SimError(f"URDF not found: {path}")
        try:
            body: int = pb.loadURDF(str(path), list(base_position), list(base_orientation), useFixedBase=fixed,
                                    flags=flags, physicsClientId=self.client)
            return body
        except pb.error as exc:
            raise SimError(f"PyBullet cannot load {path}: {exc}") from exc

    def _com_offset(self, body_id: int) -> np.ndarray:
        info = pb.getDynamicsInfo(body_id, -1, physicsClientId=self.client)
        return pos_quat_to_transform(info[3], info[4])
