"""The MuJoCo model of the world the MuJoCo robot executes in: arm + hand, table, object, obstacles.

- Robot: the project's combined URDF (`shared.robots.arms.combined_urdf`: the arm with the hand fixed to
  its flange by `mount`, the frames the planner uses), read by `mujoco.MjSpec.from_file` and compiled
  with `compiler.balanceinertia` (some hand links' URDF inertias break the triangle inequality). Its base
  stands at `T_world_base`. Every joint gets a position servo (config.ControlConfig) whose force is capped at
  the URDF effort, and every link gravity compensation through its actuators.
- Collisions: robot links collide with the table, the object and obstacles but not with each other (as in
  PyBullet's default, which the planner's validity checks assume: finger self-collision is the pose
  generator's job). The table is a plane at z = 0 (a 3 m square to cameras, infinite to collisions).
- Object: a free body whose frame is O (centre of mass and principal axes: its inertia is diagonal), its
  collision geoms the convex pieces of `decompose.convex_pieces`, its mass and centre of mass those of the
  world (a drawn world's may differ from the model's).
- Contacts: MuJoCo's soft contacts with the cone, impedance and solver of config.ContactConfig; each pair's
  friction is set where it is drawn (config.MaterialConfig): the table's and the robot's geoms outrank
  the object's, each finger's geoms carry the hand's friction times that finger's scale.
- Rendering: an offscreen framebuffer of `OFFSCREEN_SIZE` (the D435's largest depth mode) for the
  depth cameras (`cameras.py`).

A model that does not compile raises `ModelError` naming the element MuJoCo blames and its reason.
"""
from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass

import mujoco
import numpy as np
from scipy.spatial.transform import Rotation

from shared.contracts.messages import CircleObstacle, Obstacle, WallObstacle
from shared.execution.robots.mujoco.config import MujocoConfig
from shared.execution.robots.mujoco.decompose import convex_pieces
from shared.robots.arms import combined_urdf, load_arm
from shared.robots.hands import load_hand
from shared.world.objects.model import ObjectModel
from shared.world.obstacles import wall_half_extents, wall_pose

OBJECT_BODY = "object"
ROBOT_GROUP, WORLD_GROUP = 1, 2  # contype / conaffinity bits: robot geoms touch the world, not each other
# MuJoCo takes a contact's friction from the geom of higher priority: the table's (object-table) and the
# robot's (hand-object) outrank the object's, so each pair's coefficient is the one drawn for it.
TABLE_PRIORITY, ROBOT_PRIORITY, OBJECT_PRIORITY = 1, 1, 0
# The hands' joints are finger after finger, four each (index, middle, ring, thumb: the Allegro's and the
# LEAP's joint order); a finger's geoms are those of the bodies its joints move.
JOINTS_PER_FINGER = 4
# A plane collides as an infinite plane whatever its size; the size is what cameras see. A finite table, not
# MuJoCo's infinite one: that one is drawn as a patch around where the last camera stood, so a pixel's depth
# changed by up to 1 mm with the previous render's camera (measured); this one is the same for every camera.
TABLE_RENDER_HALF_M = 1.5
OFFSCREEN_SIZE = (1280, 720)  # the D435's largest depth mode; a larger render grows the model's buffer


class ModelError(ValueError):
    """A MuJoCo model failed to compile: names the element (body, joint, geom) and MuJoCo's reason."""


@dataclass(frozen=True)
class PlacedObject:
    """The object as it truly is, where it truly stands."""

    obj: ObjectModel
    T_world_O: np.ndarray
    mass_scale: float = 1.0
    com_offset_m: tuple[float, float, float] = (0.0, 0.0, 0.0)


def wxyz(rotation: np.ndarray) -> np.ndarray:
    x, y, z, w = Rotation.from_matrix(rotation).as_quat()
    return np.array([w, x, y, z])


def robot_spec(arm: str, hand: str) -> mujoco.MjSpec:
    """The arm + hand of the project's combined URDF as an MjSpec (not yet compiled)."""
    spec = mujoco.MjSpec.from_file(str(combined_urdf(arm, hand)))
    spec.compiler.balanceinertia = True
    return spec


def compile_spec(spec: mujoco.MjSpec, what: str) -> mujoco.MjModel:
    """Compile `spec`; ModelError naming `what`, the element MuJoCo blames and its reason."""
    try:
        return spec.compile()
    except ValueError as exc:
        text = str(exc).strip()
        reason = re.sub(r"^Error:\s*", "", text.splitlines()[0]) if text else "unknown reason"
        match = re.search(r"Element name '([^']*)', id (\d+)", text)
        element = f"element {match.group(1)!r} (id {match.group(2)})" if match else "an unnamed element"
        raise ModelError(f"{what}: MuJoCo cannot compile {element}: {reason}") from None


