"""An arm with its hand on the table, next to an object and obstacles: collision checks and physics.

Used by the planner (state validity for OMPL, Cartesian segments) and by the simulated robot bridge
(executing plans with physics). One `RobotScene` wraps one `SimScene` (a PyBullet DIRECT world with
the table plane at z = 0) and the arm + hand loaded from `shared.robots.arms.combined_urdf`, fixed at
`T_world_base` (default: the world origin, on the table).

Collision rules (what counts as a collision of a configuration):
- any robot link within `clearance_m` of the table, except the arm's base link (and links fixed to
  it), which stands on it;
- any robot link within `clearance_m` of an obstacle;
- any robot link within `clearance_m` of the object, unless the caller allows hand-object contact
  (a pre-contact pose touches the object on purpose; the push segment pushes it);
- an arm link within `clearance_m` of a hand link (the arm folding into its own hand), except the
  arm links rigidly attached to the hand (after the last moving arm joint), which touch it by design.
Hand-vs-hand and arm-vs-arm checks are left out: finger self-collision is the pose generator's job,
and the arm's joint limits keep its own links apart.
"""
from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pybullet as pb

from shared.contracts.messages import Obstacle, WallObstacle
from shared.robots.arms import ArmModel, combined_urdf, load_arm, mount_joint_name
from shared.robots.hands import HandModel, load_hand
from shared.world.obstacles import wall_half_extents, wall_pose
from shared.world.sim.params import PhysicsParams
from shared.world.sim.scene import Body, SimError, SimScene, c_stdout_to_stderr, transform_to_pos_quat

Joints = Sequence[float] | np.ndarray  # joint angles (rad)



@dataclass(frozen=True)
class Collision:
    """One offending pair: a robot link and what it touches (distance < 0 is penetration)."""

    robot_link: str
    other: str  # "table", "object", "obstacle N" (a cylinder), "wall N", "neighbour N" or a robot link name
    distance_m: float

    def __str__(self) -> str:
        return f"{self.robot_link} vs {self.other} ({self.distance_m * 1000:.1f} mm)"


class RobotScene:
    """PyBullet world: table, arm + hand (fixed base), optional object, cylinder obstacles and walls."""

    def __init__(
        self,
        arm: ArmModel | str,
        hand: HandModel | str,
        *,
        T_world_base: np.ndarray | None = None,
        params: PhysicsParams | None = None,
    ):
        self.arm = load_arm(arm) if isinstance(arm, str) else arm
        self.hand = load_hand(hand) if isinstance(hand, str) else hand
        self.T_world_base = np.eye(4) if T_world_base is None else np.asarray(T_world_base, dtype=np.float64)
        self.sim = SimScene(params)
        self.client = self.sim.client
        self.robot_id = self._load_robot(combined_urdf(self.arm, self.hand))
        self._index_links()
        self._self_check_links = self.self_check_arm_links + sorted(self.hand_links)
        self._centres_local, self._radii = self._bounding_spheres(self._self_check_links)
        self.object: Body | None = None
        self.obstacles: list[Body] = []  # the cylinders
        self.walls: list[Body] = []
        self.neighbours: list[Body] = []  # other movable objects beside the one pushed (clutter)

    # ------------------------------------------------------------------------------------- building

    def _load_robot(self, urdf: Path) -> int:
        pos, quat = transform_to_pos_quat(self.T_world_base)
        # Implicit cylinders: exact finger shapes, not faceted hulls with a 1 mm margin (as the validator).
        with c_stdout_to_stderr():  # PyBullet warns on stdout (links without inertia): keep stdout clean
            # Without the visual meshes: a depth camera (the simulated robot's image tracker) then sees the
            # collision shapes, which TinyRenderer draws 4x faster than the Panda's and Allegro's visual meshes
            # (measured: 3 cameras at 424 x 240, 0.12 -> 0.03 s; the robot's silhouette differs by a few
            # pixels, and its self-filter mask is drawn from the same shapes). Nothing else renders this scene.
            robot: int = pb.loadURDF(str(urdf), pos, quat, useFixedBase=True,
                                     flags=pb.URDF_USE_IMPLICIT_CYLINDER | pb.URDF_IGNORE_VISUAL_SHAPES,
                                     physicsClientId=self.client)
        for link in range(-1, pb.getNumJoints(robot, physicsClientId=self.client)):
            pb.changeDynamics(robot, link, lateralFriction=self.sim.params.hand_friction, physicsClientId=self.client)
        return robot

    def _index_links(self) -> None:
        client = self.client
        by_joint: dict[str, int] = {}
        self.link_names: dict[int, str] = {-1: self.arm.base_link}
        parent: dict[int, int] = {}
        # The base and whatever is bolted to it (e.g. the xArm's world -> link_base): stands on the table.
        self.base_links = {-1}
        for j in range(pb.getNumJoints(self.robot_id, physicsClientId=client)):  # parents before children
            info = pb.getJointInfo(self.robot_id, j, physicsClientId=client)
            by_joint[info[1].decode()] = j
            self.link_names[j] = info[12].decode()
            parent[j] = info[16]
            if info[2] == pb.JOINT_FIXED and parent[j] in self.base_links:
                self.base_links.add(j)
        missing = [n for n in (*self.arm.joint_names, *self.hand.joint_names) if n not in by_joint]
        if missing:
            raise SimError(f"combined {self.arm.name}+{self.hand.name} URDF lacks joints {missing}")
        self.arm_joints = [by_joint[n] for n in self.arm.joint_names]
        self.hand_joints = [by_joint[n] for n in self.hand.joint_names]
        self.joint_names: tuple[str, ...] = (*self.arm.joint_names, *self.hand.joint_names)
        mount_joint = mount_joint_name(self.arm.name, self.hand.name)
        if mount_joint not in by_joint:
            raise SimError(f"combined URDF lacks the mount joint {mount_joint!r}")
        hand_root = by_joint[mount_joint]  # PyBullet: a joint's index is its child link's index
        # Hand links: the palm (child of the mount joint) and everything below it.
        self.hand_links = {j for j in self.link_names if j >= 0 and _descends_from(j, hand_root, parent)}
        self.arm_links = set(self.link_names) - self.hand_links
        last_moving = self.arm_joints[-1]
        rigid_with_hand = {j for j in self.arm_links if j >= 0 and _descends_from(j, last_moving, parent)}
        self.self_check_arm_links = sorted(self.arm_links - rigid_with_hand - self.base_links)

    def _bounding_spheres(self, links: list[int]) -> tuple[np.ndarray, np.ndarray]:
        """Per link, a sphere around its collision shape: centre in the link frame [n,3] and radius [n].

        Taken from the AABBs PyBullet computed at load, when they match the link poses (it does not
        update them on `resetJointState`); the sphere around an AABB bounds the shape in any pose.
        """
        centres, radii = np.zeros((len(links), 3)), np.zeros(len(links))
        states = pb.getLinkStates(self.robot_id, links, computeForwardKinematics=True, physicsClientId=self.client)
        for i, (link, state) in enumerate(zip(links, states, strict=True)):
            low, high = (np.asarray(v) for v in pb.getAABB(self.robot_id, link, physicsClientId=self.client))
            rotation = np.asarray(pb.getMatrixFromQuaternion(state[5])).reshape(3, 3)
            centres[i] = rotation.T @ ((low + high) / 2 - np.asarray(state[4]))
            radii[i] = np.linalg.norm(high - low) / 2
        return centres, radii

    def use_contact_physics(self, params: PhysicsParams) -> None:
        """Set the friction of the table and the robot, and the rolling friction of objects added from now
        on, to `params`' (a drawn world's): another world without reloading the robot. The solver settings
        must stay those the scene was built with."""
        built = self.sim.params
        if (params.solver_iterations, params.time_step_s) != (built.solver_iterations, built.time_step_s):
            raise SimError("use_contact_physics changes friction only: build a new scene for other solver settings")
        self.sim.params = params
        pb.changeDynamics(self.sim.table.id, -1, lateralFriction=params.table_friction, physicsClientId=self.client)
        for link in range(-1, pb.getNumJoints(self.robot_id, physicsClientId=self.client)):
            pb.changeDynamics(self.robot_id, link, lateralFriction=params.hand_friction, physicsClientId=self.client)

    def add_object(self, urdf_path: str | Path, T_world_O: np.ndarray) -> Body:
        """Load the object (URDF from `shared.world.objects.write_object_urdf`) with its frame O at `T_world_O`."""
        if self.object is not None:
            raise SimError("the scene already has an object")
        self.object = self.sim.add_object(urdf_path, T_world_O)
        return self.object

    def add_neighbour(self, urdf_path: str | Path, T_world_O: np.ndarray) -> Body:
        """Another movable object on the table (one the push must leave where it stands)."""
        body = self.sim.add_object(urdf_path, T_world_O)
        self.neighbours.append(body)
        return body

    def add_obstacles(self, obstacles: Iterable[Obstacle]) -> None:
        """Static cylinders and walls (`shared.contracts.messages.Obstacle`) standing on the table."""
        for obstacle in obstacles:
            if isinstance(obstacle, WallObstacle):
                self.walls.append(self.sim.add_box_obstacle(wall_pose(obstacle), wall_half_extents(obstacle)))
            else:
                self.obstacles.append(self.sim.add_cylinder_obstacle(obstacle.x, obstacle.y, obstacle.radius,
                                                                     obstacle.height_m))

    def clear_environment(self) -> None:
        """Remove the object, its neighbours, the obstacles and the walls (the robot and the table stay): reuse the
        scene for another world without reloading the robot (its URDF load is most of a scene's cost, ~0.7 s)."""
        for body in ([self.object] if self.object is not None else []) + self.neighbours + self.obstacles + self.walls:
            pb.removeBody(body.id, physicsClientId=self.client)
        self.object = None
        self.neighbours, self.obstacles, self.walls = [], [], []

    def close(self) -> None:
        self.sim.close()

    def __enter__(self) -> RobotScene:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------------------------- state

    def set_configuration(self, q_arm: Joints, q_hand: Joints | None = None) -> None:
        """Teleport the joints (zero velocity); hand joints unchanged when `q_hand` is None."""
        if len(q_arm) != len(self.arm_joints):
            raise SimError(f"{self.arm.name} has {len(self.arm_joints)} joints, got {len(q_arm)} angles")
        joints, angles = self.arm_joints, list(q_arm)
        if q_hand is not None:
            if len(q_hand) != len(self.hand_joints):
                raise SimError(f"{self.hand.name} has {len(self.hand_joints)} joints, got {len(q_hand)} angles")
            joints, angles = joints + self.hand_joints, angles + list(q_hand)
        pb.resetJointStatesMultiDof(self.robot_id, joints, [[float(a)] for a in angles], [[0.0]] * len(joints),
                                    physicsClientId=self.client)

    def joint_state(self) -> tuple[np.ndarray, np.ndarray]:
        """Positions and velocities of every joint (arm then hand, `joint_names` order)."""
        states = pb.getJointStates(self.robot_id, self.arm_joints + self.hand_joints, physicsClientId=self.client)
        return np.array([s[0] for s in states]), np.array([s[1] for s in states])

    def link_pose(self, link_name: str) -> np.ndarray:
        """World pose (4x4) of a robot link's URDF frame."""
        index = next((j for j, n in self.link_names.items() if n == link_name), None)
        if index is None:
            raise SimError(f"robot has no link {link_name!r}")
        if index == -1:
            base: np.ndarray = self.T_world_base.copy()
            return base
        state = pb.getLinkState(self.robot_id, index, computeForwardKinematics=True, physicsClientId=self.client)
        out = np.eye(4)
        out[:3, :3] = np.asarray(pb.getMatrixFromQuaternion(state[5])).reshape(3, 3)
        out[:3, 3] = state[4]
        return out

    # --------------------------------------------------------------------------------- collisions

    def collisions(
        self,
        q_arm: Joints | None = None,
        q_hand: Joints | None = None,
        *,
        clearance_m: float = 0.0,
        allow_hand_object: bool = False,
        first_only: bool = False,
    ) -> list[Collision]:
        """Collisions of the robot at (q_arm, q_hand) — or as it stands — under the module's rules.

        A pair collides when its distance is below `clearance_m`; a negative value tolerates that much
        penetration (e.g. fingertips grazing the table during a push).
        """
        if q_arm is not None:
            self.set_configuration(q_arm, q_hand)
        found: list[Collision] = []
        for body, name, skip_links in self._environment(allow_hand_object):
            found += self._robot_vs(body, name, clearance_m, skip_links)
            if first_only and found:
                return found[:1]
        found += self._arm_vs_hand(clearance_m, first_only)
        return found[:1] if first_only else found

    def contacts(self, allow_hand_object: bool = True) -> list[Collision]:
        """Contacts of the last physics step under the same rules (executions: the paper's L_coll)."""
        found: list[Collision] = []
        for body, name, skip_links in self._environment(allow_hand_object):
            deepest: dict[int, float] = {}
            for point in pb.getContactPoints(self.robot_id, body, physicsClientId=self.client):
                link = point[3]
                if link not in skip_links:
                    deepest[link] = min(point[8], deepest.get(link, np.inf))
            found += [Collision(self.link_names[link], name, d) for link, d in sorted(deepest.items())]
        return found

    def object_touches_obstacle(self) -> bool:
        """Whether the object touched a cylinder obstacle in the last physics step (false without an object; it
        may slide along a wall)."""
        return self.object is not None and any(
            pb.getContactPoints(self.object.id, obstacle.id, physicsClientId=self.client) for obstacle in self.obstacles)

    def is_collision_free(self, q_arm: Joints, q_hand: Joints | None = None, *,
                          clearance_m: float = 0.0, allow_hand_object: bool = False) -> bool:
        return not self.collisions(q_arm, q_hand, clearance_m=clearance_m, allow_hand_object=allow_hand_object,
                                   first_only=True)

    def _environment(self, allow_hand_object: bool) -> list[tuple[int, str, set[int]]]:
        env = [(self.sim.table.id, "table", self.base_links)]
        if self.object is not None:
            env.append((self.object.id, "object", self.hand_links if allow_hand_object else set()))
        env += [(body.id, f"obstacle {i}", set()) for i, body in enumerate(self.obstacles)]
        env += [(body.id, f"wall {i}", set()) for i, body in enumerate(self.walls)]
        env += [(body.id, f"neighbour {i}", set()) for i, body in enumerate(self.neighbours)]
        return env

    def _robot_vs(self, body: int, name: str, clearance_m: float, skip_links: set[int]) -> list[Collision]:
        points = pb.getClosestPoints(self.robot_id, body, max(clearance_m, 0.0), physicsClientId=self.client)
        worst: dict[int, float] = {}
        for point in points:
            link, distance = point[3], point[8]
            if link not in skip_links and distance < clearance_m:
                worst[link] = min(distance, worst.get(link, np.inf))
        return [Collision(self.link_names[link], name, d) for link, d in sorted(worst.items())]

    def _arm_vs_hand(self, clearance_m: float, first_only: bool) -> list[Collision]:
        found = []
        for arm_link, hand_link in self._self_check_pairs(max(clearance_m, 0.0)):
            points = pb.getClosestPoints(self.robot_id, self.robot_id, max(clearance_m, 0.0), arm_link, hand_link,
                                         physicsClientId=self.client)
            distance = min((p[8] for p in points), default=np.inf)
            if distance < clearance_m:
                found.append(Collision(self.link_names[arm_link], self.link_names[hand_link], distance))
                if first_only:
                    return found
        return found

    def _self_check_pairs(self, distance_m: float) -> list[tuple[int, int]]:
        """(arm link, hand link) pairs whose bounding spheres come closer than `distance_m`, in check order.

        A broad phase: most configurations leave every pair far apart, and one `getLinkStates` call
        replaces ~120 `getClosestPoints` calls (most of a collision check's time in RRTConnect).
        """
        states = pb.getLinkStates(self.robot_id, self._self_check_links, computeForwardKinematics=True,
                                  physicsClientId=self.client)
        positions = np.array([s[4] for s in states])
        quaternions = np.array([s[5] for s in states])  # x, y, z, w
        centres = positions + _rotate(quaternions, self._centres_local)
        n_arm = len(self.self_check_arm_links)
        gaps = (np.linalg.norm(centres[:n_arm, None] - centres[None, n_arm:], axis=-1)
                - self._radii[:n_arm, None] - self._radii[None, n_arm:])
        return [(self._self_check_links[a], self._self_check_links[n_arm + h]) for a, h in np.argwhere(gaps < distance_m)]


def _rotate(quaternions: np.ndarray, vectors: np.ndarray) -> np.ndarray:
    """Vectors [n,3] rotated by unit quaternions [n,4] (x, y, z, w)."""
    axis, w = quaternions[:, :3], quaternions[:, 3:]
    t = 2.0 * _cross(axis, vectors)
    rotated: np.ndarray = vectors + w * t + _cross(axis, t)
    return rotated


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross product of [n,3] arrays (np.cross costs more than the whole broad phase here)."""
    return np.stack([a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1], a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2],
                     a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]], axis=1)


def _descends_from(link: int, ancestor: int, parent: dict[int, int]) -> bool:
    """True if `link` is `ancestor` or below it in the kinematic tree."""
    while link >= 0:
        if link == ancestor:
            return True
        link = parent[link]
    return False