def build_spec(config: MujocoConfig, placed: PlacedObject | None = None,
               obstacles: Sequence[Obstacle] = (), neighbours: Sequence[PlacedObject] = ()) -> mujoco.MjSpec:
    """The full world's MjSpec: robot with servos, table, object (if any) and its neighbours (bodies
    `neighbour_body(k)`), obstacles, contact settings."""
    spec = robot_spec(config.arm, config.hand)
    _contact_options(spec, config)
    arm, hand = load_arm(config.arm), load_hand(config.hand)
    root = spec.worldbody.first_body()
    T_world_base = np.eye(4) if config.T_world_base is None else np.asarray(config.T_world_base, dtype=np.float64)
    root.pos, root.quat = T_world_base[:3, 3], wxyz(T_world_base[:3, :3])
    spec.visual.global_.offwidth, spec.visual.global_.offheight = OFFSCREEN_SIZE
    materials = config.materials
    fingers = finger_of_body(spec, hand.joint_names)
    if materials.finger_friction_scales and len(materials.finger_friction_scales) != max(fingers.values()) + 1:
        raise ModelError(f"{config.arm}+{config.hand}: {len(materials.finger_friction_scales)} finger friction scales "
                         f"for a hand of {max(fingers.values()) + 1} fingers")
    for geom in spec.geoms:
        geom.contype, geom.conaffinity = ROBOT_GROUP, 0
        finger = fingers.get(geom.parent.name)
        scale = 1.0 if finger is None or not materials.finger_friction_scales else materials.finger_friction_scales[finger]
        geom.friction = [materials.hand_friction * scale, materials.torsional_friction, materials.rolling_friction]
        geom.priority, geom.condim = ROBOT_PRIORITY, materials.condim
    for body in spec.bodies:
        if body.name != "world":
            body.gravcomp = 1.0
    _servos(spec, config, arm.joint_names, hand.joint_names)
    table = spec.worldbody.add_geom(name="table", type=mujoco.mjtGeom.mjGEOM_PLANE,
                                    size=[TABLE_RENDER_HALF_M, TABLE_RENDER_HALF_M, 0.05])
    table.contype, table.conaffinity = WORLD_GROUP, ROBOT_GROUP | WORLD_GROUP
    table.friction = [materials.table_friction, materials.torsional_friction, materials.rolling_friction]
    table.priority, table.condim = TABLE_PRIORITY, materials.condim
    if placed is not None:
        _add_object(spec, config, placed)
    for index, neighbour in enumerate(neighbours):
        _add_object(spec, config, neighbour, neighbour_body(index))
    cylinders = [o for o in obstacles if isinstance(o, CircleObstacle)]
    walls = [o for o in obstacles if isinstance(o, WallObstacle)]
    for index, circle in enumerate(cylinders):
        geom = spec.worldbody.add_geom(name=f"obstacle {index}", type=mujoco.mjtGeom.mjGEOM_CYLINDER,
                                       size=[circle.radius, circle.height_m / 2, 0.0],
                                       pos=[circle.x, circle.y, circle.height_m / 2])
        geom.contype, geom.conaffinity = WORLD_GROUP, ROBOT_GROUP | WORLD_GROUP
        geom.condim = materials.condim
    for index, wall in enumerate(walls):
        T = wall_pose(wall)
        geom = spec.worldbody.add_geom(name=f"wall {index}", type=mujoco.mjtGeom.mjGEOM_BOX,
                                       size=wall_half_extents(wall).tolist(), pos=T[:3, 3].tolist(), quat=wxyz(T[:3, :3]))
        geom.contype, geom.conaffinity = WORLD_GROUP, ROBOT_GROUP | WORLD_GROUP
        geom.friction = [materials.table_friction, materials.torsional_friction, materials.rolling_friction]
        geom.condim = materials.condim
    _contact_geoms(spec, config)
    return spec


def _contact_geoms(spec: mujoco.MjSpec, config: MujocoConfig) -> None:
    """Every geom's contact impedance: config.ContactConfig's (a pair of equal values keeps them)."""
    solref, solimp = list(config.contact.solref), [*config.contact.solimp, 0.5, 2.0]
    for geom in spec.geoms:
        geom.solref, geom.solimp = solref, solimp


def finger_of_body(spec: mujoco.MjSpec, hand_joints: Sequence[str]) -> dict[str, int]:
    """Body name -> finger (0 index, 1 middle, 2 ring, 3 thumb) of every body a finger joint moves."""
    finger_of_joint = {name: k // JOINTS_PER_FINGER for k, name in enumerate(hand_joints)}
    fingers: dict[str, int] = {}
    for body in spec.bodies:
        walk = body
        while walk is not None and walk.name != "world":
            moved_by = [finger_of_joint[j.name] for j in walk.joints if j.name in finger_of_joint]
            if moved_by:
                fingers[body.name] = moved_by[0]
                break
            walk = walk.parent
    return fingers


def build_model(config: MujocoConfig, placed: PlacedObject | None = None,
                obstacles: Sequence[Obstacle] = (), neighbours: Sequence[PlacedObject] = ()) -> mujoco.MjModel:
    """The compiled world (ModelError naming what failed)."""
    what = f"{config.arm}+{config.hand}" + (f" with object {placed.obj.id}" if placed is not None else "")
    return compile_spec(build_spec(config, placed, obstacles, neighbours), what)


def _contact_options(spec: mujoco.MjSpec, config: MujocoConfig) -> None:
    c = config.contact
    option = spec.option
    option.timestep = c.time_step_s
    option.cone = mujoco.mjtCone.mjCONE_ELLIPTIC if c.cone == "elliptic" else mujoco.mjtCone.mjCONE_PYRAMIDAL
    option.solver = {"Newton": mujoco.mjtSolver.mjSOL_NEWTON, "CG": mujoco.mjtSolver.mjSOL_CG,
                     "PGS": mujoco.mjtSolver.mjSOL_PGS}[c.solver]
    option.iterations = c.iterations
    option.noslip_iterations = c.noslip_iterations
    option.impratio = c.impratio
    option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST  # stiff servos and damping, stable at 2 ms
    # Every geom gets the same solref / solimp (`_contact_geoms`), so every contact has them. Not MuJoCo's
    # override flag: it would also override every contact's friction with o_friction (1 for all pairs).


def _servos(spec: mujoco.MjSpec, config: MujocoConfig, arm_joints: Sequence[str], hand_joints: Sequence[str]) -> None:
    """One servo per joint: ctrl is q_ref + (kv / kp) qd_ref, so force = kp (q_ref - q) + kv (qd_ref - qd)."""
    from shared.execution.robots.sim.config import limits

    device = limits(config.arm, config.hand)
    effort = dict(zip(device.joint_names, device.effort, strict=True))
    control = config.control
    joints = {j.name: j for j in spec.joints}
    for name in (*arm_joints, *hand_joints):
        if name not in joints:
            raise ModelError(f"{config.arm}+{config.hand}: the model has no joint {name!r}")
        is_arm = name in arm_joints
        kp, kv = (control.arm_kp, control.arm_kv) if is_arm else (control.hand_kp, control.hand_kv)
        joint = joints[name]
        joint.armature = control.arm_armature if is_arm else control.hand_armature
        # The URDFs' joint friction and damping are not the servos' (the Allegro's says 10 Nm of friction on
        # a 15 Nm finger): the servo's kv is the damping, the hand keeps a small passive damping of its own.
        joint.frictionloss = 0.0
        joint.damping = [0.0 if is_arm else control.hand_damping, 0.0, 0.0]
        joint.actgravcomp = True
        actuator = spec.add_actuator(name=name, target=name, trntype=mujoco.mjtTrn.mjTRN_JOINT)
        actuator.gaintype = mujoco.mjtGain.mjGAIN_FIXED
        actuator.gainprm[0] = kp
        actuator.biastype = mujoco.mjtBias.mjBIAS_AFFINE
        actuator.biasprm[:3] = [0.0, -kp, -kv]
        actuator.ctrllimited = mujoco.mjtLimited.mjLIMITED_FALSE
        actuator.forcelimited = mujoco.mjtLimited.mjLIMITED_TRUE
        actuator.forcerange = [-effort[name], effort[name]]


def neighbour_body(index: int) -> str:
    return f"neighbour {index}"


def _add_object(spec: mujoco.MjSpec, config: MujocoConfig, placed: PlacedObject, name: str = OBJECT_BODY) -> None:
    obj = placed.obj
    T = np.asarray(placed.T_world_O, dtype=np.float64)
    body = spec.worldbody.add_body(name=name, pos=T[:3, 3], quat=wxyz(T[:3, :3]))
    body.add_freejoint(name=f"{name}_free")
    body.explicitinertial = True
    body.mass = obj.mass * placed.mass_scale
    body.ipos = list(placed.com_offset_m)
    body.iquat = [1.0, 0.0, 0.0, 0.0]
    inertia = np.diag(obj.inertia) if np.ndim(obj.inertia) == 2 else np.asarray(obj.inertia)
    body.inertia = inertia * placed.mass_scale
    for index, piece in enumerate(convex_pieces(obj)):
        mesh = spec.add_mesh(name=f"{name}_piece{index}")
        mesh.uservert = np.asarray(piece.vertices, dtype=np.float64).ravel().tolist()
        mesh.userface = np.asarray(piece.faces, dtype=np.int32).ravel().tolist()
        mesh.inertia = mujoco.mjtMeshInertia.mjMESH_INERTIA_CONVEX
        geom = body.add_geom(name=f"{name}_piece{index}", type=mujoco.mjtGeom.mjGEOM_MESH, meshname=mesh.name)
        geom.contype, geom.conaffinity = WORLD_GROUP, ROBOT_GROUP | WORLD_GROUP
        materials = config.materials
        geom.friction = [materials.object_friction, materials.torsional_friction, materials.rolling_friction]
        geom.priority, geom.condim = OBJECT_PRIORITY, materials.condim
        geom.mass = 0.0  # the body's explicit inertia is the object's
